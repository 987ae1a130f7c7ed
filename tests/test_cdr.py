"""ROS 2 CDR and JSON payload codecs (leafgate.transport.cdr, leafgate.transport.payloads)."""

from __future__ import annotations

import contextlib
import functools
import json
import math
import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from leafgate.errors import TransportError
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
from leafgate.transport.cdr import PayloadError
from leafgate.transport.payloads import (
    ControlMode,
    ControlModeStatus,
    GearStatus,
    SentCommand,
    SteeringStatus,
    VelocityStatus,
    codecs,
    control_mode,
    decode_trajectory_cdr,
    from_ros_time,
    ros_to_trajectory,
    sent_command,
    steering_status,
    to_ros_time,
    trajectory_to_ros,
    velocity_status,
)

ENCODINGS = ("cdr", "json")

finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
angles = st.floats(min_value=-math.pi + 1e-9, max_value=math.pi, allow_nan=False)
stamps = st.one_of(st.just(math.nan), st.floats(min_value=1.0, max_value=2.0e9))


def angle_diff(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2.0 * math.pi))


def f32(value: float) -> float:
    """What a float32 field of a ROS message stores."""
    return float(np.float32(value))


def same_stamp(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9 * max(1.0, abs(a))


# --- type registration ------------------------------------------------------------------------


@pytest.mark.parametrize("typename", cdr.KEY_TYPES)
def test_every_key_type_has_an_mcap_schema(typename: str) -> None:
    text = cdr.msg_definition(typename)
    first = text.splitlines()[0]
    assert first and not first.startswith("MSG:")
    # every type it refers to is spelt out after a separator, as MCAP's ros2msg wants
    for line in text.splitlines():
        field_type = line.split(" ")[0].split("[")[0]
        if "/" in field_type and "=" not in line:
            assert f"MSG: {field_type}" in text


def test_msg_definition_of_unknown_type_raises() -> None:
    with pytest.raises(TransportError, match="no_pkg/msg/Nothing"):
        cdr.msg_definition("no_pkg/msg/Nothing")


@pytest.mark.parametrize(
    ("typename", "fields"),
    [
        (
            cdr.TRAJECTORY_POINT,
            [
                "time_from_start",
                "pose",
                "longitudinal_velocity_mps",
                "lateral_velocity_mps",
                "acceleration_mps2",
                "heading_rate_rps",
                "front_wheel_angle_rad",
                "rear_wheel_angle_rad",
            ],
        ),
        (cdr.TRAJECTORY, ["header", "points"]),
        (cdr.CONTROL, ["stamp", "control_time", "lateral", "longitudinal"]),
        (
            cdr.LATERAL,
            [
                "stamp",
                "control_time",
                "steering_tire_angle",
                "steering_tire_rotation_rate",
                "is_defined_steering_tire_rotation_rate",
            ],
        ),
        (
            cdr.LONGITUDINAL,
            [
                "stamp",
                "control_time",
                "velocity",
                "acceleration",
                "jerk",
                "is_defined_acceleration",
                "is_defined_jerk",
            ],
        ),
        (cdr.STEERING_REPORT, ["stamp", "steering_tire_angle"]),
        (
            cdr.VELOCITY_REPORT,
            ["header", "longitudinal_velocity", "lateral_velocity", "heading_rate"],
        ),
        (cdr.GEAR_REPORT, ["stamp", "report"]),
        (cdr.CONTROL_MODE_REPORT, ["stamp", "mode"]),
    ],
)
def test_autoware_types_have_the_upstream_field_order(typename: str, fields: list[str]) -> None:
    # the wire layout is the field order: a reordering would silently garble every message
    assert [name for name, _ in cdr.store().fielddefs[typename][1]] == fields


def test_control_wire_layout_matches_a_hand_packed_message() -> None:
    # Independent of rosbags' serialiser: pack the CDR by hand from the .msg layout.
    sec, ns = 12, 500_000_000
    time_ = struct.pack("<iI", sec, ns)
    reference = (
        b"\x00\x01\x00\x00"
        + time_
        + time_
        + time_  # lateral.stamp
        + time_
        + struct.pack("<ff?", 0.25, 0.5, True)
        + b"\x00" * 3  # align the next Time to 4
        + time_  # longitudinal.stamp
        + time_
        + struct.pack("<fff??", -1.5, 0.75, 0.0, True, False)
    )
    command = SentCommand(
        steer_angle=0.25, steer_rate=0.5, speed=-1.5, accel=0.75, accel_defined=True, stamp=12.5
    )
    encoded = codecs("cdr").command.encode(command)
    assert encoded.rstrip(b"\x00") == reference.rstrip(b"\x00")
    assert codecs("cdr").command.decode(reference) == command


def test_gear_report_wire_layout_matches_a_hand_packed_message() -> None:
    reference = b"\x00\x01\x00\x00" + struct.pack("<iIB", 3, 0, 22)  # PARK at t = 3 s
    assert codecs("cdr").gear.decode(reference) == GearStatus(Gear.P, 3.0)
    assert codecs("cdr").gear.encode(GearStatus(Gear.P, 3.0)).startswith(reference)


# --- conversions: Odometry ⇄ Pose ------------------------------------------------------------


@functools.cache
def _rosbags_store() -> Any:
    return get_typestore(Stores.ROS2_HUMBLE)


def _independent_odometry(
    x: float, y: float, yaw: float, speed: float, yaw_rate: float, sec: int, ns: int, scale: float
) -> bytes:
    """An Odometry serialised with rosbags' own Humble store (not leafgate's)."""
    ts = _rosbags_store()
    t = ts.types
    odom = t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id="map"
        ),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.3),
                orientation=t["geometry_msgs/msg/Quaternion"](
                    x=0.0, y=0.0, z=scale * math.sin(yaw / 2), w=scale * math.cos(yaw / 2)
                ),
            ),
            covariance=np.arange(36, dtype=np.float64),
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=t["geometry_msgs/msg/Vector3"](x=speed, y=0.1, z=0.0),
                angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=yaw_rate),
            ),
            covariance=np.zeros(36, dtype=np.float64),
        ),
    )
    return bytes(ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))


