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
