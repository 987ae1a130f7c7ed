"""Audit items 1-3 and 5: a closed stdout/stderr, bad option values, a failed ``sim --record``,
a disk-full write that names no file, and the tools' missing test extra: one line each, the
right exit status, no traceback and no claim of work not done."""

from __future__ import annotations

import argparse
import errno
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from leafgate import cli
from leafgate.cliargs import (
    non_negative_int,
    non_negative_seconds,
    positive_int,
    positive_number,
    positive_seconds,
)

ROOT = Path(__file__).resolve().parents[1]
SIM_YAML = str(ROOT / "config" / "sim.yaml")


def _sh(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``script`` in sh with $0 the interpreter (so it can close fds as a shell does)."""
    return subprocess.run(
        ["sh", "-c", script, sys.executable, *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )


# --- item 1: stdout / stderr closed (`>&-`) ----------------------------------------------------


def test_closed_stdout_is_refused_in_one_line() -> None:
    done = _sh('"$0" -m leafgate check-config "$1" >&-', SIM_YAML)
    assert done.returncode == cli.EXIT_USAGE, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip() == done.stderr.strip().splitlines()[0]
    assert "standard output is closed" in done.stderr


def test_closed_stdout_in_process(monkeypatch: pytest.MonkeyPatch, capsys: Any) -> None:
    monkeypatch.setattr(sys, "stdout", None)
    assert cli.main(["check-config", SIM_YAML]) == cli.EXIT_USAGE
    assert "standard output is closed" in capsys.readouterr().err


def test_closed_stderr_keeps_errors_off_stdout() -> None:
    done = _sh('"$0" -m leafgate check-config /nonexistent/x.yaml 2>&-')
    assert done.returncode == cli.EXIT_USAGE
    assert done.stdout == ""


# --- item 2: bad timeouts, durations, counts and worker numbers ---------------------------------

BAD = [
    (["reset", "--config", "c.yaml", "--timeout", "-1"], "--timeout"),
    (["disengage", "--config", "c.yaml", "--timeout", "-1"], "--timeout"),
    (["engage", "--config", "c.yaml", "--timeout", "nan", "--wait", "0"], "--timeout"),
    (["engage", "--config", "c.yaml", "--timeout", "inf", "--wait", "0"], "--timeout"),
    (["engage", "--config", "c.yaml", "--timeout", "0"], "--timeout"),
    (["engage", "--config", "c.yaml", "--wait", "nan"], "--wait"),
    (["engage", "--config", "c.yaml", "--wait", "-1"], "--wait"),
    (["status", "--config", "c.yaml", "--duration", "inf"], "--duration"),
    (["status", "--config", "c.yaml", "--duration", "-1"], "--duration"),
    (["status", "--config", "c.yaml", "--duration", "nan"], "--duration"),
    (["publish-trajectory", "--config", "c.yaml", "--count", "-1"], "--count"),
    (["publish-trajectory", "--config", "c.yaml", "--count", "1.5"], "--count"),
    (["publish-trajectory", "--config", "c.yaml", "--wait", "nan"], "--wait"),
    (["publish-trajectory", "--config", "c.yaml", "--period", "0"], "--period"),
    (["sim", "--window-period", "0"], "--window-period"),
    (["sim", "--rolling-window", "nan"], "--rolling-window"),
    (["sim", "--window-behind", "-1"], "--window-behind"),
    (["replay", "check", "x.blf", "--gap-periods", "-1"], "--gap-periods"),
    (["batch", "check", "d", "--timeout", "-1"], "--timeout"),
    (["batch", "check", "d", "--gap-periods", "nan"], "--gap-periods"),
    (["batch", "sim", "s.yaml", "--workers", "0"], "--workers"),
    (["batch", "rerun", "d", "--workers", "-3"], "--workers"),
    (["batch", "rerun", "d", "--timeout", "inf"], "--timeout"),
    (["batch", "sim", "s.yaml", "--wait-workers", "-1"], "--wait-workers"),
    (["compare", "--workers", "-3"], "--workers"),
    (["replay", "play", "x.blf", "--speed", "nan"], "--speed"),
    (["replay", "play", "x.blf", "--start", "-5"], "--start"),
    # old code: passed on as LEAFGATE_BENCH, then blamed on that variable
    (["--bench", "-1", "check-config", "c.yaml"], "--bench"),
    (["--bench", "1000", "check-config", "c.yaml"], "--bench"),
]


@pytest.mark.parametrize(("argv", "option"), BAD, ids=[" ".join(a) for a, _ in BAD])
def test_bad_value_is_a_usage_error_naming_the_option(
    argv: list[str], option: str, capsys: Any
) -> None:
    with pytest.raises(SystemExit) as info:
        cli.build_parser().parse_args(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and f"argument {option}" in errors[0], err


def test_meaningful_values_are_kept() -> None:
    parser = cli.build_parser()
    args = parser.parse_args(["engage", "--config", "c.yaml", "--wait", "0", "--timeout", "2"])
    assert (args.wait, args.timeout) == (0.0, 2.0)
    args = parser.parse_args(["publish-trajectory", "--config", "c.yaml", "--count", "0"])
    assert args.count == 0
    args = parser.parse_args(["batch", "sim", "s.yaml", "--workers", "2", "--wait-workers", "0"])
    assert (args.workers, args.wait_workers) == (2, 0.0)


def test_the_types() -> None:
    assert positive_seconds("1.5") == 1.5
    assert non_negative_seconds("0") == 0.0
    assert positive_number("3") == 3.0
    assert positive_int("4") == 4
    assert non_negative_int("0") == 0
    for fn, text in [
        (positive_seconds, "0"),
        (positive_seconds, "-inf"),
        (non_negative_seconds, "nan"),
        (positive_int, "0"),
        (non_negative_int, "-1"),
        (positive_int, "x"),
    ]:
        with pytest.raises(argparse.ArgumentTypeError, match=repr(text)):
            fn(text)


# --- item 3: a failed --record is not called recorded; a full disk names the output ------------


def test_sim_record_failure_is_said_and_fails(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: Any
) -> None:
    from leafgate.record import recorder

    original = recorder._BackgroundWriter.__init__

    def disk_full_can_log(self: Any, name: str, write: Any, *args: Any, **kwargs: Any) -> None:
        def full(_item: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        original(self, name, full if name.startswith("can-log") else write, *args, **kwargs)

    monkeypatch.setattr(recorder._BackgroundWriter, "__init__", disk_full_can_log)
    rec = tmp_path / "rec"
    status = cli.main(["sim", "--no-plots", "--out", str(tmp_path / "out"), "--record", str(rec)])
    out, err = capsys.readouterr()
    assert status == cli.EXIT_ERROR
    assert not [line for line in out.splitlines() if line.startswith("recorded") and ".blf" in line]
    assert [line for line in out.splitlines() if line.startswith("recorded") and ".mcap" in line]
    assert "recording failed" in err and "No space left on device" in err
    assert "the drive finished, but --record" in err


def test_disk_full_without_a_file_name_names_the_output(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: Any
) -> None:
    def full(_args: Any) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")  # as file.write raises it

    monkeypatch.setattr(cli, "cmd_sim", full)
    out = tmp_path / "o"
    assert cli.main(["sim", "--out", str(out)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert err.strip() == f"leafgate: error: No space left on device (writing --out {out})"


# --- item 5: the tools that need the test extra say so ------------------------------------------


@pytest.mark.parametrize(
    ("tool", "module"),
    [("generated_routes.py", "hypothesis"), ("report_age_soak.py", "pytest")],
)
def test_tool_without_the_test_extra_says_which(tool: str, module: str) -> None:
    code = (
        f"import runpy, sys; sys.modules[{module!r}] = None; "
        f"sys.argv = ['tools/{tool}', '--help']; "
        f"runpy.run_path('tools/{tool}', run_name='__main__')"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert (
        done.stderr.strip()
        == f"{tool}: needs {module}, from the test extra: pip install -e '.[test]'"
    )


# --- the reviewer's cosmetic slips -------------------------------------------------------------


def test_a_usage_error_names_the_options_not_the_config(tmp_path: Path, capsys: Any) -> None:
    """Old code: "leafgate: error: c.yaml: publish-trajectory: give a FILE …", the config file
    named as if it were at fault (sim --config did the same)."""
    config = tmp_path / "c.yaml"
    config.write_text("{}\n", encoding="utf-8")
    assert cli.main(["publish-trajectory", "--config", str(config)]) == 2
    assert capsys.readouterr().err == (
        "leafgate: error: publish-trajectory: give a FILE or --scenario NAME (one of them)\n"
    )
    argv = ["sim", "--config", str(config), "--scenario", "straight", "--trajectory", "x.csv"]
    assert cli.main([*argv, "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == (
        "leafgate: error: sim: give --scenario NAME or --trajectory FILE, not both\n"
    )


def test_bench_from_the_environment_is_still_named_so(tmp_path: Path, capsys: Any) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("bench: 1\n", encoding="utf-8")
    with pytest.MonkeyPatch.context() as env:
        env.setenv("LEAFGATE_BENCH", "-1")
        assert cli.main(["check-config", str(config)]) == 2
    assert "LEAFGATE_BENCH='-1': '-1' is not a bench number" in capsys.readouterr().err


def test_publish_trajectory_states_the_spacing_in_metres(
    tmp_path: Path, capsys: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Old code: "route.csv: 5 waypoints, spacing Spacing(min=0.5, median=0.5, max=0.5)"."""
    from leafgate.errors import TransportError
    from leafgate.transport import session

    def no_session(cfg: Any) -> Any:
        raise TransportError("no network in this test")

    monkeypatch.setattr(session, "open_session", no_session)
    route = tmp_path / "route.csv"
    route.write_text(
        "x,y,heading,speed\n0,0,0,0.3\n0.5,0,0,0.6\n1,0,0,0.6\n2,0,0,0.3\n2.5,0,0,0\n",
        encoding="utf-8",
    )
    config = tmp_path / "c.yaml"
    config.write_text("{}\n", encoding="utf-8")
    assert cli.main(["publish-trajectory", str(route), "--config", str(config)]) == 1
    assert capsys.readouterr().out == f"{route}: 5 waypoints, 0.50-1.00 m (median 0.50 m) apart\n"
