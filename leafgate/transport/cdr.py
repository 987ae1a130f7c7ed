"""ROS 2 message types and CDR serialisation, through rosbags (no ROS install needed).

The Autoware messages leafgate exchanges are registered in a rosbags type store from their
``.msg`` field lists, which live here and nowhere else (:data:`MSG_TEXTS`); the same texts give
the MCAP ``ros2msg`` schemas (:func:`msg_definition`). ``nav_msgs/msg/Odometry`` and the
standard messages it uses come with the store (ROS 2 Humble definitions).

The field lists follow ``autowarefoundation/autoware_msgs`` 1.x: ``Control``, ``Lateral`` and
``Longitudinal`` carry the ``control_time`` field added in 2024, so the layout matches current
Autoware (a ``Control`` from an older Autoware will fail to decode and be counted).

>>> raw = serialize(store().types[STEERING_REPORT](
...     stamp=store().types[TIME](sec=1, nanosec=5), steering_tire_angle=0.25), STEERING_REPORT)
>>> deserialize(raw, STEERING_REPORT).steering_tire_angle
0.25
"""

from __future__ import annotations

import functools
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from leafgate.errors import PayloadError, TransportError

# --- type names ------------------------------------------------------------------------------

ODOMETRY = "nav_msgs/msg/Odometry"
TRAJECTORY = "autoware_planning_msgs/msg/Trajectory"
TRAJECTORY_POINT = "autoware_planning_msgs/msg/TrajectoryPoint"
CONTROL = "autoware_control_msgs/msg/Control"
LATERAL = "autoware_control_msgs/msg/Lateral"
LONGITUDINAL = "autoware_control_msgs/msg/Longitudinal"
STEERING_REPORT = "autoware_vehicle_msgs/msg/SteeringReport"
VELOCITY_REPORT = "autoware_vehicle_msgs/msg/VelocityReport"
GEAR_REPORT = "autoware_vehicle_msgs/msg/GearReport"
CONTROL_MODE_REPORT = "autoware_vehicle_msgs/msg/ControlModeReport"
TURN_INDICATORS_REPORT = "autoware_vehicle_msgs/msg/TurnIndicatorsReport"
HAZARD_LIGHTS_REPORT = "autoware_vehicle_msgs/msg/HazardLightsReport"
CONTROL_MODE_COMMAND = "autoware_vehicle_msgs/srv/ControlModeCommand"  # a service
CONTROL_MODE_COMMAND_REQUEST = CONTROL_MODE_COMMAND + "_Request"
CONTROL_MODE_COMMAND_RESPONSE = CONTROL_MODE_COMMAND + "_Response"

# Standard types used while building messages.
TIME = "builtin_interfaces/msg/Time"
DURATION = "builtin_interfaces/msg/Duration"
HEADER = "std_msgs/msg/Header"


# --- the .msg texts (autoware_msgs 1.x) -------------------------------------------------------

MSG_TEXTS: dict[str, str] = {
    TRAJECTORY_POINT: """\
builtin_interfaces/Duration time_from_start
geometry_msgs/Pose pose
float32 longitudinal_velocity_mps
float32 lateral_velocity_mps
# acceleration_mps2 increases/decreases based on absolute vehicle motion and does not consider vehicle direction (forward/backward)
float32 acceleration_mps2
float32 heading_rate_rps
float32 front_wheel_angle_rad
float32 rear_wheel_angle_rad
""",
    TRAJECTORY: """\
std_msgs/Header header
autoware_planning_msgs/TrajectoryPoint[] points
""",
    LATERAL: """\
# Lateral control message for Ackermann-style platforms
# Positive values represents left inclination (if forward)

# Time this message was created
builtin_interfaces/Time stamp

# Time this configuration state is expected to be achieved in (optional)
builtin_interfaces/Time control_time

# Desired angle of the steering tire in rad (radians)
float32 steering_tire_angle

# Desired rate of change of the steering tire angle in rad/s
float32 steering_tire_rotation_rate

# Controller has filled in the steering_tire_rotation_rate value
bool is_defined_steering_tire_rotation_rate
""",
    LONGITUDINAL: """\
# Longitudinal control message
# Values are in the base_link frame in X axis; positive forward, negative backward

# Time this message was created
builtin_interfaces/Time stamp

# Time this configuration state is expected to be achieved in (optional)
builtin_interfaces/Time control_time

# Desired vehicle velocity in m/s
float32 velocity

# Desired vehicle acceleration in m/s²
float32 acceleration

# Desired vehicle jerk in m/s³
float32 jerk

# Controller has filled in the acceleration value
bool is_defined_acceleration

# Controller has filled in the jerk value
bool is_defined_jerk
""",
    CONTROL: """\
# Control message with lateral and longitudinal components

# Time this message was created
builtin_interfaces/Time stamp

# Time this configuration state is expected to be achieved in (optional)
builtin_interfaces/Time control_time

# Lateral control command
Lateral lateral

# Longitudinal control command
Longitudinal longitudinal
""",
    STEERING_REPORT: """\
builtin_interfaces/Time stamp
# Steering tire angle [rad]. Positive: left, Negative: right
float32 steering_tire_angle
""",
    VELOCITY_REPORT: """\
std_msgs/Header header
# Longitudinal velocity [m/s]. Positive: forward, Negative: backward
float32 longitudinal_velocity
# Lateral velocity [m/s]. Positive: left, Negative: right
float32 lateral_velocity
# Heading rate (yaw rate) [rad/s]. Positive: counter-clockwise
float32 heading_rate
""",
    GEAR_REPORT: """\
uint8 NONE = 0
uint8 NEUTRAL = 1
uint8 DRIVE = 2
uint8 DRIVE_2 = 3
uint8 DRIVE_3 = 4
uint8 DRIVE_4 = 5
uint8 DRIVE_5 = 6
uint8 DRIVE_6 = 7
uint8 DRIVE_7 = 8
uint8 DRIVE_8 = 9
uint8 DRIVE_9 = 10
uint8 DRIVE_10 = 11
uint8 DRIVE_11 = 12
uint8 DRIVE_12 = 13
uint8 DRIVE_13 = 14
uint8 DRIVE_14 = 15
uint8 DRIVE_15 = 16
uint8 DRIVE_16 = 17
uint8 DRIVE_17 = 18
uint8 DRIVE_18 = 19
uint8 REVERSE = 20
uint8 REVERSE_2 = 21
uint8 PARK = 22
uint8 LOW = 23
uint8 LOW_2 = 24

builtin_interfaces/Time stamp
uint8 report
""",
    CONTROL_MODE_REPORT: """\
uint8 NO_COMMAND = 0
uint8 AUTONOMOUS = 1
uint8 AUTONOMOUS_STEER_ONLY = 2
uint8 AUTONOMOUS_VELOCITY_ONLY = 3
uint8 MANUAL = 4
uint8 DISENGAGED = 5
uint8 NOT_READY = 6

builtin_interfaces/Time stamp
uint8 mode
""",
    TURN_INDICATORS_REPORT: """\
uint8 DISABLE = 1
uint8 ENABLE_LEFT = 2
uint8 ENABLE_RIGHT = 3

builtin_interfaces/Time stamp
uint8 report
""",
    HAZARD_LIGHTS_REPORT: """\
uint8 DISABLE = 1
uint8 ENABLE = 2

builtin_interfaces/Time stamp
uint8 report
""",
}

