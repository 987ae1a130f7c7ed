"""The fault suite's parts, in-process and fast: the gateway's command-conflict and
plan-replacement decisions, the echo bookkeeping for buses that do and do not deliver their own
frames, ``sim-ecu``'s injections, the session fields, truncated text logs and the table tool.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

import can
import numpy as np
import pytest

from leafgate.can.codec import CanCodec
from leafgate.config import VehicleConfig
from leafgate.config.gateway import GatewayConfig
from leafgate.config.sim import LocalizationConfig
from leafgate.errors import ConfigError
from leafgate.gateway.core import FOREIGN_QUIET, Gateway, GatewayInputs
from leafgate.messages import (
    ControlOutput,
    EcuState,
    GatewayState,
    Gear,
    LongCommand,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerCommand,
    SteerReport,
    SystemReport,
    Trajectory,
)
from leafgate.record.logs import FrameSource
from leafgate.record.session import decode_inputs, encode_inputs
from leafgate.runtime.loop import Runtime
from leafgate.runtime.receiver import CanReceiver, SentFrames
from leafgate.sim.realtime import EngagedInjection, InjectionSchedule, LocalizationFeed

ROOT = Path(__file__).resolve().parents[2]
PERIOD = 0.02  # s, control tick
STRAIGHT = Trajectory(
    x=np.arange(-2.0, 30.0, 0.5),
    y=np.zeros(64),
    heading=np.zeros(64),
    speed=np.full(64, 1.0),
)


class Cruise:
    """A controller asking for gentle acceleration with straight wheels."""

    period = PERIOD

    def __init__(self) -> None:
        self.trajectories: list[Trajectory] = []

    def reset(self) -> None:
        pass

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        self.trajectories.append(trajectory)
        return ControlOutput(steer_angle=0.0, accel=0.3, speed=1.0, gear=Gear.D)


class EngagedRig:
    """A gateway with fresh inputs from an ECU that follows ENABLE (driving along +x at 1 m/s)."""

    def __init__(self) -> None:
        self.controller = Cruise()
        self.gw = Gateway(GatewayConfig(), VehicleConfig(), self.controller)
        self.k = 0
        self.enabled = False
        self.trajectory = STRAIGHT
        self.trajectory_valid = True  # False: refused where it arrived (the transport)

    @property
    def now(self) -> float:
        return self.k * PERIOD

    def step(self, **kw: object) -> tuple[GatewayState, str]:
        now, speed = self.now, 1.0 if self.enabled else 0.0
        e = self.enabled
        inputs = GatewayInputs(
            pose=Stamped(Pose(now * speed, 0.0, 0.0, speed), now),
            trajectory=Stamped(self.trajectory, now, self.trajectory_valid),
            steer_report=Stamped(SteerReport(0.0, 0.0, 0.0, e, False, False, False), now),
            long_report=Stamped(
                LongReport(speed, 0.0, Gear.D, 0.0, 0.0, e, False, False, False), now
            ),
            system_report=Stamped(
                SystemReport(
                    EcuState.ENGAGED if e else EcuState.READY, False, False, False, False, 0
                ),
                now,
            ),
            good_report_frames=3,
        )
        if kw:
            inputs = dataclasses.replace(inputs, **kw)  # type: ignore[arg-type]
        result = self.gw.step(now, inputs)
        self.enabled = result.commands.steer.enable
        self.k += 1
        return self.gw.state, result.diagnostics.reason

    def engage(self) -> None:
        for _ in range(3):
            self.step()
        self.step(request=OperatorRequest.ENGAGE)
        for _ in range(5):
            self.step()
        assert self.gw.state == GatewayState.ENGAGED


# --- core: command conflict -----------------------------------------------------------------------


def test_foreign_command_frames_fault_with_a_named_conflict() -> None:
    rig = EngagedRig()
    rig.engage()
    state, reason = rig.step(
        foreign_command_frames=2, foreign_command_names=("DBW_LONG_CMD", "DBW_STEER_CMD")
    )
    assert state == GatewayState.FAULT
    assert reason == "command conflict: 2 foreign DBW_LONG_CMD, DBW_STEER_CMD frame(s) on the bus"
    assert "command_conflict" in rig.gw.machine.fault_causes


def test_foreign_command_frames_fault_in_standby_too() -> None:
    rig = EngagedRig()
    rig.step()
    state, _ = rig.step(foreign_command_frames=1, foreign_command_names=("DBW_SYSTEM_CMD",))
    assert state == GatewayState.FAULT


def test_command_conflict_reset_refused_until_the_bus_is_quiet() -> None:
    rig = EngagedRig()
    rig.step(foreign_command_frames=1, foreign_command_names=("DBW_STEER_CMD",))
    rig.step()
    refused = rig.gw.step(
        rig.now,
        GatewayInputs(None, None, None, None, None, request=OperatorRequest.RESET),
    )
    assert refused.reply is not None and not refused.reply.accepted
    assert "foreign command frames seen" in refused.reply.reason
    rig.k += round(FOREIGN_QUIET / PERIOD) + 1
    accepted = rig.gw.step(
        rig.now,
        GatewayInputs(None, None, None, None, None, request=OperatorRequest.RESET),
    )
    assert accepted.reply is not None and accepted.reply.accepted, accepted.reply
    assert rig.gw.state == GatewayState.STANDBY


# --- core: a replaced plan ------------------------------------------------------------------------


def _shifted(trajectory: Trajectory, dy: float) -> Trajectory:
    return dataclasses.replace(trajectory, y=trajectory.y + dy)


def test_plan_replaced_far_from_the_vehicle_stops_without_chasing() -> None:
    rig = EngagedRig()
    rig.engage()
    calls = len(rig.controller.trajectories)
    rig.trajectory = _shifted(STRAIGHT, 5.0)
    state, reason = rig.step()
    assert state == GatewayState.STOPPING
    assert reason.startswith("trajectory replaced: vehicle 5.00 m from the new plan"), reason
    assert len(rig.controller.trajectories) == calls  # the controller never saw the far plan


def test_plan_replaced_within_the_engage_envelope_is_followed() -> None:
    rig = EngagedRig()
    rig.engage()
    near = _shifted(STRAIGHT, 0.5)
    rig.trajectory = near
    state, _ = rig.step()
    assert state == GatewayState.ENGAGED
    assert rig.controller.trajectories[-1] is near


def test_plan_replaced_with_a_reversed_heading_stops() -> None:
    rig = EngagedRig()
    rig.engage()
    # the same line driven the other way: a plan the car, facing +x, is 180° off
    rig.trajectory = dataclasses.replace(STRAIGHT, x=STRAIGHT.x[::-1], heading=np.full(64, math.pi))
    state, reason = rig.step()
    assert state == GatewayState.STOPPING
    assert "heading 180.0° off the new plan" in reason, reason


@pytest.mark.parametrize("by_transport", [False, True])
def test_plan_replaced_by_one_that_cannot_be_driven_stops_naming_why(by_transport: bool) -> None:
    """Old code: the refused plan was dropped and the car went on with the older one, the
    planner's newest word unheard (here: headings against the way the path runs)."""
    rig = EngagedRig()
    rig.engage()
    bad = dataclasses.replace(STRAIGHT, heading=np.full(64, math.pi))
    rig.trajectory = bad
    if by_transport:  # refused where it arrived (the transport's check marks it invalid)
        rig.trajectory_valid = False
    state, reason = rig.step()
    assert state == GatewayState.STOPPING
    assert reason.startswith("trajectory replaced by one that cannot be driven: trajectory: row 1:")
    assert "heading 3.142 rad is 180° off the way the path runs" in reason, reason


