"""leafgate's ROS 2 face on a Zenoh session: keys, attachments and discovery tokens per mode.

:class:`RosFace` declares publishers, subscribers and service queryables for the roles of
:data:`~leafgate.config.transport.DEFAULT_TOPICS` in the mode the configuration chooses
(``zenoh.ros``, see :mod:`leafgate.transport.ros2`): the key expression, the attachment on each
publication, and the liveliness token that lets ROS tools discover the entity. The gateway
(:mod:`leafgate.runtime.node`) and the tools (:mod:`leafgate.transport.client`) both use it,
so a key is built in one place.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from leafgate.config.transport import ZenohConfig
from leafgate.errors import TransportError
from leafgate.transport import ros2


class RosPublisher:
    """A Zenoh publisher of one ROS topic; in rmw_zenoh mode every put carries an attachment."""

    def __init__(
        self, publisher: zenoh.Publisher, key: str, gid: bytes | None, wall: Callable[[], float]
    ) -> None:
        self.publisher = publisher
        self.key = key
        self._gid = gid
        self._wall = wall
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()
        # Zenoh's global ID of the publisher (session ID, entity ID); a stand-in publisher (the
        # fuzzer's stub session) has none, and its samples go out unidentified
        self._id: zenoh.EntityGlobalId | None = getattr(publisher, "id", None)

    def put(self, payload: bytes) -> None:
        """Publish ``payload`` with the publisher's identity: rmw_zenoh's attachment (GID,
        sequence number, source time) in that mode, else Zenoh's source info (the publisher's
        entity ID and a sequence number), so a subscriber can tell publishers apart
        (:func:`sample_source`)."""
        with self._lock:  # sequence numbers in publication order
            sequence = next(self._sequence)
            if self._gid is None:
                if self._id is None:
                    self.publisher.put(payload)
                else:
                    self.publisher.put(payload, source_info=zenoh.SourceInfo(self._id, sequence))
                return
            self.publisher.put(
                payload,
                attachment=ros2.attachment(sequence, round(self._wall() * 1e9), self._gid),
            )

    @property
    def identity(self) -> str:
        """What :func:`sample_source` makes of this publisher's samples."""
        if self._gid is not None:
            return "gid:" + self._gid.hex()
        return "" if self._id is None else _zenoh_identity(self._id)

    def undeclare(self) -> None:
        self.publisher.undeclare()


def sample_source(sample: zenoh.Sample) -> str:
    """The identity of a sample's publisher, ``""`` when the sample carries none.

    ``gid:<hex>`` from an rmw_zenoh attachment (the publisher's GID, ros2/rmw_zenoh
    ``docs/design.md``), else ``zid:<session>/<entity>`` from Zenoh's source info, which
    leafgate's own publishers set (:meth:`RosPublisher.put`). Publishers that send neither (a
    plain ``put``, zenoh-bridge-ros2dds) cannot be told apart: the identity is self-declared,
    so it names a second publisher that does not hide, not one that forges another's.
    """
    attachment = sample.attachment
    if attachment is not None:
        try:
            _, _, gid = ros2.parse_attachment(attachment.to_bytes())
        except TransportError:
            pass  # someone else's attachment: fall through to the source info
        else:
            return "gid:" + gid.hex()
    info = getattr(sample, "source_info", None)  # unstable in zenoh-python: may be absent
    return "" if info is None else _zenoh_identity(info.source_id)


def _zenoh_identity(entity: zenoh.EntityGlobalId) -> str:
    return f"zid:{entity.zid}/{entity.eid}"


