"""Payload codecs: leafgate messages ⇄ ROS 2 messages (CDR) or flat JSON.

One :class:`Codec` per Zenoh key type converts between a leafgate value and bytes, in the
encoding the configuration chooses (``cdr``: ROS 2 CDR through rosbags, what
zenoh-bridge-ros2dds carries; ``json``: flat SI objects for scripts). Decoding never lets a
foreign exception out: anything wrong with a payload is a
:class:`~leafgate.transport.cdr.PayloadError`, which subscribers count and drop.

Conventions at this edge:

- Pose is the rear-axle centre, which is Autoware's ``base_link``; heading is the yaw of the
  orientation quaternion; speed is ``twist.linear.x`` (signed, in ``base_link``); the x, y
  and yaw variances are the diagonal entries 0, 7 and 35 of the pose covariance (both ways;
  a publisher that leaves them zero says nothing about its uncertainty, and is accepted).
- Stamps are float seconds inside; ROS time ``{sec: 0, nanosec: 0}`` means "not set" and maps
  to NaN both ways.
- Statuses the gateway publishes have small value types here (:class:`SteeringStatus` …) with
  builder functions from the DBW reports, so each key has exactly one value type.

>>> codec = codecs("cdr").pose
>>> pose = codec.decode(codec.encode(Pose(x=1.0, y=2.0, heading=0.5, speed=-1.0, stamp=3.0)))
>>> (pose.x, pose.y, round(pose.heading, 12), pose.speed, pose.stamp)
(1.0, 2.0, 0.5, -1.0, 3.0)
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar, get_type_hints

import numpy as np

from leafgate.errors import PayloadError, TransportError
from leafgate.jsonconv import to_json
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    LongCommand,
    LongMode,
    LongReport,
    Pose,
    SteerCommand,
    SteerReport,
    Trajectory,
)
from leafgate.transport import cdr

Encoding = Literal["cdr", "json"]
T = TypeVar("T")

MAP_FRAME = "map"  # frame of poses and trajectories
BASE_FRAME = "base_link"  # Autoware's vehicle frame: the rear-axle centre

_INT32_MAX = 2**31 - 1
_NS_PER_S = 1_000_000_000  # ns/s


# --- status values published by the gateway ---------------------------------------------------


class ControlMode(enum.IntEnum):
    """autoware_vehicle_msgs/msg/ControlModeReport ``mode``."""

    NO_COMMAND = 0
    AUTONOMOUS = 1
    AUTONOMOUS_STEER_ONLY = 2
    AUTONOMOUS_VELOCITY_ONLY = 3
    MANUAL = 4
    DISENGAGED = 5
    NOT_READY = 6


class TurnIndicators(enum.IntEnum):
    """autoware_vehicle_msgs/msg/TurnIndicatorsReport ``report``."""

    DISABLE = 1
    ENABLE_LEFT = 2
    ENABLE_RIGHT = 3


class HazardLights(enum.IntEnum):
    """autoware_vehicle_msgs/msg/HazardLightsReport ``report``."""

    DISABLE = 1
    ENABLE = 2


@dataclass(frozen=True, slots=True)
class TurnIndicatorsStatus:
    """``vehicle/status/turn_indicators_status``: DISABLE on profiles without indicators."""

    report: TurnIndicators = TurnIndicators.DISABLE
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class HazardLightsStatus:
    """``vehicle/status/hazard_lights_status``: DISABLE on profiles without hazard lights."""

    report: HazardLights = HazardLights.DISABLE
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class SteeringStatus:
    """``vehicle/status/steering_status``: the measured road-wheel angle."""

    angle: float  # rad, positive left
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class VelocityStatus:
    """``vehicle/status/velocity_status``."""

    speed: float  # m/s, signed: negative when reversing
    lateral_speed: float = 0.0  # m/s, positive left
    yaw_rate: float = 0.0  # rad/s, counter-clockwise
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class GearStatus:
    """``vehicle/status/gear_status``."""

    gear: Gear
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class ControlModeStatus:
    """``vehicle/status/control_mode``."""

    mode: ControlMode
    stamp: float = math.nan  # s


@dataclass(frozen=True, slots=True)
class SentCommand:
    """``control/command/control_cmd``: the command actually sent to the ECU.

    ``speed`` is signed (negative in reverse) as Autoware's ``Longitudinal.velocity`` is;
    ``accel_defined`` is true in acceleration mode, where the ECU follows ``accel``.
    """

    steer_angle: float  # rad
    steer_rate: float = 0.0  # rad/s, 0 = ECU default (then not "defined" for Autoware)
    speed: float = 0.0  # m/s, signed
    accel: float = 0.0  # m/s²
    accel_defined: bool = True
    stamp: float = math.nan  # s


def steering_status(report: SteerReport, stamp: float) -> SteeringStatus:
    """The steering status to publish for a DBW_STEER_RPT received at ``stamp`` (s)."""
    return SteeringStatus(angle=report.angle, stamp=stamp)


def velocity_status(report: LongReport, yaw_rate: float, stamp: float) -> VelocityStatus:
    """The velocity status for a DBW_LONG_RPT; ``yaw_rate`` (rad/s) comes from localization."""
    return VelocityStatus(speed=report.speed, lateral_speed=0.0, yaw_rate=yaw_rate, stamp=stamp)


def control_mode(gateway: GatewayState, ecu: EcuState | None) -> ControlMode:
    """Autoware's control mode for the gateway's and the ECU's states.

    ``ecu`` is None while no DBW_SYSTEM_RPT has been received. A driver override wins over the
    gateway's state (the driver is in control), a fault on either side is ``DISENGAGED``.
    """
    if ecu is None or ecu == EcuState.NOT_READY:
        return ControlMode.NOT_READY
    if gateway == GatewayState.FAULT or ecu == EcuState.FAULT:
        return ControlMode.DISENGAGED
    if ecu == EcuState.OVERRIDE:
        return ControlMode.MANUAL
    if gateway in (GatewayState.ENGAGED, GatewayState.STOPPING):
        return ControlMode.AUTONOMOUS
    return ControlMode.MANUAL


def sent_command(
    steer: SteerCommand, long: LongCommand, stamp: float, *, reverse: bool = False
) -> SentCommand:
    """The command as sent, for ``control/command/control_cmd``.

    The DBW speed is a magnitude whose direction comes from the gear: a gear request of R or D
    decides it, otherwise ``reverse`` (the gear currently engaged) does.
    """
    if long.gear == Gear.R:
        reverse = True
    elif long.gear == Gear.D:
        reverse = False
    return SentCommand(
        steer_angle=steer.angle,
        steer_rate=steer.rate_limit,
        speed=-long.speed if reverse else long.speed,
        accel=long.accel,
        accel_defined=long.mode == LongMode.ACCELERATION,
        stamp=stamp,
    )


# --- helpers --------------------------------------------------------------------------------


def _types() -> Any:
    return cdr.store().types


def to_ros_time(stamp: float) -> Any:
    """Float seconds → ``builtin_interfaces/msg/Time``; NaN → zero time ("not set").

    :raises ValueError: if the stamp does not fit a ROS time (int32 seconds)
    """
    time_cls = _types()[cdr.TIME]
    if math.isnan(stamp):
        return time_cls(sec=0, nanosec=0)
    if not math.isfinite(stamp) or not -(2**31) <= stamp <= _INT32_MAX:
        raise ValueError(f"stamp {stamp!r} s does not fit a ROS time")
    sec = math.floor(stamp)
    nanosec = round((stamp - sec) * _NS_PER_S)
    if nanosec >= _NS_PER_S:  # rounding carried into the next second
        sec, nanosec = sec + 1, nanosec - _NS_PER_S
    return time_cls(sec=int(sec), nanosec=int(nanosec))


def from_ros_time(time: Any) -> float:
    """``builtin_interfaces/msg/Time`` → float seconds; zero time → NaN.

    :raises PayloadError: if ``nanosec`` is not below one second
    """
    if time.nanosec >= _NS_PER_S:
        raise PayloadError(f"time nanosec {time.nanosec} is not below 1e9")
    if time.sec == 0 and time.nanosec == 0:
        return math.nan
    return float(time.sec) + float(time.nanosec) * 1e-9


def _header(stamp: float, frame_id: str) -> Any:
    return _types()[cdr.HEADER](stamp=to_ros_time(stamp), frame_id=frame_id)


def _quaternion(yaw: float) -> Any:
    """A planar rotation about +z by ``yaw`` (rad)."""
    half = 0.5 * yaw
    return _types()["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)
    )


def _yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rad) of a quaternion, which need not be normalised (the ratio cancels the norm).

    :raises PayloadError: for a zero quaternion, which has no orientation
    """
    norm2 = x * x + y * y + z * z + w * w
    if not norm2 > 1e-12:  # also catches NaN
        if math.isnan(norm2):
            return math.nan  # a NaN pose is decoded and marked invalid by the subscriber
        raise PayloadError("orientation is a zero quaternion")
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def _vector3(x: float, y: float, z: float) -> Any:
    return _types()["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


# --- conversions to and from the ROS objects --------------------------------------------------


# The pose's variances in the 6×6 row-major covariance of geometry_msgs/PoseWithCovariance,
# whose rows and columns are x, y, z, rotation about x, about y, about z (yaw).
COVARIANCE_X, COVARIANCE_Y, COVARIANCE_YAW = 0, 7, 35


def pose_to_odometry(pose: Pose) -> Any:
    """Pose → nav_msgs/msg/Odometry: the pose covariance carries the x, y and yaw variances
    on its diagonal (zeros elsewhere, and a zero twist covariance)."""
    t = _types()
    covariance = np.zeros(36, dtype=np.float64)
    covariance[COVARIANCE_X] = pose.var_x
    covariance[COVARIANCE_Y] = pose.var_y
    covariance[COVARIANCE_YAW] = pose.var_heading
    return t[cdr.ODOMETRY](
        header=_header(pose.stamp, MAP_FRAME),
        child_frame_id=BASE_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=pose.x, y=pose.y, z=0.0),
                orientation=_quaternion(pose.heading),
            ),
            covariance=covariance,
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=_vector3(pose.speed, 0.0, 0.0),
                angular=_vector3(0.0, 0.0, pose.yaw_rate),
            ),
            covariance=np.zeros(36, dtype=np.float64),
        ),
    )


