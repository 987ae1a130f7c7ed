"""Ctrl-C at the edges of a command — while leafgate loads, and once the command has returned
while Python shuts down — ends with status 130 (or the command's own status, when the signal
came too late to matter) and at most one line: never a traceback, never death by SIGINT.

Old code: a second Ctrl-C during the shutdown after the first one (scipy and numpy loaded: tens of
ms of module teardown) killed the process by SIGINT (status -2) in about half of the tries, and
one that landed in scipy's import ended as "ImportError: initialization failed" with a traceback.

The processes run ``python -m leafgate``; each signal is sent after a readiness mark (a line on
stdout, a library mapped into the process), never after a fixed sleep.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "leafgate"]
CONFIG = str(ROOT / "config" / "sim.yaml")


def _default_sigint() -> None:
    """Ctrl-C as at a terminal (a background job inherits SIGINT ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*CLI, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        preexec_fn=_default_sigint,
    )


def _interrupt(process: subprocess.Popen[str], times: int) -> None:
    for _ in range(times):
        if process.poll() is not None:
            return
        process.send_signal(signal.SIGINT)


def _ended_cleanly(process: subprocess.Popen[str], allowed: tuple[int, ...]) -> None:
    _out, err = process.communicate(timeout=120)
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert process.returncode in allowed, f"status {process.returncode}\n{err}"
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("leafgate: warning:")]
    assert all(x == "leafgate: interrupted" for x in lines), err


@pytest.mark.parametrize("times", [1, 2, 3])
def test_ctrl_c_after_the_command_has_answered_exits_130_not_by_sigint(times: int) -> None:
    for _ in range(3):  # the shutdown is short: a few tries for one to land in it
        process = _start("check-config", CONFIG)
        assert process.stdout is not None
        for line in process.stdout:  # the command's last line: it is returning now
            if line.startswith("ROS 2:"):
                break
        _interrupt(process, times)
        _ended_cleanly(process, (0, 130))


def _maps(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return ""


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc")
@pytest.mark.parametrize("library", ["_multiarray_umath", "_highs"])
@pytest.mark.parametrize("times", [1, 3])
def test_ctrl_c_while_a_native_library_loads_is_one_line_and_130(library: str, times: int) -> None:
    """The signal comes as soon as the library is mapped: its import is under way."""
    process = _start("check-config", CONFIG)
    deadline = time.monotonic() + 60
    while library not in _maps(process.pid) and process.poll() is None:
        assert time.monotonic() < deadline, f"{library} never loaded"
        time.sleep(0.001)
    _interrupt(process, times)
    _ended_cleanly(process, (0, 130))
