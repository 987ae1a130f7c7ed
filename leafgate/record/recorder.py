"""Recording a drive: CAN logs in python-can formats and whole sessions in MCAP.

The hooks are called from the threads that see the data — the python-can Notifier thread
(received frames), Zenoh callback threads (inputs) and the control thread (ticks and sent
frames). They only put an item on a bounded queue and return: a writer thread per file does
the encoding and the disk I/O, so a slow disk never delays a control tick. When the queue is
full, items are dropped and counted, and marked in the file where they were lost, written in
time order with the rest (drops close together, while the mark is still held back to be
ordered, are one mark): frames by a drop marker (:func:`~leafgate.record.logs.drop_marker`)
at the first dropped frame's time, with how many and over how long; a session's ticks and
Zenoh inputs by a ``/leafgate/lost`` record (:meth:`~leafgate.record.session.SessionWriter.lost`)
saying how many of which, from when to when. A session's ticks are numbered too (``seq``), so
a reader sees every tick missing from the file. So a check of the file tells the recorder's
loss from a silent bus or a skipped counter, and a re-run knows where it cannot go on.

Crash safety: the writer thread makes the file readable up to the last item every
``flush_period`` (≤ 1 s): the MCAP chunk in progress is closed, the BLF container in progress
is compressed and written and the BLF header updated, text formats are flushed. A clean
:meth:`close` finishes every file properly (MCAP summary and footer, BLF header).

Disk full, an unwritable directory, any write error: the recorder's :attr:`fault` says what
and where and its counters grow; nothing is raised into the caller's thread — the control loop
keeps running. The failed file is given up as it is (no end marker: ``replay check`` calls it
incomplete; nothing is appended after a broken tail) and items are dropped and counted. Every
``retry_period`` the writer starts a new file (the CAN log's next part, the session's
``<name>.2.mcap`` …); once that works the fault clears, and a warning says how many items the
outage lost. A full disk is a fault while it lasts, not until the daemon restarts.

Wiring (daemon)::

    recording = open_recording(config.recording, config, clock=runtime_clock)
    receiver.on_frame = lambda msg, decoded: recording.on_can_frame(msg, "rx")
    runtime = Runtime(..., on_tick=recording.on_tick,
                      extra_diagnostics=lambda: {"recording": recording.diagnostics()})
    # each Zenoh input sample: recording.on_zenoh_input(key, payload, received, typename)
    ...
    recording.close()   # after the runtime has stopped
"""

from __future__ import annotations

import heapq
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import IO, Any, Final, Generic, Literal, Protocol, Self, TypeVar

import can
import numpy as np

from leafgate.can.bus import copy_frame
from leafgate.config.recording import CAN_LOG_SUFFIXES, RecordingConfig
from leafgate.control.base import Controller
from leafgate.gateway.core import GatewayInputs, StepResult
from leafgate.messages import ControlOutput, Pose, Trajectory
from leafgate.record.logs import (
    DROP_MAX_FRAMES,
    DROP_MAX_SPAN,
    drop_marker,
    end_marker,
    is_end_marker,
)
from leafgate.record.session import SessionWriter, epoch_offset
from leafgate.settings import LeafgateConfig

__all__ = [
    "CanLogRecorder",
    "ControllerTap",
    "Direction",
    "Recorder",
    "Recording",
    "SessionRecorder",
    "end_marker",
    "is_end_marker",
    "open_recording",
]

log = logging.getLogger(__name__)

Direction = Literal["rx", "tx"]
_STOP: Final = object()
_ROTATE_CHECK_EVERY: Final = 256  # frames between file-size checks (tell() is not free)
DEFAULT_REORDER_WINDOW: Final = 0.25  # s, twice the worst disorder measured under load
_ITEM_OVERHEAD: Final = 200  # bytes counted per queued item besides its payloads
DEFAULT_RETRY_PERIOD: Final = 2.0  # s between attempts at a new file after a write failure


def _item_bytes(item: Any) -> int:
    """Rough size of a queued item: its payload bytes plus a fixed overhead."""
    if isinstance(item, can.Message):
        return _ITEM_OVERHEAD + len(item.data)
    if isinstance(item, tuple):
        return _ITEM_OVERHEAD + sum(len(x) for x in item if isinstance(x, (bytes, bytearray)))
    return _ITEM_OVERHEAD


#: What a dropped item was: a CAN frame, a session's control tick, a session's Zenoh input.
DropKind = Literal["can", "tick", "zenoh"]


class _Drops:
    """Items of one kind dropped when the queue overflowed: how many, the first and last one's
    time (s), and for Zenoh inputs how many of each key. One mark in the file (a frames' drop
    marker holds at most what a marker can say; a lost record the same, to keep them alike)."""

    __slots__ = ("count", "first", "keys", "kind", "last", "written")

    def __init__(self, kind: DropKind, t: float, key: str | None = None) -> None:
        self.kind = kind
        self.first = self.last = t
        self.count = 1
        self.keys: dict[str, int] = {} if key is None else {key: 1}
        self.written = False  # its mark is in the file: nothing more is added

    def absorb(self, other: _Drops) -> bool:
        """Add ``other``'s items when one mark can say both (False: it cannot)."""
        first, last = min(self.first, other.first), max(self.last, other.last)
        if (
            other.kind != self.kind
            or last - first > DROP_MAX_SPAN
            or self.count + other.count > DROP_MAX_FRAMES
        ):
            return False
        self.first, self.last = first, last
        self.count += other.count
        for key, n in other.keys.items():
            self.keys[key] = self.keys.get(key, 0) + n
        return True

    def marker(self, t: float, channel: Any = None) -> can.Message:
        """The frames' drop marker, written at ``t`` (its first frame's time, unless it came
        late)."""
        self.written = True
        return drop_marker(t, max(self.last, t), self.count, channel)