@settings(max_examples=40, deadline=None)
@given(
    x=finite,
    y=finite,
    yaw=angles,
    speed=st.floats(-5.0, 5.0),
    yaw_rate=st.floats(-1.0, 1.0),
    sec=st.integers(1, 2_000_000_000),
    ns=st.integers(0, 999_999_999),
    scale=st.floats(0.5, 2.0),  # quaternions need not arrive normalised
)
def test_odometry_from_rosbags_decodes_to_the_rear_axle_pose(
    x: float, y: float, yaw: float, speed: float, yaw_rate: float, sec: int, ns: int, scale: float
) -> None:
    raw = _independent_odometry(x, y, yaw, speed, yaw_rate, sec, ns, scale)
    pose = codecs("cdr").pose.decode(raw)
    assert (pose.x, pose.y, pose.speed, pose.yaw_rate) == (x, y, speed, yaw_rate)
    assert angle_diff(pose.heading, yaw) < 1e-9
    assert pose.stamp == pytest.approx(sec + ns * 1e-9, abs=1e-6)


def test_big_endian_cdr_decodes_too() -> None:
    ts = cdr.store()
    msg = ts.types[cdr.STEERING_REPORT](
        stamp=ts.types[cdr.TIME](sec=7, nanosec=0), steering_tire_angle=-0.125
    )
    raw = bytes(ts.serialize_cdr(msg, cdr.STEERING_REPORT, little_endian=False))
    assert raw[:2] == b"\x00\x00"
    assert codecs("cdr").steering.decode(raw) == SteeringStatus(-0.125, 7.0)


