"""A ROS 2 node on rmw_zenoh, as the tests see one: written from ros2/rmw_zenoh docs/design.md
and REP-2011, not from leafgate's code.

- :func:`rihs01` hashes a type description per REP-2011 (sha256 over the canonical JSON of the
  type and every type it references, sorted by name; field type ids from
  ``type_description_interfaces/msg/FieldType``), from the ``.msg`` texts in :data:`MSGS`
  (upstream common_interfaces and autoware_msgs);
- :class:`Peer` is one Zenoh session in peer mode connected to the router, with a node token,
  publishers that attach ``<seq int64 LE><timestamp ns int64 LE><16><GID>``, subscribers that
  read the attachment, a graph view from the ``@ros2_lv`` tokens, and service calls.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

# --- .msg texts (constants and comments left out: they are not part of the hash) -----------

MSGS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/msg/String": "string data",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist"
    ),
    "autoware_planning_msgs/msg/TrajectoryPoint": (
        "builtin_interfaces/Duration time_from_start\ngeometry_msgs/Pose pose\n"
        "float32 longitudinal_velocity_mps\nfloat32 lateral_velocity_mps\n"
        "float32 acceleration_mps2\nfloat32 heading_rate_rps\n"
        "float32 front_wheel_angle_rad\nfloat32 rear_wheel_angle_rad"
    ),
    "autoware_planning_msgs/msg/Trajectory": "std_msgs/Header header\nTrajectoryPoint[] points",
    "autoware_vehicle_msgs/msg/SteeringReport": (
        "builtin_interfaces/Time stamp\nfloat32 steering_tire_angle"
    ),
    "autoware_vehicle_msgs/msg/VelocityReport": (
        "std_msgs/Header header\nfloat32 longitudinal_velocity\nfloat32 lateral_velocity\n"
        "float32 heading_rate"
    ),
    "autoware_vehicle_msgs/msg/GearReport": "builtin_interfaces/Time stamp\nuint8 report",
    "autoware_vehicle_msgs/msg/ControlModeReport": "builtin_interfaces/Time stamp\nuint8 mode",
    "autoware_vehicle_msgs/msg/TurnIndicatorsReport": "builtin_interfaces/Time stamp\nuint8 report",
    "autoware_vehicle_msgs/msg/HazardLightsReport": "builtin_interfaces/Time stamp\nuint8 report",
    "service_msgs/msg/ServiceEventInfo": (
        "uint8 event_type\nbuiltin_interfaces/Time stamp\nchar[16] client_gid\n"
        "int64 sequence_number"
    ),
}
SRVS: dict[str, tuple[str, str]] = {
    "autoware_vehicle_msgs/srv/ControlModeCommand": (
        "builtin_interfaces/Time stamp\nuint8 mode",
        "bool success",
    ),
    "example_interfaces/srv/AddTwoInts": ("int64 a\nint64 b", "int64 sum"),
}

# type_description_interfaces/msg/FieldType; 'char' is uint8 once rosidl turns .msg into IDL.
_TYPE_IDS = {
    "int8": 2,
    "uint8": 3,
    "char": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "bool": 15,
    "byte": 16,
    "string": 17,
}


def _field(line: str, package: str) -> tuple[str, dict[str, Any]]:
    typ, name = line.split()[:2]
    capacity, offset = 0, 0
    if typ.endswith("]"):
        typ, bound = typ[:-1].split("[")
        if bound == "":
            offset = 144  # unbounded sequence
        elif bound.startswith("<="):
            offset, capacity = 96, int(bound[2:])
        else:
            offset, capacity = 48, int(bound)
    nested = ""
    if typ in _TYPE_IDS:
        type_id = _TYPE_IDS[typ]
    else:
        pkg, _, base = typ.rpartition("/")
        nested = f"{pkg or package}/msg/{base}"
        type_id = 1
    return name, {
        "type_id": type_id + offset,
        "capacity": capacity,
        "string_capacity": 0,
        "nested_type_name": nested,
    }


def _description(name: str, text: str) -> dict[str, Any]:
    package = name.split("/")[0]
    fields = [_field(line, package) for line in text.splitlines() if line.strip()]
    return {"type_name": name, "fields": [{"name": n, "type": t} for n, t in fields]}


def _descriptions() -> dict[str, dict[str, Any]]:
    out = {name: _description(name, text) for name, text in MSGS.items()}
    for name, (request, response) in SRVS.items():
        req, resp, event = (f"{name}_{p}" for p in ("Request", "Response", "Event"))
        out[req] = _description(req, request)
        out[resp] = _description(resp, response)

        def nested(n: str, t: str, kind: int = 1, cap: int = 0) -> dict[str, Any]:
            return {
                "name": n,
                "type": {
                    "type_id": kind,
                    "capacity": cap,
                    "string_capacity": 0,
                    "nested_type_name": t,
                },
            }

        out[event] = {
            "type_name": event,
            "fields": [
                nested("info", "service_msgs/msg/ServiceEventInfo"),
                nested("request", req, 97, 1),
                nested("response", resp, 97, 1),
            ],
        }
        out[name] = {
            "type_name": name,
            "fields": [
                nested("request_message", req),
                nested("response_message", resp),
                nested("event_message", event),
            ],
        }
    return out


DESCRIPTIONS = _descriptions()


def rihs01(typename: str) -> str:
    """REP-2011 RIHS01 hash of a message or service type."""
    refs: dict[str, dict[str, Any]] = {}
    todo = [typename]
    while todo:
        for f in DESCRIPTIONS[todo.pop()]["fields"]:
            nested = f["type"]["nested_type_name"]
            if nested and nested not in refs:
                refs[nested] = DESCRIPTIONS[nested]
                todo.append(nested)
    hashable = {
        "type_description": DESCRIPTIONS[typename],
        "referenced_type_descriptions": [refs[k] for k in sorted(refs)],
    }
    text = json.dumps(hashable, separators=(", ", ": "), ensure_ascii=True)
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()


# --- rmw_zenoh names (design.md) -------------------------------------------------------------


def dds_name(typename: str) -> str:
    pkg, kind, base = typename.split("/")
    return f"{pkg}::{kind}::dds_::{base}_"


def key_of(domain: int, name: str, typename: str) -> str:
    return f"{domain}/{name.strip('/')}/{dds_name(typename)}/{rihs01(typename)}"


def attachment(seq: int, gid: bytes) -> bytes:
    return (
        seq.to_bytes(8, "little", signed=True)
        + time.time_ns().to_bytes(8, "little")
        + (bytes([16]) + gid)
    )


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    assert len(data) == 33 and data[16] == 16, data.hex()
    seq, stamp = struct.unpack_from("<qq", data)
    return seq, stamp, data[17:]


class Peer:
    """One ROS 2 context on rmw_zenoh: a peer-mode session connected to the router."""

    def __init__(self, router: str, domain: int = 0, name: str = "ros_peer") -> None:
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("connect/endpoints", json.dumps([router]))
        config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        config.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(config)
        self.domain = domain
        self.name = name
        self.zid = str(self.session.zid())
        self._ids = itertools.count(1)
        self._held: list[Any] = []
        self._held.append(
            self.session.liveliness().declare_token(
                f"@ros2_lv/{domain}/{self.zid}/0/0/NN/%/%/{name}"
            )
        )

    def _token(self, kind: str, topic: str, typename: str, qos: str = "::,1:,:,:,,") -> None:
        chunks = [
            "@ros2_lv",
            str(self.domain),
            self.zid,
            "0",
            str(next(self._ids)),
            kind,
            "%",
            "%",
            self.name,
            topic.replace("/", "%"),
            dds_name(typename),
            rihs01(typename),
            qos,
        ]
        self._held.append(self.session.liveliness().declare_token("/".join(chunks)))

    def graph(self, timeout: float = 2.0) -> list[list[str]]:
        """Every ``@ros2_lv`` token of the domain, split into its chunks."""
        replies = self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=timeout)
        return [str(r.ok.key_expr).split("/") for r in replies if r.ok is not None]

    def publisher(self, topic: str, typename: str) -> Callable[[bytes], None]:
        key = key_of(self.domain, topic, typename)
        pub = self.session.declare_publisher(key)
        self._held.append(pub)
        self._token("MP", topic, typename)
        gid = os.urandom(16)
        counter = itertools.count(1)
        lock = threading.Lock()

        def put(payload: bytes) -> None:
            with lock:
                pub.put(payload, attachment=attachment(next(counter), gid))

        return put

    def subscribe(
        self, topic: str, typename: str, callback: Callable[[bytes, tuple[int, int, bytes]], None]
    ) -> None:
        def on_sample(sample: zenoh.Sample) -> None:
            raw = sample.attachment
            callback(sample.payload.to_bytes(), read_attachment(raw.to_bytes() if raw else b""))

        key = key_of(self.domain, topic, typename)
        self._held.append(self.session.declare_subscriber(key, on_sample))
        self._token("MS", topic, typename)

    def call(
        self, service: str, typename: str, request: bytes, timeout: float = 5.0
    ) -> tuple[bytes, tuple[int, int, bytes]] | None:
        """One service call: a query to all complete queryables with the request attachment."""
        key = key_of(self.domain, service, typename)
        gid = os.urandom(16)
        for reply in self.session.get(
            key,
            payload=request,
            attachment=attachment(7, gid),
            target=zenoh.QueryTarget.ALL_COMPLETE,
            timeout=timeout,
        ):
            if reply.ok is not None:
                raw = reply.ok.attachment
                meta = read_attachment(raw.to_bytes() if raw else b"")
                assert meta[0] == 7 and meta[2] == gid, "the reply names another request"
                return reply.ok.payload.to_bytes(), meta
        return None

    def close(self) -> None:
        for entity in reversed(self._held):
            entity.undeclare()
        self.session.close()