class Recorder(Protocol):
    """What the simulator and the runtime call; every method returns at once."""

    def on_can_frame(self, msg: can.Message, direction: Direction) -> None: ...

    def on_tick(
        self, now: float, inputs: GatewayInputs, result: StepResult, frames: Sequence[can.Message]
    ) -> None: ...

    def wrap_controller(self, controller: Controller) -> Controller: ...


class ControllerTap:
    """A transparent controller wrapper that keeps the last :class:`ControlOutput`.

    The gateway's :class:`~leafgate.gateway.core.StepResult` carries the controller's figures
    but not its predicted path; wrapping the controller lets the session record it. Behaviour
    is unchanged: every call goes to the wrapped controller.
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.period = controller.period
        self.last_output: ControlOutput | None = None

    def reset(self) -> None:
        self.controller.reset()

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        out = self.controller.step(pose, steer_angle, trajectory)
        self.last_output = out
        return out

    def take(self) -> ControlOutput | None:
        """The output since the last take (None when the controller did not run)."""
        out, self.last_output = self.last_output, None
        return out


class _BackgroundWriter:
    """A bounded queue drained by one thread that writes, flushes on time and closes.

    :param name: thread name and the start of every fault message
    :param write: called on the thread for each item; returns how many items it wrote to the
        file (a writer that holds items back to order them writes them later)
    :param flush: makes everything written so far durable in the file
    :param close: finishes the file
    :param reopen: gives the failed file up (no end marker) and starts a new one; raises when
        it cannot. None: a failure is final
    :param abandon: closes the failed file without finishing it (on :meth:`close`)
    :param retry_period: s between attempts at :param:`reopen` while failing
    :param dropped: what a queued item is and its time (s), with a Zenoh input's key (else
        None); None for an item whose loss is not marked: an item dropped when the queue is
        full is marked in the file (the frames the recorder lost are not a silent bus, the
        ticks it lost not a drive that went on unseen)
    :param mark: called on the thread with the items of one kind dropped since its last
        call, to write their mark in time order; returns how many items it wrote (as
        ``write``)
    """

    def __init__(
        self,
        name: str,
        write: Callable[[Any], int],
        flush: Callable[[], None],
        close: Callable[[], None],
        flush_period: float,
        queue_size: int,
        drain: Callable[[], int] | None = None,
        queue_bytes: int = 64 * 1024 * 1024,
        reopen: Callable[[], None] | None = None,
        abandon: Callable[[], None] | None = None,
        retry_period: float = DEFAULT_RETRY_PERIOD,
        dropped: Callable[[Any], tuple[DropKind, float, str | None] | None] | None = None,
        mark: Callable[[_Drops], int] | None = None,
    ) -> None:
        self.name = name
        self._dropped = dropped
        self._mark = mark
        self._drops: list[_Drops] = []  # items dropped since the thread last took them
        # per kind, the last marked, maybe not written yet
        self._held_drops: dict[DropKind, _Drops] = {}
        # items dropped as the queue overflowed, by kind (each in a mark in the file):
        # ``overflowed`` the frames, ``overflowed_ticks`` and ``overflowed_inputs`` a session's
        self._overflowed: dict[DropKind, int] = {"can": 0, "tick": 0, "zenoh": 0}
        self._reopen = reopen
        self._abandon = abandon
        self.retry_period = retry_period
        self._retry_at = 0.0  # monotonic s of the next attempt at a new file
        self._failed_since = 0.0  # monotonic s
        self._dropped_at_failure = 0
        self.recoveries = 0  # new files started after a failure
        # items lost to the failures recovered from: dropped during the outage, and those
        # written since the last flush before it (the failed file may not hold them)
        self.lost = 0
        self._unflushed = 0  # items written to the file since the last flush
        self._lost_unflushed = 0  # … when the failure came
        self._outage_fault = ""  # the fault that began the outage
        # from a failure until a new file has flushed what was written to it: the fault holds
        self._outage = False
        self.last_fault = ""  # the last fault, kept after it cleared
        self.queue_bytes = queue_bytes
        self._bytes = 0  # bytes of the items queued now (approximate, _item_bytes)
        self._write = write
        self._flush = flush
        self._close = close
        self._drain = drain  # writes what the writer holds back, on a flush request
        self._period = flush_period
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self._lock = threading.Lock()
        self.fault = ""  # the last problem, "" while healthy
        self.failed = False  # the file was given up after a write error
        self.errors = 0  # write/flush/close errors
        self.dropped = 0  # items not written (queue full, or after a failure)
        self.dropped_bytes = 0  # … of which over the byte bound, their bytes
        self.written = 0
        self.flushes = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: Any) -> None:
        """Queue an item; never blocks."""
        if self.failed or self._closed:
            self.dropped += 1
            return
        size = _item_bytes(item)
        with self._lock:
            if self._bytes + size > self.queue_bytes:
                self.dropped += 1
                self.dropped_bytes += size
                self._overflow(item)
                return
            self._bytes += size
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._bytes -= size
                self.dropped += 1
                self._overflow(item)

    @property
    def overflowed(self) -> int:
        """Frames dropped as the queue overflowed (each in a drop marker)."""
        return self._overflowed["can"]

    def _overflow(self, item: Any) -> None:
        """Note an item dropped as the queue overflowed, for its mark (lock held)."""
        what = None if self._dropped is None or self._mark is None else self._dropped(item)
        if what is None or not math.isfinite(what[1]):
            return
        kind, t, key = what
        self._overflowed[kind] += 1
        drops = _Drops(kind, t, key)
        last = next((d for d in reversed(self._drops) if d.kind == kind), None)
        if last is None or not last.absorb(drops):
            self._drops.append(drops)

    def _take_drops(self) -> int:
        """Mark the items dropped since the last call (writer thread): added to the mark of
        their kind still held back to be ordered when it can say them too, else a new mark."""
        if not self._drops or self._mark is None:
            return 0
        with self._lock:
            taken, self._drops = self._drops, []
        written = 0
        for drops in taken:
            held = self._held_drops.get(drops.kind)
            # held back at its first item's time: it can take later items, not earlier ones
            if (
                held is not None
                and not held.written
                and drops.first >= held.first
                and held.absorb(drops)
            ):
                continue
            self._held_drops[drops.kind] = drops
            written += self._mark(drops)
        return written

    def fail(self, what: str, exc: BaseException) -> None:
        """Record a fault; an OSError (disk full, permissions …) gives the file up."""
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        self.fault = f"{self.name}: {what}: {reason or type(exc).__name__}"
        self.last_fault = self.fault
        self.errors += 1
        if isinstance(exc, OSError):
            with self._lock:  # dropped before the outage: lost with it, between the files
                self._drops.clear()
            self._held_drops.clear()
            now = time.monotonic()
            if not self._outage:  # a new outage (a new file failing before its first flush
                self._outage = True  # goes on with the one that made it)
                self._failed_since = now
                self._dropped_at_failure = self.dropped
                self._lost_unflushed = 0
                self._outage_fault = self.fault
            if not self.failed:
                self.failed = True
                self._lost_unflushed += self._unflushed
                self._unflushed = 0
                self._retry_at = now + self.retry_period
            log.warning("recording failed, the file is given up: %s", self.fault)
        else:
            log.warning("recording problem: %s", self.fault)

    def _guarded(self, what: str, fn: Callable[[], Any]) -> Any:
        if self.failed:
            return None
        try:
            return fn()
        except Exception as exc:  # nothing may escape into (or kill) the writer thread
            self.fail(what, exc)
            return None

    def _run(self) -> None:
        period = self._period
        next_flush = time.monotonic() + period
        dirty = False
        while True:
            timeout = max(0.0, next_flush - time.monotonic())
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is _STOP:
                self._guarded("write", self._take_drops)
                break
            if item is not None and not isinstance(item, threading.Event):
                with self._lock:
                    self._bytes -= _item_bytes(item)
            if item is not None and self._drops:  # before what came after them
                self._unflushed += self._guarded("write", self._take_drops) or 0
            if isinstance(item, threading.Event):  # a flush request
                if self._drain is not None:
                    self._unflushed += self._guarded("write", self._drain) or 0
                if dirty:
                    self._flushed()
                    dirty = False
                item.set()
                continue
            if item is not None:
                if self.failed:
                    self.dropped += 1
                else:
                    try:
                        self._unflushed += self._write(item)
                        self.written += 1
                        dirty = True
                    except Exception as exc:
                        self.fail("write", exc)
            now = time.monotonic()
            if now >= next_flush:
                if dirty:
                    self._flushed()
                    dirty = False
                next_flush = now + period
            if self.failed and self._reopen is not None and now >= self._retry_at:
                self._retry(now)
        if self.failed and self._abandon is not None:
            try:
                self._abandon()
            except Exception as exc:  # the failed file is given up anyway
                log.debug("closing a failed recording: %s", exc)
        self._guarded("close", self._close)

    def _flushed(self) -> None:
        self._guarded("flush", self._flush)
        self.flushes += 1
        if not self.failed:
            self._unflushed = 0
            if self._outage:
                self._recovered()

    def _retry(self, now: float) -> None:
        """One attempt at a new file after a failure (bounded to one per retry period)."""
        assert self._reopen is not None
        self._retry_at = now + self.retry_period
        try:
            self._reopen()
        except Exception as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            self.fault = f"{self.name}: new file: {reason or type(exc).__name__}"
            self.last_fault = self.fault
            self.errors += 1
            return
        # the fault holds until items written to the new file have been flushed: a header
        # may fit on a disk where the data does not
        self.failed = False

    def _recovered(self) -> None:
        """Writing works again: clear the fault and say what the outage lost."""
        now = time.monotonic()
        self._outage = False
        dropped = self.dropped - self._dropped_at_failure
        self.lost += dropped + self._lost_unflushed
        self.recoveries += 1
        log.warning(
            "recording resumed in a new file after %.1f s: %d items dropped, and up to %d "
            "written before the failure may be missing from the failed file (%s)",
            now - self._failed_since,
            dropped,
            self._lost_unflushed,
            self._outage_fault,
        )
        self.fault = ""

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is written and flushed (for tests and tools)."""
        if self._closed:
            return False
        done = threading.Event()
        try:
            self._queue.put(done, timeout=timeout)
        except queue.Full:
            return False
        return done.wait(timeout)

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued, finish the file and stop the thread."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join(timeout)

    def counters(self) -> dict[str, Any]:
        return {
            "written": self.written,
            "dropped": self.dropped,
            "errors": self.errors,
            "flushes": self.flushes,
            "queued": self._queue.qsize(),
            "queued_bytes": self._bytes,
            "dropped_bytes": self.dropped_bytes,
            "overflowed": self.overflowed,
            "overflowed_ticks": self._overflowed["tick"],
            "overflowed_inputs": self._overflowed["zenoh"],
            "fault": self.fault,
            "recoveries": self.recoveries,
            "lost": self.lost,
            "last_fault": self.last_fault,
        }


