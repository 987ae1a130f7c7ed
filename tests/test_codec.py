"""CanCodec: strict encoding, never-raising decoding with E2E checks, counted per ID."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.can import e2e
from leafgate.can.codec import (
    CanCodec,
    EncodableMessage,
    EncodeError,
    _compile,
    _compile_encoder,
)
from leafgate.can.profile import load_profile
from leafgate.errors import CanCodecError
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    GearPosition,
    LongCommand,
    LongMode,
    LongReport,
    MotorSpeed,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    WheelSpeeds,
)

CODEC = CanCodec(
    profile="leafgate-dbw"
)  # for DBC look-ups only; tests that encode/decode make their own
DBW, CAR = CODEC.databases
DEG = math.pi / 180.0  # rad/deg
KMH = 1 / 3.6  # (m/s)/(km/h)
MPS_PER_COUNT = KMH / 8.570637  # (m/s) per count of 0x176 bytes 0-1 (wheel rpm)

# (message, signal) → (SI value from the DBC value, message built with that field)
FIELDS: dict[tuple[str, str], tuple[float, Callable[[float], EncodableMessage]]] = {
    ("DBW_STEER_CMD", "STEER_ANGLE_CMD"): (1.0, lambda v: SteerCommand(angle=v)),
    ("DBW_STEER_CMD", "STEER_RATE_LIMIT"): (1.0, lambda v: SteerCommand(0.0, rate_limit=v)),
    ("DBW_LONG_CMD", "ACCEL_CMD"): (1.0, lambda v: LongCommand(accel=v)),
    ("DBW_LONG_CMD", "SPEED_CMD"): (1.0, lambda v: LongCommand(speed=v)),
    ("DBW_STEER_RPT", "STEER_ANGLE"): (
        1.0,
        lambda v: SteerReport(v, 0.0, 0.0, False, False, False, False),
    ),
    ("DBW_STEER_RPT", "STEER_RATE"): (
        1.0,
        lambda v: SteerReport(0.0, v, 0.0, False, False, False, False),
    ),
    ("DBW_STEER_RPT", "DRIVER_TORQUE"): (
        1.0,
        lambda v: SteerReport(0.0, 0.0, v, False, False, False, False),
    ),
    ("DBW_LONG_RPT", "SPEED"): (
        1.0,
        lambda v: LongReport(v, 0.0, Gear.D, 0.0, 0.0, False, False, False, False),
    ),
    ("DBW_LONG_RPT", "ACCEL"): (
        1.0,
        lambda v: LongReport(0.0, v, Gear.D, 0.0, 0.0, False, False, False, False),
    ),
    ("DBW_LONG_RPT", "BRAKE_PEDAL"): (
        1.0,
        lambda v: LongReport(0.0, 0.0, Gear.D, v, 0.0, False, False, False, False),
    ),
    ("DBW_LONG_RPT", "ACCEL_PEDAL"): (
        1.0,
        lambda v: LongReport(0.0, 0.0, Gear.D, 0.0, v, False, False, False, False),
    ),
    ("DBW_SYSTEM_RPT", "RX_ERROR_COUNT"): (
        1.0,
        lambda v: SystemReport(EcuState.READY, False, False, False, False, round(v)),
    ),
    ("STEER_ANGLE_SENSOR", "STEER_ANGLE"): (DEG, lambda v: SteeringWheelAngle(v)),
    ("OUTPUT_SPEED", "OUTPUT_REVS"): (MPS_PER_COUNT, lambda v: MotorSpeed(v)),
    ("WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FL"): (KMH, lambda v: WheelSpeeds(v, 0.0, "front")),
    ("WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FR"): (KMH, lambda v: WheelSpeeds(0.0, v, "front")),
    ("WHEEL_SPEEDS_REAR", "WHEEL_SPEED_RL"): (KMH, lambda v: WheelSpeeds(v, 0.0, "rear")),
    ("WHEEL_SPEEDS_REAR", "WHEEL_SPEED_RR"): (KMH, lambda v: WheelSpeeds(0.0, v, "rear")),
}


def signal(message: str, name: str) -> cantools.database.can.Signal:
    db = DBW if message.startswith("DBW_") else CAR
    return db.get_message_by_name(message).get_signal_by_name(name)


def limits(message: str, name: str) -> tuple[float, float]:
    """The DBC's physical range of a signal (DBC units)."""
    sig = signal(message, name)
    assert sig.minimum is not None and sig.maximum is not None
    return float(sig.minimum), float(sig.maximum)


