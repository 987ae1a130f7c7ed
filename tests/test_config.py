"""The strict YAML loader: every error names the file and the dotted key."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from leafgate.config import VehicleConfig, from_mapping
from leafgate.errors import ConfigError
from leafgate.settings import LeafgateConfig, load_config


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "leafgate.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_defaults_hold_the_leaf_numbers() -> None:
    cfg = load_config(None)
    assert cfg.vehicle.wheelbase == pytest.approx(2.70)
    assert cfg.vehicle.max_steer_angle == pytest.approx(math.radians(31.0))
    assert cfg.vehicle.max_accel == 3.0 and cfg.vehicle.min_accel == -6.0


def test_unknown_key_names_file_and_dotted_key(tmp_path: Path) -> None:
    path = write(tmp_path, "vehicle:\n  wheelbse: 2.7\n")
    with pytest.raises(ConfigError, match=r"leafgate\.yaml: vehicle\.wheelbse: unknown key"):
        load_config(path)


def test_wrong_type_names_the_key(tmp_path: Path) -> None:
    path = write(tmp_path, "controller:\n  mpc:\n    prediction_horizon: thirty\n")
    with pytest.raises(
        ConfigError, match=r"controller\.mpc\.prediction_horizon: expected an integer"
    ):
        load_config(path)


def test_literal_choices_listed(tmp_path: Path) -> None:
    path = write(tmp_path, "controller:\n  mpc:\n    solver: gurobi\n")
    with pytest.raises(ConfigError, match=r"'gurobi' is not one of 'daqp', 'hildreth', 'osqp'"):
        load_config(path)


def test_value_rejected_by_section_names_section(tmp_path: Path) -> None:
    path = write(tmp_path, "vehicle:\n  wheelbase: -1\n")
    with pytest.raises(ConfigError, match=r"vehicle: wheelbase must be a positive number"):
        load_config(path)


def test_degrees_suffix_converts_to_radians() -> None:
    cfg = from_mapping(VehicleConfig, {"max_steer_angle_deg": 25}, "x.yaml")
    assert cfg.max_steer_angle == pytest.approx(math.radians(25.0))


def test_same_field_with_and_without_suffix_is_an_error() -> None:
    with pytest.raises(ConfigError, match="given twice"):
        from_mapping(VehicleConfig, {"max_steer_angle": 0.5, "max_steer_angle_deg": 25}, "x.yaml")


def test_bool_is_not_a_number() -> None:
    with pytest.raises(ConfigError, match="expected a number"):
        from_mapping(VehicleConfig, {"wheelbase": True}, "x.yaml")


def test_missing_file_and_bad_yaml_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "absent.yaml")
    bad = write(tmp_path, "vehicle: [unclosed\n")
    with pytest.raises(ConfigError, match=r"invalid YAML at line \d+") as info:
        load_config(bad)
    assert "\n" not in str(info.value)


def test_empty_file_gives_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, "")) == LeafgateConfig()


@pytest.mark.parametrize("name", ["sim.yaml", "leafgate.yaml"])
def test_shipped_configs_load(name: str) -> None:
    path = Path(__file__).resolve().parent.parent / "config" / name
    if not path.exists():
        pytest.skip(f"{name} not written yet")
    load_config(path)


# --- a key given twice is refused, with the file, line and key (audit item 4) -----------------


def test_duplicate_key_is_refused_naming_file_line_and_key(tmp_path: Path) -> None:
    bad = write(tmp_path, "controller:\n  kind: stanley\ncontroller:\n  kind: mpc\n")
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    text = str(info.value)
    assert str(bad) in text and "line 3" in text and "duplicate key 'controller'" in text
    assert "first at line 1" in text and "\n" not in text


def test_duplicate_nested_key_is_refused(tmp_path: Path) -> None:
    bad = write(tmp_path, "controller:\n  kind: stanley\n  kind: mpc\n")
    with pytest.raises(ConfigError, match=r"line 3, column 3: duplicate key 'kind'"):
        load_config(bad)


def test_merge_keys_may_still_be_overridden() -> None:
    from leafgate.config import safe_load_yaml

    data = safe_load_yaml("a: &x {b: 1, c: 2}\nd:\n  <<: *x\n  b: 3\n")
    assert data["d"] == {"b": 3, "c": 2}


def test_shipped_yaml_files_have_no_duplicate_keys() -> None:
    from leafgate.config import load_yaml

    root = Path(__file__).resolve().parent.parent
    files = [*(root / "config").glob("*.yaml"), *(root / "leafgate" / "data").rglob("*.yaml")]
    assert files
    for path in files:
        load_yaml(path)