def odometry_to_pose(msg: Any) -> Pose:
    """nav_msgs/msg/Odometry of ``base_link`` (the rear-axle centre) → Pose, with the x, y and
    yaw variances of the pose covariance (the gateway judges them)."""
    position = msg.pose.pose.position
    q = msg.pose.pose.orientation
    twist = msg.twist.twist
    covariance = msg.pose.covariance
    if len(covariance) != 36:
        raise PayloadError(f"pose covariance has {len(covariance)} values, not 36")
    return Pose(
        x=float(position.x),
        y=float(position.y),
        heading=_yaw(q.x, q.y, q.z, q.w),
        speed=float(twist.linear.x),
        yaw_rate=float(twist.angular.z),
        stamp=from_ros_time(msg.header.stamp),
        var_x=float(covariance[COVARIANCE_X]),
        var_y=float(covariance[COVARIANCE_Y]),
        var_heading=float(covariance[COVARIANCE_YAW]),
    )


def trajectory_to_ros(trajectory: Trajectory) -> Any:
    """Trajectory → autoware_planning_msgs/msg/Trajectory.

    Only pose and ``longitudinal_velocity_mps`` are filled; ``time_from_start`` stays zero
    because leafgate's trajectories are geometric with a speed profile.
    """
    t = _types()
    point_cls = t[cdr.TRAJECTORY_POINT]
    pose_cls = t["geometry_msgs/msg/Pose"]
    point_xyz = t["geometry_msgs/msg/Point"]
    zero = t[cdr.DURATION](sec=0, nanosec=0)
    points = [
        point_cls(
            time_from_start=zero,
            pose=pose_cls(position=point_xyz(x=x, y=y, z=0.0), orientation=_quaternion(h)),
            longitudinal_velocity_mps=v,
            lateral_velocity_mps=0.0,
            acceleration_mps2=0.0,
            heading_rate_rps=0.0,
            front_wheel_angle_rad=0.0,
            rear_wheel_angle_rad=0.0,
        )
        for x, y, h, v in zip(
            trajectory.x.tolist(),
            trajectory.y.tolist(),
            trajectory.heading.tolist(),
            trajectory.speed.tolist(),
            strict=True,
        )
    ]
    return t[cdr.TRAJECTORY](header=_header(trajectory.stamp, MAP_FRAME), points=points)