def field_value(decoded: object, message: str, name: str) -> float:
    """The decoded dataclass field that carries ``message.name`` (SI)."""
    probe = {
        "STEER_ANGLE_CMD": "angle",
        "STEER_RATE_LIMIT": "rate_limit",
        "ACCEL_CMD": "accel",
        "SPEED_CMD": "speed",
        "STEER_RATE": "rate",
        "DRIVER_TORQUE": "driver_torque",
        "ACCEL": "accel",
        "BRAKE_PEDAL": "brake_pedal_pct",
        "ACCEL_PEDAL": "accel_pedal_pct",
        "RX_ERROR_COUNT": "rx_error_count",
        "OUTPUT_REVS": "speed",
        "WHEEL_SPEED_FL": "left",
        "WHEEL_SPEED_RL": "left",
        "WHEEL_SPEED_FR": "right",
        "WHEEL_SPEED_RR": "right",
    }
    attr = probe.get(name, "speed" if name == "SPEED" else "angle")
    return float(getattr(decoded, attr))


def roundtrip(value: EncodableMessage) -> object:
    msg = CanCodec(profile="leafgate-dbw").encode(value)
    decoded = CanCodec(profile="leafgate-dbw").decode(msg)
    assert decoded.valid, decoded
    return decoded.value


# --- limits: min, max, just inside, just outside ------------------------------------------------


def limit_cases() -> list[tuple[str, str, str]]:
    return [(m, s, case) for (m, s) in FIELDS for case in ("min", "max", "in_min", "in_max")]


@pytest.mark.parametrize(("message", "name", "case"), limit_cases())
def test_values_at_and_just_inside_every_limit_round_trip(
    message: str, name: str, case: str
) -> None:
    factor, make = FIELDS[(message, name)]
    lo, hi = limits(message, name)
    lsb = abs(signal(message, name).scale)
    dbc_value = {
        "min": lo,
        "max": hi,
        "in_min": lo + lsb,
        "in_max": hi - lsb,
    }[case]
    decoded = roundtrip(make(dbc_value * factor))
    assert field_value(decoded, message, name) == pytest.approx(
        dbc_value * factor, abs=lsb * factor * 0.5 + 1e-9
    )


@pytest.mark.parametrize(("message", "name"), list(FIELDS))
@pytest.mark.parametrize("side", ["below_min", "above_max"])
def test_out_of_range_encode_raises_encode_error(message: str, name: str, side: str) -> None:
    factor, make = FIELDS[(message, name)]
    lo, hi = limits(message, name)
    lsb = abs(signal(message, name).scale)
    dbc_value = lo - lsb if side == "below_min" else hi + lsb
    with pytest.raises(EncodeError) as info:
        CanCodec(profile="leafgate-dbw").encode(make(dbc_value * factor))
    assert isinstance(info.value, CanCodecError)
    assert isinstance(info.value, cantools.database.EncodeError)
    assert name in str(info.value)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_raise_encode_error(bad: float) -> None:
    with pytest.raises(EncodeError, match="not finite"):
        CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=bad))


def test_enum_code_outside_the_value_table_raises_encode_error() -> None:
    with pytest.raises(EncodeError):
        CanCodec(profile="leafgate-dbw").encode(LongCommand(gear=5))  # type: ignore[arg-type]


def test_unknown_axle_and_unknown_type_raise_encode_error() -> None:
    with pytest.raises(EncodeError, match="axle"):
        CanCodec(profile="leafgate-dbw").encode(WheelSpeeds(1.0, 1.0, "middle"))
    with pytest.raises(EncodeError, match="str"):
        CanCodec(profile="leafgate-dbw").encode("not a message")  # type: ignore[arg-type]


# --- round trips ----------------------------------------------------------------------------


def within(sig_message: str, sig_name: str) -> st.SearchStrategy[float]:
    lo, hi = limits(sig_message, sig_name)
    return st.floats(min_value=lo, max_value=hi, allow_nan=False)


def close(a: float, b: float, message: str, name: str, factor: float = 1.0) -> bool:
    return abs(a - b) <= abs(signal(message, name).scale) * factor * 0.5 + 1e-9