# --- runtime: own frames and foreign ones ---------------------------------------------------------


def _frame(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def test_sent_frames_take_each_echo_once() -> None:
    sent = SentFrames(window=1.0)
    a = _frame(0x0A0, bytes(8))
    sent.add(a, 0.0)
    assert sent.take(a, 0.001)
    assert not sent.take(a, 0.002)  # a second copy is not ours


def test_a_repeated_frame_keeps_its_echo_when_an_older_copy_expires() -> None:
    # STANDBY frames repeat byte for byte whenever the alive counter wraps (16 frames).
    sent = SentFrames(window=1.0)
    frame = _frame(0x0A0, bytes(8))
    sent.add(frame, 0.0)
    assert sent.take(frame, 0.001)  # its echo
    sent.add(frame, 0.99)  # the same bytes again, its echo on the way …
    assert sent.take(frame, 1.01)  # … arriving as the first copy leaves the window
    assert len(sent) == 0
    sent.add(frame, 2.0)  # a copy whose echo never comes (a bus without echoes) …
    sent.add(frame, 3.5)  # … expires when the next copy is sent, without taking its place
    assert sent.take(frame, 3.501)
    assert len(sent) == 0


def test_a_late_echo_within_the_window_is_ours() -> None:
    sent = SentFrames(window=2.0)
    frame = _frame(0x0A1, b"\x01" * 8)
    sent.add(frame, 0.0)
    assert sent.take(frame, 1.9)


def test_an_echo_after_the_window_is_foreign() -> None:
    sent = SentFrames(window=2.0)
    frame = _frame(0x0A1, b"\x01" * 8)
    sent.add(frame, 0.0)
    assert not sent.take(frame, 2.1)


def test_receiver_drops_own_echoes_and_counts_and_records_foreign_frames() -> None:
    now = [0.0]
    receiver = CanReceiver(CanCodec(profile="leafgate-dbw"), lambda: now[0])
    recorded: list[int] = []
    receiver.on_frame = lambda msg, _decoded: recorded.append(msg.arbitration_id)
    ours = CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=0.1))
    receiver.sent.add(ours, 0.0)
    receiver.on_message_received(ours)
    rogue = CanCodec(profile="leafgate-dbw").encode(LongCommand(accel=1.0, enable=True))
    receiver.on_message_received(rogue)
    assert receiver.own_echoes == 1
    assert receiver.take_foreign() == (1, ("DBW_LONG_CMD",))
    assert receiver.take_foreign() == (0, ())
    assert recorded == [0x0A1]  # the echo is recorded once, as sent, not again as received