# --- round trips --------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ENCODINGS)
@settings(max_examples=30, deadline=None)
@given(x=finite, y=finite, heading=angles, speed=finite, yaw_rate=finite, stamp=stamps)
def test_pose_round_trips(
    encoding: str, x: float, y: float, heading: float, speed: float, yaw_rate: float, stamp: float
) -> None:
    codec = codecs(encoding).pose  # type: ignore[arg-type]
    pose = Pose(x=x, y=y, heading=heading, speed=speed, yaw_rate=yaw_rate, stamp=stamp)
    back = codec.decode(codec.encode(pose))
    assert (back.x, back.y, back.speed, back.yaw_rate) == (x, y, speed, yaw_rate)
    assert angle_diff(back.heading, heading) < 1e-12
    assert same_stamp(back.stamp, stamp)


trajectories = st.integers(0, 60).flatmap(
    lambda n: st.tuples(
        *(st.lists(s, min_size=n, max_size=n) for s in (finite, finite, angles, finite)),
        stamps,
    )
)


@pytest.mark.parametrize("encoding", ENCODINGS)
@settings(max_examples=25, deadline=None)
@given(data=trajectories)
def test_trajectory_round_trips(encoding: str, data: tuple) -> None:  # type: ignore[type-arg]
    x, y, heading, speed, stamp = data
    codec = codecs(encoding).trajectory  # type: ignore[arg-type]
    trajectory = Trajectory(x=x, y=y, heading=heading, speed=speed, stamp=stamp)
    back = codec.decode(codec.encode(trajectory))
    assert len(back) == len(trajectory)
    np.testing.assert_array_equal(back.x, trajectory.x)
    np.testing.assert_array_equal(back.y, trajectory.y)
    if len(back):
        assert (
            np.max(
                np.abs(np.remainder(back.heading - trajectory.heading + np.pi, 2 * np.pi) - np.pi)
            )
            < 1e-12
        )
    # longitudinal_velocity_mps is float32 in CDR
    expected_speed = [f32(v) for v in speed] if encoding == "cdr" else speed
    np.testing.assert_array_equal(back.speed, np.asarray(expected_speed, dtype=np.float64))
    assert same_stamp(back.stamp, stamp)


@settings(max_examples=40, deadline=None)
@given(data=trajectories, frame=st.text(max_size=9))
def test_fast_trajectory_decoder_agrees_with_rosbags(data: tuple, frame: str) -> None:  # type: ignore[type-arg]
    # the frame id's length moves the points' alignment (padding before the first Pose)
    x, y, heading, speed, stamp = data
    message = trajectory_to_ros(Trajectory(x=x, y=y, heading=heading, speed=speed, stamp=stamp))
    message.header.frame_id = frame
    raw = cdr.serialize(message, cdr.TRAJECTORY)
    fast = decode_trajectory_cdr(raw)
    slow = ros_to_trajectory(cdr.deserialize(raw, cdr.TRAJECTORY))
    for name in ("x", "y", "heading", "speed"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name))
    assert same_stamp(fast.stamp, slow.stamp)
    with pytest.raises(PayloadError):
        decode_trajectory_cdr(raw[:-4])


def _statuses() -> list[tuple[str, object]]:
    return [
        ("steering", SteeringStatus(angle=f32(-0.3), stamp=100.25)),
        ("steering", SteeringStatus(angle=0.0)),
        (
            "velocity",
            VelocityStatus(speed=f32(-1.2), lateral_speed=0.0, yaw_rate=f32(0.05), stamp=5.5),
        ),
        *[("gear", GearStatus(gear=g, stamp=1.0)) for g in Gear],
        *[("control_mode", ControlModeStatus(mode=m, stamp=2.0)) for m in ControlMode],
        (
            "command",
            SentCommand(
                steer_angle=f32(0.1),
                steer_rate=f32(0.2),
                speed=f32(-0.8),
                accel=f32(-0.4),
                accel_defined=True,
                stamp=3.0,
            ),
        ),
        (
            "command",
            SentCommand(
                steer_angle=f32(-0.1),
                steer_rate=0.0,
                speed=f32(2.5),
                accel=0.0,
                accel_defined=False,
                stamp=math.nan,
            ),
        ),
    ]


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize(("kind", "value"), _statuses())
def test_status_round_trips(encoding: str, kind: str, value: object) -> None:
    codec = getattr(codecs(encoding), kind)  # type: ignore[arg-type]
    back = codec.decode(codec.encode(value))
    assert type(back) is type(value)
    for name in value.__dataclass_fields__:  # type: ignore[attr-defined]
        a, b = getattr(back, name), getattr(value, name)
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), name


