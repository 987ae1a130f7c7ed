"""Counter skips after a receive stall are lost frames, not ECU errors (issue 17, finding 7).

On a loaded machine the CAN receive thread is starved, its socket fills, and the kernel drops the
frames that arrive meanwhile: the next frame of every report ID then skips its alive counter.
Before, each skip counted as a report error, and six IDs at once reached the limit of five: a
FAULT no ECU caused. Now a skip whose ID was read late (python-can's receive timestamp against
the clock) and whose receive time leaves a gap of missing frames is counted apart
(``stall_skips``). A skip without a stall, or a second bad counter before a good frame, stays
an error.
"""

from __future__ import annotations

import can

from leafgate.can.codec import CanCodec
from leafgate.messages import SteerReport
from leafgate.runtime.receiver import STALL_LAG, CanReceiver

EPOCH = 1_700_000_000.0  # s, the wall clock of python-can's receive timestamps
PERIOD = 0.010  # s, DBW_STEER_RPT


class Clocks:
    """The receiver's monotonic clock and the wall clock, moved together by the test."""

    def __init__(self) -> None:
        self.now = 100.0

    def mono(self) -> float:
        return self.now

    def wall(self) -> float:
        return EPOCH + self.now


def steer(ecu: CanCodec) -> can.Message:
    return ecu.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False))


def rig() -> tuple[Clocks, CanReceiver, CanCodec]:
    clocks = Clocks()
    receiver = CanReceiver(CanCodec(profile="leafgate-dbw"), clocks.mono, clocks.wall)
    return clocks, receiver, CanCodec(profile="leafgate-dbw")


def deliver(receiver: CanReceiver, clocks: Clocks, msg: can.Message, arrived: float) -> None:
    """``msg`` arrived (kernel timestamp) at ``arrived`` and is read now (``clocks.now``)."""
    msg.timestamp = EPOCH + arrived
    receiver.on_message_received(msg)


def prompt(receiver: CanReceiver, clocks: Clocks, ecu: CanCodec, frames: int) -> None:
    """``frames`` reports every 10 ms, each read as it arrives."""
    for _ in range(frames):
        clocks.now += PERIOD
        deliver(receiver, clocks, steer(ecu), clocks.now)


def test_frames_lost_while_the_receive_thread_was_starved_are_no_report_errors() -> None:
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 20)
    start = clocks.now
    buffered = [steer(ecu) for _ in range(10)]  # arrive in the socket while nobody reads …
    lost = [steer(ecu) for _ in range(15)]  # … then the socket is full: dropped by the kernel
    assert lost
    clocks.now = start + 0.3  # the thread wakes up 300 ms late and reads the backlog
    for k, msg in enumerate(buffered, start=1):
        deliver(receiver, clocks, msg, start + k * PERIOD)
    clocks.now = start + 26 * PERIOD
    deliver(receiver, clocks, steer(ecu), clocks.now)  # the first frame after the drop: a skip
    prompt(receiver, clocks, ecu, 5)
    good, bad = receiver.take_counts()
    assert bad == 0  # counted as a report error before: six IDs at once → FAULT
    assert receiver.stall_skips == 1
    assert good == 20 + 10 + 5


def test_a_skip_without_a_stall_stays_an_error() -> None:
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 20)
    steer(ecu)  # never delivered, yet the thread was never late: a sender skipping, or a forgery
    prompt(receiver, clocks, ecu, 1)
    assert receiver.take_counts()[1] == 1
    assert receiver.stall_skips == 0


def test_a_late_thread_without_a_gap_excuses_nothing() -> None:
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 20)
    forger = CanCodec(profile="leafgate-dbw")  # a second sender with a counter of its own
    for _ in range(3):
        forger.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False))
    clocks.now += PERIOD
    arrived = clocks.now
    clocks.now += 2 * STALL_LAG  # read late, but right after the genuine frame: no gap
    deliver(receiver, clocks, steer(forger), arrived - PERIOD / 2)
    assert receiver.take_counts()[1] == 1
    assert receiver.stall_skips == 0


def test_only_one_skip_per_id_is_excused_per_stall() -> None:
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 20)
    start = clocks.now
    for _ in range(20):
        steer(ecu)  # lost
    clocks.now = start + 0.3
    deliver(receiver, clocks, steer(ecu), start + 0.21)  # read late after a gap: excused
    forger = CanCodec(profile="leafgate-dbw")
    deliver(receiver, clocks, steer(forger), start + 0.25)  # a second bad counter: an error
    assert receiver.stall_skips == 1
    assert receiver.take_counts()[1] == 1


class PreemptedClocks(Clocks):
    """The thread is preempted for ``pause`` s right after its first monotonic read."""

    def __init__(self, pause: float) -> None:
        super().__init__()
        self.pause = pause

    def mono(self) -> float:
        now = self.now
        if self.pause:
            self.now, self.pause = self.now + self.pause, 0.0  # the next read comes later
        return now


def test_a_preemption_between_two_clock_reads_does_not_age_a_frame() -> None:
    # before: age = wall() - timestamp, read after now = clock(); a 40 ms preemption between
    # the two made a frame just received 40 ms old (a report-age FAULT on a loaded machine)
    clocks = PreemptedClocks(pause=0.040)
    receiver = CanReceiver(CanCodec(profile="leafgate-dbw"), clocks.mono, clocks.wall)
    msg = steer(CanCodec(profile="leafgate-dbw"))
    msg.timestamp = clocks.wall() - 0.002  # arrived 2 ms ago
    arrived = clocks.now - 0.002
    assert abs(receiver.received_at(msg) - arrived) < 1e-6  # epoch floats: 0.2 µs steps


def test_a_stall_right_after_the_first_frame_is_judged_by_the_profiles_period() -> None:
    """At start-up (Zenoh opening, the controller built) the receive thread stalled after the
    first report of each ID, before any interval was measured: old code counted each ID's skip
    as a report error, six at once, and the daemon latched FAULT before anyone engaged. The
    profile's send period stands in until the frames show theirs."""
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 1)
    start = clocks.now
    for _ in range(20):
        steer(ecu)  # dropped while nobody read
    clocks.now = start + 0.3
    deliver(receiver, clocks, steer(ecu), start + 0.21)
    assert receiver.take_counts()[1] == 0
    assert receiver.stall_skips == 1


def test_a_skip_right_after_the_first_frame_without_a_stall_stays_an_error() -> None:
    clocks, receiver, ecu = rig()
    prompt(receiver, clocks, ecu, 1)
    steer(ecu)  # not delivered, the thread on time: a sender skipping
    prompt(receiver, clocks, ecu, 1)
    assert receiver.take_counts()[1] == 1
    assert receiver.stall_skips == 0
