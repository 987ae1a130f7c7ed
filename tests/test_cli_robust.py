"""Every subcommand × {output folder that cannot be created, closed stdout, Ctrl-C}: one line on
stderr, no traceback, a non-zero exit status (issue 19, item 4).

The commands run as processes (``python -m leafgate``), as an operator runs them. The ones that
talk to a gateway find none here and are given a short timeout; the daemon-like ones (``run``,
``sim-ecu``, ``publish-trajectory``) stop on Ctrl-C by design, with status 0.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from leafgate.cli import OUTPUT_FILES, OUTPUT_FOLDERS, build_parser
from tests.conftest import free_port

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "leafgate"]
SWEEP = str(ROOT / "config" / "sweep.yaml")
SIGINT_AFTER = 4.0  # s: the command is past its imports and at work (two busy cores)
#: stopping these with Ctrl-C is their normal end (the daemon disengages first): status 0
STOP_BY_SIGNAL = {"run", "sim-ecu", "publish-trajectory"}


def _default_sigint() -> None:
    """Ctrl-C as at a terminal: a shell's background job (as CI may run pytest) inherits
    SIGINT ignored, and Python keeps an ignored SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    tmp = tmp_path_factory.mktemp("robust")
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    cfg["can"]["dbw"]["channel"] = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    cfg["can"]["dbw"]["kwargs"] = {"port": free_port()}
    (tmp / "sim.yaml").write_text(yaml.safe_dump(cfg))
    subprocess.run(
        [*CLI, "sim", "--record", str(tmp / "rec"), "--no-plots", "--out", str(tmp / "o")],
        check=True,
        capture_output=True,
        timeout=300,
    )
    # a long candump log: decode and check are still at work when Ctrl-C comes
    lines = [
        f"({100 + i * 0.001:.6f}) can0 0B0#{i % 256:02X}00000000000000" for i in range(300_000)
    ]
    (tmp / "big.log").write_text("\n".join(lines) + "\n")
    (tmp / "file").write_text("a file, not a folder\n")
    return {
        "config": str(tmp / "sim.yaml"),
        "blf": str(next((tmp / "rec").glob("can-*.blf"))),
        "mcap": str(next((tmp / "rec").glob("session-*.mcap"))),
        "big": str(tmp / "big.log"),
        "bad": str(tmp / "file" / "sub"),  # under a regular file: can never be created
        "tmp": str(tmp),
    }


