"""The gateway's side of Zenoh: input slots, status publishers, the engage queryable.

Zenoh calls the subscriber and queryable callbacks on its own threads. Each input key has a
:class:`~leafgate.runtime.slots.LatestSlot` that keeps only the newest decoded sample as a
:class:`~leafgate.messages.Stamped` value with its receive time; the control thread reads the
slots without waiting (a read is one reference load of an immutable object). Nothing in here
raises into the control loop or into Zenoh's threads: undecodable payloads and unencodable
values are counted per key and dropped.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import zenoh

from leafgate.config.transport import ZenohConfig
from leafgate.errors import TransportError
from leafgate.gateway.state import STATE_UNKNOWN
from leafgate.gateway.watchdog import pose_is_valid, trajectory_is_valid
from leafgate.jsonconv import to_json
from leafgate.messages import (
    STOP_REQUESTS,
    Gear,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerReport,
    Trajectory,
)
from leafgate.runtime.slots import LatestSlot
from leafgate.transport import cdr, keys
from leafgate.transport.cdr import PayloadError
from leafgate.transport.payloads import (
    Codec,
    ControlModeStatus,
    GearStatus,
    HazardLightsStatus,
    SentCommand,
    SteeringStatus,
    TurnIndicatorsStatus,
    VelocityStatus,
    codecs,
    control_mode,
    sent_command,
    steering_status,
    velocity_status,
)
from leafgate.transport.rosnode import RosFace, RosPublisher, sample_source
from leafgate.transport.session import open_session, zenoh_message

T = TypeVar("T")

DIAGNOSTICS = "diagnostics"  # publisher role of gateway/diagnostics (leafgate's own JSON key)

log = logging.getLogger(__name__)

Clock = Callable[[], float]
EngageHandler = Callable[[OperatorRequest], Mapping[str, Any]]

REQUEST_PARAMETER = "request"  # selector parameter alternative to the query payload
# autoware_vehicle_msgs/srv/ControlModeCommand modes → the operator request they stand for.
_CONTROL_MODE_REQUESTS: dict[int, OperatorRequest] = {
    1: OperatorRequest.ENGAGE,  # AUTONOMOUS
    4: OperatorRequest.DISENGAGE,  # MANUAL
}
_NO_COMMAND = 0
QUERY_JOIN_TIMEOUT = 2.0  # s, how long close() waits for an engage handler still running
MAX_REQUEST_BYTES = 16  # longer request payloads are refused before they are decoded
MAX_SERVICE_REQUEST_BYTES = 64  # a ControlModeCommand request is 4 + 12 bytes of CDR
REQUEST_QUEUE_LENGTH = 8  # queries waiting per lane (stops, others); more are refused at once
# s a query may wait in its lane before the handler sees it; an older one is dropped as
# abandoned. With the runtime's 1 s decision timeout a request is answered or withdrawn within
# 1.5 s, before a tool's default query_timeout (2 s) has given up on it.
REQUEST_MAX_AGE = 0.5


# s a publisher heard on an input key counts as present: two within this window are two
# sources (the localization's FAULT). Longer than any gap of a live localization (the fault
# age is 0.5 s), short enough that a publisher replaced on purpose is forgotten soon.
SOURCE_WINDOW = 1.0


class SourceTracker:
    """The publishers heard on one input key within the last ``window`` seconds.

    Fed on Zenoh's thread with every sample's identity (:func:`~leafgate.transport.rosnode.
    sample_source`, ``""`` for none) and receive time; each sample carries the answer in its
    :attr:`~leafgate.messages.Stamped.sources`, so the control thread, which sees only the
    newest sample, still learns of a second publisher whose samples it never saw.
    """

    def __init__(self, window: float = SOURCE_WINDOW) -> None:
        self.window = window
        self._seen: dict[str, float] = {}  # identity → receive time of its newest sample
        self._lock = threading.Lock()

    def note(self, source: str, received: float) -> tuple[str, ...]:
        """Record a sample; the identities heard within the window, sorted."""
        with self._lock:
            seen = self._seen
            seen[source] = max(received, seen.get(source, received))
            if len(seen) > 1:
                for other in [s for s, t in seen.items() if received - t > self.window]:
                    del seen[other]
            return tuple(sorted(seen))

    def heard(self) -> list[str]:
        """Every identity currently remembered ("unidentified" for samples without one)."""
        with self._lock:
            return sorted(s or "unidentified" for s in self._seen)


@dataclasses.dataclass
class _PendingQuery:
    query: zenoh.Query
    request: OperatorRequest
    received: float  # s, on the transport's clock
    service: bool = False  # a ROS ControlModeCommand call: answered in CDR


class _QueryLanes:
    """Queries waiting for the handler, in two bounded lanes: stops, and everything else.

    Each lane has its own worker thread, so a stop never waits behind an engage the handler
    is still deciding. A stop that arrives drops every queued engage and reset (they are
    answered as superseded): nothing asked before a disengage runs after it.
    """

    def __init__(self, length: int) -> None:
        self.length = length
        self.cond = threading.Condition()
        self.stops: collections.deque[_PendingQuery] = collections.deque()
        self.others: collections.deque[_PendingQuery] = collections.deque()
        self.closed = False

    def put(self, item: _PendingQuery) -> tuple[bool, list[_PendingQuery]]:
        """Queue ``item``: (queued, items it displaced, to be answered by the caller)."""
        with self.cond:
            if self.closed:
                return False, []
            if item.request in STOP_REQUESTS:
                displaced = list(self.others)
                self.others.clear()
                if len(self.stops) >= self.length:  # keep the newest stops: one is enough
                    displaced.append(self.stops.popleft())
                self.stops.append(item)
            elif len(self.others) >= self.length:
                return False, []
            else:
                self.others.append(item)
                displaced = []
            self.cond.notify_all()
        return True, displaced

    def get(self, stops: bool) -> _PendingQuery | None:
        """The oldest query of a lane, waiting for one; None once closed and drained."""
        lane = self.stops if stops else self.others
        with self.cond:
            while not lane and not self.closed:
                self.cond.wait()
            return lane.popleft() if lane else None

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


def _reply_json(reply: Mapping[str, Any], state: str = STATE_UNKNOWN) -> dict[str, Any]:
    """The engage reply with its five fields always present (docs/state-machine.md).

    :param state: the state to name when ``reply`` names none
    """
    out = to_json(dict(reply))
    out["accepted"] = bool(out.get("accepted", False))
    out["state"] = str(out.get("state") or state)
    out["reason"] = str(out.get("reason") or "")
    out["changed"] = bool(out.get("changed", False))
    out["already"] = bool(out.get("already", False))
    return out


def parse_request(query_payload: bytes | None, parameter: str | None) -> OperatorRequest | str:
    """The operator request of a query: payload text, else the ``request=`` parameter.

    Strict: the text must be exactly one of the request words (lower case, nothing around
    it); anything else, longer than :data:`MAX_REQUEST_BYTES` or not ASCII, is refused. When
    both a payload and a parameter are given they must agree.

    :returns: the request, or a short quotable description of what was sent (for the refusal)
    """
    texts = [t for t in (query_payload, parameter.encode() if parameter else None) if t]
    if not texts:
        return ""
    for raw in texts:
        if len(raw) > MAX_REQUEST_BYTES:
            return f"<{len(raw)} bytes, at most {MAX_REQUEST_BYTES}>"
    if len(texts) == 2 and texts[0] != texts[1]:
        return f"{_quotable(texts[0])} with request={_quotable(texts[1])}"
    try:
        return OperatorRequest(texts[0].decode("ascii"))
    except ValueError:  # UnicodeDecodeError included
        return _quotable(texts[0])


def unknown_request(text: str) -> str:
    """The refusal reason for text that is not a request word.

    The text is quoted as it came, not as its ``repr``: the reply is JSON, which escapes a
    newline itself; a ``repr`` had it escaped twice (``'engage\\\\n'`` on the screen).
    """
    known = ", ".join(r.value for r in OperatorRequest)
    return f"unknown request '{text}' (expected one of: {known})"


def _quotable(raw: bytes) -> str:
    """Bounded text of a refused request for its reply (never the whole payload)."""
    return raw[:MAX_REQUEST_BYTES].decode("utf-8", errors="replace")


def _valid_value(sample: Any, kind: type[T]) -> T | None:
    """The value of a valid ``Stamped`` sample of type ``kind``, else None."""
    if isinstance(sample, Stamped) and sample.valid and isinstance(sample.value, kind):
        return sample.value
    return None


class GatewayTransport:
    """The daemon's Zenoh endpoints.

    Subscribes to ``{prefix}/localization/kinematic_state`` and ``{prefix}/planning/trajectory``
    into latest-value slots, declares the status publishers, the ``gateway/engage`` queryable
    and the ``gateway/alive`` liveliness token. A context manager; :meth:`close` undeclares
    everything (and closes the session if this object opened it).

    :param session: an open Zenoh session (see :func:`~leafgate.transport.session.open_session`)
    :param cfg: the Zenoh section (prefix, encoding, express)
    :param handler: called for each valid ``engage``/``disengage``/``reset`` query, one at a
        time on the transport's own ``leafgate-engage`` thread, returns
        ``{accepted, state, reason}`` (enums are sent by name); it may block, e.g. until the
        control thread has decided
    :param clock: receive-time source, s (``time.monotonic`` by default; inject a fake in tests)
    :param stamp_clock: the time written into published ROS stamps by :meth:`publish_step`, s
        (``time.time``: ROS consumers expect wall-clock stamps, not the gateway's monotonic clock)

    .. note:: Publishing uses Zenoh's default congestion control for data (drop when the
       network is congested), so a status is never waited for.
    """

    def __init__(
        self,
        session: zenoh.Session,
        cfg: ZenohConfig,
        handler: EngageHandler,
        *,
        clock: Clock = time.monotonic,
        stamp_clock: Clock = time.time,
        owns_session: bool = False,
    ) -> None:
        self._session = session
        self._cfg = cfg
        self._handler = handler
        self._clock = clock
        self._stamp_clock = stamp_clock
        self._owns_session = owns_session
        self._closed = False
        self._codecs = codecs(cfg.encoding)
        self._publish_errors: dict[str, int] = {}
        self._handler_errors = 0
        # the state the gateway last published: what a refusal made here names (one str,
        # replaced whole by the publisher thread)
        self._state = STATE_UNKNOWN
        # Called with (ROS topic name, raw payload, receive time, ROS type name or None for JSON)
        # for every input sample before it is decoded: the session recorder's tap (its channels
        # carry the ROS names, so they line up with rosbag2 recordings in either ROS mode).
        self.on_raw: Callable[[str, bytes, float, str | None], None] | None = None
        self._tap_errors = 0
        # Called on Zenoh's thread with every valid plan before the control thread can see it:
        # the daemon builds the controller's reference path there
        # (:func:`~leafgate.control.reference.prebuild`), so no control tick builds one.
        self.on_plan: Callable[[Trajectory], None] | None = None
        self._lock = threading.Lock()
        # Queries are parsed on Zenoh's thread (refusals answered there at once) and answered
        # on threads of our own: the handler may wait for the control thread, and a Zenoh
        # callback that blocks stalls the link it arrived on (and with it the localization
        # samples behind it). Stops have their own lane and thread.
        self._engage_key = cfg.key(keys.ENGAGE)
        self._lanes = _QueryLanes(REQUEST_QUEUE_LENGTH)
        self._request_refusals = 0  # queries refused before the handler (parse, key, busy, age)
        self._query_workers = [
            threading.Thread(target=self._answer_queries, args=(stops,), name=name, daemon=True)
            for stops, name in ((False, "leafgate-engage"), (True, "leafgate-stop"))
        ]
        for worker in self._query_workers:
            worker.start()

        self._sources: dict[str, SourceTracker] = {}  # per input key
        self._declared: list[Any] = []
        self._publishers: dict[str, tuple[RosPublisher, Codec[Any] | None]] = {}
        try:
            # The ROS face: keys, attachments and discovery tokens of the configured mode.
            self.ros = RosFace(session, cfg, wall=stamp_clock)
            self._declared.append(self.ros)
            self.pose: LatestSlot[Pose] = LatestSlot(self.ros.key("kinematic_state", cdr.ODOMETRY))
            self.trajectory: LatestSlot[Trajectory] = LatestSlot(
                self.ros.key("trajectory", cdr.TRAJECTORY)
            )
            self._declared.append(
                self.ros.subscriber(
                    "kinematic_state",
                    cdr.ODOMETRY,
                    self._subscriber(
                        self.pose,
                        self._codecs.pose,
                        # the core's one rule; it applies the configured covariance bounds
                        pose_is_valid,
                        cdr.ODOMETRY,
                        cfg.topic("kinematic_state"),
                    ),
                )
            )
            self._declared.append(
                self.ros.subscriber(
                    "trajectory",
                    cdr.TRAJECTORY,
                    self._subscriber(
                        self.trajectory,
                        self._codecs.trajectory,
                        trajectory_is_valid,
                        cdr.TRAJECTORY,
                        cfg.topic("trajectory"),
                    ),
                )
            )
            self._declared.append(session.declare_queryable(self._engage_key, self._on_query))
            self._service_key = ""
            if cfg.encoding == "cdr" and cfg.topic("control_mode_request"):
                self._service_key = self.ros.key("control_mode_request", cdr.CONTROL_MODE_COMMAND)
                self._declared.append(
                    self.ros.service(
                        "control_mode_request", cdr.CONTROL_MODE_COMMAND, self._on_service_query
                    )
                )
            for role, codec in (
                ("steering_status", self._codecs.steering),
                ("velocity_status", self._codecs.velocity),
                ("gear_status", self._codecs.gear),
                ("control_mode", self._codecs.control_mode),
                ("turn_indicators_status", self._codecs.turn_indicators),
                ("hazard_lights_status", self._codecs.hazard_lights),
                ("command_echo", self._codecs.command),
            ):
                if cfg.topic(role):  # "" switches a role off (the command echo by default)
                    publisher = self.ros.publisher(
                        role, codec.typename, mime=codec.mime, express=cfg.express
                    )
                    self._declared.append(publisher)
                    self._publishers[role] = (publisher, codec)
            diagnostics = session.declare_publisher(
                cfg.key(keys.DIAGNOSTICS),
                encoding=zenoh.Encoding("application/json"),
                express=cfg.express,
            )
            self._declared.append(diagnostics)
            self._publishers[DIAGNOSTICS] = (
                RosPublisher(diagnostics, cfg.key(keys.DIAGNOSTICS), None, stamp_clock),
                None,
            )
            self._declared.append(session.liveliness().declare_token(cfg.key(keys.ALIVE)))
            # The operator tools take a reply only from the session holding this token.
            self._declared.append(
                session.liveliness().declare_token(f"{cfg.key(keys.ALIVE)}/{session.info.zid()}")
            )
        except zenoh.ZError as exc:
            self.close()
            raise TransportError(
                f"cannot declare the gateway's endpoints under {cfg.prefix!r}: {zenoh_message(exc)}"
            ) from None

    @classmethod
    def open(
        cls,
        cfg: ZenohConfig,
        handler: EngageHandler,
        *,
        clock: Clock = time.monotonic,
        stamp_clock: Clock = time.time,
    ) -> GatewayTransport:
        """Open a session from ``cfg`` and declare the gateway on it (closed with this object).

        :raises TransportError: if the session cannot be opened
        """
        session = open_session(cfg)
        try:
            return cls(
                session, cfg, handler, clock=clock, stamp_clock=stamp_clock, owns_session=True
            )
        except BaseException:
            session.close()
            raise

    # --- inputs ---------------------------------------------------------------------------

    def _subscriber(
        self,
        slot: LatestSlot[T],
        codec: Codec[T],
        valid: Callable[[T], bool],
        typename: str,
        topic: str | None = None,
    ) -> Callable[[zenoh.Sample], None]:
        clock = self._clock
        typename_or_none = typename if self._cfg.encoding == "cdr" else None
        name = topic or slot.key

        sources = self._sources[slot.key] = SourceTracker()
        max_bytes = self._cfg.max_payload_bytes
        max_points = self._cfg.max_plan_points
        max_offset = self._cfg.max_clock_offset
        stamp_clock = self._stamp_clock

        def on_sample(sample: zenoh.Sample) -> None:
            received = clock()  # before decoding: the age counts from arrival
            heard = sources.note(sample_source(sample), received)
            size = len(sample.payload)
            if size > max_bytes:  # refused before it is copied or decoded
                slot.count_error(f"payload of {size} bytes > {max_bytes} (max_payload_bytes)")
                return
            payload = sample.payload.to_bytes()
            if self.on_raw is not None:
                try:
                    self.on_raw(name, payload, received, typename_or_none)
                except Exception:  # a recorder problem must not stop the inputs
                    self._tap_errors += 1
            try:
                value = codec.decode(payload)
                ok = valid(value)
            except Exception as exc:  # PayloadError, or a bug: never raise into Zenoh
                slot.count_error(str(exc))
                return
            if isinstance(value, Trajectory) and len(value) > max_points:
                slot.count_error(f"plan of {len(value)} points > {max_points} (max_plan_points)")
                return
            if isinstance(value, Trajectory) and ok and self.on_plan is not None:
                try:  # the controller's reference, built here and not in a control tick
                    self.on_plan(value)
                except Exception as exc:  # the controller then builds it itself
                    log.warning("could not prepare a plan's reference: %r", exc)
            if isinstance(value, Pose) and math.isfinite(value.stamp):
                # The measurement's age by its header stamp counts as well as the arrival's.
                lag = stamp_clock() - value.stamp
                if lag > max_offset:
                    received -= lag - max_offset
                elif lag < -max_offset:
                    ok = False  # from the future: the sender's clock is off, or the stamp forged
            slot.put(Stamped(value, received, valid=ok, sources=heard))

        return on_sample

    def latest_pose(self) -> Stamped[Pose] | None:
        """The newest localization sample (receive time on the injected clock)."""
        return self.pose.get()

    def latest_trajectory(self) -> Stamped[Trajectory] | None:
        """The newest trajectory sample (a new object for every message received)."""
        return self.trajectory.get()

    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session the gateway is declared on."""
        return self._session

    @property
    def decode_errors(self) -> dict[str, int]:
        """Dropped payloads per input key."""
        return {self.pose.key: self.pose.errors, self.trajectory.key: self.trajectory.errors}

    @property
    def last_errors(self) -> dict[str, str]:
        """Why the last dropped payload of each input key was dropped ("" if none was)."""
        return {
            self.pose.key: self.pose.last_error,
            self.trajectory.key: self.trajectory.last_error,
        }

    @property
    def invalid_samples(self) -> dict[str, int]:
        """Samples per input key that decoded but were stored marked invalid (the control
        path refuses them); together with :attr:`decode_errors`, every rejected sample."""
        return {self.pose.key: self.pose.invalid, self.trajectory.key: self.trajectory.invalid}

    @property
    def input_sources(self) -> dict[str, list[str]]:
        """The publishers heard on each input key recently (:class:`SourceTracker`), for
        diagnostics: "unidentified" where a sample names none, so one such entry is one or
        more publishers that cannot be told apart."""
        return {key: tracker.heard() for key, tracker in self._sources.items()}

    @property
    def publish_errors(self) -> dict[str, int]:
        """Values per output key that could not be encoded or sent."""
        with self._lock:
            return dict(self._publish_errors)

    @property
    def handler_errors(self) -> int:
        """Engage queries whose handler raised (answered with accepted=false)."""
        return self._handler_errors

    # --- engage queryable -----------------------------------------------------------------

    def _on_query(self, query: zenoh.Query) -> None:
        """Zenoh's callback: check and parse at once, queue what the handler must decide."""
        received = self._clock()
        try:
            self._queue(query, self._check_query(query), received, service=False)
        except Exception as exc:  # never raise into Zenoh
            log.warning("could not handle an engage query: %s", exc)
            query.drop()

    def _on_service_query(self, query: zenoh.Query) -> None:
        """A ROS ``ControlModeCommand`` call (CDR request): AUTONOMOUS engages, MANUAL
        disengages, NO_COMMAND does nothing; the partial modes are refused (the DBW ECU engages
        steering and speed together). Queued in the same lanes as the engage queries."""
        received = self._clock()
        try:
            if str(query.key_expr) != self._service_key:  # a wildcard: never a service call
                with self._lock:
                    self._request_refusals += 1
                query.drop()
                return
            request: OperatorRequest | str
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                if len(payload) > MAX_SERVICE_REQUEST_BYTES:
                    raise PayloadError(
                        f"{len(payload)} bytes (at most {MAX_SERVICE_REQUEST_BYTES})"
                    )
                mode = int(cdr.deserialize(payload, cdr.CONTROL_MODE_COMMAND_REQUEST).mode)
            except PayloadError as exc:
                log.warning("bad ControlModeCommand request: %s", exc)
                request = f"bad ControlModeCommand request: {exc}"
            else:
                if mode == _NO_COMMAND:
                    self._send_service_reply(query, {"accepted": True})
                    return
                request = _CONTROL_MODE_REQUESTS.get(mode, f"control mode {mode} not supported")
            self._queue(query, request, received, service=True)
        except Exception as exc:  # never raise into Zenoh
            log.warning("could not handle a ControlModeCommand call: %s", exc)
            query.drop()

    def _queue(
        self, query: zenoh.Query, request: OperatorRequest | str, received: float, service: bool
    ) -> None:
        if not isinstance(request, OperatorRequest):
            self._refuse(query, request, service)
            return
        queued, displaced = self._lanes.put(_PendingQuery(query, request, received, service))
        for item in displaced:
            self._refuse(
                item.query, f"{item.request.value} superseded by a disengage", item.service
            )
        if not queued:
            self._refuse(
                query, f"busy: {REQUEST_QUEUE_LENGTH} {request.value} requests wait", service
            )

    def _check_query(self, query: zenoh.Query) -> OperatorRequest | str:
        """The request of a query, or why it is refused (exact key, bounded size, one word)."""
        key = str(query.key_expr)
        if key != self._engage_key:
            return f"requests are taken on {self._engage_key} exactly, not on {key}"
        payload = query.payload
        if payload is not None and len(payload) > MAX_REQUEST_BYTES:
            return f"request of {len(payload)} bytes refused (at most {MAX_REQUEST_BYTES})"
        request = parse_request(
            payload.to_bytes() if payload is not None else None,
            query.parameters.get(REQUEST_PARAMETER),
        )
        return request if isinstance(request, OperatorRequest) else unknown_request(request)

    def _refuse(self, query: zenoh.Query, reason: str, service: bool = False) -> None:
        with self._lock:
            self._request_refusals += 1
        reply = self._refusal(reason)
        if service:
            self._send_service_reply(query, reply)
        else:
            self._send_reply(query, reply)

    def _answer_queries(self, stops: bool) -> None:
        while (item := self._lanes.get(stops)) is not None:
            waited = self._clock() - item.received
            if waited > REQUEST_MAX_AGE:
                # Its client has given up by now: never execute it late.
                self._refuse(
                    item.query,
                    f"{item.request.value} abandoned after waiting {waited:.2f} s "
                    f"(at most {REQUEST_MAX_AGE:g} s)",
                    item.service,
                )
            elif item.service:
                self._send_service_reply(item.query, self.answer(item.request))
            else:
                self._send_reply(item.query, self.answer(item.request))
            del item  # drop our reference before waiting for the next one

    def _send_service_reply(self, query: zenoh.Query, reply: Mapping[str, Any]) -> None:
        """The ControlModeCommand response (``success``) for an engage-handler reply."""
        try:
            types = cdr.store().types
            response = cdr.serialize(
                types[cdr.CONTROL_MODE_COMMAND_RESPONSE](success=bool(reply.get("accepted"))),
                cdr.CONTROL_MODE_COMMAND_RESPONSE,
            )
            query.reply(
                query.key_expr,
                response,
                encoding=zenoh.Encoding("application/cdr"),
                attachment=self.ros.reply_attachment(query),
            )
        except (zenoh.ZError, TransportError) as exc:
            log.warning("could not reply to a ControlModeCommand call: %s", exc)
        finally:
            query.drop()

    def _send_reply(self, query: zenoh.Query, reply: Mapping[str, Any]) -> None:
        try:
            query.reply(
                self._engage_key,
                json.dumps(reply).encode(),
                encoding=zenoh.Encoding("application/json"),
            )
        except zenoh.ZError as exc:
            log.warning("could not reply to an engage query: %s", exc)
        finally:
            # Finalise the query now: with the default reply consolidation the querier only
            # sees the reply once the query is final, which waiting for the GC would delay.
            query.drop()

    @property
    def request_refusals(self) -> int:
        """Queries refused before reaching the handler (bad word or key, too big, busy, stale)."""
        return self._request_refusals

    def answer(self, request: OperatorRequest | str) -> dict[str, Any]:
        """The JSON reply to an operator request (unrecognised text is refused here).

        Kept apart from the Zenoh query so that a traceback of the handler never holds the
        query open.
        """
        if not isinstance(request, OperatorRequest):
            return self._refusal(unknown_request(request))
        try:
            return _reply_json(self._handler(request), self._state)
        except Exception as exc:  # the handler's bug must not kill Zenoh's thread
            with self._lock:
                self._handler_errors += 1
            log.error("engage handler failed on %s: %r", request.value, exc)
            return self._refusal(f"handler failed: {exc}")

    def _refusal(self, reason: str) -> dict[str, Any]:
        """A request refused here, before the control loop: changed nothing, in the state the
        gateway last published (``UNKNOWN`` before its first tick)."""
        return _reply_json({"accepted": False, "reason": reason}, self._state)

    # --- outputs --------------------------------------------------------------------------

    def _publish(self, suffix: str, value: Any) -> bool:
        if self._closed or suffix not in self._publishers:  # a role switched off
            return False
        publisher, codec = self._publishers[suffix]
        try:
            if codec is None:
                payload = json.dumps(to_json(value), allow_nan=False).encode()
            else:
                payload = codec.encode(value)
            publisher.put(payload)
        except Exception:  # a bad value or a closed session: count, never raise into the loop
            with self._lock:
                self._publish_errors[suffix] = self._publish_errors.get(suffix, 0) + 1
            return False
        return True

    def publish_steering(self, status: SteeringStatus) -> None:
        """Publish ``vehicle/status/steering_status``; failures are counted, never raised."""
        self._publish("steering_status", status)

    def publish_velocity(self, status: VelocityStatus) -> None:
        """Publish ``vehicle/status/velocity_status``; failures are counted, never raised."""
        self._publish("velocity_status", status)

    def publish_gear(self, status: GearStatus) -> None:
        """Publish ``vehicle/status/gear_status``; failures are counted, never raised."""
        self._publish("gear_status", status)

    def publish_control_mode(self, status: ControlModeStatus) -> None:
        """Publish ``vehicle/status/control_mode``; failures are counted, never raised."""
        self._publish("control_mode", status)

    def publish_lamps(self, stamp: float) -> None:
        """Publish the turn-indicator and hazard-light statuses: DISABLE, since no vehicle
        profile commands them (Autoware's vehicle interface expects both topics)."""
        self._publish("turn_indicators_status", TurnIndicatorsStatus(stamp=stamp))
        self._publish("hazard_lights_status", HazardLightsStatus(stamp=stamp))

    def publish_command(self, command: SentCommand) -> None:
        """Publish the command echo (what was sent), when ``topics.command_echo`` is set."""
        self._publish("command_echo", command)

    def publish_step(self, now: float, result: Any, reports: Mapping[str, Any]) -> None:
        """Publish the vehicle status and the command of one control tick.

        The runtime's publisher thread calls this (the ``Publisher`` protocol of
        :mod:`leafgate.runtime.loop`); only what is known is published.

        :param now: the gateway clock at the tick, s (not used for stamps: see ``stamp_clock``)
        :param result: the tick's ``StepResult`` (``commands``; ``diagnostics.state`` and
            ``diagnostics.ecu_state``)
        :param reports: the latest ``Stamped`` DBW reports by kind (``"steer"``, ``"long"``),
            None where none was received
        """
        stamp = self._stamp_clock()
        steer = _valid_value(reports.get("steer"), SteerReport)
        long = _valid_value(reports.get("long"), LongReport)
        if steer is not None:
            self.publish_steering(steering_status(steer, stamp))
        if long is not None:
            pose = self.pose.get()
            yaw_rate = pose.value.yaw_rate if pose is not None and pose.valid else 0.0
            self.publish_velocity(velocity_status(long, yaw_rate, stamp))
            self.publish_gear(GearStatus(gear=long.gear, stamp=stamp))
        diagnostics = getattr(result, "diagnostics", None)
        if diagnostics is not None:
            self._state = diagnostics.state.name
            mode = control_mode(diagnostics.state, diagnostics.ecu_state)
            self.publish_control_mode(ControlModeStatus(mode=mode, stamp=stamp))
            self.publish_lamps(stamp)
        commands = getattr(result, "commands", None)
        if commands is not None and "command_echo" in self._publishers:
            reverse = long is not None and long.gear == Gear.R
            self.publish_command(
                sent_command(commands.steer, commands.long, stamp, reverse=reverse)
            )

    def publish_diagnostics(self, diagnostics: Mapping[str, Any]) -> None:
        """Publish ``gateway/diagnostics`` as a JSON object (:mod:`leafgate.jsonconv`)."""
        self._publish(DIAGNOSTICS, diagnostics)

    # --- lifecycle ------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare the subscribers, queryable, publishers and liveliness token. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for entity in reversed(self._declared):
            with contextlib.suppress(zenoh.ZError):  # already gone with a closed session
                entity.undeclare()
        self._declared.clear()
        self._lanes.close()  # stop the query threads once they have answered what is queued
        for worker in self._query_workers:
            if worker is not threading.current_thread():
                worker.join(timeout=QUERY_JOIN_TIMEOUT)
        if self._owns_session:
            self._session.close()

    def __enter__(self) -> GatewayTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
