"""The daemon's real-time runtime: threads, sockets and the clock around ``Gateway.step``.

Threads and what they own:

- python-can's ``Notifier`` thread decodes every received frame and writes the latest report of
  each kind into a slot (with its receive time and validity) and counts good and bad frames.
  It also watches the gateway's own command IDs: a frame there that the gateway did not send
  (another node commanding the ECU) is counted as foreign, and the core faults on it.
- Zenoh's callback threads (inside :class:`~leafgate.runtime.node.GatewayTransport`) write the
  latest localization and trajectory into their slots, and queue operator requests.
- One control thread (the caller of :meth:`Runtime.run`) ticks on absolute deadlines of
  ``time.perf_counter``: it reads the slots without blocking, calls ``Gateway.step``, encodes and
  sends the command frames. Nothing else runs on it.
- A publisher thread sends vehicle status, the sent command and diagnostics over Zenoh, so a slow
  network never delays a tick; when it falls behind, publications are dropped and counted.

The simulator (:func:`leafgate.sim.runner.run`) runs this same :meth:`Runtime.tick` and
:class:`~leafgate.runtime.receiver.CanReceiver` without the threads: it hands the receiver each
frame itself and ticks on its simulated clock (``clock=``, ``receive_buses=()``).

Faults in the loop are state, never exceptions: a bus send error is counted and reported to the
gateway, which latches FAULT; an encode error (a value the safety gate should have clamped) drops
that frame, is counted and likewise faults.

Own frames and foreign ones: python-can's ``udp_multicast`` delivers every frame a bus sends back
to that same bus (the socket joins the group with multicast loopback on), while SocketCAN does
not (unless ``receive_own_messages``) and ``virtual`` does not. :class:`~leafgate.runtime.receiver.SentFrames` therefore
remembers each frame sent for :data:`~leafgate.runtime.receiver.ECHO_WINDOW`; a received frame on a command ID that
matches one, byte for byte, is our own echo and is dropped (the recorder already has it as
sent); any other is foreign. Both bus behaviours give the same verdicts.
"""

from __future__ import annotations

import logging
import math
import queue
import select
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import can
import numpy as np

from leafgate.can.codec import CanCodec
from leafgate.gateway.core import Gateway, GatewayInputs, StepResult
from leafgate.gateway.state import STATE_UNKNOWN, EngageReply, refusal
from leafgate.messages import (
    STOP_REQUESTS,
    GatewayState,
    OperatorRequest,
    Pose,
    Stamped,
    Trajectory,
)
from leafgate.runtime.receiver import CanReceiver, _watch_ids

log = logging.getLogger(__name__)

T = TypeVar("T")

SHUTDOWN_TICKS = 5  # ticks of ENABLE=0 frames sent before exit (100 ms at 50 Hz)
DIAGNOSTICS_PERIOD = 0.1  # s, 10 Hz
STATS_WINDOW = 3000  # ticks kept for the timing figures (one minute at 50 Hz)
REQUEST_TIMEOUT = 1.0  # s an operator request waits for the control thread


class InputSource(Protocol):
    """Where localization and trajectory come from (Zenoh in the daemon, the plant in tests)."""

    def latest_pose(self) -> Stamped[Pose] | None: ...

    def latest_trajectory(self) -> Stamped[Trajectory] | None: ...


class Publisher(Protocol):
    """What the runtime publishes (Zenoh in the daemon)."""

    def publish_step(self, now: float, result: StepResult, reports: dict[str, Any]) -> None: ...

    def publish_diagnostics(self, diagnostics: dict[str, Any]) -> None: ...


@dataclass
class _Request:
    request: OperatorRequest
    future: Future[dict[str, Any]] = field(default_factory=Future)


REQUEST_BOX_LENGTH = 16  # requests waiting for the control thread; more are refused at once


@dataclass
class TakenRequests:
    """What the control thread takes from the :class:`RequestBox` in one tick.

    ``chosen`` is executed by this tick's ``Gateway.step``; ``companions`` are further stops of
    the same tick (they share its answer); ``superseded`` requests are refused unexecuted,
    because a stop came in the same tick.
    """

    chosen: _Request | None = None
    companions: list[_Request] = field(default_factory=list)
    superseded: list[_Request] = field(default_factory=list)

    @property
    def request(self) -> OperatorRequest | None:
        return self.chosen.request if self.chosen is not None else None

    def answer(self, reply: dict[str, Any], state: str) -> None:
        """Send ``reply`` to the chosen request and its companions, a refusal to the rest."""
        for item in (self.chosen, *self.companions) if self.chosen is not None else ():
            item.future.set_result(dict(reply))
        for item in self.superseded:
            item.future.set_result(
                refusal(state, f"{item.request.value} superseded by a disengage")
            )