class RosFace:
    """The ROS 2 entities of one process on ``session`` (a node in rmw_zenoh mode).

    :param session: an open session (the caller owns it)
    :param cfg: the Zenoh section (``ros``, ``prefix``, topics, domain, node)
    :param node_name: the rmw_zenoh node name (``cfg.node_name`` if None)
    :param wall: the clock of attachment time stamps, s since the Unix epoch
    """

    def __init__(
        self,
        session: zenoh.Session,
        cfg: ZenohConfig,
        *,
        node_name: str | None = None,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self._session = session
        self._cfg = cfg
        self._wall = wall
        self._zid = str(session.zid())
        self.node = ros2.Node(
            domain_id=cfg.domain_id,
            session_id=self._zid,
            namespace=cfg.node_namespace,
            name=node_name or cfg.node_name,
        )
        self._entity_ids = itertools.count(1)
        self._tokens: list[Any] = []
        self.token_keys: list[str] = []  # every liveliness token declared, for diagnostics
        if cfg.ros == "rmw_zenoh":
            self._token(self.node.node_token())

    @property
    def rmw_zenoh(self) -> bool:
        return self._cfg.ros == "rmw_zenoh"

    def type_hash(self, typename: str) -> str:
        return ros2.type_hash(typename, self._cfg.ros_distro)

    def key(self, role: str, typename: str) -> str:
        """The Zenoh key of ``role``'s ROS name carrying ``typename``."""
        fqn = self._cfg.topic(role)
        if self.rmw_zenoh:
            return ros2.topic_key(self._cfg.domain_id, fqn, typename, self.type_hash(typename))
        return self._cfg.key(fqn.lstrip("/"))

    def _token(self, key: str) -> None:
        self._tokens.append(self._session.liveliness().declare_token(key))
        self.token_keys.append(key)

    def _announce(self, kind: str, role: str, typename: str, qos: ros2.Qos) -> bytes:
        """Declare the discovery token of an entity; returns its GID."""
        if self.rmw_zenoh:
            token = self.node.entity_token(
                next(self._entity_ids),
                kind,
                self._cfg.topic(role),
                typename,
                self.type_hash(typename),
                qos,
            )
        else:
            hash_ = None if self._cfg.ros_distro == "humble" else self.type_hash(typename)
            token = ros2.bridge_token(
                self._zid, kind, self.key(role, typename), typename, qos, hash_
            )
        self._token(token)
        return ros2.gid_of(token)

    def publisher(
        self,
        role: str,
        typename: str,
        *,
        mime: str,
        express: bool,
        qos: ros2.Qos = ros2.STATUS_QOS,
    ) -> RosPublisher:
        """Declare a publisher for ``role`` and its MP token."""
        key = self.key(role, typename)
        publisher = self._session.declare_publisher(
            key, encoding=zenoh.Encoding(mime), express=express
        )
        gid = self._announce("MP", role, typename, qos)
        return RosPublisher(publisher, key, gid if self.rmw_zenoh else None, self._wall)

    def subscriber(
        self,
        role: str,
        typename: str,
        callback: Callable[[zenoh.Sample], None],
        *,
        qos: ros2.Qos = ros2.INPUT_QOS,
    ) -> zenoh.Subscriber[None]:
        """Declare a subscriber for ``role`` and its MS token."""
        subscriber = self._session.declare_subscriber(self.key(role, typename), callback)
        self._announce("MS", role, typename, qos)
        return subscriber

    def service(
        self, role: str, typename: str, callback: Callable[[zenoh.Query], None]
    ) -> zenoh.Queryable[None]:
        """Declare a service server for ``role`` (a complete queryable) and its SS token."""
        queryable = self._session.declare_queryable(
            self.key(role, typename), callback, complete=True
        )
        self._announce("SS", role, typename, ros2.SERVICE_QOS)
        return queryable

    def reply_attachment(self, query: zenoh.Query) -> bytes | None:
        """The attachment of a service reply: the request's sequence number and client GID
        with a new source time stamp (rmw_zenoh); None when the request had none."""
        raw = query.attachment
        if raw is None:
            return None
        try:
            sequence, _, gid = ros2.parse_attachment(raw.to_bytes())
        except TransportError:  # not rmw_zenoh's (zenoh-bridge-ros2dds sends a request id)
            return None
        return ros2.attachment(sequence, round(self._wall() * 1e9), gid)

    def close(self) -> None:
        """Undeclare the liveliness tokens. Idempotent."""
        for token in reversed(self._tokens):
            with contextlib.suppress(zenoh.ZError):
                token.undeclare()
        self._tokens.clear()

    undeclare = close  # undeclared with the gateway's other entities