@pytest.mark.parametrize("echoes", [True, False], ids=["bus-echoes-own-frames", "no-echo"])
def test_runtime_faults_only_on_frames_it_did_not_send(echoes: bool) -> None:
    """udp_multicast delivers a bus's own frames back to it, SocketCAN does not: both work."""
    channel = f"faults-echo-{echoes}"
    codec = CanCodec(profile="leafgate-dbw")
    clock = [0.0]
    ecu = CanCodec(profile="leafgate-dbw")
    with (
        can.Bus(interface="virtual", channel=channel, receive_own_messages=echoes) as bus,
        can.Bus(interface="virtual", channel=channel) as other,
    ):
        bus.set_filters([{"can_id": 0x0B0, "can_mask": 0x7FF, "extended": False}])
        receiver = CanReceiver(codec, lambda: clock[0])
        gateway = Gateway(GatewayConfig(), VehicleConfig(), Cruise())
        pose = Stamped(Pose(0.0, 0.0, 0.0, 0.0), 0.0)

        class Inputs:
            def latest_pose(self) -> Stamped[Pose]:
                return dataclasses.replace(pose, received=clock[0])

            def latest_trajectory(self) -> Stamped[Trajectory]:
                return Stamped(STRAIGHT, clock[0])

        runtime = Runtime(gateway, codec, bus, receiver, Inputs(), PERIOD, clock=lambda: clock[0])
        assert bus.filters is not None and len(bus.filters) == 4  # report ID + 3 command IDs

        def pump() -> None:
            while (msg := bus.recv(timeout=0.0)) is not None:
                receiver.on_message_received(msg)

        for _ in range(20):
            other.send(ecu.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False)))
            pump()
            runtime.tick(clock[0])
            clock[0] += PERIOD
        pump()
        assert gateway.state == GatewayState.STANDBY, gateway.machine.reason
        assert receiver.foreign_total == 0
        assert (receiver.own_echoes > 0) == echoes
        other.send(CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=0.2, enable=True)))
        pump()
        runtime.tick(clock[0])
        assert gateway.state == GatewayState.FAULT
        assert "command conflict: 1 foreign DBW_STEER_CMD" in gateway.machine.fault_reason


# --- sim-ecu injections ---------------------------------------------------------------------------