@settings(max_examples=60, deadline=None)
@given(
    within("DBW_STEER_CMD", "STEER_ANGLE_CMD"),
    within("DBW_STEER_CMD", "STEER_RATE_LIMIT"),
    st.booleans(),
    st.booleans(),
)
def test_steer_command_round_trip(angle: float, rate: float, enable: bool, clear: bool) -> None:
    out = roundtrip(SteerCommand(angle, rate, enable, clear))
    assert isinstance(out, SteerCommand)
    assert close(out.angle, angle, "DBW_STEER_CMD", "STEER_ANGLE_CMD")
    assert close(out.rate_limit, rate, "DBW_STEER_CMD", "STEER_RATE_LIMIT")
    assert (out.enable, out.clear_override) == (enable, clear)


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(LongMode),
    within("DBW_LONG_CMD", "ACCEL_CMD"),
    within("DBW_LONG_CMD", "SPEED_CMD"),
    st.sampled_from(Gear),
    st.booleans(),
    st.booleans(),
)
def test_long_command_round_trip(
    mode: LongMode, accel: float, speed: float, gear: Gear, enable: bool, clear: bool
) -> None:
    out = roundtrip(LongCommand(mode, accel, speed, gear, enable, clear))
    assert isinstance(out, LongCommand)
    assert out.mode is mode and out.gear is gear
    assert close(out.accel, accel, "DBW_LONG_CMD", "ACCEL_CMD")
    assert close(out.speed, speed, "DBW_LONG_CMD", "SPEED_CMD")
    assert (out.enable, out.clear_override) == (enable, clear)


@given(st.sampled_from(GatewayState), st.booleans())
def test_system_command_round_trip(state: GatewayState, clear: bool) -> None:
    assert roundtrip(SystemCommand(state, clear)) == SystemCommand(state, clear)


@settings(max_examples=60, deadline=None)
@given(
    within("DBW_STEER_RPT", "STEER_ANGLE"),
    within("DBW_STEER_RPT", "STEER_RATE"),
    within("DBW_STEER_RPT", "DRIVER_TORQUE"),
    st.lists(st.booleans(), min_size=4, max_size=4),
)
def test_steer_report_round_trip(
    angle: float, rate: float, torque: float, flags: list[bool]
) -> None:
    out = roundtrip(SteerReport(angle, rate, torque, *flags))
    assert isinstance(out, SteerReport)
    assert close(out.angle, angle, "DBW_STEER_RPT", "STEER_ANGLE")
    assert close(out.rate, rate, "DBW_STEER_RPT", "STEER_RATE")
    assert close(out.driver_torque, torque, "DBW_STEER_RPT", "DRIVER_TORQUE")
    assert [out.enabled, out.override, out.fault, out.cmd_timeout] == flags


@settings(max_examples=60, deadline=None)
@given(
    within("DBW_LONG_RPT", "SPEED"),
    within("DBW_LONG_RPT", "ACCEL"),
    st.sampled_from(Gear),
    within("DBW_LONG_RPT", "BRAKE_PEDAL"),
    within("DBW_LONG_RPT", "ACCEL_PEDAL"),
    st.lists(st.booleans(), min_size=4, max_size=4),
)
def test_long_report_round_trip(
    speed: float, accel: float, gear: Gear, brake: float, pedal: float, flags: list[bool]
) -> None:
    out = roundtrip(LongReport(speed, accel, gear, brake, pedal, *flags))
    assert isinstance(out, LongReport)
    assert close(out.speed, speed, "DBW_LONG_RPT", "SPEED")
    assert close(out.accel, accel, "DBW_LONG_RPT", "ACCEL")
    assert out.gear is gear
    assert close(out.brake_pedal_pct, brake, "DBW_LONG_RPT", "BRAKE_PEDAL")
    assert close(out.accel_pedal_pct, pedal, "DBW_LONG_RPT", "ACCEL_PEDAL")
    assert [out.enabled, out.override, out.fault, out.cmd_timeout] == flags


@given(
    st.sampled_from(EcuState),
    st.lists(st.booleans(), min_size=4, max_size=4),
    st.integers(min_value=0, max_value=65535),
)
def test_system_report_round_trip(state: EcuState, flags: list[bool], count: int) -> None:
    value = SystemReport(state, flags[0], flags[1], flags[2], flags[3], count)
    assert roundtrip(value) == value


@given(within("STEER_ANGLE_SENSOR", "STEER_ANGLE"))
def test_steering_wheel_angle_round_trip(angle_deg: float) -> None:
    out = roundtrip(SteeringWheelAngle(angle_deg * DEG))
    assert isinstance(out, SteeringWheelAngle)
    assert close(out.angle, angle_deg * DEG, "STEER_ANGLE_SENSOR", "STEER_ANGLE", DEG)


