"""Operator and test tools' side of Zenoh: engage requests, diagnostics, input publishers.

These are tooling, not control path: failures raise
:class:`~leafgate.errors.TransportError` with a one-line message.

Example, with a gateway running on the configured endpoints::

    request(cfg, "engage", timeout=2.0)
    # {'accepted': True, 'state': 'ENGAGED', 'reason': 'engaged', 'changed': True, 'already': False}
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Generic, Self, TypeVar

import zenoh

from leafgate.config.transport import ZenohConfig
from leafgate.errors import TransportError
from leafgate.messages import OperatorRequest, Pose, Trajectory
from leafgate.transport import keys
from leafgate.transport.payloads import Codec, codecs
from leafgate.transport.ros2 import INPUT_QOS
from leafgate.transport.rosnode import RosFace, sample_source
from leafgate.transport.session import open_session, zenoh_message

T = TypeVar("T")

_POLL = 0.01  # s, how often a wait for a matching peer looks again
TOKEN_POLL = 0.05  # s, how often a request looks again for the gateway's liveliness token


@contextmanager
def _session_for(cfg: ZenohConfig, session: zenoh.Session | None) -> Iterator[zenoh.Session]:
    """Use the caller's session, or open one for the duration of the call."""
    if session is not None:
        yield session
        return
    own = open_session(cfg)
    try:
        yield own
    finally:
        own.close()


def _matching(entity: zenoh.Publisher | zenoh.Querier) -> bool:
    """Whether Zenoh knows a subscriber/queryable for the entity's key."""
    status: Any = entity.matching_status  # a MatchingStatus at run time (the stub says bool)
    return bool(getattr(status, "matching", status))


def _wait_matching(
    entity: zenoh.Publisher | zenoh.Querier,
    deadline: float,
    stop: threading.Event | None = None,
) -> bool:
    """Wait until Zenoh knows a subscriber/queryable for the entity's key, or the deadline (or
    ``stop`` is set)."""
    while True:
        if _matching(entity):
            return True
        if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
            return False
        if stop is None:
            time.sleep(_POLL)
        else:
            stop.wait(_POLL)


def gateway_ids(cfg: ZenohConfig, session: zenoh.Session, timeout: float) -> set[str]:
    """Zenoh IDs of the gateways whose liveliness token is up under ``cfg``'s prefix.

    A gateway holds ``{prefix}/gateway/alive/<its Zenoh ID>`` besides ``gateway/alive``.
    """
    base = cfg.key(keys.ALIVE) + "/"
    found = set()
    for reply in session.liveliness().get(base + "*", timeout=timeout):
        if reply.ok is not None:
            found.add(str(reply.ok.key_expr).removeprefix(base))
    return found