def test_injection_parse_fills_defaults_and_reads_parameters() -> None:
    inj = EngagedInjection.parse("localization-jump@3s+1.5:lateral=-2.5")
    assert (inj.kind, inj.at, inj.duration) == ("localization-jump", 3.0, 1.5)
    assert inj.params == {"lateral": -2.5, "longitudinal": 0.0}
    assert EngagedInjection.parse("corrupt-crc@2").params == {}
    assert EngagedInjection.parse("localization-delay@1").params == {"delay": 0.4}


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("localization-stop", "expected KIND@TIME"),
        ("teleport@3", "unknown kind 'teleport'"),
        ("override-torque@3:force=2", "unknown parameter 'force' for override-torque"),
        ("override-torque@3:torque=abc", "torque='abc' is not a number"),
        ("localization-delay@3:delay=0", "delay must be positive"),
        ("corrupt-crc@3+0", "duration must be positive"),
    ],
)
def test_injection_parse_errors_name_the_text_in_one_line(text: str, expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        EngagedInjection.parse(text)
    message = str(err.value)
    assert expected in message and repr(text) in message and "\n" not in message


class _Plant:
    def __init__(self) -> None:
        self.x = 0.0

    def pose(self) -> Pose:
        return Pose(self.x, 0.0, 0.0, 1.0)


class _Ecu:
    """What the schedule and the feed read of the simulated ECU."""

    def __init__(self) -> None:
        self.engaged = False
        self.plant = _Plant()
        self.injected: list[tuple[str, float, float | None, Mapping[str, float]]] = []

    def inject(self, kind: str, at: float, duration: float | None = None, **params: float) -> None:
        self.injected.append((kind, at, duration, params))


def _drive(feed: LocalizationFeed, schedule: InjectionSchedule, ecu: _Ecu, until: float) -> None:
    """1 kHz ticks, 1 m/s along +x, engaged from t = 1 s."""
    for k in range(round(until * 1000)):
        now = k / 1000
        ecu.engaged = now >= 1.0
        ecu.plant.x = now
        schedule.on_tick(now, ecu)  # type: ignore[arg-type]
        feed.on_tick(now, ecu)  # type: ignore[arg-type]


def test_schedule_arms_at_the_first_engagement_and_hands_ecu_faults_over() -> None:
    ecu = _Ecu()
    clock = iter(range(1000, 100000))
    schedule = InjectionSchedule(
        [
            EngagedInjection.parse("corrupt-crc@2+0.5"),
            EngagedInjection.parse("localization-stop@1"),
        ],
        clock=lambda: float(next(clock)),
    )
    feed = LocalizationFeed(lambda pose: None, LocalizationConfig(), schedule.params)
    _drive(feed, schedule, ecu, 4.0)
    assert schedule.engaged_at == 1.0
    assert ecu.injected == [("corrupt-crc", 3.0, 0.5, {})]
    events = [(e["event"], e.get("kind"), e["t"]) for e in schedule.events]
    assert events == [
        ("engaged", None, 1.0),
        ("injection-start", "localization-stop", 2.0),
        ("injection-start", "corrupt-crc", 3.0),
        ("injection-end", "corrupt-crc", 3.5),
    ]
    assert all("mono" in e for e in schedule.events)


def test_localization_stop_publishes_nothing_while_active() -> None:
    published: list[Pose] = []
    ecu = _Ecu()
    schedule = InjectionSchedule([EngagedInjection.parse("localization-stop@1+0.5")])
    feed = LocalizationFeed(published.append, LocalizationConfig(rate_hz=50.0), schedule.params)
    _drive(feed, schedule, ecu, 3.0)
    xs = np.array([p.x for p in published])
    assert not ((xs >= 2.0) & (xs < 2.5)).any()  # nothing measured in the outage went out
    assert (xs >= 2.5).any() and feed.suppressed == 25  # 0.5 s at 50 Hz


def test_localization_jump_offsets_the_position_to_the_left() -> None:
    published: list[Pose] = []
    ecu = _Ecu()
    schedule = InjectionSchedule([EngagedInjection.parse("localization-jump@1")])
    feed = LocalizationFeed(published.append, LocalizationConfig(rate_hz=50.0), schedule.params)
    _drive(feed, schedule, ecu, 2.5)
    before = [p for p in published if p.x < 2.0]
    after = [p for p in published if p.x >= 2.0]
    assert all(p.y == 0.0 for p in before)
    assert after and all(p.y == pytest.approx(2.0) for p in after)  # heading 0: left is +y


def test_localization_delay_publishes_each_sample_400_ms_after_its_stamp() -> None:
    published: list[tuple[float, Pose]] = []
    ecu = _Ecu()
    now = [0.0]
    schedule = InjectionSchedule([EngagedInjection.parse("localization-delay@1")])

    def publish(pose: Pose) -> None:
        published.append((now[0], pose))

    feed = LocalizationFeed(publish, LocalizationConfig(rate_hz=50.0), schedule.params)
    for k in range(3000):
        now[0] = k / 1000
        ecu.engaged = now[0] >= 1.0
        ecu.plant.x = now[0]  # the plant's position is its measurement time here
        schedule.on_tick(now[0], ecu)  # type: ignore[arg-type]
        feed.on_tick(now[0], ecu)  # type: ignore[arg-type]
    late = [(t, p.x) for t, p in published if p.x >= 2.0]
    assert late and all(t - x == pytest.approx(0.4) for t, x in late)
    times = [t for t, _ in published]
    gaps = np.diff(times)
    assert gaps.max() == pytest.approx(0.42, abs=1e-6)  # the onset: 0.4 s more than a period
    assert [p.x for _, p in published] == sorted(p.x for _, p in published)  # in order


# --- recording: the new inputs, truncated logs ----------------------------------------------------


def test_session_keeps_foreign_command_inputs_and_reads_older_sessions() -> None:
    inputs = GatewayInputs(
        None,
        None,
        None,
        None,
        None,
        foreign_command_frames=3,
        foreign_command_names=("DBW_STEER_CMD",),
    )
    data = json.loads(json.dumps(encode_inputs(inputs, None)))
    assert decode_inputs(data, lambda ref, obj: STRAIGHT) == inputs
    del data["foreign_command_frames"], data["foreign_command_names"]
    old = decode_inputs(data, lambda ref, obj: STRAIGHT)
    assert old.foreign_command_frames == 0 and old.foreign_command_names == ()


def test_text_log_cut_mid_line_reads_up_to_the_last_whole_line(tmp_path: Path) -> None:
    path = tmp_path / "can.log"
    writer = can.CanutilsLogWriter(path)
    for i in range(10):
        writer.on_message_received(
            can.Message(timestamp=100 + i, arbitration_id=0x0A0, data=bytes([i] * 8))
        )
    writer.stop()
    text = path.read_bytes()
    last = text.rstrip(b"\n").rfind(b"\n") + 1
    path.write_bytes(text[: last + 30])  # the last line cut inside its data
    source = FrameSource(path)
    frames = list(source)
    assert len(frames) == 9 and source.truncated
    assert all(len(f.data) == 8 for f in frames)


# --- the results table ----------------------------------------------------------------------------


def test_fault_table_prints_the_last_outcome_of_each_fault(tmp_path: Path) -> None:
    results = tmp_path / "faults.jsonl"
    rows = [
        {"fault": "a", "detected": True, "state": "FAULT", "reason": "x | y", "reaction_s": 0.1},
        {"fault": "b", "detected": False, "state": None, "reason": "", "frames_missing": 3},
        {"fault": "a", "detected": True, "state": "STANDBY", "reason": "z", "safe_state_s": 1.5},
    ]
    results.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "fault_table.py"), str(results)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    assert out[0].startswith("| fault | detected | final state |")
    assert out[2].startswith("| b | no | – |") and "| 3 |" in out[2]
    assert out[3].startswith("| a | yes | STANDBY | z | – | 1.500 |")
    assert len(out) == 4