class _BlfWriter(can.BLFWriter):
    """python-can's BLF writer with a flush that leaves a readable file behind.

    ``BLFWriter`` writes a container only when 128 KiB are buffered and fills in the file
    header only in ``stop()``; here a flush writes the partial container and updates the
    header (start time, object count), so a crash loses nothing flushed. It uses two
    internals of python-can 4.x (``_flush``, ``_write_header``); tests cover them.
    """

    def flush(self) -> None:
        while self._buffer_size > 0:
            self._flush()
        if self.file.seekable():
            end = self.file.tell()
            self.file.seek(0)
            self._write_header(end)
            self.file.seek(end)
        self.file.flush()


class _AscWriter(can.ASCWriter):
    """python-can's ASC writer with the start time's milliseconds zero-padded.

    python-can 4.6 writes 31 ms as ``…:20.31``, which its own reader (and CANoe) read as
    310 ms: every absolute time in the file moves by up to a second.
    """

    FORMAT_DATE = "%a %b %d %H:%M:%S.{:03d} %Y"


#: Suffixes of the CAN log formats that store a channel number, not a name (python-can's
#: writers hold an integer: a name's trailing digits, + 1 in the file).
_NUMBERED_FORMATS: Final = (".blf", ".asc")


def _open_can_writer(path: Path, channel: str) -> can.io.generic.FileIOMessageWriter[Any]:
    """The writer for the suffix; ``channel`` names frames without one in ``.log`` files
    (BLF and ASC are given each frame's bus number: :meth:`CanLogRecorder._numbered`)."""
    if path.suffix.lower() == ".blf":
        return _BlfWriter(path)
    if path.suffix.lower() == ".log":
        return can.CanutilsLogWriter(path, channel=channel)
    return _AscWriter(path)


