"""The CAN receiver: decodes frames on python-can's Notifier thread into latest-value slots,
and tells the gateway's own echoes from foreign frames on its command IDs (``SentFrames``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from leafgate.can.codec import CanCodec, Decoded
from leafgate.messages import (
    LongReport,
    Stamped,
    SteerReport,
    SystemReport,
)
from leafgate.runtime.slots import LatestSlot

log = logging.getLogger(__name__)


# s a sent frame waits for its echo. Loopback delivers in well under a millisecond, but the
# Notifier thread may be starved for far longer on a loaded machine; a late echo must not count
# as foreign. A foreign frame byte-identical to one we sent within this window passes as ours.
# s, how far back a frame's own receive timestamp (python-can ``msg.timestamp``, wall clock) is
# believed; a timestamp older than this, in the future or unset counts as "received now".
TIMESTAMP_TRUST = 10.0
CLOCK_READS = 4  # bracketed readings of the two clocks at most, per frame
CLOCK_BRACKET = 2e-4  # s, a bracket this narrow is taken at once
ECHO_WINDOW = 2.0

FOREIGN_LOGGED = 20  # foreign frames logged one by one, then every thousandth

# A starved receive thread loses frames: the socket's buffer fills while nobody reads it and the
# kernel drops what arrives meanwhile, so the next frame of every ID skips its alive counter.
# Such a skip is a lost frame, not an ECU error (issue 17, finding 7), when its ID's frame was
# read at least STALL_LAG late (the one before it or itself) AND its receive time follows the
# one before by more than STALL_GAP of the ID's usual interval (the frames between are missing).
STALL_LAG = 0.05  # s
STALL_GAP = 1.5  # usual intervals


class _Sent:
    """One frame sent, waiting for its echo."""

    __slots__ = ("key", "taken", "time")

    def __init__(self, time: float, key: tuple[int, bytes]) -> None:
        self.time = time  # s, when it was sent
        self.key = key
        self.taken = False  # its echo came back


class SentFrames:
    """The command frames sent in the last ``window`` seconds, to recognise their echoes.

    Written by the control thread (:meth:`add`, before the send) and read by the Notifier
    thread (:meth:`take`). Frames are keyed by ``(ID, data)``; the same key recurs (a STANDBY
    frame repeats whenever its 4-bit alive counter wraps), so each key holds its sent frames in
    order and an echo takes the oldest one still waiting.

    :param window: s a sent frame waits for its echo
    """

    def __init__(self, window: float = ECHO_WINDOW) -> None:
        self.window = window
        self._lock = threading.Lock()
        self._waiting: dict[tuple[int, bytes], deque[_Sent]] = {}
        self._order: deque[_Sent] = deque()  # every frame of the window, oldest first

    def add(self, msg: can.Message, now: float) -> None:
        """Remember a frame about to be sent at ``now``."""
        sent = _Sent(now, (msg.arbitration_id, bytes(msg.data)))
        with self._lock:
            self._expire(now)
            self._order.append(sent)
            waiting = self._waiting.get(sent.key)
            if waiting is None:
                self._waiting[sent.key] = deque((sent,))
            else:
                waiting.append(sent)

    def take(self, msg: can.Message, now: float) -> bool:
        """True (and forgotten) when ``msg`` is the echo of a frame we sent."""
        key = (msg.arbitration_id, bytes(msg.data))
        with self._lock:
            self._expire(now)
            waiting = self._waiting.get(key)
            if not waiting:
                return False
            waiting.popleft().taken = True
            if not waiting:
                del self._waiting[key]
            return True

    def __len__(self) -> int:
        """Frames still waiting for their echo."""
        with self._lock:
            return sum(len(w) for w in self._waiting.values())

    def _expire(self, now: float) -> None:
        order = self._order
        while order and now - order[0].time > self.window:
            sent = order.popleft()
            if sent.taken:
                continue
            # The oldest frame of the window still waiting is the oldest waiting for its key.
            waiting = self._waiting[sent.key]
            waiting.popleft()
            if not waiting:
                del self._waiting[sent.key]


class CanReceiver(can.Listener):
    """Decodes report frames on the Notifier thread into latest-value slots.

    Frames on the gateway's own command IDs are not decoded: an echo of one we sent is dropped,
    any other is counted as foreign (and handed to the recorder hook, as evidence).
    """

    def __init__(
        self,
        codec: CanCodec,
        clock: Callable[[], float],
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.codec = codec
        self.clock = clock
        self.wall_clock = wall_clock
        self.command_ids = codec.receive_ids("commands")
        self.sent = SentFrames()
        self.horizon = -math.inf  # s, receive time of the newest frame read (any ID)
        self.own_echoes = 0  # echoes of our own frames received (udp_multicast delivers them)
        self.foreign_total = 0  # foreign frames on our command IDs since start
        self._foreign = 0  # … since the last take_foreign()
        self._foreign_ids: set[int] = set()
        self.steer: LatestSlot[SteerReport] = LatestSlot()
        self.long: LatestSlot[LongReport] = LatestSlot()
        self.system: LatestSlot[SystemReport] = LatestSlot()
        self.car: dict[str, LatestSlot[Any]] = {}
        self._lock = threading.Lock()
        self._good = 0
        self._bad = 0
        #: counter skips taken as frames lost in a receive stall (STALL_LAG), not counted as
        #: report errors; each stands for one or more lost frames of its ID
        self.stall_skips = 0
        # per ID: receive time and read lag of its last frame, its usual interval (s, 0 until
        # known), and whether a stall has been excused since its last good frame
        self._rx_timing: dict[int, list[Any]] = {}
        # the profile's send period of each periodic report, the usual interval until the
        # frames have shown theirs: a stall right after the first frame of an ID (start-up,
        # while the daemon opens Zenoh and builds the controller) skipped six counters at once
        # with no interval known, and latched a FAULT no ECU caused
        profile = codec.profile
        self._nominal = {
            codec.frame_id(spec.name): spec.period
            for spec in profile.frames_of("report")
            if not spec.on_change
        }
        self.on_frame: Callable[[can.Message, Decoded], None] | None = None  # recorder hook

    def received_at(self, msg: can.Message) -> float:
        """When ``msg`` arrived, on :attr:`clock`: from its receive timestamp, not from now.

        python-can stamps a frame when the interface receives it (the kernel's timestamp on
        SocketCAN, the datagram's arrival on ``udp_multicast``), on the wall clock. A Notifier
        thread that gets to a frame late must not make the ECU's report look stale (issue 17,
        finding 7), nor the echo of our own frame look foreign after a stall: the frame's age
        is taken from its timestamp and subtracted from now on the monotonic clock.
        """
        received = msg.timestamp - self._wall_minus_mono()
        now = self.clock()
        if msg.timestamp > 0.0 and 0.0 <= now - received <= TIMESTAMP_TRUST:
            return received
        return now

    def _wall_minus_mono(self) -> float:
        """The wall clock minus :attr:`clock`, s, from the tightest of a few bracketed readings
        (wall, monotonic, wall): a thread preempted between two clock reads must not move a
        frame's receive time by the length of the preemption, which on a loaded machine is tens
        of milliseconds, a report-age FAULT by itself."""
        best, offset = math.inf, 0.0
        for _ in range(CLOCK_READS):
            before = self.wall_clock()
            mono = self.clock()
            width = self.wall_clock() - before
            if width < best:
                best, offset = width, before + 0.5 * width - mono
                if width <= CLOCK_BRACKET:
                    break
        return offset

    def _lost_in_stall(self, frame_id: int, received: float, lag: float, valid: bool) -> bool:
        """Whether a bad-counter frame follows a receive stall (see STALL_LAG); also keeps the
        ID's timing for the next frame. One skip per ID is excused per stall: a second bad
        counter before a good frame (two senders taking turns, a replay) stays an error."""
        timing = self._rx_timing.get(frame_id)
        if timing is None:
            self._rx_timing[frame_id] = [received, lag, 0.0, False]
            return False
        last, last_lag, interval, excused = timing
        usual = interval if interval > 0.0 else self._nominal.get(frame_id, 0.0)
        gap = received - last
        timing[0], timing[1] = received, lag
        if valid:
            if gap > 0.0:  # the usual interval, from frames that arrived in turn
                timing[2] = gap if interval == 0.0 else 0.9 * interval + 0.1 * gap
            timing[3] = False
            return False
        stalled = max(lag, last_lag) > STALL_LAG and usual > 0.0 and gap > STALL_GAP * usual
        if stalled and not excused:
            timing[3] = True
            return True
        return False

    def on_message_received(self, msg: can.Message) -> None:
        read = self.clock()
        now = self.received_at(msg)
        if now > self.horizon:
            self.horizon = now
        if msg.arbitration_id in self.command_ids and not msg.is_extended_id:
            if self.sent.take(msg, now):
                self.own_echoes += 1
                return
            with self._lock:
                self._foreign += 1
                self.foreign_total += 1
                self._foreign_ids.add(msg.arbitration_id)
                total = self.foreign_total
            if total <= FOREIGN_LOGGED or total % 1000 == 0:
                log.warning(
                    "foreign frame on our command ID 0x%03X: %s (%d so far)",
                    msg.arbitration_id,
                    bytes(msg.data).hex(" "),
                    total,
                )
            if self.on_frame is not None:
                # not decoded: the codec's alive-counter state belongs to our own frames
                name = self.codec.name_of(msg.arbitration_id)
                self.on_frame(msg, Decoded(msg.arbitration_id, name, None, False, None))
            return
        decoded = self.codec.decode(msg)
        if self.on_frame is not None:
            self.on_frame(msg, decoded)
        values = decoded.values  # a frame may refresh several messages
        if decoded.counts_for_reports:
            lost = (decoded.error == "bad_counter" or decoded.valid) and self._lost_in_stall(
                msg.arbitration_id, now, read - now, decoded.valid
            )
            with self._lock:
                if decoded.valid:
                    self._good += 1
                elif lost:
                    self.stall_skips += 1
                else:
                    self._bad += 1
        if not decoded.valid:
            return
        for value in values:
            if isinstance(value, SteerReport):
                self.steer.put(Stamped(value, now))
            elif isinstance(value, LongReport):
                self.long.put(Stamped(value, now))
            elif isinstance(value, SystemReport):
                self.system.put(Stamped(value, now))
            else:
                self.car.setdefault(type(value).__name__, LatestSlot()).put(Stamped(value, now))

    def car_value(self, kind: str) -> Stamped[Any] | None:
        """The latest CAR-CAN value of a message type (``"WheelSpeeds"`` …), None if none yet."""
        slot = self.car.get(kind)
        return slot.get() if slot is not None else None

    def take_counts(self) -> tuple[int, int]:
        """Good and bad report frames since the last call."""
        with self._lock:
            good, bad = self._good, self._bad
            self._good = self._bad = 0
        return good, bad

    def take_foreign(self) -> tuple[int, tuple[str, ...]]:
        """Foreign frames on our command IDs since the last call, and their DBC names."""
        with self._lock:
            count, ids = self._foreign, self._foreign_ids
            self._foreign, self._foreign_ids = 0, set()
        if not count:
            return 0, ()
        return count, tuple(sorted(self.codec.name_of(i) or f"0x{i:03X}" for i in ids))

    def on_error(self, exc: Exception) -> None:
        log.error("CAN receive error: %s", exc)


def _watch_ids(bus: can.BusABC, ids: frozenset[int]) -> None:
    """Widen ``bus``'s receive filter by ``ids`` (no-op when it delivers everything already)."""
    filters = bus.filters
    if filters is None or not ids:
        return
    extra = [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(ids)]
    bus.set_filters([*filters, *extra])  # type: ignore[list-item]