def ros_to_trajectory(msg: Any) -> Trajectory:
    """autoware_planning_msgs/msg/Trajectory → Trajectory (x, y, yaw, longitudinal speed)."""
    points = msg.points
    n = len(points)
    xy = np.empty((n, 2))
    quat = np.empty((n, 4))
    speed = np.empty(n)
    for i, p in enumerate(points):
        pos, q = p.pose.position, p.pose.orientation
        xy[i] = (pos.x, pos.y)
        quat[i] = (q.x, q.y, q.z, q.w)
        speed[i] = p.longitudinal_velocity_mps
    qx, qy, qz, qw = quat.T
    with np.errstate(over="ignore", invalid="ignore"):  # as in decode_trajectory_cdr
        norm2 = np.einsum("ij,ij->i", quat, quat)
        if np.any(norm2 <= 1e-12):
            bad = int(np.flatnonzero(norm2 <= 1e-12)[0])
            raise PayloadError(f"trajectory point {bad}: orientation is a zero quaternion")
        heading = np.arctan2(2.0 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)
    return Trajectory(
        x=xy[:, 0],
        y=xy[:, 1],
        heading=heading,
        speed=speed,
        stamp=from_ros_time(msg.header.stamp),
    )


# TrajectoryPoint in little-endian CDR: Duration time_from_start (8 bytes), Pose (7 float64,
# aligned to 8 bytes counted from after the 4-byte encapsulation header), six float32: 88
# bytes. If the first point starts at 4 mod 8, four padding bytes follow its Duration and every
# later point is 8-aligned without padding. Either way, Pose + floats (80 bytes) repeat every
# 88 bytes from the first Pose on, which a strided numpy view reads directly.
_POSE_AND_FLOATS = np.dtype(
    [(name, "<f8") for name in ("px", "py", "pz", "qx", "qy", "qz", "qw")]
    + [(name, "<f4") for name in ("v", "lateral_v", "accel", "heading_rate", "front", "rear")]
)
_POINT_STRIDE = 88  # bytes: Duration 8 + Pose 56 + 6 × float32 24
_CDR_SLACK = 3  # bytes of end padding a CDR payload may carry (as rosbags accepts)