def request(
    cfg: ZenohConfig,
    what: str | OperatorRequest,
    timeout: float | None = None,
    *,
    session: zenoh.Session | None = None,
) -> dict[str, Any]:
    """Ask the gateway to ``engage``, ``disengage`` or ``reset``; return its JSON reply.

    Only a reply from a session holding the gateway's liveliness token counts: any other
    reply on the key is not believed, and is listed under ``"ignored_replies"`` (replier ID and
    reply); when more than one session claims to be the gateway, the replies of the others
    are listed under ``"conflicting_replies"``. Either key present means someone else
    answers on the gateway's key.

    :param cfg: the Zenoh section (endpoints, prefix)
    :param what: the request; sent as given, so the gateway's refusal of an unknown word
        comes back as a reply with ``accepted`` false
    :param timeout: s to wait for the gateway (``cfg.query_timeout`` if None)
    :param session: an open session to use (else one is opened and closed)
    :returns: ``{"accepted": bool, "state": str | None, "reason": str, "changed": bool,
        "already": bool}`` and the keys above (``already``: the request found nothing to do)
    :raises TransportError: if no gateway answers in time, or it answers with an error
    """
    text = what.value if isinstance(what, OperatorRequest) else str(what)
    wait = cfg.query_timeout if timeout is None else timeout
    key = cfg.key(keys.ENGAGE)
    deadline = time.monotonic() + wait
    answers: dict[str, dict[str, Any]] = {}
    others: list[dict[str, Any]] = []
    with _session_for(cfg, session) as s:
        # No consolidation: every replier's reply is seen, each as soon as it arrives.
        querier = s.declare_querier(key, timeout=wait, consolidation=zenoh.ConsolidationMode.NONE)
        try:
            # A query sent before the gateway's queryable is known goes nowhere: wait for it.
            if not _wait_matching(querier, deadline):
                raise TransportError(f"no gateway answered on {key} within {round(wait, 1):g} s")
            # Its token may reach us a moment after its queryable (a gateway just starting).
            gateways = gateway_ids(cfg, s, max(0.05, deadline - time.monotonic()))
            while not gateways and time.monotonic() < deadline:
                time.sleep(TOKEN_POLL)
                gateways = gateway_ids(cfg, s, max(0.05, deadline - time.monotonic()))
            if not gateways:
                raise TransportError(f"no gateway liveliness token under {cfg.key(keys.ALIVE)}")
            for reply in querier.get(payload=text.encode()):
                replier = reply.replier_id
                zid = str(replier.zid) if replier is not None else "?"
                if reply.ok is not None:
                    try:
                        answer = json.loads(reply.ok.payload.to_bytes())
                    except ValueError:
                        answer = None
                    if zid not in gateways:
                        others.append({"replier": zid, "reply": answer})
                        continue
                    if not isinstance(answer, dict):
                        raise TransportError(f"{key}: the gateway's reply is not a JSON object")
                    answers[zid] = answer
                elif reply.err is not None and zid in gateways:
                    detail = reply.err.payload.to_string()
                    raise TransportError(f"{key}: query failed: {detail or 'no detail'}")
        except zenoh.ZError as exc:
            raise TransportError(f"{key}: query failed: {zenoh_message(exc)}") from None
        finally:
            querier.undeclare()
    if not answers:
        raise TransportError(
            f"no gateway answered on {key} within {round(wait, 1):g} s"
            + (
                f" ({len(others)} reply(ies) from sessions without its token ignored)"
                if others
                else ""
            )
        )
    first, *rest = sorted(answers)
    result = dict(answers[first])
    if others:
        result["ignored_replies"] = others
    if rest:
        result["conflicting_replies"] = [{"replier": z, "reply": answers[z]} for z in rest]
    return result


def engage(
    cfg: ZenohConfig,
    wait: float,
    *,
    on_waiting: Callable[[str], None] | None = None,
    session: zenoh.Session | None = None,
    poll: float = 0.2,
) -> dict[str, Any]:
    """Ask the gateway to engage, asking again while it refuses for a reason that may pass.

    A gateway that has just started lacks inputs for a moment (localization, trajectory, the
    ECU's reports): its refusal names what is missing, and this asks again every ``poll`` s
    until ``wait`` s have passed. A refusal that waiting cannot cure ends at once: a latched
    fault (reset first) or a request that changes nothing (already engaged).

    :param wait: s to wait for the gateway and for its inputs, in all
    :param on_waiting: called with the refusal's reason each time it changes
    :returns: the last reply
    :raises TransportError: if no gateway answers within ``wait``
    """
    deadline = time.monotonic() + wait
    last = ""
    with _session_for(cfg, session) as s:
        while True:
            left = max(deadline - time.monotonic(), 0.1)
            reply = request(cfg, "engage", timeout=left, session=s)
            final = reply.get("state") == "FAULT" or bool(reply.get("already"))
            if reply.get("accepted") or final or time.monotonic() + poll >= deadline:
                return reply
            reason = str(reply.get("reason", ""))
            if reason != last and on_waiting is not None:
                on_waiting(reason)
            last = reason
            time.sleep(poll)