def _tx_copy(msg: can.Message, timestamp: float, channel: str) -> can.Message:
    return copy_frame(
        msg,
        timestamp=timestamp,
        channel=msg.channel if msg.channel is not None else channel,
        is_rx=False,
    )


def _close_quietly(file: IO[Any] | None) -> None:
    """Close a file given up after a write error; closing flushes, which fails again."""
    if file is None:
        return
    try:
        file.close()
    except Exception as exc:  # the descriptor is closed even when the flush fails
        log.debug("closing a failed recording file: %s", exc)


class _ClosedOnExit:
    """``with recorder:`` closes it at the end of the block."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _FileRecorder(_ClosedOnExit):
    """The control side both file recorders share: a :class:`_BackgroundWriter` owns the file;
    its fault, flush and close are the recorder's."""

    _bg: _BackgroundWriter

    @property
    def fault(self) -> str:
        """The last recording problem ("" while healthy)."""
        return self._bg.fault

    def flush(self, timeout: float = 5.0) -> bool:
        """Block until everything handed in so far is in the file (a crash now loses none)."""
        return self._bg.flush(timeout)

    def close(self) -> None:
        """Write what is queued and finish the file properly (MCAP summary, BLF header)."""
        self._bg.close()


T = TypeVar("T")


class _ReorderWindow(Generic[T]):
    """Items held back until one ``window`` s newer has arrived, then released in time order
    (equal times in arrival order): the one time order of the CAN log and the session, whose
    items come from several threads. An item older than the last one released is released at
    that time and counted in :attr:`late`."""

    def __init__(self, window: float) -> None:
        self.window = window
        self.late = 0
        self.last = -math.inf  # s, time of the last item released
        self._heap: list[tuple[float, int, T]] = []
        self._arrivals = 0
        self._newest = -math.inf  # s, the newest time pushed

    def push(self, t: float, item: T) -> list[tuple[float, T]]:
        """Hold ``item`` (at time ``t``, s); the items now older than the window, in order."""
        heapq.heappush(self._heap, (t, self._arrivals, item))
        self._arrivals += 1
        self._newest = max(self._newest, t)
        return self.release(self._newest - self.window)

    def discard(self) -> int:
        """Drop every item held (how many): those held when a file failed. Written to the next
        file they would be an island from before the outage, and the outage a hole inside that
        file, which no reader can tell from a silent bus; dropped, the recording's one hole is
        between the failed file and the next."""
        held = len(self._heap)
        self._heap.clear()
        return held

    def release(self, until: float = math.inf) -> list[tuple[float, T]]:
        """The items held with a time up to ``until``, each with the time to write it at."""
        out = []
        heap = self._heap
        while heap and heap[0][0] <= until:
            t, _, item = heapq.heappop(heap)
            if t < self.last:  # beyond the window: kept in order at the last time
                self.late += 1
                t = self.last
            self.last = t
            out.append((t, item))
        return out