@given(
    within("WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FL"),
    within("WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FR"),
    st.sampled_from(["front", "rear"]),
)
def test_wheel_speeds_round_trip(left_kmh: float, right_kmh: float, axle: str) -> None:
    out = roundtrip(WheelSpeeds(left_kmh * KMH, right_kmh * KMH, axle))
    assert isinstance(out, WheelSpeeds)
    assert out.axle == axle
    assert close(out.left, left_kmh * KMH, "WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FL", KMH)
    assert close(out.right, right_kmh * KMH, "WHEEL_SPEEDS_FRONT", "WHEEL_SPEED_FR", KMH)


@given(within("OUTPUT_SPEED", "OUTPUT_REVS"))
def test_motor_speed_round_trip(rpm: float) -> None:
    out = roundtrip(MotorSpeed(rpm * MPS_PER_COUNT))
    assert isinstance(out, MotorSpeed)
    assert close(out.speed, rpm * MPS_PER_COUNT, "OUTPUT_SPEED", "OUTPUT_REVS", MPS_PER_COUNT)


@pytest.mark.parametrize("gear", [Gear.P, Gear.R, Gear.N, Gear.D, Gear.NONE])
def test_gear_position_round_trip(gear: Gear) -> None:
    assert roundtrip(GearPosition(gear)) == GearPosition(gear)


# --- edge conversions and byte layouts --------------------------------------------------------


def test_steering_wheel_left_is_a_negative_raw_int16_little_endian() -> None:
    msg = CanCodec(profile="leafgate-dbw").encode(SteeringWheelAngle(10.0 * DEG))  # 10° to the left
    assert len(msg.data) == 5
    assert int.from_bytes(msg.data[0:2], "little", signed=True) == -100  # 0.1° per bit


def test_wheel_speed_is_big_endian_right_wheel_first() -> None:
    msg = CanCodec(profile="leafgate-dbw").encode(WheelSpeeds(left=1.0, right=2.0, axle="front"))
    assert msg.arbitration_id == 0x284
    assert int.from_bytes(msg.data[0:2], "big") == round(2.0 * 3.6 / 0.005)
    assert int.from_bytes(msg.data[2:4], "big") == round(1.0 * 3.6 / 0.005)


@pytest.mark.parametrize(
    ("byte0", "gear"),
    [
        (0x08, Gear.P),
        (0x10, Gear.R),
        (0x18, Gear.N),
        (0x20, Gear.D),
        (0x38, Gear.D),
        (0x00, Gear.NONE),
    ],
)
def test_gear_lever_byte_decodes_to_gear(byte0: int, gear: Gear) -> None:
    # 0x38 is B (regenerative drive mode): a forward gear; 0x00 is not a lever position
    frame = can.Message(arbitration_id=0x421, data=[byte0, 0, 0], is_extended_id=False)
    out = CanCodec(profile="leafgate-dbw").decode(frame)
    assert out.valid and out.value == GearPosition(gear)


def test_a_one_byte_gear_frame_is_the_wrong_length() -> None:
    # the AZE0 sends 0x421 with 3 bytes in every frame (issue 15); 1 byte is not the car's
    out = CanCodec(profile="leafgate-dbw").decode(
        can.Message(arbitration_id=0x421, data=[0x20], is_extended_id=False)
    )
    assert out.error == "wrong_length"


def test_longer_car_frame_is_accepted_as_model_years_differ() -> None:
    # unprotected car frames may carry trailing bytes a model year adds
    out = CanCodec(profile="leafgate-dbw").decode(
        can.Message(arbitration_id=0x421, data=[0x20, 0xAA, 0x55, 0x00], is_extended_id=False)
    )
    assert out.valid and out.value == GearPosition(Gear.D)


def test_encoded_frames_are_standard_8_byte_with_timestamp_and_e2e() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    for frame_id in sorted(codec.receive_ids("commands") | codec.receive_ids("reports")):
        name = codec.name_of(frame_id)
        values: dict[str, EncodableMessage] = {
            "DBW_STEER_CMD": SteerCommand(0.0),
            "DBW_LONG_CMD": LongCommand(),
            "DBW_SYSTEM_CMD": SystemCommand(GatewayState.STANDBY),
            "DBW_STEER_RPT": SteerReport(0.0, 0.0, 0.0, False, False, False, False),
            "DBW_LONG_RPT": LongReport(0.0, 0.0, Gear.P, 0.0, 0.0, False, False, False, False),
            "DBW_SYSTEM_RPT": SystemReport(EcuState.READY, False, False, False, False, 0),
        }
        value = values[name or ""]
        msg = codec.encode(value, timestamp=12.5)
        assert msg.arbitration_id == frame_id and not msg.is_extended_id
        assert msg.dlc == 8 and len(msg.data) == 8 and msg.timestamp == 12.5
        assert e2e.verify(frame_id, msg.data)


