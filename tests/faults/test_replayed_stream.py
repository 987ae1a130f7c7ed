"""A replayed command stream racing the gateway (issue 17, finding 2), across processes.

A rogue node on the bus answers each of the gateway's command frames at once with an ENABLE=1
frame of the same ID whose alive counter is the genuine one + 1 (valid CRC): the gateway's own
next frame then looks "repeated" to the ECU. Before, the simulated ECU dropped the gateway's
ENABLE=0 frames, engaged on the rogue's edge and drove the car 5.2 m at up to 1.9 m/s while
the gateway sat in FAULT. Now the ECU sees a counter race and faults, braking to rest: the
car never moves.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import can
import numpy as np
from harness import PROCESS_TEST, FaultRun, read_trace

from leafgate.can import e2e
from leafgate.can.codec import CanCodec
from leafgate.messages import EcuState, LongCommand, SteerCommand

pytestmark = PROCESS_TEST

ATTACK = 3.0  # s the rogue races the gateway
MOVED = 0.05  # m, more than this is the car driven by the rogue


class Racer(can.Listener):
    """Sends, right after each genuine command frame, a forged ENABLE=1 frame with counter + 1."""

    def __init__(self, bus: can.BusABC, run: FaultRun) -> None:
        codec = CanCodec(profile="leafgate-dbw")
        self.bus = bus
        self.run = run
        self.sent = 0
        self.mine: set[bytes] = set()
        self.forged = {
            msg.arbitration_id: msg.data
            for msg in (
                codec.encode(SteerCommand(0.1, enable=True)),
                codec.encode(LongCommand(accel=1.5, enable=True)),
            )
        }

    def on_message_received(self, msg: can.Message) -> None:
        data = self.forged.get(msg.arbitration_id)
        if data is None or msg.is_extended_id or bytes(msg.data) in self.mine:
            return
        counter = (e2e.counter_of(msg.data) + 1) % e2e.COUNTER_MODULO
        forged = can.Message(
            arbitration_id=msg.arbitration_id,
            data=e2e.apply(msg.arbitration_id, data, counter),
            is_extended_id=False,
        )
        self.mine.add(bytes(forged.data))  # its own echo is not the gateway's frame
        self.bus.send(forged)
        self.run.excluded[(forged.arbitration_id, bytes(forged.data))] += 1
        self.sent += 1


def test_replayed_stream_racing_the_gateway_never_drives_the_car(
    make_run: Callable[..., FaultRun],
) -> None:
    run = make_run("replayed stream races the gateway's counters")
    with run.start():
        dbw = run.cfg["can"]["dbw"]
        time.sleep(1.0)  # the gateway in STANDBY, sending ENABLE=0
        bus = can.Bus(interface="udp_multicast", channel=dbw["channel"], port=dbw["kwargs"]["port"])
        racer = Racer(bus, run)
        notifier = can.Notifier(bus, [racer], timeout=0.05)
        started = run.sniffer_time()
        try:
            run.wait_for("the attack", lambda: run.sniffer_time() >= started + ATTACK, 30)
        finally:
            notifier.stop()
            bus.shutdown()
        system = run.sniffer.system if run.sniffer is not None else None
        status = run.status()
        run.shutdown()

    rows, _ = read_trace(run.trace)
    after = rows[rows[:, 6] >= started]
    moved = float(np.hypot(after[:, 1] - after[0, 1], after[:, 2] - after[0, 2]).max())
    top_speed = float(np.abs(after[:, 4]).max())
    outcome = run.outcome(started, status=status)
    outcome.extra.update(
        forged_frames=racer.sent, moved_m=round(moved, 3), top_speed_mps=round(top_speed, 3)
    )
    outcome.report()
    assert racer.sent > 50, racer.sent  # the race really ran
    assert moved <= MOVED, (moved, top_speed)
    assert top_speed < 0.1
    assert system is not None and system.state == EcuState.FAULT  # the ECU saw the race
    assert status["state"] == "FAULT" and "command conflict" in status["reason"], status
