"""ROS 2 names on Zenoh: rmw_zenoh key expressions, attachments, liveliness tokens, type hashes.

Two ways of meeting ROS 2 (``zenoh.ros`` in the configuration):

- ``rmw_zenoh`` — leafgate is a ROS 2 node on the Zenoh middleware of ROS 2 (``rmw_zenoh_cpp``,
  ros2/rmw_zenoh ``docs/design.md``):

  - a topic or service is the key ``<domain_id>/<fully qualified name without the leading
    '/'>/<DDS type name>/<RIHS01 type hash>``, e.g.
    ``0/vehicle/status/steering_status/autoware_vehicle_msgs::msg::dds_::SteeringReport_/RIHS01_…``;
  - every publication and service reply carries an attachment: sequence number (int64 LE),
    source timestamp (ns since the Unix epoch, int64 LE), GID length (one byte, 16) and GID;
  - the node and each publisher (``MP``), subscription (``MS``) and service server (``SS``)
    declare a liveliness token ``@ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/
    <kind>/<enclave>/<namespace>/<node_name>[/<topic>/<type>/<hash>/<qos>]`` with every
    ``/`` inside a name replaced by ``%``.

- ``bridge`` — leafgate speaks plain Zenoh next to ``zenoh-bridge-ros2dds`` started with the
  ROS namespace ``/<prefix>`` (e.g. ``-n /leaf``): the key of the absolute ROS name ``/a/b`` is
  ``<prefix>/a/b`` and the bridge routes it to ``/a/b`` on its DDS side. Announcement tokens in
  the bridge's format (``@/<zenoh_id>/@ros2_lv/MP/<key with '/' as '§'>/<type>/<qos>``) make
  the bridges create the DDS endpoints, so ROS tools see the topics.

Type hashes are REP-2011 RIHS01 hashes (sha256 over the canonical JSON of the type
description), computed from the ``.msg`` definitions for the configured ROS distribution.
``tests/test_ros2_names.py`` checks them against published Jazzy values (``std_msgs/msg/String``
and the ``example_interfaces/srv/AddTwoInts`` service from the design document,
``nav_msgs/msg/Odometry`` and seven Autoware messages) and against an independent REP-2011
implementation. The GID of an entity is the XXH3-128 of its liveliness token, as rmw_zenoh
computes it (:func:`gid_of`), so the GID in leafgate's attachments is the one ROS tools list for
its endpoints.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from typing import Any

import xxhash
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

from leafgate.errors import TransportError
from leafgate.transport import cdr

ADMIN_SPACE = "@ros2_lv"  # rmw_zenoh's liveliness prefix (a hermetic Zenoh namespace)
SLASH = "%"  # rmw_zenoh's replacement for '/' inside a token chunk
BRIDGE_SLASH = "§"  # zenoh-plugin-ros2dds's replacement for '/'
GID_SIZE = 16  # bytes
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE  # bytes
NO_TYPE_HASH = "TypeHashNotSupported"  # what rmw_zenoh writes on Humble, which has no hashes

# Distributions with REP-2011 type hashes (Iron and later) and the rosbags store of each.
_STORES: dict[str, Stores] = {
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}
DISTROS = ("humble", *_STORES)

# ROS 2 ``rmw_qos_*`` enum values (rmw/types.h).
RELIABLE = 1
BEST_EFFORT = 2
TRANSIENT_LOCAL = 1
VOLATILE = 2
KEEP_LAST = 1
KEEP_ALL = 2


@dataclass(frozen=True)
class Qos:
    """The QoS of one ROS 2 entity (the settings rmw_zenoh and the bridge encode)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 1

    def rmw_zenoh_keyexpr(self) -> str:
        """rmw_zenoh's compact form: each value empty where it equals rmw_zenoh's default.

        ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
        <liveliness>,<lease s>,<ns>``; the defaults are RELIABLE, VOLATILE, KEEP_LAST, depth
        42, infinite durations and AUTOMATIC liveliness, which leafgate does not change.
        """
        reliability = "" if self.reliability == RELIABLE else str(self.reliability)
        durability = "" if self.durability == VOLATILE else str(self.durability)
        history = "" if self.history == KEEP_LAST else str(self.history)
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{reliability}:{durability}:{history},{depth}:,:,:,,"

    def bridge_keyexpr(self, type_hash: str | None) -> str:
        """zenoh-plugin-ros2dds's form ``<keyless>:<reliability>:<durability>:<history>,<depth>
        [:<user data>]`` with DDS enum values; since Iron the user data carries the type hash.
        """
        reliability = "1" if self.reliability == RELIABLE else "0"  # DDS RELIABLE / BEST_EFFORT
        durability = "1" if self.durability == TRANSIENT_LOCAL else "0"  # DDS TRANSIENT_LOCAL
        history = "1" if self.history == KEEP_ALL else "0"  # DDS KEEP_ALL / KEEP_LAST
        text = f":{reliability}:{durability}:{history},{self.depth}"
        if type_hash is not None and type_hash != NO_TYPE_HASH:
            text += f":typehash={type_hash};"
        return text