def test_alive_counters_are_per_instance_and_per_id_and_wrap() -> None:
    gateway, ecu = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    steer = [gateway.encode(SteerCommand(0.0)) for _ in range(18)]
    long = gateway.encode(LongCommand())
    assert [e2e.counter_of(m.data) for m in steer] == [n % 16 for n in range(18)]
    assert e2e.counter_of(long.data) == 0  # its own counter
    assert e2e.counter_of(ecu.encode(SteerCommand(0.0)).data) == 0  # another instance
    decoder = CanCodec(profile="leafgate-dbw")
    assert all(decoder.decode(m).valid for m in steer)  # 15 → 0 accepted


# --- decode faults: detected, counted, never raised ---------------------------------------------


def test_bad_crc_is_detected_counted_and_value_kept_for_logging() -> None:
    tx, rx = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    msg = tx.encode(SteerCommand(0.25, enable=True))
    data = bytearray(msg.data)
    data[0] ^= 0x01
    out = rx.decode(can.Message(arbitration_id=0x0A0, data=data, is_extended_id=False))
    assert (out.valid, out.error, out.name) == (False, "bad_crc", "DBW_STEER_CMD")
    assert isinstance(out.value, SteerCommand)
    assert rx.stats[0x0A0].bad_crc == 1 and rx.stats[0x0A0].frames == 1


def test_repeated_counter_is_detected_and_counted() -> None:
    tx, rx = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    msg = tx.encode(SteerReport(0.0, 0.0, 0.0, True, False, False, False))
    assert rx.decode(msg).valid
    out = rx.decode(msg)
    assert (out.valid, out.error) == (False, "bad_counter")
    assert isinstance(out.value, SteerReport)
    assert rx.stats[0x0B0].bad_counter == 1 and rx.stats[0x0B0].frames == 2


def test_skipped_counter_is_detected_and_counted() -> None:
    tx, rx = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    frames = [tx.encode(SystemCommand(GatewayState.ENGAGED)) for _ in range(3)]
    assert rx.decode(frames[0]).valid
    assert rx.decode(frames[2]).error == "bad_counter"  # frame 1 lost
    assert rx.stats[0x0A2].bad_counter == 1


@pytest.mark.parametrize("length", [0, 1, 7])
def test_wrong_length_is_detected_counted_and_has_no_value(length: int) -> None:
    rx = CanCodec(profile="leafgate-dbw")
    out = rx.decode(can.Message(arbitration_id=0x0B1, data=bytes(length), is_extended_id=False))
    assert (out.valid, out.error, out.value) == (False, "wrong_length", None)
    assert rx.stats[0x0B1].wrong_length == 1


def test_short_car_frame_is_wrong_length() -> None:
    rx = CanCodec(profile="leafgate-dbw")
    out = rx.decode(can.Message(arbitration_id=0x284, data=bytes(3), is_extended_id=False))
    assert out.error == "wrong_length"
    assert rx.stats[0x284].wrong_length == 1


def test_unknown_id_and_extended_id_are_counted_as_unknown() -> None:
    rx = CanCodec(profile="leafgate-dbw")
    out = rx.decode(can.Message(arbitration_id=0x555, data=bytes(8), is_extended_id=False))
    assert (out.valid, out.error, out.name, out.value) == (False, "unknown_id", None, None)
    ext = rx.decode(can.Message(arbitration_id=0x0A0, data=bytes(8), is_extended_id=True))
    assert ext.error == "unknown_id"
    assert rx.stats[0x555].unknown_id == 1
    assert rx.unknown_id_count == 2


def test_value_outside_a_value_table_in_a_valid_frame_is_a_decode_error() -> None:
    rx = CanCodec(profile="leafgate-dbw")
    data = bytearray(8)
    data[3] = 6 << 4  # DBW_LONG_RPT.GEAR (bits 28..30) = 6, not a gear
    msg = can.Message(
        arbitration_id=0x0B1, data=e2e.apply(0x0B1, bytes(data), 0), is_extended_id=False
    )
    out = rx.decode(msg)
    assert (out.valid, out.error, out.value) == (False, "decode_error", None)
    assert rx.stats[0x0B1].decode_error == 1