# Services: (request, response) field lists (autoware_msgs 1.x).
SRV_TEXTS: dict[str, tuple[str, str]] = {
    CONTROL_MODE_COMMAND: (
        """\
uint8 NO_COMMAND = 0
uint8 AUTONOMOUS = 1
uint8 AUTONOMOUS_STEER_ONLY = 2
uint8 AUTONOMOUS_VELOCITY_ONLY = 3
uint8 MANUAL = 4

builtin_interfaces/Time stamp
uint8 mode
""",
        "bool success\n",
    ),
}

# Every type a leafgate key carries (docs/design.md, "The Zenoh interface").
KEY_TYPES: tuple[str, ...] = (
    ODOMETRY,
    TRAJECTORY,
    STEERING_REPORT,
    VELOCITY_REPORT,
    GEAR_REPORT,
    CONTROL_MODE_REPORT,
    TURN_INDICATORS_REPORT,
    HAZARD_LIGHTS_REPORT,
    CONTROL,
)


@functools.cache
def store() -> Typestore:
    """The shared type store: ROS 2 Humble plus the Autoware messages of :data:`MSG_TEXTS`.

    Built once per process; rosbags generates the (de)serialisers lazily on first use.
    """
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for typename, text in MSG_TEXTS.items():
        types.update(get_types_from_msg(text, typename))
    for typename, (request, response) in SRV_TEXTS.items():
        # rosbags names .msg types pkg/msg/Name; a request or response is stored under its
        # ROS name, pkg/srv/Name_Request and pkg/srv/Name_Response.
        for suffix, text in (("_Request", request), ("_Response", response)):
            ((_, fields),) = get_types_from_msg(text, "leafgate_tmp/msg/Tmp").items()
            types[typename + suffix] = fields
    typestore.register(types)
    return typestore


def msg_definition(typename: str) -> str:
    """The full ``ros2msg`` definition of ``typename``, as an MCAP schema wants it.

    The type's own fields first, then every type it uses after a ``MSG: pkg/Type`` separator
    line (the ROS 2 ``ros2msg`` schema encoding of MCAP).

    :param typename: e.g. ``"autoware_planning_msgs/msg/Trajectory"``
    :raises TransportError: if the type is unknown to the store
    """
    typestore = store()
    if typename not in typestore.fielddefs:
        raise TransportError(f"unknown ROS message type {typename!r}")
    text, _ = typestore.generate_msgdef(typename, ros_version=2)
    return text


def serialize(message: object, typename: str) -> bytes:
    """Serialise a rosbags message object to little-endian CDR (with the 4-byte header).

    :raises TransportError: if the object does not fit the type (a programming error)
    """
    try:
        return bytes(store().serialize_cdr(message, typename))
    except Exception as exc:  # rosbags raises assorted errors for bad field values
        raise TransportError(f"cannot serialise {typename}: {exc}") from exc


def deserialize(payload: bytes | memoryview, typename: str) -> Any:
    """Deserialise CDR into a rosbags message object.

    :raises PayloadError: on a truncated or malformed payload, or one with trailing bytes
    """
    data = bytes(payload)
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        # CDR encapsulation header: 0x00 0x00 (big endian) or 0x00 0x01 (little endian)
        raise PayloadError(f"{typename}: not a CDR payload (header {data[:4].hex() or 'missing'})")
    try:
        return store().deserialize_cdr(data, typename)
    except Exception as exc:  # struct.error, IndexError, UnicodeDecodeError, AssertionError …
        raise PayloadError(f"{typename}: cannot decode {len(data)} bytes: {exc}") from None
