"""Config says what it does (issue 14, item 5): the profile's adjustments are listed, a profile
may not overrule a value set explicitly, and every entry point names the file in an error."""

from __future__ import annotations

from pathlib import Path

import pytest

from leafgate import cli
from leafgate.errors import ConfigError
from leafgate.settings import LeafgateConfig, load_config, with_profile


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "leafgate.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_check_config_lists_every_adjustment_of_the_profile(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, "vehicle:\n  profile: sze-hlc\n")
    assert cli.main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "profile adjustments: 4" in out
    assert "controller.mpc.mode: acceleration -> velocity (profile sze-hlc: speed-only" in out
    assert "gateway.engage.allow_reverse: True -> False" in out
    assert "gateway.watchdog.system_report_period: 0.1 -> None" in out
    assert "only end-to-end check" in out  # the profile's protection, said where it is chosen


def test_the_default_profile_adjusts_nothing() -> None:
    assert load_config(None).adjustments == ()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "vehicle:\n  profile: sze-hlc\ncontroller:\n  mpc:\n    mode: acceleration\n",
            "controller.mpc.mode: acceleration is not available with profile sze-hlc "
            "(speed-only interface)",
        ),
        (
            "vehicle:\n  profile: leaf-ze1-lkas\ngateway:\n  rate_hz: 20\n",
            "gateway.rate_hz: 20.0 contradicts profile leaf-ze1-lkas",
        ),
        (
            "vehicle:\n  profile: sze-hlc\ngateway:\n  engage:\n    allow_reverse: true\n",
            "gateway.engage.allow_reverse: True contradicts profile sze-hlc",
        ),
    ],
)
def test_a_profile_contradicting_an_explicit_value_is_an_error_naming_file_key_profile(
    tmp_path: Path, text: str, message: str
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: {message}" or str(info.value).startswith(
        f"{path}: {message}"
    )


def test_an_explicit_value_the_profile_agrees_with_is_fine(tmp_path: Path) -> None:
    path = write(
        tmp_path, "vehicle:\n  profile: sze-hlc\ncontroller:\n  mpc:\n    mode: velocity\n"
    )
    assert load_config(path).controller.mpc.mode == "velocity"


def test_switching_profile_keeps_the_files_explicit_values(tmp_path: Path) -> None:
    path = write(tmp_path, "controller:\n  mpc:\n    mode: acceleration\n")
    cfg = load_config(path)
    with pytest.raises(ConfigError, match=rf"^{path}: controller.mpc.mode: acceleration"):
        with_profile(cfg, "sze-hlc")
    assert with_profile(LeafgateConfig(), "sze-hlc").controller.mpc.mode == "velocity"


def test_a_command_line_value_the_profile_contradicts_is_named_as_such(
    capsys: pytest.CaptureFixture[str],
) -> None:
    status = cli.main(["sim", "--mode", "acceleration", "--profile", "sze-hlc", "--no-plots"])
    assert status == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "command line: controller.mpc.mode: acceleration is not available" in err


def test_run_names_the_file_in_a_cross_section_config_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, "vehicle:\n  profile: leafgate-dbw\n")

    def run_daemon(cfg: LeafgateConfig) -> int:
        raise ConfigError("controller.mpc.horizon: longer than the trajectory buffer")

    monkeypatch.setattr("leafgate.runtime.daemon.run_daemon", run_daemon)
    assert cli.main(["run", "--config", str(path)]) == cli.EXIT_USAGE
    assert f"leafgate: error: {path}: controller.mpc.horizon" in capsys.readouterr().err


def test_a_profile_file_whose_dbc_is_not_beside_it_says_the_packaged_one_is_used(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A copied profile decoded with leafgate's own DBC of the same name, and said nothing."""
    import shutil
    from importlib import resources

    data = resources.files("leafgate") / "data"
    prof = tmp_path / "prof"
    prof.mkdir()
    shutil.copy(str(data / "profiles" / "leafgate-dbw.yaml"), prof / "mycar.yaml")
    shutil.copy(str(data / "dbc" / "leafgate_dbw.dbc"), prof / "leafgate_dbw.dbc")
    path = write(tmp_path, "vehicle:\n  profile: prof/mycar.yaml\n")
    assert cli.main(["check-config", str(path)]) == 0
    err = capsys.readouterr().err
    assert "names the DBC leaf_aze0_car.dbc, which is not beside it" in err
    assert "leafgate_dbw.dbc" not in err  # the one beside it is used, and not named
    assert load_config(path).profile.dbc_from_package == ("leaf_aze0_car.dbc",)
    assert load_config(None).profile.dbc_from_package == ()  # packaged: nothing to say
