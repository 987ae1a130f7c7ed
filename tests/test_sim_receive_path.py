"""The simulator runs the daemon's receive path (issue 14, item 2 "One loop").

``leafgate sim`` drives the gateway through ``Runtime.tick`` and its ``CanReceiver`` on the
``virtual`` bus: a frame another node sends on a command ID is counted as foreign and faults the
gateway (a command conflict), while the gateway's own frames, heard back as on
``udp_multicast``, pass the echo filter and are not.
"""

from __future__ import annotations

import math
from typing import Any

import can
import pytest

from leafgate.can.codec import CanCodec, EncodeError
from leafgate.messages import GatewayState
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import WALL_CLOCK_METRICS, Injection, run
from leafgate.sim.scenarios import get_scenario

pytestmark = pytest.mark.slow  # closed-loop drives

STEER_CMD = 0x0A0  # DBW_STEER_CMD of the leafgate-dbw profile
FOREIGN_AT = 5.0  # s, engaged and driving by then


class ForeignNode:
    """Stands where the recorder stands: it learns the simulator's bus channel from the frames
    the gateway receives, and at ``at`` another node of its own sends one frame on ``frame_id``.
    """

    def __init__(self, at: float, frame_id: int) -> None:
        self.at = at
        self.frame_id = frame_id
        self.channel: Any = None
        self.sent_at: float | None = None

    def wrap_controller(self, controller: Any) -> Any:
        return controller

    def on_can_frame(self, msg: can.Message, direction: str) -> None:
        self.channel = msg.channel

    def on_tick(self, now: float, inputs: Any, result: Any, frames: Any) -> None:
        if self.sent_at is not None or now < self.at:
            return
        assert self.channel is not None, "no frame received before the foreign frame is due"
        with can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True) as bus:
            msg = can.Message(
                arbitration_id=self.frame_id, is_extended_id=False, data=bytes(8), timestamp=now
            )
            bus.send(msg)
        self.sent_at = now


def _conflicts(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    return [t for t in metrics["transitions"] if t["reason"].startswith("command conflict")]


def test_a_foreign_frame_on_a_command_id_faults_the_simulated_gateway() -> None:
    """The old runner read report IDs only and never looked at its command IDs: the drive
    finished as if nobody else were on the bus."""
    node = ForeignNode(FOREIGN_AT, STEER_CMD)
    result = run(LeafgateConfig(), get_scenario("s-curve"), recorder=node)  # type: ignore[arg-type]
    metrics = result.metrics
    assert node.sent_at is not None
    assert metrics["final_state"] == GatewayState.FAULT.name
    (conflict,) = _conflicts(metrics)
    assert conflict["from"] == "ENGAGED" and conflict["to"] == "FAULT"
    assert "1 foreign DBW_STEER_CMD frame(s)" in conflict["reason"]
    # the next control tick, 20 ms later, saw it
    assert conflict["t"] == pytest.approx(node.sent_at + LeafgateConfig().gateway.period)
    assert metrics["can_foreign_frames"] == 1
    assert not metrics["finished"] and "command conflict" in metrics["not_finished_reason"]


def test_the_gateways_own_frames_come_back_and_are_not_foreign() -> None:
    result = run(LeafgateConfig(), get_scenario("s-curve"))
    metrics = result.metrics
    assert metrics["finished"], metrics.get("not_finished_reason")
    assert _conflicts(metrics) == []
    assert metrics["can_foreign_frames"] == 0
    # every frame sent was heard back and taken as ours, but those of the last tick (the
    # drive ended before the receiver read them): at most one tick's three frames
    sent, echoes = metrics["can_frames_sent"], metrics["can_own_echoes"]
    assert sent > 1000 and 0 <= sent - echoes <= 3


def test_foreign_command_injection_is_a_command_conflict() -> None:
    """``leafgate sim --inject foreign-command@5s``: another node commands the ECU."""
    result = run(
        LeafgateConfig(),
        get_scenario("s-curve"),
        injections=(Injection.parse("foreign-command@5s+0.1"),),
    )
    metrics = result.metrics
    assert metrics["final_state"] == GatewayState.FAULT.name
    (conflict,) = _conflicts(metrics)
    assert conflict["t"] == pytest.approx(FOREIGN_AT)
    command_names = sorted(
        CanCodec(profile="leafgate-dbw").name_of(i) or ""
        for i in CanCodec(profile="leafgate-dbw").receive_ids("commands")
    )
    assert all(name in conflict["reason"] for name in command_names)
    # sent once per control tick for 0.1 s, on each command ID
    assert metrics["can_foreign_frames"] == 5 * len(command_names)
    assert abs(result.trace.speed[-1]) < 0.01  # the ECU brought the car to rest


def test_report_errors_go_through_the_receivers_counts() -> None:
    """A corrupted report is rejected by the receiver and counted toward the error counter."""
    result = run(
        LeafgateConfig(), get_scenario("s-curve"), injections=(Injection.parse("corrupt-crc@5s"),)
    )
    metrics = result.metrics
    assert metrics["can_frames_rejected"] > 0
    assert metrics["final_state"] == GatewayState.FAULT.name


def test_two_runs_give_identical_results() -> None:
    """Deterministic: the receiver is fed synchronously, on the simulated clock."""
    cfg = LeafgateConfig()
    injections = (Injection.parse("foreign-command@6s+0.04"),)
    a, b = (run(cfg, get_scenario("slalom"), injections=injections) for _ in range(2))
    keep = {k: v for k, v in a.metrics.items() if k not in WALL_CLOCK_METRICS}
    assert keep == {k: v for k, v in b.metrics.items() if k not in WALL_CLOCK_METRICS}
    assert a.timeline == b.timeline and a.states == b.states
    for key, series in a.series.items():
        assert series.tobytes() == b.series[key].tobytes(), key
    assert all(math.isfinite(v) for v in a.series["x"])


def test_an_encode_error_in_the_simulator_stops_the_drive_loudly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The daemon's loop counts an encode error and faults; in the simulator the safety gate
    keeps every value in range, so one is a bug and the drive raises, naming the frame."""
    encode = CanCodec.encode_commands

    def broken(self: CanCodec, commands: Any, timestamp: float = 0.0) -> list[can.Message]:
        frames = encode(self, commands, timestamp)
        if timestamp >= 2.0:
            self.last_errors.append("DBW_STEER_CMD: STEER_ANGLE_CMD out of range (planted)")
            return frames[1:]
        return frames

    monkeypatch.setattr(CanCodec, "encode_commands", broken)
    with pytest.raises(EncodeError, match="STEER_ANGLE_CMD out of range"):
        run(LeafgateConfig(), get_scenario("s-curve"))