@settings(max_examples=300, deadline=None)
@given(
    st.integers(min_value=0, max_value=0x1FFFFFFF),
    st.binary(max_size=8),
    st.booleans(),
    st.booleans(),
    st.booleans(),
)
def test_decode_never_raises(
    frame_id: int, data: bytes, extended: bool, remote: bool, error: bool
) -> None:
    rx = CanCodec(profile="leafgate-dbw")
    msg = can.Message(
        arbitration_id=frame_id if extended else frame_id & 0x7FF,
        data=data,
        is_extended_id=extended,
        is_remote_frame=remote and not error,
        is_error_frame=error,
        check=False,
    )
    out = rx.decode(msg)
    assert out.valid == (out.error is None)
    assert sum(s.frames for s in rx.stats.values()) == 1


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(sorted(f.name for f in load_profile().frames)),
    st.binary(min_size=8, max_size=8),
)
def test_compiled_decoder_matches_cantools_on_random_payloads(name: str, data: bytes) -> None:
    db = DBW if name.startswith("DBW_") else CAR
    message = db.get_message_by_name(name)
    names = tuple(sig.name for sig in message.signals)
    fast = _compile(message, names, lambda *values: values)(data)
    reference = message.decode(data[: message.length], decode_choices=False, scaling=True)
    assert isinstance(reference, dict)
    assert fast == pytest.approx(tuple(reference[n] for n in names), abs=1e-9)


def test_receive_ids_per_direction() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    assert codec.receive_ids("reports") == {0x0B0, 0x0B1, 0x0B2}
    assert codec.receive_ids("commands") == {0x0A0, 0x0A1, 0x0A2}
    assert codec.receive_ids("car") == {0x002, 0x176, 0x284, 0x285, 0x421}
    with pytest.raises(ValueError, match="direction"):
        codec.receive_ids("sideways")  # type: ignore[arg-type]


def test_missing_dbc_file_is_a_codec_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(CanCodecError, match=r"nope\.dbc: no such DBC file"):
        CanCodec(dbw_dbc=tmp_path / "nope.dbc", profile="leafgate-dbw")


def test_dbc_lacking_a_frame_is_a_codec_error_naming_it(tmp_path: Path) -> None:
    source = Path(__file__).parents[1] / "dbc" / "leafgate_dbw.dbc"
    text = source.read_text(encoding="utf-8").replace("DBW_SYSTEM_RPT", "DBW_SYSTEM_REPORT")
    path = tmp_path / "renamed.dbc"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(
        CanCodecError, match=r"frame DBW_SYSTEM_RPT is in no DBC of the profile \(.*renamed\.dbc"
    ):
        CanCodec(dbw_dbc=path, profile="leafgate-dbw")


def test_invalid_dbc_is_a_codec_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.dbc"
    path.write_text("BO_ this is not a dbc\n", encoding="utf-8")
    with pytest.raises(CanCodecError, match=r"broken\.dbc: invalid DBC"):
        CanCodec(car_dbc=path, profile="leafgate-dbw")


def test_failed_encode_does_not_advance_the_alive_counter() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    assert e2e.counter_of(codec.encode(SteerCommand(0.0)).data) == 0
    with pytest.raises(EncodeError):
        codec.encode(SteerCommand(5.0))  # far outside the angle range
    assert e2e.counter_of(codec.encode(SteerCommand(0.0)).data) == 1


def test_non_number_field_raises_encode_error() -> None:
    with pytest.raises(EncodeError, match="not a number"):
        CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle="left"))  # type: ignore[arg-type]


# --- the compiled encoder against cantools' strict encode ------------------------------------

E2E_NAMES = ("ALIVE_COUNTER", "CRC")
ALL_MESSAGES = sorted(f.name for f in load_profile().frames)


def dbc_message(name: str) -> cantools.database.can.Message:
    return (DBW if name.startswith("DBW_") else CAR).get_message_by_name(name)


def payload_signals(message: cantools.database.can.Message) -> tuple[str, ...]:
    """Every signal of a message except the E2E ones, which e2e.apply fills."""
    return tuple(s.name for s in message.signals if s.name not in E2E_NAMES)


def tolerance(sig: cantools.database.can.Signal) -> float:
    return abs(sig.conversion.scale) * 1e-6  # cantools' slack beyond min/max


def near_limits(sig: cantools.database.can.Signal) -> list[float]:
    """Values packed around a signal's min and max: on them, on cantools' tolerance, one ulp
    either side of both, half and one LSB beyond, and the value-table codes."""
    lsb = abs(sig.conversion.scale)
    out: list[float] = []
    for bound, outward in ((sig.minimum, -math.inf), (sig.maximum, math.inf)):
        assert bound is not None
        edge = bound - tolerance(sig) if outward < 0 else bound + tolerance(sig)
        for x in (float(bound), edge):
            out += [x, math.nextafter(x, outward), math.nextafter(x, -outward)]
        step = lsb if outward > 0 else -lsb
        out += [bound + step / 2, bound + step, bound - step / 2]
    return out + [float(code) for code in (sig.conversion.choices or {})]


