"""A vehicle profile pointed at a foreign DBC (opendbc's ``nissan_leaf_2018_generated.dbc``).

opendbc's 0x185 ``STEER_TORQUE_SENSOR`` has a signal leafgate's ZE1 DBC leaves out
(``LKAS_STATUS``, 4 bits at bit 55) and gives raw ranges as physical ones (``STEER_ANGLE``
``[0|262143]``). The gateway only decodes the reports, so it takes that DBC; the simulated
ECU sends them, and used to drop every such frame silently: `leafgate sim` then said
``steer_report missing`` (or FAULT on its age) instead of why. The DBCs here are the packaged
ZE1 one with opendbc's differences written in, so the tests need no opendbc.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from leafgate.can.codec import CanCodec, EncodeError
from leafgate.config import VehicleConfig
from leafgate.config.sim import EcuConfig
from leafgate.errors import CanCodecError
from leafgate.messages import Pose
from leafgate.settings import LeafgateConfig, with_profile
from leafgate.sim.ecu import SimulatedEcu
from leafgate.sim.plant import KinematicPlant
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario

ROOT = Path(__file__).resolve().parent.parent
ANGLE = ' SG_ STEER_ANGLE : 23|18@0+ (-0.01,1310) [-1311.43|1310] "deg" GATEWAY\n'


def ze1_profile(tmp_path: Path, dbc_text: str) -> Path:
    """The packaged ZE1 profile, as a file next to ``dbc_text`` as its DBC."""
    (tmp_path / "leaf_ze1_lkas.dbc").write_text(dbc_text)
    source = ROOT / "leafgate" / "data" / "profiles" / "leaf-ze1-lkas.yaml"
    path = tmp_path / "ze1.yaml"
    path.write_text(source.read_text().replace("name: leaf-ze1-lkas", "name: ze1-foreign"))
    return path


def packaged_ze1_dbc() -> str:
    text = (ROOT / "dbc" / "leaf_ze1_lkas.dbc").read_text()
    assert ANGLE in text
    return text


def test_the_ecu_refuses_a_report_frame_it_can_never_send(tmp_path: Path) -> None:
    extra = ANGLE + ' SG_ LKAS_STATUS : 55|4@0+ (1,0) [0|15] "" GATEWAY\n'
    path = ze1_profile(tmp_path, packaged_ze1_dbc().replace(ANGLE, extra))
    codec = CanCodec(profile=str(path))  # the gateway: it only decodes 0x185
    assert codec.cannot_encode("STEER_TORQUE_SENSOR") is not None
    assert codec.cannot_encode("LKAS") is None
    plant = KinematicPlant(VehicleConfig(), Pose(0.0, 0.0, 0.0, 0.0))
    with pytest.raises(CanCodecError) as info:
        SimulatedEcu(EcuConfig(), plant, VehicleConfig(), codec)
    text = str(info.value)
    assert str(path) in text and str(tmp_path / "leaf_ze1_lkas.dbc") in text
    assert "STEER_TORQUE_SENSOR (0x185)" in text and "LKAS_STATUS" in text


def test_sim_names_the_report_frame_the_ecu_could_not_encode(tmp_path: Path) -> None:
    raw_range = ANGLE.replace("[-1311.43|1310]", "[0|262143]")  # as opendbc writes it
    path = ze1_profile(tmp_path, packaged_ze1_dbc().replace(ANGLE, raw_range))
    config = with_profile(LeafgateConfig(), str(path))
    with pytest.raises(EncodeError) as info:
        run(config, get_scenario("s-curve"))
    text = str(info.value)
    assert "simulated ECU" in text and "STEER_TORQUE_SENSOR (0x185) STEER_ANGLE" in text
    assert "outside its range [0, 262143]" in text


def test_check_config_warns_the_simulated_ecu_cannot_send_a_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: `ok offline` and nothing else, then `sim` and `sim-ecu` failed on it."""
    from leafgate import cli

    extra = ANGLE + ' SG_ LKAS_STATUS : 55|4@0+ (1,0) [0|15] "" GATEWAY\n'
    profile = ze1_profile(tmp_path, packaged_ze1_dbc().replace(ANGLE, extra))
    config = tmp_path / "car.yaml"
    config.write_text(f"vehicle: {{profile: {profile}}}\ngateway: {{rate_hz: 100}}\n")
    assert cli.main(["check-config", str(config)]) == 0
    out, err = capsys.readouterr()
    assert "ok offline" in out
    assert "simulated ECU (sim, sim-ecu) cannot send STEER_TORQUE_SENSOR (0x185)" in err
    assert "LKAS_STATUS" in err