class RequestBox:
    """Operator requests from the query threads to the control thread, answered with a reply.

    - A stop (``disengage``) wins: when one is pending, the control thread executes it in its
      next tick and refuses every other pending request as superseded, so an engage queued
      before a disengage can never run after it.
    - A request whose caller gave up (``submit`` timed out) is withdrawn and never executed.
    - At most ``length`` requests wait; more are refused at once.
    """

    def __init__(self, length: int = REQUEST_BOX_LENGTH) -> None:
        self._lock = threading.Lock()
        self._items: deque[_Request] = deque()
        self._length = length

    def submit(self, request: OperatorRequest, timeout: float = REQUEST_TIMEOUT) -> dict[str, Any]:
        """Block (on the caller's thread) until the control thread has decided.

        On timeout the request is withdrawn (never executed later) unless the control thread
        is deciding it at that moment, in which case its decision is returned.
        """
        item = _Request(request)
        with self._lock:
            waiting = len(self._items)
            if waiting < self._length:
                self._items.append(item)
        if waiting >= self._length:
            return refusal(
                STATE_UNKNOWN, f"busy: {waiting} requests already wait for the control loop"
            )
        try:
            return item.future.result(timeout=timeout)
        except FutureTimeout:
            if item.future.cancel():
                return refusal(
                    STATE_UNKNOWN, "control loop did not answer in time (request withdrawn)"
                )
            return item.future.result()  # taken by this very tick: its answer comes at once

    def __len__(self) -> int:
        """Requests waiting (withdrawn ones included until the next take)."""
        with self._lock:
            return len(self._items)

    def take(self) -> TakenRequests:
        """The request to execute this tick (a pending stop first) and those it supersedes."""
        taken = TakenRequests()
        with self._lock:
            items = list(self._items)
            self._items.clear()
            stops = [i for i in items if i.request in STOP_REQUESTS]
            if not stops:
                while items:
                    item = items.pop(0)
                    if item.future.set_running_or_notify_cancel():
                        taken.chosen = item
                        break
                self._items.extend(items)  # one request per tick, in order
                return taken
        for item in items:
            if not item.future.set_running_or_notify_cancel():
                continue  # withdrawn by its caller
            if item.request not in STOP_REQUESTS:
                taken.superseded.append(item)
            elif taken.chosen is None:
                taken.chosen = item
            else:
                taken.companions.append(item)
        return taken


@dataclass
class LoopStats:
    """Timing of the control loop, measured on the control thread."""

    ticks: int = 0
    overruns: int = 0  # ticks that started more than one period late
    skipped: int = 0  # ticks dropped to re-anchor after a long stall
    send_errors: int = 0
    encode_errors: int = 0
    publish_dropped: int = 0
    compute: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_WINDOW))  # s
    lateness: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_WINDOW))  # s

    def summary(self) -> dict[str, float | int]:
        def pct(values: deque[float], q: float) -> float:
            return float(np.percentile(np.fromiter(values, float), q)) if values else float("nan")

        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "skipped_ticks": self.skipped,
            "send_errors": self.send_errors,
            "encode_errors": self.encode_errors,
            "publish_dropped": self.publish_dropped,
            "compute_median_s": pct(self.compute, 50),
            "compute_p99_s": pct(self.compute, 99),
            "compute_max_s": max(self.compute, default=float("nan")),
            "start_lateness_median_s": pct(self.lateness, 50),
            "start_lateness_p99_s": pct(self.lateness, 99),
        }


def frames_waiting(buses: Sequence[can.BusABC]) -> bool:
    """Whether a frame waits, unread, in any of the buses' sockets (False when unknown).

    The Notifier thread reads them; while one waits, that thread is behind the bus and the
    reports' ages can only be judged up to what it has read.
    """
    fds = []
    for bus in buses:
        try:
            fds.append(bus.fileno())
        except Exception:  # NotImplementedError (virtual), a closed bus …
            continue
    if not fds:
        return False
    try:
        readable, _, _ = select.select(fds, [], [], 0.0)
    except (OSError, ValueError):
        return False
    return bool(readable)