def test_json_is_flat_si_with_nan_as_null() -> None:
    payload = codecs("json").pose.encode(Pose(x=1.0, y=2.0, heading=0.5, speed=-1.0))
    assert json.loads(payload) == {
        "x": 1.0,
        "y": 2.0,
        "heading": 0.5,
        "speed": -1.0,
        "yaw_rate": 0.0,
        "stamp": None,
        "var_x": 0.0,
        "var_y": 0.0,
        "var_heading": 0.0,
    }
    gear = json.loads(codecs("json").gear.encode(GearStatus(Gear.R, 1.0)))
    assert gear == {"gear": "R", "stamp": 1.0}


@settings(max_examples=200, deadline=None)
@given(stamp=st.floats(min_value=-2.0e9, max_value=2.0e9))
def test_ros_time_round_trips_to_the_nanosecond(stamp: float) -> None:
    time_ = to_ros_time(stamp)
    assert 0 <= time_.nanosec < 1_000_000_000
    back = from_ros_time(time_)
    if time_.sec == 0 and time_.nanosec == 0:
        assert math.isnan(back)  # zero time means "not set"
    else:
        assert abs(back - stamp) <= 1e-9 + 2e-16 * abs(stamp)


def test_unset_stamp_is_zero_ros_time() -> None:
    time_ = to_ros_time(math.nan)
    assert (time_.sec, time_.nanosec) == (0, 0)


# --- builders from the DBW reports -------------------------------------------------------------


def test_reports_become_autoware_statuses() -> None:
    steer = SteerReport(0.2, 0.0, 0.0, True, False, False, False)
    long = LongReport(-1.0, 0.0, Gear.R, 0.0, 0.0, True, False, False, False)
    assert steering_status(steer, 4.0) == SteeringStatus(0.2, 4.0)
    assert velocity_status(long, 0.1, 4.0) == VelocityStatus(-1.0, 0.0, 0.1, 4.0)


@pytest.mark.parametrize(
    ("gateway", "ecu", "mode"),
    [
        (GatewayState.ENGAGED, EcuState.ENGAGED, ControlMode.AUTONOMOUS),
        (GatewayState.STOPPING, EcuState.ENGAGED, ControlMode.AUTONOMOUS),
        (GatewayState.STANDBY, EcuState.READY, ControlMode.MANUAL),
        (GatewayState.ENGAGED, EcuState.OVERRIDE, ControlMode.MANUAL),
        (GatewayState.FAULT, EcuState.READY, ControlMode.DISENGAGED),
        (GatewayState.STANDBY, EcuState.FAULT, ControlMode.DISENGAGED),
        (GatewayState.STANDBY, EcuState.NOT_READY, ControlMode.NOT_READY),
        (GatewayState.STANDBY, None, ControlMode.NOT_READY),
    ],
)
def test_control_mode_reflects_gateway_and_ecu(
    gateway: GatewayState, ecu: EcuState | None, mode: ControlMode
) -> None:
    assert control_mode(gateway, ecu) is mode


@pytest.mark.parametrize(
    ("gear", "reverse", "signed_speed"),
    [(Gear.R, False, -1.5), (Gear.D, True, 1.5), (Gear.NONE, True, -1.5), (Gear.NONE, False, 1.5)],
)
def test_sent_command_speed_takes_its_sign_from_the_gear(
    gear: Gear, reverse: bool, signed_speed: float
) -> None:
    long = LongCommand(mode=LongMode.SPEED, accel=0.3, speed=1.5, gear=gear, enable=True)
    command = sent_command(SteerCommand(0.1, 0.2, True), long, 1.0, reverse=reverse)
    assert command.speed == signed_speed
    assert command.accel_defined is False  # speed mode: the ECU follows the speed


