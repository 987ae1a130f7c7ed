"""What check-config and the daemon's start-up check offline (one truth), relative paths,
numbers with an exponent and ``--set bench``."""

from __future__ import annotations

import re
import shutil
import threading
from pathlib import Path

import pytest

from leafgate import cli
from leafgate.can.codec import CanCodec
from leafgate.config import parse_overrides
from leafgate.errors import ConfigError
from leafgate.runtime.checks import offline_checks, recording_directory_problem
from leafgate.runtime.daemon import run_daemon
from leafgate.settings import BENCH_ENV, bench_ports, load_config

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT / "config" / "sim.yaml"
SECURE = ROOT / "config" / "zenoh" / "secure.json5"
PROFILE = ROOT / "leafgate" / "data" / "profiles" / "leafgate-dbw.yaml"


def write(tmp_path: Path, text: str, name: str = "leafgate.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


BAD = {
    "zenoh: {config_file: nosuch.json5}\n": r"zenoh\.config_file: .*nosuch\.json5: no such file",
    f"zenoh: {{config_file: {SECURE}}}\n": r"zenoh\.config_file: transport/link/tls/"
    r"root_ca_certificate: /etc/leafgate/tls/ca\.pem: no such file",
    "can: {dbw: {interface: nosuchbus}}\n": r"can\.dbw\.interface: 'nosuchbus' is not a "
    r"python-can interface",
    "can: {car: {interface: nosuchbus, channel: x}}\n": r"can\.car\.interface: 'nosuchbus'",
    'zenoh: {connect: ["not an endpoint"]}\n': r"zenoh\.connect: bad endpoint 'not an endpoint'",
    'zenoh: {listen: ["tcp/127.0.0.1:99999"]}\n': r"zenoh\.listen: bad endpoint "
    r"'tcp/127.0.0.1:99999': port 99999 is not in 0–65535",
    'zenoh: {connect: ["tcp/127.0.0.1:0"]}\n': r"zenoh\.connect: bad endpoint .*port 0 is not",
    'zenoh: {connect: ["tcp/127.0.0.1"]}\n': r"zenoh\.connect: bad endpoint .*host:port",
    "recording: {enabled: true, required: true, directory: /proc/x/y}\n": r"recording\."
    r"directory: /proc/x/y: cannot be created",
}


@pytest.mark.parametrize("text", list(BAD))
def test_check_config_refuses_what_start_up_would_in_one_line(
    tmp_path: Path, text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, text)
    assert cli.main(["check-config", str(path)]) != 0
    out, err = capsys.readouterr()
    assert "ok" not in out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert re.search(f"{re.escape(str(path))}: {BAD[text]}", lines[0]), lines[0]


@pytest.mark.parametrize("text", list(BAD))
def test_start_up_refuses_the_same_before_opening_anything(tmp_path: Path, text: str) -> None:
    path = write(tmp_path, text)
    cfg = load_config(path)  # loading alone still accepts it: the checks are the offline ones
    stop = threading.Event()
    stop.set()  # were the check missing, the daemon would stop at once instead of running on
    with pytest.raises(ConfigError, match=f"{re.escape(str(path))}: {BAD[text]}"):
        run_daemon(cfg, stop)


def test_ok_line_says_what_was_not_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(
        tmp_path,
        "can: {dbw: {interface: socketcan, channel: can0}}\n"
        'zenoh: {listen: ["tcp/127.0.0.1:7450"]}\n',
    )
    assert cli.main(["check-config", str(path)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"{path}: ok offline (not checked here: ")
    assert "the bus can0 exists and is up (needs the car)" in first
    assert "Zenoh endpoints" in first


def test_recording_directory_not_required_is_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, "recording: {enabled: true, directory: /proc/x/y}\n")
    assert cli.main(["check-config", str(path)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {path}: recording.directory: /proc/x/y: cannot be created" in err


def test_recording_directory_probe_leaves_nothing_behind(tmp_path: Path) -> None:
    target = tmp_path / "a" / "b"
    assert recording_directory_problem(str(target)) is None
    assert list(tmp_path.iterdir()) == []  # not created, no probe left
    (tmp_path / "file").write_text("x")
    problem = recording_directory_problem(str(tmp_path / "file" / "rec"))
    assert problem is not None and "is not a directory" in problem
    assert recording_directory_problem(str(tmp_path)) is None
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_the_shipped_sim_config_passes_the_offline_checks() -> None:
    report = offline_checks(load_config(SIM))
    assert report.warnings == []


# --- relative paths: from the config file's directory --------------------------------------


def test_relative_profile_and_zenoh_file_are_taken_from_the_config_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "etc"
    folder.mkdir()
    shutil.copy(PROFILE, folder / "mycar.yaml")
    shutil.copy(ROOT / "config" / "zenoh" / "router.json5", folder / "z.json5")
    path = write(folder, "vehicle: {profile: mycar.yaml}\nzenoh: {config_file: z.json5}\n")
    monkeypatch.chdir(tmp_path)  # not the config's directory (systemd: "/")
    cfg = load_config(path)
    assert cfg.vehicle.profile == str(folder / "mycar.yaml")
    assert cfg.zenoh.config_file == str(folder / "z.json5")
    assert cfg.profile.where.endswith("mycar.yaml")


def test_relative_dbc_and_key_files_are_taken_from_the_config_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The codec opens the DBCs a config names wherever the daemon was started."""
    folder = tmp_path / "etc"
    folder.mkdir()
    packaged = ROOT / "dbc"
    shutil.copy(packaged / "leafgate_dbw.dbc", folder / "dbw.dbc")
    shutil.copy(packaged / "leaf_aze0_car.dbc", folder / "car.dbc")
    path = write(folder, "can: {dbw_dbc: dbw.dbc, car_dbc: car.dbc, auth_key_file: k.key}\n")
    monkeypatch.chdir(tmp_path)  # not the config's directory (systemd: "/")
    cfg = load_config(path)
    assert (cfg.can.dbw_dbc, cfg.can.car_dbc, cfg.can.auth_key_file) == tuple(
        str(folder / name) for name in ("dbw.dbc", "car.dbc", "k.key")
    )
    codec = CanCodec.for_config(cfg, key=bytes(16))
    assert [db.messages[0].name for db in codec.databases] == [
        db.messages[0].name for db in CanCodec.for_config(load_config(None)).databases
    ]


def test_a_packaged_profile_name_is_not_a_path(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "vehicle: {profile: sze-hlc}\n"))
    assert cfg.vehicle.profile == "sze-hlc"


def test_command_line_paths_stay_relative_to_the_working_directory(tmp_path: Path) -> None:
    path = write(tmp_path, "{}\n")
    cfg = load_config(path, parse_overrides(["zenoh.config_file=x.json5"]))
    assert cfg.zenoh.config_file == "x.json5"


# --- numbers with an exponent -------------------------------------------------------------


@pytest.mark.parametrize(("text", "value"), [("1e-3", 1e-3), ("+2E-2", 0.02), ("5e-1", 0.5)])
def test_exponent_numbers_are_numbers(tmp_path: Path, text: str, value: float) -> None:
    cfg = load_config(write(tmp_path, f"sim:\n  localization:\n    latency: {text}\n"))
    assert cfg.sim.localization.latency == pytest.approx(value)


def test_exponent_numbers_on_the_command_line() -> None:
    cfg = load_config(SIM, parse_overrides(["sim.localization.latency=1e-2"]))
    assert cfg.sim.localization.latency == pytest.approx(0.01)
    cfg = load_config(SIM, parse_overrides(["gateway.safety.max_speed=3e0"]))
    assert cfg.gateway.safety.max_speed == 3.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("nan", "expected a number, got 'nan'"),
        ("inf", "expected a number, got 'inf'"),
        (".nan", "expected a finite number, got nan"),
        ("1e999", "expected a finite number, got inf"),
        ("1_0e3", "expected a number, got '1_0e3'"),
        ("0x1p3", "expected a number, got '0x1p3'"),
    ],
)
def test_nan_inf_and_other_strings_stay_refused(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, f"sim:\n  localization:\n    latency: {text}\n")
    with pytest.raises(ConfigError, match=re.escape(f"sim.localization.latency: {message}")):
        load_config(path)


def test_an_integer_key_does_not_take_an_exponent(tmp_path: Path) -> None:
    path = write(tmp_path, "controller:\n  mpc:\n    prediction_horizon: 3e1\n")
    with pytest.raises(ConfigError, match="expected an integer, got '3e1'"):
        load_config(path)


# --- --set bench ---------------------------------------------------------------------------


def test_set_bench_picks_the_bench_like_the_file(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(BENCH_ENV, raising=False)
    cfg = load_config(SIM, parse_overrides(["bench=5"]))
    can_port, zenoh_port = bench_ports(5)
    assert cfg.can.dbw.kwargs["port"] == can_port
    assert cfg.zenoh.listen == (f"tcp/127.0.0.1:{zenoh_port}",)
    monkeypatch.setenv(BENCH_ENV, "7")  # the command line's --set is the more specific
    assert load_config(SIM, parse_overrides(["bench=5"])).can.dbw.kwargs["port"] == can_port


def test_set_bench_refuses_a_bad_number() -> None:
    with pytest.raises(ConfigError, match=r"--set: bench: 'x' is not a bench number"):
        load_config(SIM, parse_overrides(["bench=x"]))


# --- README's example error is the real one ------------------------------------------------


def test_readme_quotes_the_real_config_error() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(SIM, {"controller.mpc.solver": "gurobi"})
    real = str(info.value).split(": ", 1)[1]  # after the source
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert f"config/sim.yaml: {real}" in readme
