"""The DBC files are the contract of docs/can-protocol.md."""

from __future__ import annotations

import enum

import pytest
from cantools.database.can import Database

from leafgate.config import VehicleConfig
from leafgate.messages import EcuState, GatewayState, Gear, LongMode
from tests.conftest import packaged_dbc

# docs/can-protocol.md frame table: ID → (name, sender, period in ms)
DESIGN_FRAMES = {
    0x0A0: ("DBW_STEER_CMD", "GATEWAY", 20),
    0x0A1: ("DBW_LONG_CMD", "GATEWAY", 20),
    0x0A2: ("DBW_SYSTEM_CMD", "GATEWAY", 100),
    0x0B0: ("DBW_STEER_RPT", "DBW_ECU", 10),
    0x0B1: ("DBW_LONG_RPT", "DBW_ECU", 20),
    0x0B2: ("DBW_SYSTEM_RPT", "DBW_ECU", 100),
}
CAR_FRAMES = {0x002: 10, 0x176: 10, 0x284: 20, 0x285: 20, 0x421: 60}  # ID → period, ms


@pytest.fixture(scope="module")
def dbw() -> Database:
    return packaged_dbc("leafgate_dbw.dbc")


@pytest.fixture(scope="module")
def car() -> Database:
    return packaged_dbc("leaf_aze0_car.dbc")


def test_both_dbcs_load_strictly_from_the_package(dbw: Database, car: Database) -> None:
    assert len(dbw.messages) == len(DESIGN_FRAMES)
    assert {m.frame_id for m in car.messages} == set(CAR_FRAMES)


def test_nodes_are_gateway_and_dbw_ecu(dbw: Database) -> None:
    assert {n.name for n in dbw.nodes} == {"GATEWAY", "DBW_ECU"}


@pytest.mark.parametrize("frame_id", sorted(DESIGN_FRAMES))
def test_every_design_frame_has_its_id_name_sender_period_and_8_bytes(
    dbw: Database, frame_id: int
) -> None:
    name, sender, period = DESIGN_FRAMES[frame_id]
    message = dbw.get_message_by_frame_id(frame_id)
    assert message.name == name
    assert not message.is_extended_frame
    assert message.length == 8
    assert message.cycle_time == period
    assert message.senders == [sender]
    assert message.comment


@pytest.mark.parametrize("frame_id", sorted(DESIGN_FRAMES))
def test_dbw_frames_carry_counter_in_byte_6_low_nibble_and_crc_in_byte_7(
    dbw: Database, frame_id: int
) -> None:
    message = dbw.get_message_by_frame_id(frame_id)
    counter = message.get_signal_by_name("ALIVE_COUNTER")
    crc = message.get_signal_by_name("CRC")
    assert (counter.start, counter.length, counter.byte_order) == (48, 4, "little_endian")
    assert (crc.start, crc.length, crc.byte_order) == (56, 8, "little_endian")


@pytest.mark.parametrize("frame_id", sorted(DESIGN_FRAMES))
def test_every_dbw_signal_is_little_endian_commented_and_bounded(
    dbw: Database, frame_id: int
) -> None:
    for sig in dbw.get_message_by_frame_id(frame_id).signals:
        assert sig.byte_order == "little_endian", sig.name
        assert sig.comment, f"{sig.name} has no comment"
        assert sig.minimum is not None and sig.maximum is not None, sig.name
        # the DBC range must be representable in the signal's bits
        lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
        hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
        raw = sorted(
            ((sig.minimum - sig.offset) / sig.scale, (sig.maximum - sig.offset) / sig.scale)
        )
        assert lo <= round(raw[0]) and round(raw[1]) <= hi, sig.name


@pytest.mark.parametrize(
    ("frame_id", "signal", "unit", "scale"),
    [
        (0x0A0, "STEER_ANGLE_CMD", "rad", 1e-4),
        (0x0A0, "STEER_RATE_LIMIT", "rad/s", 1e-3),
        (0x0A1, "ACCEL_CMD", "m/s^2", 1e-3),
        (0x0A1, "SPEED_CMD", "m/s", 1e-3),
        (0x0B0, "STEER_ANGLE", "rad", 1e-4),
        (0x0B0, "DRIVER_TORQUE", "Nm", 0.01),
        (0x0B1, "SPEED", "m/s", None),
        (0x0B1, "BRAKE_PEDAL", "%", None),
        (0x0B1, "ACCEL_PEDAL", "%", None),
    ],
)
def test_design_scales_and_units(
    dbw: Database, frame_id: int, signal: str, unit: str, scale: float | None
) -> None:
    sig = dbw.get_message_by_frame_id(frame_id).get_signal_by_name(signal)
    assert sig.unit == unit
    if scale is not None:
        assert sig.scale == pytest.approx(scale)