# --- commands judged against the plant's true state (issue 17's goal) ---------------------------


def _true_state_rows(speed: float, angle: float, until: float) -> np.ndarray:
    """A plant trace (t, x, y, heading, speed, steer_angle, mono) every 20 ms up to ``until``."""
    mono = np.arange(0.0, until + 1e-9, 0.02)
    rows = np.zeros((len(mono), 7))
    rows[:, 4], rows[:, 5], rows[:, 6] = speed, angle, mono
    return rows


@pytest.mark.parametrize(
    "first_deg, outside",
    [(0.2, 0), (30.3, 1)],  # 30.3°: the first command seeded from a forged 40° report
)
def test_commands_are_judged_against_the_true_wheel_angle(
    tmp_path: Path, first_deg: float, outside: int
) -> None:
    from harness import judge_commands_on_true_state, write_config

    config = tmp_path / "sim.yaml"
    write_config(config, tmp_path / "rec")
    codec = CanCodec(profile="leafgate-dbw")
    frames: list[tuple[float, can.Message]] = []
    for k, enable in enumerate((False, True, True)):
        angle = math.radians(first_deg) if enable else 0.0
        t = 0.5 + k * PERIOD
        frames.append((t, codec.encode(SteerCommand(angle=angle, enable=enable))))
        frames.append((t + 1e-4, codec.encode(LongCommand(enable=enable))))
    rows = _true_state_rows(0.0, 0.0, 2.0)  # the wheel truly stands at 0°
    judged = judge_commands_on_true_state(frames, collections.Counter(), rows, config)
    assert judged.checked == 4  # two steering and two longitudinal ENABLE=1 frames
    assert judged.outside == outside, judged.examples