def commands(f: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Per subcommand: arguments that keep it at work, and where it writes an output folder."""
    c = f["config"]
    out = f"{f['tmp']}/out-{random.randint(0, 10**9)}"
    return {
        "sim": {
            "work": ["sim", "--realtime", "--no-plots", "--out", out],
            "pipe": ["sim", "--no-plots", "--out", out],
            "bad": [
                ["sim", "--no-plots", "--out", f["bad"]],
                ["sim", "--no-plots", "--out", out, "--record", f["bad"]],
            ],
        },
        "run": {"work": ["run", "--config", c]},
        "sim-ecu": {
            "work": ["sim-ecu", "--config", c],
            "bad": [["sim-ecu", "--config", c, "--trace", f["bad"] + "/trace.csv"]],
        },
        "engage": {"work": ["engage", "--config", c, "--wait", "30", "--timeout", "30"]},
        "disengage": {"work": ["disengage", "--config", c, "--timeout", "30"]},
        "reset": {"work": ["reset", "--config", c, "--timeout", "30"]},
        "status": {"work": ["status", "--config", c, "--duration", "30"]},
        "compare": {
            "work": ["compare", "--out", out, "--workers", "2", "--no-plots"],
            "pipe": ["compare", "--out", out, "--scenario", "straight", "--plant", "kinematic"],
            "bad": [["compare", "--out", f["bad"]]],
        },
        "replay check": {"work": ["replay", "check", f["big"], "--profile", "leafgate-dbw"]},
        "replay play": {
            "work": [
                "replay",
                "play",
                f["blf"],
                "--profile",
                "leafgate-dbw",
                "-i",
                "virtual",
                "-c",
                "robust",
            ]
        },
        "replay rerun": {"work": ["replay", "rerun", f["mcap"]]},
        "replay plot": {
            "work": ["replay", "plot", f["mcap"], "--out", out],
            "bad": [["replay", "plot", f["mcap"], "--out", f["bad"]]],
        },
        "check-config": {"work": ["check-config", c]},
        "keygen": {"work": ["keygen", f"{f['tmp']}/key-{random.randint(0, 10**9)}"]},
        "publish-trajectory": {
            "work": ["publish-trajectory", "--scenario", "s-curve", "--config", c, "--wait", "1"]
        },
        "decode": {"work": ["decode", f["big"], "--profile", "leafgate-dbw"]},
        "batch sim": {
            "work": ["batch", "sim", SWEEP, "--out", out, "--workers", "2"],
            "bad": [["batch", "sim", SWEEP, "--out", f["bad"]]],
        },
        "batch check": {
            "work": ["batch", "check", f["tmp"], "--out", out, "--profile", "leafgate-dbw"],
            "bad": [["batch", "check", f["tmp"], "--out", f["bad"]]],
        },
        "batch rerun": {
            "work": ["batch", "rerun", f["tmp"], "--out", out],
            "bad": [["batch", "rerun", f["tmp"], "--out", f["bad"]]],
        },
    }


_PLACEHOLDERS = dict.fromkeys(("config", "blf", "mcap", "big", "bad", "tmp"), "x")
NAMES = sorted(commands(_PLACEHOLDERS))
WRITERS = sorted(n for n, spec in commands(_PLACEHOLDERS).items() if "bad" in spec)


def _subcommands() -> set[str]:
    import argparse

    names: set[str] = set()
    parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                nested = [a for a in sub._actions if isinstance(a, argparse._SubParsersAction)]
                if nested:
                    names |= {f"{name} {n}" for n in nested[0].choices}
                else:
                    names.add(name)
    return names


def _writes_output(name: str) -> bool:
    import argparse

    parser = build_parser()
    sub: Any = parser
    for word in name.split():
        action = next(a for a in sub._actions if isinstance(a, argparse._SubParsersAction))
        sub = action.choices[word]
    dests = {a.dest for a in sub._actions}
    # `batch`'s --out is `out_dir`: it creates the folder itself once its inputs are checked
    return bool(dests & {*OUTPUT_FOLDERS, *OUTPUT_FILES, "out_dir"})


def _check(name: str, condition: str, status: int | None, stderr: str) -> None:
    assert status is not None, f"{name} × {condition}: still running (killed)"
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, (
        f"{name} × {condition}:\n{stderr}"
    )
    # warnings said while working are not how the command ended
    lines = [
        line
        for line in stderr.splitlines()
        if line.strip() and not line.startswith("leafgate: warning:")
    ]
    assert len(lines) <= 1, f"{name} × {condition}: more than one line:\n{stderr}"
    if condition == "sigint" and name in STOP_BY_SIGNAL:
        # its last words may meet the closed pipe (141); a Ctrl-C that lands while Zenoh
        # closes its session ends the process by SIGINT itself (a shell shows 130 as well)
        assert status in (0, 130, 141, -signal.SIGINT), (
            f"{name} × {condition}: status {status}\n{stderr}"
        )
    else:
        assert status != 0, f"{name} × {condition}: status 0\n{stderr}"
        assert lines, f"{name} × {condition}: non-zero status {status} without a line"


def _start(args: list[str], stdout: Any, err: Any, cwd: Path) -> subprocess.Popen[Any]:
    return subprocess.Popen(
        [*CLI, *args], stdout=stdout, stderr=err, cwd=cwd, preexec_fn=_default_sigint
    )


def _stop(process: subprocess.Popen[Any]) -> int | None:
    try:
        return process.wait(timeout=120)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        return None


def test_the_sweep_covers_every_subcommand(files: dict[str, str]) -> None:
    missing = _subcommands() - set(commands(files))
    assert not missing, f"add {sorted(missing)} to commands() in this test"
    for name, spec in commands(files).items():
        assert _writes_output(name) == ("bad" in spec), f"{name}: output folder case"


@pytest.mark.parametrize("name", NAMES)
def test_sigint(name: str, files: dict[str, str], tmp_path: Path) -> None:
    args = commands(files)[name]["work"]
    with (tmp_path / "err").open("w+") as err:
        process = _start(args, subprocess.DEVNULL, err, tmp_path)
        deadline = time.monotonic() + SIGINT_AFTER
        while time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.05)
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        else:
            pytest.skip(f"{name} finished within {SIGINT_AFTER:g} s (status {process.returncode})")
        status = _stop(process)
        err.seek(0)
        _check(name, "sigint", status, err.read())


@pytest.mark.parametrize("name", NAMES)
def test_closed_stdout(name: str, files: dict[str, str], tmp_path: Path) -> None:
    spec = commands(files)[name]
    args = spec.get("pipe", spec["work"])
    with (tmp_path / "err").open("w+") as err:
        process = _start(args, subprocess.PIPE, err, tmp_path)
        assert process.stdout is not None
        process.stdout.close()  # the reader is gone (`… | head` after its lines)
        if name in STOP_BY_SIGNAL:  # they keep working without their log; stop them
            time.sleep(SIGINT_AFTER)
            process.send_signal(signal.SIGINT)
        status = _stop(process)
        err.seek(0)
        text = err.read()
    if name in STOP_BY_SIGNAL:
        _check(name, "sigint", status, text)
    else:
        _check(name, "closed stdout", status, text)


@pytest.mark.parametrize("name", WRITERS)
def test_output_folder_cannot_be_created(name: str, files: dict[str, str], tmp_path: Path) -> None:
    for args in commands(files)[name]["bad"]:
        done = subprocess.run(
            [*CLI, *args], capture_output=True, text=True, timeout=120, cwd=tmp_path
        )
        _check(name, "bad output folder", done.returncode, done.stderr)
        assert files["bad"] in done.stderr and "cannot create the output folder" in done.stderr
        assert not Path(files["bad"]).exists()


def test_main_returns_141_on_a_closed_pipe(monkeypatch: pytest.MonkeyPatch) -> None:
    from leafgate import cli

    def broken(_args: Any) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    parser = cli.build_parser()
    args = parser.parse_args(["check-config", "x"])
    args.func = broken
    monkeypatch.setattr(cli, "build_parser", lambda: _Fixed(parser, args))
    assert cli.main(["check-config", "x"]) == cli.EXIT_PIPE


class _Fixed:
    def __init__(self, parser: Any, args: Any) -> None:
        self.parser, self.args = parser, args

    def parse_args(self, _argv: Any) -> Any:
        return self.args


class _Interrupted:
    def parse_args(self, _argv: Any) -> Any:
        raise KeyboardInterrupt  # Ctrl-C while argparse reads the command line


def test_ctrl_c_while_the_command_line_is_read_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in the moment between building the parser and the command (parse_args, the
    signal release, logging set up) ended in argparse's traceback (once in 40 Ctrl-Cs of
    `status`, on two loaded cores); it is "interrupted" and status 130 as everywhere else."""
    from leafgate import cli

    monkeypatch.setattr(cli, "build_parser", _Interrupted)
    try:
        code = cli.main(["status", "--config", "x"])
    except KeyboardInterrupt:  # not let through: it would end the test run
        pytest.fail("Ctrl-C escaped leafgate's main (the process shows its traceback)")
    assert code == cli.EXIT_INTERRUPTED
    assert capsys.readouterr().err == "leafgate: interrupted\n"


PUBLICATIONS = 1000  # at 10 ms: ten seconds of publishing, unless the Ctrl-C stops it


class _InterruptedWhileFinalised:
    """Dropped on the third publication: its finaliser is where Ctrl-C lands (as it landed in
    importlib's module-lock callback during the first publication's imports)."""

    def __del__(self) -> None:
        signal.raise_signal(signal.SIGINT)


def test_a_ctrl_c_that_lands_in_a_finaliser_still_stops_publish_trajectory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """publish-trajectory stopped on KeyboardInterrupt; one raised inside a finaliser is
    swallowed by Python ("Exception ignored in … KeyboardInterrupt") and the command published
    on until the next Ctrl-C (1 in 40 Ctrl-Cs in the trials). A stop signal now sets an event
    (runtime.signals), which no finaliser swallows."""
    from leafgate import cli
    from leafgate.transport.client import TrajectoryPublisher

    config = tmp_path / "tool.yaml"
    config.write_text(yaml.safe_dump({"zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"]}}))
    real = TrajectoryPublisher.publish
    calls = []

    def publish(self: TrajectoryPublisher, trajectory: Any) -> None:
        calls.append(1)
        if len(calls) == 3:
            _InterruptedWhileFinalised()  # dropped at once: its __del__ runs here
        real(self, trajectory)

    monkeypatch.setattr(TrajectoryPublisher, "publish", publish)
    # Ctrl-C as at a terminal (pytest run as a background job inherits it ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = cli.main(
            [
                "publish-trajectory",
                "--scenario",
                "straight",
                "--config",
                str(config),
                "--wait",
                "0",
                "--period",
                "0.01",
                "--count",
                str(PUBLICATIONS),
            ]
        )
    finally:
        signal.signal(signal.SIGINT, previous)
    assert code == 0
    assert len(calls) < PUBLICATIONS, "the Ctrl-C was lost: it published to the end"
    assert f"published the trajectory {len(calls)} times" in capsys.readouterr().out