class CanLogRecorder(_FileRecorder):
    """Every CAN frame in and out, in a python-can log file with size rotation.

    The format follows the suffix of ``path``: ``.blf`` (Vector binary logging), ``.log``
    (``candump -L``, which ``cantools decode`` reads) or ``.asc``. Files are numbered:
    ``can.blf`` is written as ``can_000.blf``, ``can_001.blf`` … each at most about
    ``max_bytes`` long.

    :param path: base file name; its directory is created
    :param max_bytes: rotate when a file reaches this size (0: never)
    :param flush_period: s between flushes (a crash loses at most this much)
    :param queue_size: frames waiting for the writer thread before frames are dropped
    :param tx_clock: stamps sent frames when given (the daemon passes ``time.time`` so sent
        frames share the clock of received ones); None keeps each frame's own timestamp
    :param channel: the drive-by-wire bus's channel name (``can.dbw.channel``), written for
        frames that carry none (sent frames)
    :param car_channel: CAR-CAN's channel name (``can.car.channel``), None without one
    :param one_bus: every frame is on one bus (the drive-by-wire and car frames share it):
        every frame is written under ``channel``, so one bus has one name in the log

    Channels (README, "Recording and replay"): ``.log`` (candump) writes a frame's bus by its
    configured name; BLF and ASC store a number, CAN 1 for the drive-by-wire bus (``channel``),
    CAN 2 for CAR-CAN (``car_channel``) and 3, 4 … for any other name a frame carries, in the
    order they appear (python-can reads them back 0-based: 0, 1 …).
    :param reorder_window: s; frames are written in time order: the writer holds each frame
        back until a frame this much newer has arrived (sent and received frames reach the
        recorder from different threads, up to ~0.12 s apart under load). A frame that
        arrives later than that is written at the last written time and counted as ``late``
        (diagnostics), so the log never goes backwards. A flush request (:meth:`flush`) and
        :meth:`close` write everything held back; the periodic flush does not.

    An unwritable directory is not raised: :attr:`fault` tells, and frames are counted as
    dropped.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        max_bytes: int = 0,
        flush_period: float = 1.0,
        queue_size: int = 20_000,
        tx_clock: Callable[[], float] | None = None,
        channel: str = "can0",
        car_channel: str | None = None,
        one_bus: bool = False,
        reorder_window: float = DEFAULT_REORDER_WINDOW,
        time_offset: float = 0.0,
        queue_bytes: int = 64 * 1024 * 1024,
        retry_period: float = DEFAULT_RETRY_PERIOD,
    ) -> None:
        self.path = Path(path)
        # s added to every frame's own timestamp (a simulated drive: simulated time → Unix time,
        # the same offset its session uses, so the log and the session line up)
        self.time_offset = time_offset
        if self.path.suffix.lower() not in CAN_LOG_SUFFIXES:
            raise ValueError(f"{self.path}: a CAN log must end in one of {CAN_LOG_SUFFIXES}")
        self.max_bytes = max_bytes
        self.tx_clock = tx_clock
        self.channel = channel
        self.one_bus = one_bus
        # the numbers BLF and ASC store, 0-based as python-can's writers take them
        self._numbers: dict[object, int] = {channel: 0, None: 0}  # none: the dbw bus
        if car_channel is not None and not one_bus:
            self._numbers.setdefault(car_channel, 1)
        self._numbered = self.path.suffix.lower() in _NUMBERED_FORMATS
        self.reorder_window = reorder_window
        self.files: list[Path] = []
        # frames (and drop markers) in time order; those that came after the window are
        # written re-stamped
        self._order: _ReorderWindow[can.Message | _Drops] = _ReorderWindow(reorder_window)
        self._writer: can.io.generic.FileIOMessageWriter[Any] | None = None
        self._part_frames = 0
        self._since_check = 0
        self._bg = _BackgroundWriter(
            f"can-log {self.path.name}",
            self._write,
            self._flush,
            self._finish,
            flush_period,
            queue_size,
            drain=self._drain,
            queue_bytes=queue_bytes,
            reopen=self._reopen,
            abandon=self._abandon,
            retry_period=retry_period,
            dropped=lambda msg: ("can", msg.timestamp, None),
            mark=self._mark_drops,
        )
        try:
            self._rotate()
        except Exception as exc:
            self._bg.fail(f"cannot open {self._next_name()}", exc)

    # -- hooks (any thread) --

    def on_can_frame(self, msg: can.Message, direction: Direction) -> None:
        """Record one frame; ``direction`` is ``"rx"`` (received) or ``"tx"`` (sent)."""
        if direction == "tx":
            stamp = self.tx_clock() if self.tx_clock is not None else msg.timestamp
            msg = _tx_copy(msg, stamp + self.time_offset, self.channel)
        elif self.time_offset:
            msg = copy_frame(msg, timestamp=msg.timestamp + self.time_offset)
        self._bg.put(msg)

    def on_tick(
        self, now: float, inputs: GatewayInputs, result: StepResult, frames: Sequence[can.Message]
    ) -> None:
        """Record the frames sent this tick."""
        for frame in frames:
            self.on_can_frame(frame, "tx")

    def on_zenoh_input(
        self, key: str, payload: bytes, received: float, typename: str | None = None
    ) -> None:
        """Zenoh inputs are not CAN frames: ignored here (the session records them)."""

    def wrap_controller(self, controller: Controller) -> Controller:
        """The controller unchanged (a CAN log records no controller internals)."""
        return controller

    # -- writer thread --

    def _next_name(self) -> Path:
        return self.path.with_name(f"{self.path.stem}_{len(self.files):03d}{self.path.suffix}")

    def _rotate(self) -> None:
        if self._writer is not None:
            writer, self._writer = self._writer, None
            self._mark_end(writer, continues=True)
            writer.stop()
        name = self._next_name()
        name.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _open_can_writer(name, self.channel)
        self._part_frames = 0  # frames written to the current part
        self.files.append(name)

    def _abandon(self) -> None:
        """Close the failed part as it is: no end marker, nothing more after its broken tail."""
        writer, self._writer = self._writer, None
        if writer is not None:
            _close_quietly(writer.file)

    def _reopen(self) -> None:
        """Give the failed part up and start the next one, with the first frame after the
        outage (:meth:`_ReorderWindow.discard`: one stretch lost, between the two parts)."""
        self._abandon()
        self._bg.dropped += self._order.discard()
        if self.files and self._part_frames == 0:
            # a part opened by an earlier attempt that failed before a frame: it holds nothing
            # of the drive, and its number is reused (no trail of empty parts in an outage)
            self.files.pop().unlink(missing_ok=True)
        name = self._next_name()
        name.parent.mkdir(parents=True, exist_ok=True)
        writer = _open_can_writer(name, self.channel)
        try:
            # the header must reach the disk now: a disk still full fails here, not later
            if isinstance(writer, _BlfWriter):
                writer.flush()
            else:
                writer.file.flush()
        except BaseException:
            _close_quietly(writer.file)
            name.unlink(missing_ok=True)  # nothing of the drive in it: the next try reuses it
            raise
        self._writer = writer
        self._part_frames = 0
        self.files.append(name)

    @property
    def late(self) -> int:
        """Frames that arrived after the reorder window (written re-stamped)."""
        return self._order.late

    def _write(self, msg: can.Message) -> int:
        """Hold the frame back in time order; write those older than the window (how many)."""
        if self.one_bus and msg.channel != self.channel:
            msg = copy_frame(msg, channel=self.channel)
        return self._emit_all(self._order.push(msg.timestamp, msg))

    def _mark_drops(self, drops: _Drops) -> int:
        """Hold the marker of frames dropped in time order, at the first one's time."""
        return self._emit_all(self._order.push(drops.first, drops))

    def _drain(self) -> int:
        return self._emit_all(self._order.release())

    def _emit_all(self, frames: list[tuple[float, can.Message | _Drops]]) -> int:
        for t, msg in frames:
            if isinstance(msg, _Drops):
                self._emit(msg.marker(t, self.channel))
            else:
                self._emit(msg if msg.timestamp == t else copy_frame(msg, timestamp=t))
        return len(frames)

    def _for_file(self, msg: can.Message) -> can.Message:
        """The frame as the format stores its channel: BLF and ASC a number (the class's
        notes), the text formats the name."""
        if not self._numbered:
            return msg
        number = self._numbers.get(msg.channel)
        if number is None:  # a name beside the configured ones: the next number
            number = self._numbers[msg.channel] = max(self._numbers.values()) + 1
        return copy_frame(msg, channel=number)

    def _emit(self, msg: can.Message) -> None:
        if self._writer is None:
            raise OSError(0, "no open log file")
        self._writer.on_message_received(self._for_file(msg))
        self._part_frames += 1
        self._since_check += 1
        if self.max_bytes and self._since_check >= _ROTATE_CHECK_EVERY:
            self._since_check = 0
            if self._writer.file_size() >= self.max_bytes:
                self._rotate()

    def _flush(self) -> None:
        if self._writer is None:
            return
        if isinstance(self._writer, _BlfWriter):
            self._writer.flush()
        else:
            self._writer.file.flush()
        if self.max_bytes and self._writer.file_size() >= self.max_bytes:
            self._rotate()

    def _mark_end(
        self, writer: can.io.generic.FileIOMessageWriter[Any], continues: bool = False
    ) -> None:
        stamp = self.tx_clock() if self.tx_clock is not None else time.time()
        # never before the last frame: a simulated drive's clock runs ahead of the wall clock
        marker = end_marker(max(stamp, self._order.last), self.channel, continues)
        writer.on_message_received(self._for_file(marker))

    def _finish(self) -> None:
        if self._writer is not None:
            try:
                self._drain()
            finally:
                writer, self._writer = self._writer, None
                self._mark_end(writer)
                writer.stop()

    # -- control (fault, flush, close: _FileRecorder) --

    def diagnostics(self) -> dict[str, Any]:
        return {"files": [str(f) for f in self.files], "late": self.late, **self._bg.counters()}


