"""The path-tracking courses of PythonRobotics' MPC example, written as leafgate trajectory files.

PythonRobotics' MPC example (``PathTracking/model_predictive_speed_and_steer_control``, commit
b38c510) defines five courses by a few waypoints each. It fits a natural cubic spline to x and y
over the chord length, samples it every metre with the yaw of the tangent, and gives every
waypoint the speed of the chord that leaves it: 10 km/h, negative where that chord runs against
the yaw, and 0 on the last waypoint. The switch-back course joins two such splines: a forward one
and a reverse one, whose yaw is the tangent's minus π, so its cusp has no waypoint at rest. The
waypoints here are that file's; the spline is scipy's (the same natural spline).

    .venv/bin/python tools/public_courses.py DIR      # DIR/straight.csv … DIR/switch-back.csv
    .venv/bin/leafgate sim --trajectory DIR/switch-back.csv
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from leafgate.messages import FloatArray

SPEED = 10.0 / 3.6  # m/s, the example's target speed
SPACING = 1.0  # m, the example's course tick
COURSES = ("straight", "straight2", "straight3", "forward", "switch-back")


def _spline(ax: list[float], ay: list[float]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """x, y and the tangent's yaw every :data:`SPACING` along a natural cubic spline through
    the waypoints, parametrised by chord length (the last sample short of the end, as there)."""
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(ax), np.diff(ay)))))
    sx, sy = CubicSpline(s, ax, bc_type="natural"), CubicSpline(s, ay, bc_type="natural")
    q = np.arange(0.0, s[-1], SPACING)
    return sx(q), sy(q), np.arctan2(sy(q, 1), sx(q, 1))


def _speeds(x: FloatArray, y: FloatArray, yaw: FloatArray) -> FloatArray:
    """Each waypoint's speed: that of the chord leaving it, reverse when the chord runs more
    than 45° off the yaw (a chord along an axis keeps the direction before it); 0 at the end."""
    speed = np.empty(len(x))
    direction = 1.0
    for i in range(len(x) - 1):
        dx, dy = x[i + 1] - x[i], y[i + 1] - y[i]
        if dx != 0.0 and dy != 0.0:
            off = abs(math.remainder(math.atan2(dy, dx) - yaw[i], 2.0 * math.pi))
            direction = -1.0 if off >= math.pi / 4.0 else 1.0
        speed[i] = direction * SPEED
    speed[-1] = 0.0
    return speed


def course(name: str) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """x, y, heading and signed speed of the course ``name`` (one of :data:`COURSES`)."""
    wavy = ([0.0, -10.0, -20.0, -40.0, -50.0, -60.0, -70.0], [0.0, -1.0, 1.0, 0.0, -1.0, 1.0, 0.0])
    if name == "straight":
        x, y, yaw = _spline([0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0], [0.0] * 7)
    elif name == "straight2":
        x, y, yaw = _spline(*wavy)
    elif name == "straight3":  # the same, the car facing the other way: driven in reverse
        x, y, yaw = _spline(*wavy)
        yaw = yaw - math.pi
    elif name == "forward":
        x, y, yaw = _spline(
            [0.0, 60.0, 125.0, 50.0, 75.0, 30.0, -10.0], [0.0, 0.0, 50.0, 65.0, 30.0, 50.0, -20.0]
        )
    elif name == "switch-back":
        x1, y1, yaw1 = _spline([0.0, 30.0, 6.0, 20.0, 35.0], [0.0, 0.0, 20.0, 35.0, 20.0])
        x2, y2, yaw2 = _spline([35.0, 10.0, 0.0, 0.0], [20.0, 30.0, 5.0, 0.0])
        x, y, yaw = np.r_[x1, x2], np.r_[y1, y2], np.r_[yaw1, yaw2 - math.pi]
    else:
        raise ValueError(f"no course {name!r} (one of {', '.join(COURSES)})")
    return x, y, yaw, _speeds(x, y, yaw)


def write_course(name: str, folder: Path) -> Path:
    """``folder/NAME.csv`` in leafgate's trajectory format (header ``x,y,heading,speed``)."""
    table = np.column_stack(course(name)).tolist()
    path = folder / f"{name}.csv"
    rows = [",".join(repr(value) for value in row) for row in table]
    path.write_text("x,y,heading,speed\n" + "\n".join(rows) + "\n", encoding="utf-8")
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="where the CSV files go (created)")
    args = parser.parse_args()
    try:
        args.folder.mkdir(parents=True, exist_ok=True)
        written = [write_course(name, args.folder) for name in COURSES]
    except OSError as exc:
        print(f"public_courses: {args.folder}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    try:
        print("\n".join(map(str, written)), flush=True)
    except BrokenPipeError:  # the reader went away: the files are written, say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, as a shell reports it
    return 0


if __name__ == "__main__":
    sys.exit(main())