def test_report_speed_is_signed(dbw: Database) -> None:
    assert dbw.get_message_by_name("DBW_LONG_RPT").get_signal_by_name("SPEED").is_signed


def test_angle_and_accel_ranges_are_wider_than_the_leaf_limits(dbw: Database) -> None:
    leaf = VehicleConfig()
    for message, signal in (("DBW_STEER_CMD", "STEER_ANGLE_CMD"), ("DBW_STEER_RPT", "STEER_ANGLE")):
        sig = dbw.get_message_by_name(message).get_signal_by_name(signal)
        assert sig.minimum is not None and sig.maximum is not None
        assert sig.minimum < -leaf.max_steer_angle and sig.maximum > leaf.max_steer_angle
        assert sig.maximum <= 1.0  # rad: physically sensible, not the raw range
    accel = dbw.get_message_by_name("DBW_LONG_CMD").get_signal_by_name("ACCEL_CMD")
    assert accel.minimum is not None and accel.maximum is not None
    assert accel.minimum < leaf.min_accel and accel.maximum > leaf.max_accel


@pytest.mark.parametrize(
    ("message", "signal", "enum_type"),
    [
        ("DBW_LONG_CMD", "MODE", LongMode),
        ("DBW_LONG_CMD", "GEAR_REQ", Gear),
        ("DBW_LONG_RPT", "GEAR", Gear),
        ("DBW_SYSTEM_CMD", "GATEWAY_STATE", GatewayState),
        ("DBW_SYSTEM_RPT", "ECU_STATE", EcuState),
    ],
)
def test_value_tables_match_the_message_enums(
    dbw: Database, message: str, signal: str, enum_type: type[enum.IntEnum]
) -> None:
    sig = dbw.get_message_by_name(message).get_signal_by_name(signal)
    assert sig.choices is not None
    table = {int(raw): str(name) for raw, name in sig.choices.items()}
    assert table == {int(member): member.name for member in enum_type}
    assert sig.maximum == max(int(m) for m in enum_type)


@pytest.mark.parametrize("frame_id", sorted(CAR_FRAMES))
def test_car_frames_cite_their_public_source_and_period(car: Database, frame_id: int) -> None:
    message = car.get_message_by_frame_id(frame_id)
    assert message.cycle_time == CAR_FRAMES[frame_id]
    assert not message.is_extended_frame
    assert message.comment is not None
    assert "opendbc" in message.comment or "dalathegreat" in message.comment
    for sig in message.signals:
        assert sig.comment, f"{message.name}.{sig.name} has no comment"


def test_steering_wheel_angle_is_int16_little_endian_with_negative_factor(car: Database) -> None:
    sig = car.get_message_by_frame_id(0x002).get_signal_by_name("STEER_ANGLE")
    assert (sig.start, sig.length, sig.byte_order, sig.is_signed) == (0, 16, "little_endian", True)
    assert sig.scale == pytest.approx(-0.1)
    assert sig.unit == "deg"


@pytest.mark.parametrize("frame_id", [0x284, 0x285])
def test_wheel_speeds_are_big_endian_16_bit_at_0_005_kmh(car: Database, frame_id: int) -> None:
    signals = [s for s in car.get_message_by_frame_id(frame_id).signals if "WHEEL" in s.name]
    assert len(signals) == 2
    for sig in signals:
        assert (sig.length, sig.byte_order, sig.is_signed) == (16, "big_endian", False)
        assert sig.scale == pytest.approx(0.005)
        assert sig.unit == "km/h"


def test_gear_is_bits_7_to_3_of_byte_0_with_a_value_table(car: Database) -> None:
    message = car.get_message_by_frame_id(0x421)
    sig = message.get_signal_by_name("GEAR_SHIFTER")
    assert (sig.start, sig.length, sig.byte_order) == (7, 5, "big_endian")
    assert sig.choices is not None
    assert {int(k): str(v) for k, v in sig.choices.items()} == {
        1: "P",
        2: "R",
        3: "N",
        4: "D",
        7: "B",
    }
    for code, byte0 in ((1, 0x08), (2, 0x10), (3, 0x18), (4, 0x20)):
        assert message.encode({"GEAR_SHIFTER": code})[0] == byte0
