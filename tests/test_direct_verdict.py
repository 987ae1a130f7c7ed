"""``sim --direct`` has no gateway, so nothing stops a car that leaves the plan: its verdict
must not call such a drive finished (reported by an outside tester with a public course)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from leafgate import cli


def _spline(ax: list[float], ay: list[float]) -> tuple[np.ndarray, ...]:
    """Waypoints 1 m apart on natural cubic splines through the points, with their headings
    (the way public path-tracking courses are made)."""
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(ax), np.diff(ay)))))
    sx, sy = CubicSpline(s, ax, bc_type="natural"), CubicSpline(s, ay, bc_type="natural")
    ss = np.arange(0.0, s[-1], 1.0)
    return sx(ss), sy(ss), np.arctan2(sy(ss, 1), sx(ss, 1))


def _switch_back(path: Path) -> Path:
    """A switch-back course of the public examples' shape: a forward leg with a turn far
    tighter than a Leaf's (0.6 m radius), then a reverse leg; each waypoint has the speed of
    the chord that leaves it (±2 m/s), headings unwrapped."""
    x1, y1, h1 = _spline([0.0, 30.0, 6.0, 20.0, 35.0], [0.0, 0.0, 20.0, 35.0, 20.0])
    x2, y2, h2 = _spline([35.0, 10.0, 0.0, 0.0], [20.0, 30.0, 5.0, 0.0])
    x, y = np.concatenate((x1, x2)), np.concatenate((y1, y2))
    heading = np.unwrap(np.concatenate((h1, h2 - math.pi)))
    chord = np.arctan2(np.diff(y), np.diff(x))
    off = np.abs(np.angle(np.exp(1j * (chord - heading[:-1]))))
    speed = np.append(np.where(off >= math.pi / 4, -2.0, 2.0), 0.0)
    rows = ["x,y,heading,speed"] + [
        f"{a:.6f},{b:.6f},{c:.6f},{d:.1f}" for a, b, c, d in zip(x, y, heading, speed, strict=True)
    ]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    return path


def test_a_direct_drive_that_left_the_plan_is_not_finished(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: the car went 6.15 m off the course at its tight turn, came back, reached the
    end, and ``sim --direct`` said finished and exited 0; the full loop stops it 2 m off. Now
    the direct verdict holds the gateway's off-the-plan limit too, and says where it was left."""
    route = _switch_back(tmp_path / "switchback.csv")
    out = tmp_path / "out"
    args = ["sim", "--no-plots", "--direct", "--trajectory", str(route), "--out", str(out)]
    assert cli.main(args) == 1
    err = capsys.readouterr().err
    assert "not finished: off the plan: " in err and "(limit 2 m) at t = " in err
    assert "(watchdog.max_path_deviation)" in err and "--direct has no gateway" in err
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["finished"] is False
    assert metrics["lateral_error_max_m"] > 2.0
    # the drive did reach the end (it is the verdict, not the run, that changed)
    assert metrics["progress_m"] > metrics["route_length_m"] - 0.5