def cantools_payload(
    message: cantools.database.can.Message, values: dict[str, Any]
) -> bytes | None:
    """cantools' strict encode with the E2E signals at 0; None where cantools refuses."""
    signals = {**values, **{n: 0 for n in E2E_NAMES if n in {s.name for s in message.signals}}}
    try:
        return message.encode(signals, scaling=True, padding=False, strict=True)
    except (cantools.database.EncodeError, ValueError, OverflowError):  # NaN, inf, no fit
        return None


def compiled_payload(
    message: cantools.database.can.Message, values: dict[str, object]
) -> bytes | None:
    names = tuple(values)
    try:
        return _compile_encoder(message, names)(*(values[n] for n in names))
    except EncodeError:
        return None


def neutral(sig: cantools.database.can.Signal) -> float:
    """A value every signal of the packaged DBCs accepts: 0 clamped into the range."""
    lo = -math.inf if sig.minimum is None else sig.minimum
    hi = math.inf if sig.maximum is None else sig.maximum
    return min(max(0.0, lo), hi)


def limit_table() -> list[tuple[str, str, float]]:
    return [
        (name, sig.name, value)
        for name in ALL_MESSAGES
        for sig in dbc_message(name).signals
        if sig.name not in E2E_NAMES
        for value in near_limits(sig)
    ]


@pytest.mark.parametrize(("name", "signal_name", "value"), limit_table())
def test_compiled_encoder_refuses_exactly_where_cantools_strict_does(
    name: str, signal_name: str, value: float
) -> None:
    message = dbc_message(name)
    values: dict[str, object] = {
        n: neutral(message.get_signal_by_name(n)) for n in payload_signals(message)
    }
    values[signal_name] = value
    reference = cantools_payload(message, values)
    assert compiled_payload(message, values) == reference


def raw_to_physical(raw: int, *, scale: float, offset: float, fraction: float) -> float:
    return (raw + fraction) * scale + offset


@st.composite
def message_values(draw: st.DrawFn, message: cantools.database.can.Message) -> dict[str, object]:
    """Values for every payload signal: mostly in range (floats, integers, table codes), some
    packed around the limits, a few out of range or not finite."""
    values: dict[str, object] = {}
    for sig in message.signals:
        if sig.name in E2E_NAMES:
            continue
        lo = -20 if sig.minimum is None else sig.minimum  # unbounded: around a small field
        hi = 20 if sig.maximum is None else sig.maximum
        lsb = abs(sig.conversion.scale)
        scale, offset = sig.conversion.scale, sig.conversion.offset
        raw_lo, raw_hi = sorted(((lo - offset) / scale, (hi - offset) / scale))
        steps = st.integers(min_value=math.floor(raw_lo), max_value=math.ceil(raw_hi))
        grid = functools.partial(raw_to_physical, scale=scale, offset=offset, fraction=0.0)
        between = functools.partial(raw_to_physical, scale=scale, offset=offset, fraction=0.5)
        values[sig.name] = draw(
            st.one_of(
                st.floats(min_value=lo, max_value=hi),
                # on the raw grid and half-way between: where rounding details show
                steps.map(grid),
                steps.map(between),
                st.integers(min_value=math.ceil(lo), max_value=math.floor(hi)),
                st.sampled_from(near_limits(sig)) if sig.minimum is not None else st.nothing(),
                st.floats(min_value=lo - 4 * lsb, max_value=hi + 4 * lsb),
                st.sampled_from([math.nan, math.inf, -math.inf]),
            )
        )
    return values