def decode_trajectory_cdr(payload: bytes) -> Trajectory:
    """Decode a little-endian CDR Trajectory with numpy, without building one object per point.

    Gives the same result as the rosbags path (:func:`ros_to_trajectory` of
    :func:`cdr.deserialize`) in a fraction of the time, so a long trajectory does not hold the
    GIL (and delay the control thread) for milliseconds.

    :raises PayloadError: on a malformed or truncated payload
    """
    data = memoryview(payload)[4:]  # after the encapsulation header
    if len(data) < 16:
        raise PayloadError(f"{cdr.TRAJECTORY}: {len(payload)} bytes is too short")
    sec, nanosec, name_len = struct.unpack_from("<iII", data, 0)
    offset = 12 + name_len
    if name_len < 1 or offset + 4 > len(data) or data[offset - 1] != 0:
        raise PayloadError(f"{cdr.TRAJECTORY}: bad header.frame_id string")
    offset += -offset % 4  # the sequence length is a uint32
    (count,) = struct.unpack_from("<I", data, offset)
    offset += 4
    pad = -(offset + 8) % 8  # before the first float64, only for the first point
    end = offset + pad + count * _POINT_STRIDE if count else offset
    if not end <= len(data) <= end + _CDR_SLACK:
        raise PayloadError(
            f"{cdr.TRAJECTORY}: {count} points need {end + 4} bytes, got {len(payload)}"
        )
    points = (
        np.ndarray(
            shape=(count,),
            dtype=_POSE_AND_FLOATS,
            buffer=data,
            offset=offset + 8 + pad,  # skip the first Duration
            strides=(_POINT_STRIDE,),
        )
        if count
        else np.zeros(0, dtype=_POSE_AND_FLOATS)
    )
    qx, qy, qz, qw = (points[q].astype(np.float64) for q in ("qx", "qy", "qz", "qw"))
    # Absurd components overflow to inf/NaN: the heading is then not finite and the subscriber
    # marks the trajectory invalid, so numpy need not warn (on Zenoh's thread) about it.
    with np.errstate(over="ignore", invalid="ignore"):
        norm2 = qx * qx + qy * qy + qz * qz + qw * qw
        if np.any(norm2 <= 1e-12):
            bad = int(np.flatnonzero(norm2 <= 1e-12)[0])
            raise PayloadError(f"trajectory point {bad}: orientation is a zero quaternion")
        heading = np.arctan2(2.0 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)
    stamp = from_ros_time(_types()[cdr.TIME](sec=sec, nanosec=nanosec))
    return Trajectory(
        x=points["px"],
        y=points["py"],
        heading=heading,
        speed=points["v"].astype(np.float64),
        stamp=stamp,
    )