STATUS_QOS = Qos(depth=1)  # Autoware's vehicle interface publishes and reads with depth 1
INPUT_QOS = Qos(depth=1)
SERVICE_QOS = Qos(depth=10)  # rclcpp's services default


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` becomes ``%`` (rmw_zenoh)."""
    return name.replace("/", SLASH)


def dds_type_name(typename: str) -> str:
    """``pkg/msg/Name`` → ``pkg::msg::dds_::Name_`` (the DDS name rmw_zenoh puts in keys)."""
    parts = typename.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise TransportError(f"not a ROS 2 interface type name: {typename!r}")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def resolve(name: str, namespace: str) -> str:
    """The fully qualified ROS name of ``name``: absolute names as given, relative ones under
    the node's ``namespace``.

    :raises TransportError: for an empty name or one with an empty chunk
    """
    if not name or name.endswith("/") or "//" in name or "~" in name:
        raise TransportError(f"bad ROS name {name!r}")
    if name.startswith("/"):
        return name
    return f"{namespace.rstrip('/')}/{name}"


def topic_key(domain_id: int, fqn: str, typename: str, type_hash: str) -> str:
    """The rmw_zenoh key expression of a topic or service."""
    return f"{domain_id}/{fqn.strip('/')}/{dds_type_name(typename)}/{type_hash}"


# --- type hashes -----------------------------------------------------------------------------

# ``service_msgs/msg/ServiceEventInfo`` as rosidl sees it: ``char[16] client_gid`` in the .msg
# file becomes ``uint8[16]`` in the IDL from which the type description is generated.
_SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
_SERVICE_EVENT_INFO_FIELDS: list[tuple[str, Any]] = [
    ("event_type", (Nodetype.BASE, ("uint8", 0))),
    ("stamp", (Nodetype.NAME, "builtin_interfaces/msg/Time")),
    ("client_gid", (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), 16))),
    ("sequence_number", (Nodetype.BASE, ("int64", 0))),
]


def _fields(text: str) -> Any:
    """The (constants, fields) of a ``.msg`` text, as rosbags stores them."""
    ((_, definition),) = get_types_from_msg(text, "leafgate_tmp/msg/Tmp").items()
    return definition


def service_types(typename: str, request: str, response: str) -> dict[str, Any]:
    """The type store entries of service ``typename`` (``pkg/srv/Name``) per REP-2011:
    ``Name_Request``, ``Name_Response``, ``Name_Event`` and the service type itself."""
    req, resp, event = (f"{typename}_{part}" for part in ("Request", "Response", "Event"))
    return {
        req: _fields(request),
        resp: _fields(response),
        event: (
            [],
            [
                ("info", (Nodetype.NAME, _SERVICE_EVENT_INFO)),
                ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, req), 1))),
                ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, resp), 1))),
            ],
        ),
        typename: (
            [],
            [
                ("request_message", (Nodetype.NAME, req)),
                ("response_message", (Nodetype.NAME, resp)),
                ("event_message", (Nodetype.NAME, event)),
            ],
        ),
    }


@functools.cache
def _hash_store(distro: str) -> Typestore:
    """A type store for hashing: the distribution's messages plus leafgate's interfaces."""
    store = get_typestore(_STORES[distro])
    types: dict[str, Any] = {}
    for typename, text in cdr.MSG_TEXTS.items():
        types.update(get_types_from_msg(text, typename))
    for typename, (request, response) in cdr.SRV_TEXTS.items():
        types.update(service_types(typename, request, response))
    store.register(types)
    consts, _ = store.fielddefs[_SERVICE_EVENT_INFO]
    store.fielddefs[_SERVICE_EVENT_INFO] = (consts, _SERVICE_EVENT_INFO_FIELDS)
    return store


def register_service(distro: str, typename: str, request: str, response: str) -> None:
    """Add a service to the hashing store of ``distro`` (tests hash well-known services)."""
    if distro in _STORES:
        _hash_store(distro).register(service_types(typename, request, response))


def type_hash(typename: str, distro: str = "jazzy") -> str:
    """The RIHS01 hash of a message or service type for ``distro``
    (``TypeHashNotSupported`` on Humble, as rmw_zenoh writes there).

    :raises TransportError: for an unknown distribution or type
    """
    if distro == "humble":
        return NO_TYPE_HASH
    if distro not in _STORES:
        raise TransportError(f"unknown ROS 2 distribution {distro!r} (one of {', '.join(DISTROS)})")
    store = _hash_store(distro)
    if typename not in store.fielddefs:
        raise TransportError(f"unknown ROS type {typename!r}")
    return store.hash_rihs01(typename)


# --- attachments -----------------------------------------------------------------------------


def gid_of(token: str) -> bytes:
    """The 16-byte GID of the entity whose liveliness token is ``token``, as rmw_zenoh derives
    it (``Entity::Entity`` in rmw_zenoh_cpp's liveliness_utils.cpp): the XXH3-128 hash of the
    token, its low 64 bits then its high 64, each little-endian — the GID a ROS node lists for
    leafgate's endpoints (``ros2 topic info -v``) and finds in its messages' attachments."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment: int64 LE sequence number, int64 LE source timestamp (ns since
    the Unix epoch), one byte GID length, the GID."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(gid)}")
    return struct.pack("<qqB", sequence, stamp_ns, GID_SIZE) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp in ns, GID) of an rmw_zenoh attachment.

    :raises TransportError: when the bytes are not such an attachment
    """
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise TransportError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    sequence, stamp_ns, _ = struct.unpack_from("<qqB", data)
    return sequence, stamp_ns, bytes(data[17:])


# --- liveliness tokens -----------------------------------------------------------------------


@dataclass(frozen=True)
class Node:
    """The identity of leafgate's ROS 2 node in the rmw_zenoh graph."""

    domain_id: int
    session_id: str  # the Zenoh session's id, as Zenoh prints it
    namespace: str = "/"
    name: str = "leafgate"
    enclave: str = "/"
    node_id: int = 0

    def _head(self, entity_id: int, kind: str) -> str:
        return "/".join(
            (
                ADMIN_SPACE,
                str(self.domain_id),
                self.session_id,
                str(self.node_id),
                str(entity_id),
                kind,
                mangle(self.enclave),
                mangle(self.namespace),
                self.name,
            )
        )

    def node_token(self) -> str:
        """The ``NN`` token of the node itself (its entity id is its node id)."""
        return self._head(self.node_id, "NN")

    def entity_token(
        self, entity_id: int, kind: str, fqn: str, typename: str, hash_: str, qos: Qos
    ) -> str:
        """The token of a publisher (``MP``), subscription (``MS``), service server (``SS``)
        or client (``SC``) on the fully qualified name ``fqn``."""
        if kind not in ("MP", "MS", "SS", "SC"):
            raise ValueError(f"unknown entity kind {kind!r}")
        return "/".join(
            (
                self._head(entity_id, kind),
                mangle(fqn),
                dds_type_name(typename),
                hash_,
                qos.rmw_zenoh_keyexpr(),
            )
        )


def bridge_token(
    zenoh_id: str,
    kind: str,
    key: str,
    typename: str,
    qos: Qos | None = None,
    hash_: str | None = None,
) -> str:
    """zenoh-plugin-ros2dds's announcement of a publisher (``MP``), subscriber (``MS``) or
    service server (``SS``, no QoS) on Zenoh ``key`` with ROS type ``typename`` (and, since
    Iron, its type hash in the QoS user data)."""
    head = f"@/{zenoh_id}/{ADMIN_SPACE}/{kind}/{key.replace('/', BRIDGE_SLASH)}"
    head += f"/{typename.replace('/', BRIDGE_SLASH)}"
    if kind in ("MP", "MS"):
        if qos is None:
            raise ValueError("publishers and subscribers announce a QoS")
        return f"{head}/{qos.bridge_keyexpr(hash_)}"
    return head