def _session_item_dropped(item: tuple[Any, ...]) -> tuple[DropKind, float, str | None]:
    """What a session's queued item is, its time, and a Zenoh input's key (for its mark)."""
    kind = item[0]
    if kind == "zenoh":
        return "zenoh", item[1], item[2]
    return ("tick" if kind == "tick" else "can"), item[1], None


class SessionRecorder(_FileRecorder):
    """The whole session in one MCAP file (see :mod:`leafgate.record.session`).

    Records are written in time order of their MCAP log time, as the CAN log's frames are
    (:class:`CanLogRecorder`): received frames (the bus thread), Zenoh inputs (Zenoh threads)
    and ticks with their sent frames (the control thread) arrive out of order by up to the
    length of a tick, so the writer holds each item back until one ``reorder_window`` newer has
    arrived. An item later than that is logged at the last time written (its JSON keeps its
    exact times) and counted as ``late``. A flush request and :meth:`close` write everything
    held back; the periodic flush does not.

    After a write failure the session goes on in a new file, ``<name>.2.mcap`` … (see the
    module's text), each a session of its own with the configuration and the metadata
    ``resumes`` naming the file before.

    :param path: the ``.mcap`` file; its directory is created
    :param config: the configuration the gateway runs with (recorded as metadata; a re-run
        rebuilds the gateway from it)
    :param clock: the gateway clock, stamping received frames as they are handed in (the
        daemon passes the runtime's clock); None uses each frame's own timestamp (simulator)
    :param tap: the controller wrapper whose output gives the predicted path (optional)
    :param diagnostics: also record ``Diagnostics.to_dict()`` every tick
    :param channel: the channel name written for sent frames, which carry none (None: none)
    :param one_bus: every frame is on one bus: every frame is written under ``channel``
    :param reorder_window: s, how long an item is held back to be written in time order
    :param retry_period: s between attempts at a new file while the file fails
    """

    def __init__(
        self,
        path: str | Path,
        config: LeafgateConfig,
        *,
        clock: Callable[[], float] | None = None,
        flush_period: float = 1.0,
        queue_size: int = 20_000,
        compression: Literal["zstd", "lz4", "none"] = "zstd",
        diagnostics: bool = True,
        tap: ControllerTap | None = None,
        session: dict[str, str] | None = None,
        channel: str | None = None,
        one_bus: bool = False,
        epoch: float | None = None,
        queue_bytes: int = 64 * 1024 * 1024,
        reorder_window: float = DEFAULT_REORDER_WINDOW,
        retry_period: float = DEFAULT_RETRY_PERIOD,
    ) -> None:
        self.path = Path(path)
        self.files: list[Path] = []  # the session's files: path, then those after failures
        self.clock = clock
        self.channel = channel  # written for sent frames (they carry none); see CanLogRecorder
        self.one_bus = one_bus
        self.tap = tap
        self.record_diagnostics = diagnostics
        self.reorder_window = reorder_window
        self.ticks = 0  # ticks written
        self._seq = 0  # ticks handed in (control thread): the next one's number in the file
        # items in log-time order; those that came after the window are logged at the last time
        self._order: _ReorderWindow[tuple[Any, ...]] = _ReorderWindow(reorder_window)
        self._file: IO[bytes] | None = None
        self._writer: SessionWriter | None = None
        self._file_items = 0
        self._config = config
        self._compression = compression
        self._bg = _BackgroundWriter(
            f"session {self.path.name}",
            self._write,
            self._flush,
            self._finish,
            flush_period,
            queue_size,
            drain=self._drain,
            queue_bytes=queue_bytes,
            reopen=self._reopen,
            abandon=self._abandon,
            retry_period=retry_period,
            dropped=_session_item_dropped,
            mark=lambda drops: self._write(("drops", drops.first, drops)),
        )
        meta = {"clock": "gateway" if clock is not None else "frame timestamps"}
        meta["started"] = datetime.now().astimezone().isoformat(timespec="seconds")
        meta.update(session or {})
        self._meta = meta
        # Unix-epoch MCAP times: the gateway clock's offset now, or for the simulator (frames
        # stamped with simulated time from 0) the wall-clock time of its start; one offset for
        # every file of the session
        self._epoch = epoch_offset(clock) if epoch is None else epoch
        try:
            self._open(self.path, meta)
        except Exception as exc:
            self._bg.fail(f"cannot open {self.path}", exc)

    # -- hooks (any thread) --

    def on_can_frame(self, msg: can.Message, direction: Direction) -> None:
        t = self.clock() if self.clock is not None else msg.timestamp
        self._bg.put(("can", t, msg, direction == "rx"))

    def on_zenoh_input(
        self, key: str, payload: bytes, received: float, typename: str | None = None
    ) -> None:
        """A raw Zenoh input sample with its receive time (gateway clock)."""
        self._bg.put(("zenoh", received, key, bytes(payload), typename))

    def on_tick(
        self, now: float, inputs: GatewayInputs, result: StepResult, frames: Sequence[can.Message]
    ) -> None:
        """One control tick and the frames it sent (control thread)."""
        xy = None
        if self.tap is not None:
            output = self.tap.take()
            if output is not None and output.predicted_xy is not None:
                # the controller may reuse its buffer next tick: copy before handing over
                xy = np.array(output.predicted_xy, dtype=np.float64)
        seq, self._seq = self._seq, self._seq + 1  # numbered when handed in: a drop is a gap
        self._bg.put(("tick", now, inputs, result, xy, seq))
        for frame in frames:
            self._bg.put(("can", now, frame, False))

    def wrap_controller(self, controller: Controller) -> Controller:
        """Wrap the controller so its predicted path is recorded (its output is unchanged)."""
        self.tap = ControllerTap(controller)
        return self.tap

    # -- writer thread --

    def _open(self, path: Path, meta: dict[str, str]) -> None:
        """Start a session file: header, configuration and metadata, on disk before it returns
        (a disk still full fails here)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        file = path.open("wb")
        try:
            writer = SessionWriter(file, self._config, self._compression, meta, self._epoch)
            file.flush()
        except BaseException:
            _close_quietly(file)
            raise
        self._file, self._writer = file, writer
        self._file_items = 0  # items written to the current file
        self.files.append(path)

    def _abandon(self) -> None:
        """Close the failed file as it is: no end marker, no summary, nothing after its tail."""
        file, self._file, self._writer = self._file, None, None
        _close_quietly(file)

    def _reopen(self) -> None:
        """Give the failed file up and go on in the next, with the first item after the
        outage (:meth:`_ReorderWindow.discard`: one stretch lost, between the two files)."""
        self._abandon()
        self._bg.dropped += self._order.discard()
        if len(self.files) > 1 and self._file_items == 0:
            # a file opened by an earlier attempt that failed before an item: it holds nothing
            # of the drive, and its name is reused (no trail of empty files in an outage)
            self.files.pop().unlink(missing_ok=True)
        previous = self.files[-1].name if self.files else ""
        path = self.path.with_name(f"{self.path.stem}.{len(self.files) + 1}{self.path.suffix}")
        try:
            self._open(path, {**self._meta, "resumes": previous})
        except BaseException:
            path.unlink(missing_ok=True)  # nothing of the drive in it: the next try reuses it
            raise

    @property
    def late(self) -> int:
        """Items that arrived after the reorder window (logged at the last time)."""
        return self._order.late

    def _write(self, item: tuple[Any, ...]) -> int:
        """Hold the item back in time order; write those older than the window (how many)."""
        released = self._order.push(item[1], item)
        for t, held in released:
            self._emit(t, held)
        return len(released)

    def _drain(self) -> int:
        released = self._order.release()
        for t, held in released:
            self._emit(t, held)
        return len(released)

    def _emit(self, t: float, item: tuple[Any, ...]) -> None:
        """Write one item at log time ``t`` (s, gateway clock)."""
        writer = self._writer
        if writer is None:
            raise OSError(0, "no open session file")
        self._file_items += 1
        kind = item[0]
        if kind == "can":
            _, _, msg, rx = item
            if self.channel is not None and (
                msg.channel is None or (self.one_bus and msg.channel != self.channel)
            ):
                msg = copy_frame(msg, channel=self.channel)  # one bus, one channel name
            writer.can_frame(t, msg, rx)
        elif kind == "drops":  # items dropped when the queue overflowed: their mark
            drops: _Drops = item[2]
            if drops.kind == "can":
                writer.can_frame(t, drops.marker(t), False)
            else:
                drops.written = True
                what = "tick" if drops.kind == "tick" else "input"
                writer.lost(t, what, drops.count, drops.first, drops.last, drops.keys)
        elif kind == "tick":
            _, now, inputs, result, xy, seq = item
            writer.tick(now, inputs, result, xy, self.record_diagnostics, log_time=t, seq=seq)
            self.ticks += 1
        else:
            _, received, key, payload, typename = item
            writer.zenoh_input(key, payload, received, typename, log_time=t)

    def _flush(self) -> None:
        if self._writer is not None and self._file is not None:
            self._writer.flush()
            self._file.flush()

    def _finish(self) -> None:
        try:
            if self._writer is not None:
                self._drain()
                t = self.clock() if self.clock is not None else self._order.last
                t = max(t, self._order.last)  # never before the last record
                if not math.isfinite(t):
                    t = 0.0  # nothing was recorded and no clock: the marker at time 0
                self._writer.can_frame(t, end_marker(t), False)
                self._writer.finish()
        finally:
            if self._file is not None:
                self._file.close()

    # -- control (fault, flush, close: _FileRecorder) --

    def diagnostics(self) -> dict[str, Any]:
        return {
            "file": str(self.files[-1] if self.files else self.path),
            "files": [str(f) for f in self.files],
            "ticks": self.ticks,
            "late": self.late,
            **self._bg.counters(),
        }


_AnyRecorder = CanLogRecorder | SessionRecorder


class Recording(_ClosedOnExit):
    """The configured recorders behind one set of hooks (what the runtime is given)."""

    def __init__(self, recorders: Sequence[_AnyRecorder] = (), epoch: float | None = None) -> None:
        self.recorders = tuple(recorders)
        #: a simulated drive's Unix time of t = 0 (its frames are stamped epoch + simulated
        #: time); None for the daemon's, on Unix time already
        self.epoch = epoch

    def wrap_controller(self, controller: Controller) -> Controller:
        """Wrap the controller so the session records its predicted path (unchanged output)."""
        for r in self.recorders:
            controller = r.wrap_controller(controller)
        return controller

    def on_can_frame(self, msg: can.Message, direction: Direction) -> None:
        for r in self.recorders:
            r.on_can_frame(msg, direction)

    def on_zenoh_input(
        self, key: str, payload: bytes, received: float, typename: str | None = None
    ) -> None:
        for r in self.recorders:
            r.on_zenoh_input(key, payload, received, typename)

    def on_tick(
        self, now: float, inputs: GatewayInputs, result: StepResult, frames: Sequence[can.Message]
    ) -> None:
        for r in self.recorders:
            r.on_tick(now, inputs, result, frames)

    @property
    def fault(self) -> str:
        """The first recorder fault ("" while every file is healthy)."""
        return next((r.fault for r in self.recorders if r.fault), "")

    def flush(self, timeout: float = 5.0) -> bool:
        return all([r.flush(timeout) for r in self.recorders])

    def close(self) -> None:
        for r in self.recorders:
            r.close()

    def diagnostics(self) -> dict[str, Any]:
        """For the runtime's diagnostics: ``{fault, can_log, session}``."""
        out: dict[str, Any] = {"fault": self.fault}
        for r in self.recorders:
            out["session" if isinstance(r, SessionRecorder) else "can_log"] = r.diagnostics()
        return out