def test_check_config_of_a_dbc_says_it_is_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: "invalid YAML at line 5, column 25: mapping values are not allowed here"."""
    from leafgate import cli

    dbc = tmp_path / "nissan_leaf_2018_generated.dbc"
    dbc.write_text(packaged_ze1_dbc())
    assert cli.main(["check-config", str(dbc)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{dbc}: a DBC file, not a leafgate config" in err


def test_a_car_dbc_without_a_checked_signal_names_the_frame_id_and_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """opendbc's 0x002 has no CHECKSUM (leafgate found it in recordings and checks it).
    Old code: "STEER_ANGLE_SENSOR.CHECKSUM is missing", no ID and no reason."""
    from leafgate import cli

    car = (ROOT / "dbc" / "leaf_aze0_car.dbc").read_text()
    line = ' SG_ CHECKSUM : 36|4@1+ (1,0) [0|15] "" GATEWAY\n'
    assert line in car
    dbc = tmp_path / "nissan_leaf_2018_generated.dbc"
    dbc.write_text(car.replace(line, "", 1))
    config = tmp_path / "car.yaml"
    config.write_text(f"can: {{car_dbc: {dbc.name}}}\n")
    assert cli.main(["check-config", str(config)]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(dbc) in err
    assert "STEER_ANGLE_SENSOR (0x002) has no signal CHECKSUM" in err and "checksum" in err


# --- a foreign DBC is refused only for the frames leafgate uses ----------------------------
# Old code loaded every DBC with cantools' strict mode, so one overlap anywhere refused the whole
# file: dalathegreat's CAR-can_AZE0.dbc (0x180 has two signals on byte 0), opendbc's Xterra DBC.

CAR_DBC = ROOT / "dbc" / "leaf_aze0_car.dbc"
# A frame the profiles do not use, shaped as dalathegreat's 0x180 (written here, not copied):
# two signals on the same byte.
UNUSED_OVERLAP = (
    "BO_ 384 TORQUE_CONTROL: 8 VCM\n"
    ' SG_ TORQUE_A : 0|8@1+ (1,0) [0|255] "" GATEWAY\n'
    ' SG_ TORQUE_B : 8|8@1+ (1,0) [0|255] "" GATEWAY\n'
    ' SG_ TORQUE_C : 0|8@1+ (1,0) [0|255] "" GATEWAY\n\n'
)
FRONT = (
    ' SG_ WHEEL_SPEED_FR : 7|16@0+ (0.005,0) [0|300] "km/h" GATEWAY\n'
    ' SG_ WHEEL_SPEED_FL : 23|16@0+ (0.005,0) [0|300] "km/h" GATEWAY\n'
)
# opendbc's nissan_xterra_2011.dbc (MIT, commaai/opendbc) ABS_1 0x284 lays the wheel speeds out
# as "WHEEL_1 : 0|16@1+" and "WHEEL_2 : 15|16@1+": bit 15 is in both. The same layout on the
# names leafgate's profile reads:
XTERRA_FRONT = (
    ' SG_ WHEEL_SPEED_FR : 0|16@1+ (0.01,0) [0|300] "km/h" GATEWAY\n'
    ' SG_ WHEEL_SPEED_FL : 15|16@1+ (0.01,0) [0|300] "km/h" GATEWAY\n'
)


def car_dbc_with(tmp_path: Path, old: str, new: str) -> Path:
    text = CAR_DBC.read_text()
    assert old in text
    path = tmp_path / "car_foreign.dbc"
    path.write_text(text.replace(old, new, 1))
    return path


def unused_overlap_dbc(tmp_path: Path) -> Path:
    return car_dbc_with(
        tmp_path, "BO_ 1057 GEAR_POSITION", UNUSED_OVERLAP + "BO_ 1057 GEAR_POSITION"
    )


def test_overlap_in_a_frame_leafgate_does_not_use_loads_and_is_reported(tmp_path: Path) -> None:
    """Old code: CanCodecError "invalid DBC: ... TORQUE_C and TORQUE_A are overlapping"."""
    dbc = unused_overlap_dbc(tmp_path)
    codec = CanCodec(car_dbc=dbc, profile="leafgate-dbw")
    (problem,) = codec.layout_problems
    assert (problem.name, problem.frame_id, problem.key) == ("TORQUE_CONTROL", 0x180, 0x180)
    assert problem.signals == ("TORQUE_A", "TORQUE_C")  # TORQUE_B is sound
    assert problem.where == str(dbc)
    (line,) = codec.dbc_warnings()
    assert line.startswith(f"{dbc}: TORQUE_CONTROL (0x180): signals TORQUE_A and TORQUE_C overlap")
    assert "leafgate-dbw does not use this frame" in line and "TORQUE_A, TORQUE_C" in line
    # the frames leafgate uses work as with the packaged DBC
    packaged = CanCodec(profile="leafgate-dbw")
    assert codec.receive_ids("car") == packaged.receive_ids("car")
    assert packaged.layout_problems == () and packaged.dbc_warnings() == []


def test_multiplexed_signals_on_different_values_are_no_overlap(tmp_path: Path) -> None:
    muxed = (
        "BO_ 1468 MUXED: 8 LBC\n"
        ' SG_ PAGE M : 0|8@1+ (1,0) [0|255] "" GATEWAY\n'
        ' SG_ ON_PAGE_1 m1 : 8|8@1+ (1,0) [0|255] "" GATEWAY\n'
        ' SG_ ON_PAGE_2 m2 : 8|16@1+ (1,0) [0|65535] "" GATEWAY\n\n'
    )
    dbc = car_dbc_with(tmp_path, "BO_ 1057 GEAR_POSITION", muxed + "BO_ 1057 GEAR_POSITION")
    assert CanCodec(car_dbc=dbc, profile="leafgate-dbw").layout_problems == ()


@pytest.mark.parametrize(
    ("old", "new", "frame", "problem"),
    [
        pytest.param(
            FRONT,
            XTERRA_FRONT,
            "WHEEL_SPEEDS_FRONT (0x284)",
            "signals WHEEL_SPEED_FR and WHEEL_SPEED_FL overlap (bit 15)",
            id="overlap",
        ),
        pytest.param(
            "BO_ 2 STEER_ANGLE_SENSOR: 5 STRG",
            "BO_ 2 STEER_ANGLE_SENSOR: 4 STRG",
            "STEER_ANGLE_SENSOR (0x002)",
            "signal COUNTER does not fit in its 4 bytes (it reaches bit 35); "
            "signal CHECKSUM does not fit in its 4 bytes (it reaches bit 39)",
            id="does-not-fit",
        ),
    ],
)
def test_a_bad_layout_in_a_frame_leafgate_reads_is_refused_in_one_line(
    tmp_path: Path, old: str, new: str, frame: str, problem: str
) -> None:
    """Old code: 'invalid DBC: DBC: "The signals WHEEL_SPEED_FL and WHEEL_SPEED_FR are
    overlapping in message WHEEL_SPEEDS_FRONT."' (no ID), and the same for an overlap anywhere."""
    dbc = car_dbc_with(tmp_path, old, new)
    with pytest.raises(CanCodecError) as info:
        CanCodec(car_dbc=dbc, profile="leafgate-dbw")
    text = str(info.value)
    assert "\n" not in text
    assert text == (
        f"{dbc}: {frame}: {problem}: profile leafgate-dbw reads this frame, so its signals must "
        "fit and must not overlap"
    )