class Runtime:
    """Runs ``Gateway.step`` on a fixed-rate loop between real inputs and a real bus.

    :param gateway: the pure decision core
    :param codec: the gateway's CAN codec (encodes commands, decodes reports)
    :param bus: where command frames are sent (the ``dbw`` channel)
    :param receiver: the Notifier listener holding the latest reports
    :param inputs: localization and trajectory source
    :param publisher: Zenoh publications (optional)
    :param period: control tick period, s
    :param clock: monotonic clock, s — the same clock must stamp the inputs
    :param watch_command_ids: add our command IDs to ``bus``'s receive filter, so frames other
        nodes send on them reach the receiver (the daemon opens the bus for reports only)
    """

    def __init__(
        self,
        gateway: Gateway,
        codec: CanCodec,
        bus: can.BusABC,
        receiver: CanReceiver,
        inputs: InputSource,
        period: float,
        publisher: Publisher | None = None,
        requests: RequestBox | None = None,
        clock: Callable[[], float] = time.perf_counter,
        on_tick: Callable[[float, GatewayInputs, StepResult, Sequence[can.Message]], None]
        | None = None,
        extra_diagnostics: Callable[[], dict[str, Any]] | None = None,
        watch_command_ids: bool = True,
        receive_buses: Sequence[can.BusABC] | None = None,
        engage_veto: Callable[[], str | None] | None = None,
    ) -> None:
        self.gateway = gateway
        # the buses the Notifier reads (the dbw bus, and the car bus when separate)
        self.receive_buses = tuple(receive_buses) if receive_buses is not None else (bus,)
        self.codec = codec
        self.bus = bus
        self.receiver = receiver
        self.inputs = inputs
        self.period = period
        self.publisher = publisher
        self.requests = requests if requests is not None else RequestBox()
        self.clock = clock
        self.on_tick = on_tick
        self.extra_diagnostics = extra_diagnostics
        self.engage_veto = engage_veto
        self.stats = LoopStats()
        self.last_result: StepResult | None = None
        self._pub_queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=64)
        self._pub_thread: threading.Thread | None = None
        self._last_diag = -1e9
        self._bus_errors_pending = 0
        if watch_command_ids:
            _watch_ids(bus, receiver.command_ids)

    # -- one tick ----------------------------------------------------------------------------

    def tick(
        self,
        now: float,
        overrun: bool = False,
        request: OperatorRequest | None = None,
        lateness: float = 0.0,
        request_reason: str = "",
    ) -> StepResult:
        """Read the slots, step the gateway, send the frames. Never raises for bus problems.

        :param request_reason: why ``request`` came when no operator sent it (the
            transition's reason: ``SIGTERM received``)
        """
        started = self.clock()
        pending = self.requests.take() if request is None else TakenRequests()
        if pending.request is OperatorRequest.ENGAGE:
            pending = self._vetoed(pending)
        good, bad = self.receiver.take_counts()
        foreign, foreign_names = self.receiver.take_foreign()
        bus_errors, self._bus_errors_pending = self._bus_errors_pending, 0
        # Reports are judged up to where the receive thread has read the bus: now, unless
        # frames still wait in a socket (the thread is late, not the ECU).
        as_of = self.receiver.horizon if frames_waiting(self.receive_buses) else now
        inputs = GatewayInputs(
            pose=self.inputs.latest_pose(),
            trajectory=self.inputs.latest_trajectory(),
            steer_report=self.receiver.steer.get(),
            long_report=self.receiver.long.get(),
            system_report=self.receiver.system.get(),
            good_report_frames=good,
            bad_report_frames=bad,
            report_error_cause=self.codec.second_senders() if bad else "",
            request=request if request is not None else pending.request,
            request_reason=request_reason if request is not None else "",
            overrun=overrun,
            lateness=lateness,
            bus_errors=bus_errors,
            foreign_command_frames=foreign,
            foreign_command_names=foreign_names,
            reports_as_of=as_of if math.isfinite(as_of) else None,
            wheel_speeds=self.receiver.car_value("WheelSpeeds"),
            steering_wheel=self.receiver.car_value("SteeringWheelAngle"),
        )
        result = self.gateway.step(now, inputs)
        state = self.gateway.state.name
        reply = result.reply
        pending.answer(
            reply.to_dict() if reply is not None else refusal(state, "no reply"),
            state,
        )
        frames = self._encode(result, now)
        sent = self.receiver.sent
        for frame in frames:
            sent.add(frame, now)  # before the send: the echo may arrive before send() returns
            try:
                self.bus.send(frame)
            except can.CanError as exc:
                self.stats.send_errors += 1
                self._bus_errors_pending += 1
                log.debug("send of 0x%03X failed: %s", frame.arbitration_id, exc)
        self.last_result = result
        if self.on_tick is not None:
            self.on_tick(now, inputs, result, frames)
        self.stats.ticks += 1
        self.stats.compute.append(self.clock() - started)
        self._queue_publications(now, result)
        return result

    def _vetoed(self, pending: TakenRequests) -> TakenRequests:
        """An engage the shell refuses (``engage_veto``: the required recording fails) is
        answered here, in the reply format of the core's refusals, and not executed.

        Only in STANDBY: in any other state the core's answer (``fault latched (…); reset
        first``, ``already engaged``, ``stopping; …``) comes first, as it names what to do.
        """
        state = self.gateway.state
        if self.engage_veto is None or state is not GatewayState.STANDBY:
            return pending
        refusal = self.engage_veto()
        if refusal is None:
            return pending
        pending.answer(EngageReply(False, state, refusal).to_dict(), state.name)
        return TakenRequests()

    def _encode(self, result: StepResult, now: float) -> list[can.Message]:
        try:
            frames = self.codec.encode_commands(result.commands, timestamp=now)
            errors = self.codec.last_errors
        except Exception as exc:  # an encode error must never end the loop
            frames, errors = [], [str(exc)]
        for error in errors:
            self.stats.encode_errors += 1
            self._bus_errors_pending += 1
            log.error("cannot encode a command frame: %s", error)
        return frames

    def _queue_publications(self, now: float, result: StepResult) -> None:
        if self.publisher is None:
            return
        reports = {
            "steer": self.receiver.steer.get(),
            "long": self.receiver.long.get(),
            "system": self.receiver.system.get(),
        }
        self._offer(("step", (now, result, reports)))
        if now - self._last_diag >= DIAGNOSTICS_PERIOD - 1e-6:
            self._last_diag = now
            self._offer(("diagnostics", self.diagnostics(result)))

    def _offer(self, item: tuple[str, Any]) -> None:
        try:
            self._pub_queue.put_nowait(item)
        except queue.Full:
            self.stats.publish_dropped += 1

    def diagnostics(self, result: StepResult | None = None) -> dict[str, Any]:
        result = result or self.last_result
        diag: dict[str, Any] = result.diagnostics.to_dict() if result is not None else {}
        diag["loop"] = self.stats.summary()
        diag["can"] = {
            f"0x{fid:03X}": vars(s) if not isinstance(s, dict) else s
            for fid, s in self.codec.stats.items()
        }
        diag["command_ids"] = {
            "own_echoes": self.receiver.own_echoes,
            "foreign_frames": self.receiver.foreign_total,
        }
        if self.extra_diagnostics is not None:
            diag.update(self.extra_diagnostics())
        return diag

    # -- the loop ----------------------------------------------------------------------------

    def _publisher_loop(self, stop: threading.Event) -> None:
        assert self.publisher is not None
        while not (stop.is_set() and self._pub_queue.empty()):
            try:
                kind, payload = self._pub_queue.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                if kind == "step":
                    self.publisher.publish_step(*payload)
                else:
                    self.publisher.publish_diagnostics(payload)
            except Exception as exc:  # a publication problem must not stop the publisher
                log.warning("publish failed: %s", exc)

    def run(
        self,
        stop: threading.Event,
        on_ready: Callable[[], None] | None = None,
        stop_reason: Callable[[], str] | None = None,
    ) -> None:
        """Tick until ``stop`` is set, then send ENABLE=0 frames for a few ticks and return.

        :param stop_reason: why ``stop`` was set, read once it is (``SIGHUP received``): the
            reason of the disengage the shutdown ticks make; "" or None: ``stop requested``
        """
        pub_stop = threading.Event()
        if self.publisher is not None:
            self._pub_thread = threading.Thread(
                target=self._publisher_loop, args=(pub_stop,), name="leafgate-publish", daemon=True
            )
            self._pub_thread.start()
        period = self.period
        t0 = self.clock()
        k = 0
        ready_sent = False
        try:
            while not stop.is_set():
                deadline = t0 + k * period
                now = self.clock()
                if now < deadline:
                    # Sleep to the absolute deadline; a relative sleep would accumulate drift.
                    stop.wait(deadline - now)
                    if stop.is_set():
                        break
                    now = self.clock()
                lateness = now - deadline
                overrun = lateness > period
                if overrun:
                    self.stats.overruns += 1
                if lateness > 3 * period:
                    # A long stall: re-anchor instead of firing a burst of catch-up ticks.
                    missed = int(lateness // period)
                    self.stats.skipped += missed
                    k += missed
                self.stats.lateness.append(max(0.0, lateness))
                self.tick(now, overrun=overrun, lateness=lateness)
                if not ready_sent and on_ready is not None:
                    on_ready()
                    ready_sent = True
                k += 1
            # Disengage cleanly: the ECU sees ENABLE=0 frames, not a silent bus (which it would
            # treat as a command timeout and brake hard).
            why = (stop_reason() if stop_reason is not None else "") or "stop requested"
            for _ in range(SHUTDOWN_TICKS):
                self.tick(self.clock(), request=OperatorRequest.DISENGAGE, request_reason=why)
                time.sleep(period)
        finally:
            pub_stop.set()
            if self._pub_thread is not None:
                self._pub_thread.join(timeout=1.0)