# --- bad payloads -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kind", ["pose", "trajectory", "steering", "velocity", "gear", "control_mode", "command"]
)
def test_truncated_cdr_raises_payload_error(kind: str) -> None:
    codec = getattr(codecs("cdr"), kind)
    samples = {
        "pose": Pose(1.0, 2.0, 0.3, 1.0, stamp=1.0),
        "trajectory": Trajectory(x=[0.0, 1.0], y=[0.0, 0.0], heading=[0.0, 0.0], speed=[1.0, 1.0]),
        "steering": SteeringStatus(0.1, 1.0),
        "velocity": VelocityStatus(1.0, 0.0, 0.0, 1.0),
        "gear": GearStatus(Gear.D, 1.0),
        "control_mode": ControlModeStatus(ControlMode.AUTONOMOUS, 1.0),
        "command": SentCommand(0.1),
    }
    raw = codec.encode(samples[kind])
    with pytest.raises(PayloadError):
        codec.decode(raw[: len(raw) // 2])
    with pytest.raises(PayloadError):
        codec.decode(raw + b"\x00" * 8)  # more than CDR's alignment padding


@pytest.mark.parametrize("encoding", ENCODINGS)
@settings(max_examples=150, deadline=None)
@given(payload=st.binary(max_size=400))
def test_arbitrary_bytes_never_raise_anything_but_payload_error(
    encoding: str, payload: bytes
) -> None:
    for kind in ("pose", "trajectory"):
        codec = getattr(codecs(encoding), kind)  # type: ignore[arg-type]
        with contextlib.suppress(PayloadError):
            codec.decode(payload)


def test_zero_quaternion_is_a_payload_error() -> None:
    raw = _independent_odometry(1.0, 2.0, 0.0, 0.0, 0.0, 1, 0, scale=0.0)
    with pytest.raises(PayloadError, match="quaternion"):
        codecs("cdr").pose.decode(raw)


def test_unknown_gear_value_is_a_payload_error() -> None:
    raw = b"\x00\x01\x00\x00" + struct.pack("<iIB", 3, 0, 99)
    with pytest.raises(PayloadError, match="99"):
        codecs("cdr").gear.decode(raw)


def test_nanoseconds_beyond_one_second_are_a_payload_error() -> None:
    raw = b"\x00\x01\x00\x00" + struct.pack("<iIf", 3, 1_000_000_000, 0.0)
    with pytest.raises(PayloadError, match="nanosec"):
        codecs("cdr").steering.decode(raw)


@pytest.mark.parametrize(
    "text",
    [
        b'{"x": 1.0, "y": 2.0}',  # missing fields
        b'{"x": 1, "y": 2, "heading": 0, "speed": 0, "colour": "red"}',  # unknown field
        b'{"x": "1", "y": 2, "heading": 0, "speed": 0}',  # wrong type
        b"[1, 2, 3]",
        b"\xff\xfe",
        b'{"x": 1.0,',
    ],
)
def test_bad_json_pose_is_a_payload_error(text: bytes) -> None:
    with pytest.raises(PayloadError):
        codecs("json").pose.decode(text)


def test_json_trajectory_with_unequal_arrays_is_a_payload_error() -> None:
    text = json.dumps({"x": [0, 1], "y": [0], "heading": [0, 0], "speed": [1, 1]}).encode()
    with pytest.raises(PayloadError, match="points"):
        codecs("json").trajectory.decode(text)


def test_unencodable_stamp_raises_transport_error() -> None:
    with pytest.raises(TransportError, match="stamp"):
        codecs("cdr").steering.encode(SteeringStatus(0.0, stamp=1e12))
    # JSON has no infinity: leafgate's convention writes it as null, read back as NaN.
    payload = codecs("json").steering.encode(SteeringStatus(math.inf))
    assert json.loads(payload)["angle"] is None
    assert math.isnan(codecs("json").steering.decode(payload).angle)