@dataclasses.dataclass
class DiagnosticsWatch:
    """What :func:`watch_diagnostics` saw besides the records it delivered."""

    #: Zenoh IDs of the gateways (liveliness token holders) whose records were delivered; more
    #: than one is a conflict: several sessions claim to be the gateway
    gateways: set[str] = dataclasses.field(default_factory=set)
    #: records not believed, per publisher identity (``zid:<session>/<entity>``, or
    #: ``unidentified``): their publisher does not hold the gateway's liveliness token
    ignored: dict[str, int] = dataclasses.field(default_factory=dict)

    #: every Zenoh ID seen holding the token while watched
    holders: set[str] = dataclasses.field(default_factory=set)

    #: set to end the watch before its duration (the callback may set it on its Zenoh thread:
    #: ``leafgate status`` does when its reader has gone, ``… | head -1``)
    done: threading.Event = dataclasses.field(default_factory=threading.Event)

    def foreign(self) -> dict[str, int]:
        """The ignored records of publishers that never held the token while watched (a
        gateway's records that arrived just before its token was seen are not foreign)."""
        return {who: n for who, n in self.ignored.items() if _zid_of(who) not in self.holders}


def _zid_of(identity: str) -> str:
    """The Zenoh session ID of a ``zid:<session>/<entity>`` identity, "" for any other."""
    return identity.removeprefix("zid:").partition("/")[0] if identity.startswith("zid:") else ""


def watch_diagnostics(
    cfg: ZenohConfig,
    callback: Callable[[dict[str, Any]], None],
    duration: float,
    *,
    session: zenoh.Session | None = None,
    watch: DiagnosticsWatch | None = None,
) -> int:
    """Call ``callback`` with each ``gateway/diagnostics`` object for ``duration`` seconds.

    Only records published by a session that holds the gateway's liveliness token
    (``gateway/alive/<its Zenoh ID>``) are believed, as :func:`request` believes only its
    replies: anyone may publish on the key, and a forged record would show the operator a
    state the gateway is not in. The gateway's publisher names itself with Zenoh's source
    info; records without it, or from another session, are skipped and counted in ``watch``,
    as are the gateways heard (more than one: a conflict). Payloads that are not JSON objects
    are skipped. The callback runs on a Zenoh thread; setting ``watch.done`` ends the watch
    early.

    :returns: the number of diagnostics objects delivered
    """
    count = 0
    closed = False  # set once the subscription is gone: a late callback delivers nothing
    lock = threading.Lock()
    delivery = threading.Lock()  # one delivery at a time, and none after ``closed``
    seen = watch if watch is not None else DiagnosticsWatch()
    holders: set[str] = set()  # Zenoh IDs holding the token now
    base = cfg.key(keys.ALIVE) + "/"

    def on_token(sample: zenoh.Sample) -> None:
        zid = str(sample.key_expr).removeprefix(base)
        with lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                holders.discard(zid)
            else:
                holders.add(zid)
                seen.holders.add(zid)

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal count
        source = sample_source(sample)
        zid = _zid_of(source)
        with lock:
            believed = bool(zid) and zid in holders
            if not believed:
                who = source or "unidentified"
                seen.ignored[who] = seen.ignored.get(who, 0) + 1
                return
        try:
            data = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if isinstance(data, dict):
            with lock:
                seen.gateways.add(zid)
            with delivery:
                if closed:
                    return
                count += 1
                callback(data)

    with _session_for(cfg, session) as s:
        # The tokens first (with those already there), so the first records are judged.
        tokens = s.liveliness().declare_subscriber(base + "*", on_token, history=True)
        try:
            subscriber = s.declare_subscriber(cfg.key(keys.DIAGNOSTICS), on_sample)
            try:
                seen.done.wait(max(0.0, duration))
            finally:
                subscriber.undeclare()
        finally:
            tokens.undeclare()
    # Zenoh's undeclare does not wait for a callback already running: close the gate so the
    # count returned is the number of objects the callback was given, now and later.
    with delivery:
        closed = True
        return count


