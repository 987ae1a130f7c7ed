"""The gateway's side of Zenoh: input slots, status publishers, the engage queryable.

Zenoh calls the subscriber and queryable callbacks on its own threads. Each input key has a
:class:`LatestSlot` that keeps only the newest decoded sample as a
:class:`~leafgate.messages.Stamped` value with its receive time; the control thread reads the
slots without waiting (a read is one reference load of an immutable object). Nothing in here
raises into the control loop or into Zenoh's threads: undecodable payloads and unencodable
values are counted per key and dropped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar

import numpy as np
import zenoh

from leafgate.control.reference import trajectory_problem
from leafgate.errors import TransportError
from leafgate.messages import (
    Gear,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerReport,
    Trajectory,
)
from leafgate.transport import cdr, keys
from leafgate.transport.config import ZenohConfig
from leafgate.transport.payloads import (
    Codec,
    ControlModeStatus,
    GearStatus,
    SentCommand,
    SteeringStatus,
    VelocityStatus,
    codecs,
    control_mode,
    sent_command,
    steering_status,
    velocity_status,
)
from leafgate.transport.session import open_session, zenoh_message

T = TypeVar("T")

log = logging.getLogger(__name__)

Clock = Callable[[], float]
EngageHandler = Callable[[OperatorRequest], Mapping[str, Any]]

REQUEST_PARAMETER = "request"  # selector parameter alternative to the query payload
QUERY_JOIN_TIMEOUT = 2.0  # s, how long close() waits for an engage handler still running


class LatestSlot(Generic[T]):
    """The newest sample of one input key, shared between a Zenoh callback and the control loop.

    Writers (Zenoh's threads) serialise through a lock; readers take no lock: replacing the
    reference to an immutable :class:`~leafgate.messages.Stamped` is atomic, so a reader sees
    either the previous or the new sample, never a mix.
    """

    def __init__(self, key: str) -> None:
        self.key = key
        self._latest: Stamped[T] | None = None
        self._lock = threading.Lock()
        self._received = 0
        self._invalid = 0
        self._errors = 0
        self._last_error = ""

    def get(self) -> Stamped[T] | None:
        """The newest decoded sample with its receive time, or None before the first one."""
        return self._latest

    def put(self, sample: Stamped[T]) -> None:
        """Replace the newest sample (called by the subscriber)."""
        with self._lock:
            self._latest = sample
            self._received += 1
            if not sample.valid:
                self._invalid += 1

    def count_error(self, reason: str) -> None:
        """Count a payload that was dropped; the newest good sample stays."""
        with self._lock:
            self._errors += 1
            self._last_error = reason

    @property
    def received(self) -> int:
        """Samples decoded and stored so far."""
        return self._received

    @property
    def invalid(self) -> int:
        """Samples decoded but stored marked invalid (not finite, no points); in ``received``."""
        return self._invalid

    @property
    def errors(self) -> int:
        """Payloads dropped because they did not decode."""
        return self._errors

    @property
    def last_error(self) -> str:
        """Why the last dropped payload was dropped ("" if none was)."""
        return self._last_error


def pose_is_valid(pose: Pose) -> bool:
    """A decoded pose is usable when every kinematic field is finite (the stamp may be unset)."""
    return all(math.isfinite(v) for v in (pose.x, pose.y, pose.heading, pose.speed, pose.yaw_rate))


def trajectory_is_valid(trajectory: Trajectory) -> bool:
    """A decoded trajectory is usable by the controller's one rule (:func:`~leafgate.control.
    reference.trajectory_problem`): finite, four or more waypoints once overlaps are removed."""
    return trajectory_problem(trajectory) is None


def to_jsonable(value: Any) -> Any:
    """Make diagnostics JSON-safe: enums by name, NaN/±inf as null, numpy as Python.

    Dataclasses become objects, tuples and arrays lists; anything else unknown becomes its
    ``str`` so a diagnostics publication never fails on an odd value.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [to_jsonable(v) for v in value.tolist()]
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return str(value)


def _reply_json(reply: Mapping[str, Any]) -> dict[str, Any]:
    """The engage reply with its three fields always present."""
    out = to_jsonable(dict(reply))
    out["accepted"] = bool(out.get("accepted", False))
    out.setdefault("state", None)
    out["reason"] = str(out.get("reason") or "")
    return out


def parse_request(query_payload: bytes | None, parameter: str | None) -> OperatorRequest | str:
    """The operator request of a query: payload text, else the ``request=`` parameter.

    :returns: the request, or the unrecognised text (for the refusal's reason)
    """
    text = query_payload.decode("utf-8", errors="replace") if query_payload else parameter or ""
    try:
        return OperatorRequest(text.strip().lower())
    except ValueError:
        return text


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
        # Called with (key, raw payload, receive time, ROS type name or None for JSON) for every
        # input sample before it is decoded: the session recorder's tap.
        self.on_raw: Callable[[str, bytes, float, str | None], None] | None = None
        self._tap_errors = 0
        self._lock = threading.Lock()
        # Queries are answered on a thread of our own: the handler may wait for the control
        # thread, and a Zenoh callback that blocks stalls the link it arrived on (and with it
        # the localization samples behind it).
        self._queries: queue.SimpleQueue[zenoh.Query | None] = queue.SimpleQueue()
        self._query_worker = threading.Thread(
            target=self._answer_queries, name="leafgate-engage", daemon=True
        )
        self._query_worker.start()

        self.pose: LatestSlot[Pose] = LatestSlot(cfg.key(keys.KINEMATIC_STATE))
        self.trajectory: LatestSlot[Trajectory] = LatestSlot(cfg.key(keys.TRAJECTORY))

        self._declared: list[Any] = []
        self._publishers: dict[str, tuple[zenoh.Publisher, Codec[Any] | None]] = {}
        try:
            self._declared.append(
                session.declare_subscriber(
                    self.pose.key,
                    self._subscriber(self.pose, self._codecs.pose, pose_is_valid, cdr.ODOMETRY),
                )
            )
            self._declared.append(
                session.declare_subscriber(
                    self.trajectory.key,
                    self._subscriber(
                        self.trajectory,
                        self._codecs.trajectory,
                        trajectory_is_valid,
                        cdr.TRAJECTORY,
                    ),
                )
            )
            self._declared.append(
                session.declare_queryable(cfg.key(keys.ENGAGE), self._queries.put)
            )
            for suffix, codec in (
                (keys.STEERING_STATUS, self._codecs.steering),
                (keys.VELOCITY_STATUS, self._codecs.velocity),
                (keys.GEAR_STATUS, self._codecs.gear),
                (keys.CONTROL_MODE, self._codecs.control_mode),
                (keys.CONTROL_CMD, self._codecs.command),
                (keys.DIAGNOSTICS, None),
            ):
                mime = codec.mime if codec is not None else "application/json"
                publisher = session.declare_publisher(
                    cfg.key(suffix), encoding=zenoh.Encoding(mime), express=cfg.express
                )
                self._declared.append(publisher)
                self._publishers[suffix] = (publisher, codec)
            self._declared.append(session.liveliness().declare_token(cfg.key(keys.ALIVE)))
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
        self, slot: LatestSlot[T], codec: Codec[T], valid: Callable[[T], bool], typename: str
    ) -> Callable[[zenoh.Sample], None]:
        clock = self._clock
        typename_or_none = typename if self._cfg.encoding == "cdr" else None

        def on_sample(sample: zenoh.Sample) -> None:
            received = clock()  # before decoding: the age counts from arrival
            payload = sample.payload.to_bytes()
            if self.on_raw is not None:
                try:
                    self.on_raw(slot.key, payload, received, typename_or_none)
                except Exception:  # a recorder problem must not stop the inputs
                    self._tap_errors += 1
            try:
                value = codec.decode(payload)
                ok = valid(value)
            except Exception as exc:  # PayloadError, or a bug: never raise into Zenoh
                slot.count_error(str(exc))
                return
            slot.put(Stamped(value, received, valid=ok))

        return on_sample

    def latest_pose(self) -> Stamped[Pose] | None:
        """The newest localization sample (receive time on the injected clock)."""
        return self.pose.get()

    def latest_trajectory(self) -> Stamped[Trajectory] | None:
        """The newest trajectory sample (a new object for every message received)."""
        return self.trajectory.get()

    @property
    def decode_errors(self) -> dict[str, int]:
        """Dropped payloads per input key."""
        return {self.pose.key: self.pose.errors, self.trajectory.key: self.trajectory.errors}

    @property
    def invalid_samples(self) -> dict[str, int]:
        """Samples per input key that decoded but were stored marked invalid (the control
        path refuses them); together with :attr:`decode_errors`, every rejected sample."""
        return {self.pose.key: self.pose.invalid, self.trajectory.key: self.trajectory.invalid}

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

    def _answer_queries(self) -> None:
        while (query := self._queries.get()) is not None:
            self._reply(query)
            del query  # drop our reference before waiting for the next one

    def _reply(self, query: zenoh.Query) -> None:
        try:
            payload = query.payload.to_bytes() if query.payload is not None else None
            reply = self.answer(parse_request(payload, query.parameters.get(REQUEST_PARAMETER)))
            query.reply(
                self._cfg.key(keys.ENGAGE),
                json.dumps(reply).encode(),
                encoding=zenoh.Encoding("application/json"),
            )
        except zenoh.ZError as exc:
            log.warning("could not reply to an engage query: %s", exc)
        finally:
            # Finalise the query now: with the default reply consolidation the querier only
            # sees the reply once the query is final, which waiting for the GC would delay.
            query.drop()

    def answer(self, request: OperatorRequest | str) -> dict[str, Any]:
        """The JSON reply to an operator request (unrecognised text is refused here).

        Kept apart from the Zenoh query so that a traceback of the handler never holds the
        query open.
        """
        if not isinstance(request, OperatorRequest):
            known = ", ".join(r.value for r in OperatorRequest)
            return {
                "accepted": False,
                "state": None,
                "reason": f"unknown request {request!r} (expected one of: {known})",
            }
        try:
            return _reply_json(self._handler(request))
        except Exception as exc:  # the handler's bug must not kill Zenoh's thread
            with self._lock:
                self._handler_errors += 1
            log.error("engage handler failed on %s: %r", request.value, exc)
            return {"accepted": False, "state": None, "reason": f"handler failed: {exc}"}

    # --- outputs --------------------------------------------------------------------------

    def _publish(self, suffix: str, value: Any) -> bool:
        if self._closed:
            return False
        publisher, codec = self._publishers[suffix]
        try:
            if codec is None:
                payload = json.dumps(to_jsonable(value), allow_nan=False).encode()
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
        self._publish(keys.STEERING_STATUS, status)

    def publish_velocity(self, status: VelocityStatus) -> None:
        """Publish ``vehicle/status/velocity_status``; failures are counted, never raised."""
        self._publish(keys.VELOCITY_STATUS, status)

    def publish_gear(self, status: GearStatus) -> None:
        """Publish ``vehicle/status/gear_status``; failures are counted, never raised."""
        self._publish(keys.GEAR_STATUS, status)

    def publish_control_mode(self, status: ControlModeStatus) -> None:
        """Publish ``vehicle/status/control_mode``; failures are counted, never raised."""
        self._publish(keys.CONTROL_MODE, status)

    def publish_command(self, command: SentCommand) -> None:
        """Publish ``control/command/control_cmd`` (what was sent)."""
        self._publish(keys.CONTROL_CMD, command)

    def publish_step(self, now: float, result: Any, reports: Mapping[str, Any]) -> None:
        """Publish the vehicle status and the command of one control tick.

        The runtime's publisher thread calls this (the ``Publisher`` protocol of
        :mod:`leafgate.gateway.runtime`); only what is known is published.

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
            mode = control_mode(diagnostics.state, diagnostics.ecu_state)
            self.publish_control_mode(ControlModeStatus(mode=mode, stamp=stamp))
        commands = getattr(result, "commands", None)
        if commands is not None:
            reverse = long is not None and long.gear == Gear.R
            self.publish_command(
                sent_command(commands.steer, commands.long, stamp, reverse=reverse)
            )

    def publish_diagnostics(self, diagnostics: Mapping[str, Any]) -> None:
        """Publish ``gateway/diagnostics`` as a JSON object (see :func:`to_jsonable`)."""
        self._publish(keys.DIAGNOSTICS, diagnostics)

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
        self._queries.put(None)  # stop the query thread once it has answered what is queued
        if self._query_worker is not threading.current_thread():
            self._query_worker.join(timeout=QUERY_JOIN_TIMEOUT)
        if self._owns_session:
            self._session.close()

    def __enter__(self) -> GatewayTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