def open_recording(
    cfg: RecordingConfig,
    config: LeafgateConfig,
    *,
    clock: Callable[[], float] | None = None,
    wall_clock: Callable[[], float] | None = time.time,
    start: datetime | None = None,
) -> Recording:
    """The recorders ``cfg`` asks for (none when ``enabled`` is false).

    Never raises for file problems: a recorder that cannot open its file reports it in
    ``fault`` (and the daemon's diagnostics).

    :param clock: the gateway clock for the session (the runtime's ``clock``)
    :param wall_clock: stamps sent frames in the CAN log; python-can stamps received frames
        with the epoch clock, so the default ``time.time`` keeps the log on one clock
    :param start: the time substituted for ``{start}`` (default now)
    """
    if not cfg.enabled:
        return Recording()
    stamp = (start or datetime.now()).strftime("%Y%m%dT%H%M%S")
    # A simulated drive (no clocks) is stamped from the wall-clock time of its start, in the CAN
    # log and the session alike; the daemon's frames and sessions are on Unix time already.
    simulated = clock is None and wall_clock is None
    sim_epoch = epoch_offset(None) if simulated else None
    directory = Path(cfg.directory)
    recorders: list[_AnyRecorder] = []
    if cfg.can_log is not None:
        recorders.append(
            CanLogRecorder(
                directory / cfg.can_log.format(start=stamp),
                max_bytes=cfg.max_bytes,
                flush_period=cfg.flush_period,
                queue_size=cfg.queue_size,
                queue_bytes=cfg.queue_bytes,
                tx_clock=wall_clock,
                channel=config.can.dbw.channel,
                car_channel=None if config.can.car is None else config.can.car.channel,
                one_bus=config.can.car is None,
                time_offset=sim_epoch or 0.0,
            )
        )
    if cfg.session is not None:
        recorders.append(
            SessionRecorder(
                directory / cfg.session.format(start=stamp),
                config,
                clock=clock,
                flush_period=cfg.flush_period,
                queue_size=cfg.queue_size,
                queue_bytes=cfg.queue_bytes,
                compression=cfg.compression,
                diagnostics=cfg.diagnostics,
                channel=config.can.dbw.channel,
                one_bus=config.can.car is None,
                epoch=sim_epoch,
            )
        )
    return Recording(recorders, epoch=sim_epoch)