def steering_to_ros(status: SteeringStatus) -> Any:
    return _types()[cdr.STEERING_REPORT](
        stamp=to_ros_time(status.stamp), steering_tire_angle=status.angle
    )


def ros_to_steering(msg: Any) -> SteeringStatus:
    return SteeringStatus(angle=float(msg.steering_tire_angle), stamp=from_ros_time(msg.stamp))


def velocity_to_ros(status: VelocityStatus) -> Any:
    return _types()[cdr.VELOCITY_REPORT](
        header=_header(status.stamp, BASE_FRAME),
        longitudinal_velocity=status.speed,
        lateral_velocity=status.lateral_speed,
        heading_rate=status.yaw_rate,
    )


def ros_to_velocity(msg: Any) -> VelocityStatus:
    return VelocityStatus(
        speed=float(msg.longitudinal_velocity),
        lateral_speed=float(msg.lateral_velocity),
        yaw_rate=float(msg.heading_rate),
        stamp=from_ros_time(msg.header.stamp),
    )


# leafgate gear ↔ GearReport.report; Autoware's numbered drive/low gears all mean D to leafgate.
_GEAR_TO_ROS: dict[Gear, int] = {Gear.NONE: 0, Gear.N: 1, Gear.D: 2, Gear.R: 20, Gear.P: 22}


def _gear_from_ros(report: int) -> Gear:
    if report == 0:
        return Gear.NONE
    if report == 1:
        return Gear.N
    if 2 <= report <= 19 or report in (23, 24):  # DRIVE…DRIVE_18, LOW, LOW_2
        return Gear.D
    if report in (20, 21):  # REVERSE, REVERSE_2
        return Gear.R
    if report == 22:
        return Gear.P
    raise PayloadError(f"unknown GearReport value {report}")


def gear_to_ros(status: GearStatus) -> Any:
    return _types()[cdr.GEAR_REPORT](
        stamp=to_ros_time(status.stamp), report=_GEAR_TO_ROS[Gear(status.gear)]
    )


def ros_to_gear(msg: Any) -> GearStatus:
    return GearStatus(gear=_gear_from_ros(int(msg.report)), stamp=from_ros_time(msg.stamp))


def control_mode_to_ros(status: ControlModeStatus) -> Any:
    return _types()[cdr.CONTROL_MODE_REPORT](
        stamp=to_ros_time(status.stamp), mode=int(ControlMode(status.mode))
    )


def ros_to_control_mode(msg: Any) -> ControlModeStatus:
    try:
        mode = ControlMode(int(msg.mode))
    except ValueError:
        raise PayloadError(f"unknown ControlModeReport value {msg.mode}") from None
    return ControlModeStatus(mode=mode, stamp=from_ros_time(msg.stamp))


def _report_to_ros(typename: str) -> Callable[[Any], Any]:
    def to_ros(status: Any) -> Any:
        return _types()[typename](stamp=to_ros_time(status.stamp), report=int(status.report))

    return to_ros


def _report_from_ros(cls: type[Any], kind: type[enum.IntEnum]) -> Callable[[Any], Any]:
    def from_ros(msg: Any) -> Any:
        try:
            report = kind(int(msg.report))
        except ValueError:
            raise PayloadError(f"unknown {cls.__name__} value {msg.report}") from None
        return cls(report=report, stamp=from_ros_time(msg.stamp))

    return from_ros


def command_to_ros(command: SentCommand) -> Any:
    t = _types()
    stamp = to_ros_time(command.stamp)
    return t[cdr.CONTROL](
        stamp=stamp,
        control_time=stamp,  # what was sent applies now
        lateral=t[cdr.LATERAL](
            stamp=stamp,
            control_time=stamp,
            steering_tire_angle=command.steer_angle,
            steering_tire_rotation_rate=command.steer_rate,
            is_defined_steering_tire_rotation_rate=command.steer_rate > 0.0,
        ),
        longitudinal=t[cdr.LONGITUDINAL](
            stamp=stamp,
            control_time=stamp,
            velocity=command.speed,
            acceleration=command.accel,
            jerk=0.0,
            is_defined_acceleration=command.accel_defined,
            is_defined_jerk=False,
        ),
    )