def test_a_bad_layout_in_a_frame_leafgate_sends_says_it_sends_it(tmp_path: Path) -> None:
    dbw = (ROOT / "dbc" / "leafgate_dbw.dbc").read_text()
    line = next(x for x in dbw.splitlines() if x.startswith(" SG_ STEER_ANGLE_CMD "))
    clash = line.replace("STEER_ANGLE_CMD", "STEER_SHADOW", 1)
    dbc = tmp_path / "dbw.dbc"
    dbc.write_text(dbw.replace(line, f"{line}\n{clash}", 1))
    with pytest.raises(CanCodecError) as info:
        CanCodec(dbw_dbc=dbc, profile="leafgate-dbw")
    text = str(info.value)
    assert text.startswith(f"{dbc}: DBW_STEER_CMD (0x0A0): signals STEER_ANGLE_CMD and ")
    assert "STEER_SHADOW overlap" in text and "leafgate-dbw sends this frame" in text


def test_check_config_warns_about_an_overlap_in_an_unused_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: exit 2, "error: …: invalid DBC: DBC: "The signals TORQUE_C and TORQUE_A are
    overlapping in message TORQUE_CONTROL."" for a frame leafgate never reads."""
    from leafgate import cli

    dbc = unused_overlap_dbc(tmp_path)
    config = tmp_path / "car.yaml"
    config.write_text(f"can: {{car_dbc: {dbc.name}}}\n")
    assert cli.main(["check-config", str(config)]) == 0
    out, err = capsys.readouterr()
    assert "ok offline" in out
    (warning,) = [line for line in err.splitlines() if "TORQUE_CONTROL" in line]
    assert warning == (
        f"leafgate: warning: {dbc}: TORQUE_CONTROL (0x180): signals TORQUE_A and TORQUE_C "
        "overlap (bits 0..7): loaded, as profile leafgate-dbw does not use this frame; "
        "TORQUE_A, TORQUE_C not to be trusted"
    )


def test_check_config_refuses_an_overlap_in_a_used_frame_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from leafgate import cli

    dbc = car_dbc_with(tmp_path, FRONT, XTERRA_FRONT)
    config = tmp_path / "car.yaml"
    config.write_text(f"can: {{car_dbc: {dbc.name}}}\n")
    assert cli.main(["check-config", str(config)]) == 1
    out, err = capsys.readouterr()
    assert "ok offline" not in out
    assert err.count("\n") == 1 and err.startswith(f"leafgate: error: {dbc}: ")
    assert "WHEEL_SPEEDS_FRONT (0x284): signals WHEEL_SPEED_FR and WHEEL_SPEED_FL overlap" in err


# --- frames a used frame hides: by its ID, by its name ----------------------------------------
# Old code: a second DBC's frame on the ID of a frame the profile reads was loaded and never
# mentioned (a received frame of that ID is decoded as the profile's), and a second definition
# of a used frame's name was dropped in silence (the first DBC's wins).

ON_WHEEL_ID = 'BO_ 644 BODY_STATUS: 8 BCM\n SG_ DOOR_OPEN : 0|1@1+ (1,0) [0|1] "" GATEWAY\n\n'


def dbw_dbc_with(tmp_path: Path, frame: str) -> Path:
    dbw = (ROOT / "dbc" / "leafgate_dbw.dbc").read_text()
    path = tmp_path / "dbw_foreign.dbc"
    path.write_text(dbw.replace("BO_ 160 DBW_STEER_CMD", frame + "BO_ 160 DBW_STEER_CMD", 1))
    return path


def test_a_frame_on_the_id_of_a_used_frame_is_a_warning_naming_both(tmp_path: Path) -> None:
    dbw = dbw_dbc_with(tmp_path, ON_WHEEL_ID)
    codec = CanCodec(dbw_dbc=dbw, profile="leafgate-dbw")
    (line,) = codec.dbc_warnings()
    assert line.startswith(f"{dbw}: BODY_STATUS (0x284) has the ID of WHEEL_SPEEDS_FRONT, ")
    assert "which profile leafgate-dbw reads" in line and "BODY_STATUS is not decoded" in line
    # the frame of that ID is still the profile's
    assert codec.name_of(0x284) == "WHEEL_SPEEDS_FRONT"


def wheel_frame() -> str:
    car = CAR_DBC.read_text()
    start = car.index("BO_ 644 WHEEL_SPEEDS_FRONT")
    return car[start : car.index("\n\n", start) + 2]


def test_another_definition_of_a_used_frame_is_a_warning(tmp_path: Path) -> None:
    """The DBW DBC comes first in the profile: its WHEEL_SPEEDS_FRONT is the one used."""
    dbw = dbw_dbc_with(tmp_path, wheel_frame())
    car = car_dbc_with(tmp_path, "BO_ 644 WHEEL_SPEEDS_FRONT", "BO_ 1445 WHEEL_SPEEDS_FRONT")
    (line,) = CanCodec(dbw_dbc=dbw, car_dbc=car, profile="leafgate-dbw").dbc_warnings()
    assert line == (
        f"{car}: WHEEL_SPEEDS_FRONT (0x5A5) is also in {dbw} (0x284), laid out otherwise: "
        "profile leafgate-dbw reads that one, and this one is not used"
    )


def test_the_same_definition_in_two_dbcs_is_no_warning(tmp_path: Path) -> None:
    dbw = dbw_dbc_with(tmp_path, wheel_frame())
    assert CanCodec(dbw_dbc=dbw, profile="leafgate-dbw").dbc_warnings() == []


def test_check_config_warns_about_a_hidden_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from leafgate import cli

    dbw = dbw_dbc_with(tmp_path, ON_WHEEL_ID)
    config = tmp_path / "dbw.yaml"
    config.write_text(f"can: {{dbw_dbc: {dbw.name}}}\n")
    assert cli.main(["check-config", str(config)]) == 0
    err = capsys.readouterr().err
    (warning,) = [line for line in err.splitlines() if "BODY_STATUS" in line]
    assert warning.startswith(f"leafgate: warning: {dbw}: BODY_STATUS (0x284) has the ID of ")