class _InputPublisher(Generic[T]):
    """A publisher of one gateway input (a topic role) in the configured encoding and ROS
    mode; it announces itself as node ``<node_name>_<role>`` in rmw_zenoh mode."""

    def __init__(self, session: zenoh.Session, cfg: ZenohConfig, role: str, codec: Codec[T]):
        self._codec = codec
        self._face = RosFace(session, cfg, node_name=f"{cfg.node_name}_{role}")
        self._ros = self._face.publisher(
            role, codec.typename, mime=codec.mime, express=cfg.express, qos=INPUT_QOS
        )
        self.key = self._ros.key
        self._publisher = self._ros.publisher

    @property
    def identity(self) -> str:
        """The publisher's identity as the gateway names it (in a second-source fault)."""
        return self._ros.identity

    @property
    def matched(self) -> bool:
        """Whether a subscriber for the key is known (the gateway is listening)."""
        return _matching(self._publisher)

    def wait_for_subscriber(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Wait up to ``timeout`` s (or until ``stop`` is set) for a subscriber; True if one is
        known."""
        return _wait_matching(self._publisher, time.monotonic() + timeout, stop)

    def _put(self, value: T) -> None:
        self._ros.put(self._codec.encode(value))

    def close(self) -> None:
        """Undeclare the publisher and its tokens (the session stays the caller's)."""
        self._publisher.undeclare()
        self._face.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class OdometryPublisher(_InputPublisher[Pose]):
    """Publishes the ``kinematic_state`` topic (nav_msgs/msg/Odometry).

    :param session: an open session (the caller closes it)
    :param cfg: the Zenoh section (prefix, encoding)
    """

    def __init__(self, session: zenoh.Session, cfg: ZenohConfig) -> None:
        super().__init__(session, cfg, "kinematic_state", codecs(cfg.encoding).pose)

    def publish(self, pose: Pose, stamp: float | None = None) -> None:
        """Publish ``pose``; ``stamp`` (s) replaces the pose's own stamp when given.

        :raises TransportError: if the pose cannot be encoded
        """
        if stamp is not None:
            pose = dataclasses.replace(pose, stamp=stamp)
        self._put(pose)


class TrajectoryPublisher(_InputPublisher[Trajectory]):
    """Publishes the ``trajectory`` topic (autoware_planning_msgs/msg/Trajectory).

    :param session: an open session (the caller closes it)
    :param cfg: the Zenoh section (prefix, encoding)
    """

    def __init__(self, session: zenoh.Session, cfg: ZenohConfig) -> None:
        super().__init__(session, cfg, "trajectory", codecs(cfg.encoding).trajectory)

    def publish(self, trajectory: Trajectory) -> None:
        """Publish ``trajectory``.

        :raises TransportError: if it cannot be encoded
        """
        self._put(trajectory)


def publish_trajectory(
    cfg: ZenohConfig,
    trajectory: Trajectory,
    timeout: float | None = None,
    *,
    session: zenoh.Session | None = None,
) -> None:
    """Publish one trajectory once the gateway's subscriber is known.

    A one-shot publication before the subscriber is known would be lost, so this waits for
    it first (up to ``timeout`` s, ``cfg.query_timeout`` if None).

    :raises TransportError: if no subscriber appears in time or the trajectory cannot be encoded
    """
    wait = cfg.query_timeout if timeout is None else timeout
    with _session_for(cfg, session) as s, TrajectoryPublisher(s, cfg) as publisher:
        if not publisher.wait_for_subscriber(wait):
            raise TransportError(f"nobody subscribes to {publisher.key} (waited {wait:g} s)")
        publisher.publish(trajectory)