def ros_to_command(msg: Any) -> SentCommand:
    lat, lon = msg.lateral, msg.longitudinal
    return SentCommand(
        steer_angle=float(lat.steering_tire_angle),
        steer_rate=float(lat.steering_tire_rotation_rate)
        if lat.is_defined_steering_tire_rotation_rate
        else 0.0,
        speed=float(lon.velocity),
        accel=float(lon.acceleration),
        accel_defined=bool(lon.is_defined_acceleration),
        stamp=from_ros_time(msg.stamp),
    )


# --- JSON -----------------------------------------------------------------------------------


def _flat_to_dict(value: Any) -> dict[str, Any]:
    """A flat dataclass → JSON object in leafgate's convention (enums by name, NaN as null)."""
    out: dict[str, Any] = to_json(value)
    return out


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:  # resolving string annotations is slow; do it once per class
        _HINTS[cls] = get_type_hints(cls)
    return _HINTS[cls]


def _flat_from_dict(cls: type[T], data: Any) -> T:
    """JSON object → flat dataclass; missing optional fields take their defaults.

    :raises PayloadError: on a missing required field, an unknown field or a wrong type
    """
    if not isinstance(data, dict):
        raise PayloadError(f"{cls.__name__}: expected a JSON object")
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - names
    if unknown:
        raise PayloadError(f"{cls.__name__}: unknown field(s) {', '.join(sorted(unknown))}")
    kwargs: dict[str, Any] = {}
    for name, raw in data.items():
        tp = hints[name]
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            if not isinstance(raw, str) or raw not in tp.__members__:
                raise PayloadError(f"{cls.__name__}.{name}: {raw!r} is not a {tp.__name__}")
            kwargs[name] = tp[raw]
        elif tp is bool:
            if not isinstance(raw, bool):
                raise PayloadError(f"{cls.__name__}.{name}: expected true or false")
            kwargs[name] = raw
        elif tp is float:
            if raw is None:
                kwargs[name] = math.nan
            elif isinstance(raw, (int, float)) and not isinstance(raw, bool):
                kwargs[name] = float(raw)
            else:
                raise PayloadError(f"{cls.__name__}.{name}: expected a number, got {raw!r}")
        else:  # pragma: no cover - only float/bool/enum fields are used here
            raise PayloadError(f"{cls.__name__}.{name}: unsupported field type")
    try:
        return cls(**kwargs)
    except TypeError as exc:  # a required field is missing
        raise PayloadError(f"{cls.__name__}: {exc}") from None


def _trajectory_to_dict(trajectory: Trajectory) -> dict[str, Any]:
    return {
        "stamp": to_json(trajectory.stamp),
        "x": trajectory.x.tolist(),
        "y": trajectory.y.tolist(),
        "heading": trajectory.heading.tolist(),
        "speed": trajectory.speed.tolist(),
    }


def _trajectory_from_dict(data: Any) -> Trajectory:
    if not isinstance(data, dict):
        raise PayloadError("Trajectory: expected a JSON object")
    arrays: dict[str, Any] = {}
    for name in ("x", "y", "heading", "speed"):
        values = data.get(name)
        if not isinstance(values, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in values
        ):
            raise PayloadError(f"Trajectory.{name}: expected a list of numbers")
        arrays[name] = np.asarray(values, dtype=np.float64)
    stamp = data.get("stamp")
    if stamp is not None and (not isinstance(stamp, (int, float)) or isinstance(stamp, bool)):
        raise PayloadError("Trajectory.stamp: expected a number or null")
    try:
        return Trajectory(stamp=math.nan if stamp is None else float(stamp), **arrays)
    except ValueError as exc:  # arrays of different lengths
        raise PayloadError(str(exc)) from None


# --- the codec ------------------------------------------------------------------------------