@settings(max_examples=400, deadline=None)
@given(
    st.sampled_from(ALL_MESSAGES).flatmap(
        lambda n: st.tuples(st.just(n), message_values(dbc_message(n)))
    )
)
def test_compiled_encoder_is_byte_identical_to_cantools_strict_encode(
    case: tuple[str, dict[str, object]],
) -> None:
    name, values = case
    message = dbc_message(name)
    reference = cantools_payload(message, values)
    assert compiled_payload(message, values) == reference
    if reference is not None and name.startswith("DBW_"):  # and so after E2E
        assert e2e.apply(message.frame_id, reference, 9) == e2e.apply(
            message.frame_id, _compile_encoder(message, tuple(values))(*values.values()), 9
        )


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(sorted(FIELDS)).flatmap(
        lambda key: st.tuples(
            st.just(key),
            st.floats(
                min_value=limits(*key)[0] - 3 * abs(signal(*key).scale),
                max_value=limits(*key)[1] + 3 * abs(signal(*key).scale),
            ),
        )
    ),
    st.integers(min_value=0, max_value=15),
)
def test_codec_encode_matches_cantools_from_message_to_frame(
    case: tuple[tuple[str, str], float], counter: int
) -> None:
    """The whole path, field mapping, unit conversion and E2E included."""
    (message, name), dbc_value = case
    factor, make = FIELDS[(message, name)]
    value = make(dbc_value * factor)
    codec = CanCodec(profile="leafgate-dbw")
    for _ in range(counter):  # bring the alive counter to `counter`
        codec.encode(make(0.0))
    try:
        reference: bytes | None = codec._encode_with_cantools(value, counter)
    except EncodeError:
        reference = None
    try:
        data: bytes | None = bytes(codec.encode(value).data)
    except EncodeError:
        data = None
    assert data == reference


# A DBC with what the leafgate DBCs lack: integer scale with an offset, big-endian signed and
# little-endian fields in one frame, a signal without a range, a value table reaching beyond
# the range, and a range wider than the bit field.
EXOTIC_DBC = """VERSION ""
BS_:
BU_: A
BO_ 1280 EXOTIC: 8 A
 SG_ INT_SCALED : 0|8@1+ (2,-5) [-5|500] "" A
 SG_ BE_SIGNED : 15|12@0- (0.25,10) [-500|500] "m" A
 SG_ UNBOUNDED : 16|4@1- (1,0) [0|0] "" A
 SG_ CODED : 24|6@1+ (1,0) [0|20] "" A
 SG_ WIDE : 39|16@0+ (0.5,-1) [-1|40000] "" A
VAL_ 1280 CODED 63 "not available" 40 "init" ;
"""


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_compiled_encoder_matches_cantools_on_exotic_layouts(data: st.DataObject) -> None:
    db = cantools.database.load_string(EXOTIC_DBC, database_format="dbc", strict=True)
    assert isinstance(db, cantools.database.can.Database)
    message = db.get_message_by_name("EXOTIC")
    values = data.draw(message_values(message))
    values["CODED"] = data.draw(st.sampled_from([0.0, 20.0, 21.0, 40.0, 63.0, 64.0, 39.6]))
    assert compiled_payload(message, values) == cantools_payload(message, values)


def test_out_of_range_error_names_frame_id_signal_value_and_range() -> None:
    with pytest.raises(EncodeError) as info:
        CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=0.9))
    assert str(info.value) == (
        "DBW_STEER_CMD (0x0A0) STEER_ANGLE_CMD: value 0.9 is outside its range [-0.8, 0.8] rad"
    )


def test_numpy_scalars_encode_like_python_numbers() -> None:
    import numpy as np

    as_numpy = CanCodec(profile="leafgate-dbw").encode(
        SystemReport(EcuState.READY, False, False, False, False, np.int64(7))  # type: ignore[arg-type]
    )
    as_python = CanCodec(profile="leafgate-dbw").encode(
        SystemReport(EcuState.READY, False, False, False, False, 7)
    )
    assert as_numpy.data == as_python.data
    steer = CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=np.float32(0.25)))  # type: ignore[arg-type]
    assert steer.data == CanCodec(profile="leafgate-dbw").encode(SteerCommand(angle=0.25)).data


def test_dbc_with_a_signal_leafgate_does_not_fill_decodes_but_refuses_to_encode(
    tmp_path: Path,
) -> None:
    source = Path(__file__).parents[1] / "dbc" / "leafgate_dbw.dbc"
    spare = ' SG_ SPARE : 8|8@1+ (1,0) [0|255] "" DBW_ECU\n'
    text = source.read_text(encoding="utf-8").replace(
        " SG_ CLEAR_FAULTS :", spare + " SG_ CLEAR_FAULTS :", 1
    )
    path = tmp_path / "spare.dbc"
    path.write_text(text, encoding="utf-8")
    codec = CanCodec(dbw_dbc=path, profile="leafgate-dbw")
    with pytest.raises(EncodeError, match=r"DBW_SYSTEM_CMD \(0x0A2\).*SPARE"):
        codec.encode(SystemCommand(GatewayState.ENGAGED))
    frame = CanCodec(profile="leafgate-dbw").encode(SystemCommand(GatewayState.ENGAGED))
    assert codec.decode(frame).value == SystemCommand(GatewayState.ENGAGED)
    assert codec.encode(SteerCommand(0.1)).arbitration_id == 0x0A0  # other frames still encode
