"""Frames that queue on the bus while the daemon starts are read away, neither used nor recorded.

Between opening the buses and starting the receive thread the daemon opens Zenoh and its
recording (a second on a loaded machine). A daemon started after its ECU recorded that backlog
as a burst stamped at the time it was read, with the socket queue's drops in it: six E2E
errors in `replay check` on every such start.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from pathlib import Path
from typing import Any

import can
import pytest

from leafgate.can.bus import discard_queued
from leafgate.config.can import BusConfig
from leafgate.runtime import node
from leafgate.runtime.daemon import run_daemon
from leafgate.settings import load_config
from tests.conftest import free_port

ROOT = Path(__file__).resolve().parents[1]
MARK = bytes([0xDE, 0xAD, 0xBE, 0xEF, 0x5A, 0xA5, 0x00, 0x01])  # no frame the ECU sends


def test_discard_queued_reads_away_what_waits_and_stops_when_empty() -> None:
    channel = f"discard-{os.getpid()}"
    with (
        can.Bus(interface="virtual", channel=channel) as rx,
        can.Bus(interface="virtual", channel=channel) as tx,
    ):
        assert discard_queued(rx) == 0
        for _ in range(37):
            tx.send(can.Message(arbitration_id=0xB0, data=MARK, is_extended_id=False))
        assert discard_queued(rx) == 37
        assert rx.recv(timeout=0.0) is None
        tx.send(can.Message(arbitration_id=0xB1, data=MARK, is_extended_id=False))
        got = rx.recv(timeout=1.0)  # what comes after is delivered as before
        assert got is not None and got.arbitration_id == 0xB1


def test_a_flooded_bus_is_discarded_for_the_budget_only() -> None:
    """A bus that never empties (a flood) does not hold the start-up longer than the budget."""

    class Endless(can.BusABC):
        def __init__(self) -> None:
            super().__init__(channel="endless")

        def _recv_internal(self, timeout: float | None) -> tuple[can.Message, bool]:
            return can.Message(arbitration_id=0x1, data=b""), False

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            pass

    ticks = iter(range(1_000_000))
    with Endless() as bus:
        # a fake clock: 0.01 s per reading, so a 0.2 s budget is 20 readings
        n = discard_queued(bus, budget=0.2, clock=lambda: next(ticks) * 0.01)
    assert 15 <= n <= 21


@pytest.mark.timeout(60)
def test_frames_queued_during_start_up_are_not_recorded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    channel = f"start-queue-{os.getpid()}"
    cfg = load_config(ROOT / "config" / "sim.yaml")
    rec = tmp_path / "recordings"
    cfg = dataclasses.replace(
        cfg,
        can=dataclasses.replace(cfg.can, dbw=BusConfig(interface="virtual", channel=channel)),
        zenoh=dataclasses.replace(cfg.zenoh, listen=(f"tcp/127.0.0.1:{free_port()}",)),
        recording=dataclasses.replace(cfg.recording, enabled=True, directory=str(rec)),
    )
    ecu = can.Bus(interface="virtual", channel=channel)
    real_open = node.GatewayTransport.open.__func__  # type: ignore[attr-defined]

    def slow_open(cls: Any, *args: Any, **kwargs: Any) -> Any:
        # the ECU goes on sending while the daemon opens Zenoh: the bus is open, nobody reads
        for _ in range(50):
            ecu.send(can.Message(arbitration_id=0xB0, data=MARK, is_extended_id=False))
        return real_open(cls, *args, **kwargs)

    monkeypatch.setattr(node.GatewayTransport, "open", classmethod(slow_open))
    runtimes: list[Any] = []
    stop = threading.Event()
    ticked = threading.Event()

    def on_runtime(runtime: Any) -> None:
        runtimes.append(runtime)
        inner = runtime.on_tick

        def counting(*args: Any) -> None:
            inner(*args)
            if runtime.stats.ticks >= 5:
                ticked.set()

        runtime.on_tick = counting

    thread = threading.Thread(
        target=run_daemon, args=(cfg, stop), kwargs={"on_runtime": on_runtime}
    )
    thread.start()
    try:
        assert ticked.wait(30.0), "the daemon did not tick"
        diag = runtimes[0].diagnostics()
    finally:
        stop.set()
        thread.join(timeout=30)
        ecu.shutdown()
    assert not thread.is_alive()
    assert diag["can_discarded_at_start"] == 50
    logs = sorted(rec.glob("*.blf"))
    assert logs, sorted(rec.iterdir())
    with can.BLFReader(str(logs[0])) as reader:
        frames = list(reader)
    assert frames, "the recording holds the drive's own frames"
    assert not [f for f in frames if bytes(f.data) == MARK]