class Codec(Generic[T]):
    """Encodes and decodes the values of one key: leafgate type ``T`` ⇄ bytes.

    :param typename: the ROS 2 type on the wire (also named in errors)
    :param encoding: ``"cdr"`` or ``"json"``
    :param fast_cdr_le: an optional direct decoder for little-endian CDR (else rosbags)
    """

    def __init__(
        self,
        typename: str,
        encoding: Encoding,
        to_ros: Callable[[T], Any],
        from_ros: Callable[[Any], T],
        to_dict: Callable[[T], dict[str, Any]],
        from_dict: Callable[[Any], T],
        fast_cdr_le: Callable[[bytes], T] | None = None,
    ) -> None:
        if encoding not in ("cdr", "json"):
            raise ValueError(f"unknown payload encoding {encoding!r} (cdr or json)")
        self.typename = typename
        self.encoding: Encoding = encoding
        self._to_ros = to_ros
        self._from_ros = from_ros
        self._to_dict = to_dict
        self._from_dict = from_dict
        self._fast_cdr_le = fast_cdr_le

    @property
    def mime(self) -> str:
        """The Zenoh encoding string the publisher declares."""
        return "application/cdr" if self.encoding == "cdr" else "application/json"

    def encode(self, value: T) -> bytes:
        """Serialise ``value``.

        :raises TransportError: if the value cannot be represented (e.g. a stamp out of range)
        """
        if self.encoding == "cdr":
            try:
                message = self._to_ros(value)
            except (ValueError, KeyError) as exc:
                raise TransportError(f"cannot encode {self.typename}: {exc}") from None
            return cdr.serialize(message, self.typename)
        try:
            return json.dumps(self._to_dict(value), allow_nan=False).encode()
        except ValueError as exc:  # ±inf has no JSON form
            raise TransportError(f"cannot encode {self.typename} as JSON: {exc}") from None

    def decode(self, payload: bytes | memoryview) -> T:
        """Deserialise a payload.

        :raises PayloadError: whatever is wrong with it (never another exception)
        """
        try:
            if self.encoding == "cdr":
                data = bytes(payload)
                if self._fast_cdr_le is not None and data[:2] == b"\x00\x01":
                    return self._fast_cdr_le(data)
                return self._from_ros(cdr.deserialize(data, self.typename))
            return self._from_dict(json.loads(bytes(payload)))
        except PayloadError:
            raise
        except Exception as exc:  # JSONDecodeError, UnicodeDecodeError, odd field values …
            raise PayloadError(f"{self.typename} ({self.encoding}): {exc}") from None


@dataclass(frozen=True)
class Codecs:
    """The codecs of every key type, for one encoding."""

    pose: Codec[Pose]
    trajectory: Codec[Trajectory]
    steering: Codec[SteeringStatus]
    velocity: Codec[VelocityStatus]
    gear: Codec[GearStatus]
    control_mode: Codec[ControlModeStatus]
    turn_indicators: Codec[TurnIndicatorsStatus]
    hazard_lights: Codec[HazardLightsStatus]
    command: Codec[SentCommand]


@functools.cache
def codecs(encoding: Encoding) -> Codecs:
    """The codecs for ``encoding`` (``"cdr"`` or ``"json"``), built once."""

    def flat(typename: str, cls: type[Any], to_ros: Any, from_ros: Any) -> Codec[Any]:
        return Codec(
            typename,
            encoding,
            to_ros,
            from_ros,
            _flat_to_dict,
            functools.partial(_flat_from_dict, cls),
        )

    return Codecs(
        pose=flat(cdr.ODOMETRY, Pose, pose_to_odometry, odometry_to_pose),
        trajectory=Codec(
            cdr.TRAJECTORY,
            encoding,
            trajectory_to_ros,
            ros_to_trajectory,
            _trajectory_to_dict,
            _trajectory_from_dict,
            fast_cdr_le=decode_trajectory_cdr,
        ),
        steering=flat(cdr.STEERING_REPORT, SteeringStatus, steering_to_ros, ros_to_steering),
        velocity=flat(cdr.VELOCITY_REPORT, VelocityStatus, velocity_to_ros, ros_to_velocity),
        gear=flat(cdr.GEAR_REPORT, GearStatus, gear_to_ros, ros_to_gear),
        control_mode=flat(
            cdr.CONTROL_MODE_REPORT, ControlModeStatus, control_mode_to_ros, ros_to_control_mode
        ),
        turn_indicators=flat(
            cdr.TURN_INDICATORS_REPORT,
            TurnIndicatorsStatus,
            _report_to_ros(cdr.TURN_INDICATORS_REPORT),
            _report_from_ros(TurnIndicatorsStatus, TurnIndicators),
        ),
        hazard_lights=flat(
            cdr.HAZARD_LIGHTS_REPORT,
            HazardLightsStatus,
            _report_to_ros(cdr.HAZARD_LIGHTS_REPORT),
            _report_from_ros(HazardLightsStatus, HazardLights),
        ),
        command=flat(cdr.CONTROL, SentCommand, command_to_ros, ros_to_command),
    )
