"""The path-tracking courses of PythonRobotics, driven as a user drives their own route.

PythonRobotics' MPC example (``PathTracking/model_predictive_speed_and_steer_control``, commit
b38c510) defines five courses by a few waypoints each. It fits a natural cubic spline to x and y
over the chord length, samples it every metre with the yaw of the tangent, and gives every
waypoint the speed of the chord that leaves it: 10 km/h, negative where that chord runs against
the yaw, and 0 on the last waypoint. The switch-back course joins two such splines: a forward one
and a reverse one, whose yaw is the tangent's minus π. So the cusp has no waypoint at rest, and
the chord into it still carries the forward sign at its start.

The waypoints below are that file's. The spline is scipy's (the same natural spline), written to
a CSV and read back by ``leafgate sim --trajectory``'s loader. Before the cusp rule of
:func:`leafgate.control.reference.chord_directions`, the switch-back course stopped at its cusp:
"no progress … at 106.5 of 167.8 m". The two long courses turn tighter than any car can at one
point: R = 0.47 m at (30, 0) on the switch-back and 0.22 m at (75, 30) on the forward course,
where the Leaf turns no tighter than 4.7 m. The car then drives them as well as it can, never
faster than the plan, and still ends on the goal.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from leafgate.cli import main
from leafgate.control.reference import split_segments
from leafgate.messages import FloatArray
from leafgate.settings import load_config
from leafgate.sim.metrics import GOAL_FINAL_POSITION, route_goal_misses
from leafgate.sim.runner import run
from leafgate.sim.scenarios import file_scenario

SPEED = 10.0 / 3.6  # m/s, the example's target speed
SPACING = 1.0  # m, the example's course tick


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


def _course(name: str) -> tuple[FloatArray, FloatArray, FloatArray]:
    wavy = ([0.0, -10.0, -20.0, -40.0, -50.0, -60.0, -70.0], [0.0, -1.0, 1.0, 0.0, -1.0, 1.0, 0.0])
    if name == "straight":
        return _spline([0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0], [0.0] * 7)
    if name == "straight2":
        return _spline(*wavy)
    if name == "straight3":  # the same, the car facing the other way: driven in reverse
        x, y, yaw = _spline(*wavy)
        return x, y, yaw - math.pi
    if name == "forward":
        return _spline(
            [0.0, 60.0, 125.0, 50.0, 75.0, 30.0, -10.0], [0.0, 0.0, 50.0, 65.0, 30.0, 50.0, -20.0]
        )
    assert name == "switch-back"
    x1, y1, yaw1 = _spline([0.0, 30.0, 6.0, 20.0, 35.0], [0.0, 0.0, 20.0, 35.0, 20.0])
    x2, y2, yaw2 = _spline([35.0, 10.0, 0.0, 0.0], [20.0, 30.0, 5.0, 0.0])
    return np.r_[x1, x2], np.r_[y1, y2], np.r_[yaw1, yaw2 - math.pi]


def _write(name: str, folder: Path) -> Path:
    x, y, yaw = _course(name)
    path = folder / f"{name}.csv"
    table = np.column_stack((x, y, yaw, _speeds(x, y, yaw))).tolist()
    rows = [",".join(repr(value) for value in row) for row in table]
    path.write_text("x,y,heading,speed\n" + "\n".join(rows) + "\n")
    return path


def test_the_switch_back_course_has_its_cusp_where_the_car_turns_back(tmp_path: Path) -> None:
    """The cusp is the forward spline's last point reached, (35, 20), not the waypoint before
    it: from there the reverse leg's first chord would lead forward, to a point ahead."""
    traj = file_scenario(str(_write("switch-back", tmp_path))).trajectory
    forward, reverse = split_segments(traj)
    cusp = forward.end
    assert (forward.direction, reverse.direction) == (1, -1) and reverse.start == cusp
    assert (traj.x[cusp], traj.y[cusp]) == (35.0, 20.0)
    assert traj.speed[cusp] < 0.0 < traj.speed[cusp - 1]  # no waypoint at rest between them


@pytest.mark.slow
@pytest.mark.parametrize("name", ["straight", "straight2", "straight3"])
def test_the_feasible_courses_meet_the_route_goals(name: str, tmp_path: Path) -> None:
    scenario = file_scenario(str(_write(name, tmp_path)))
    metrics = run(load_config(None, {"sim.plant.kind": "kinematic"}), scenario).metrics
    assert route_goal_misses(metrics, "kinematic", feasible=True) == []


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, tight, where", [("switch-back", 0.47, (30.0, -0.7)), ("forward", 0.22, (75.0, 29.7))]
)
def test_a_course_tighter_than_the_car_turns_is_stopped_off_the_plan_and_said_why(
    name: str, tight: float, where: tuple[float, float], tmp_path: Path, capsys: Any
) -> None:
    """By default the car is stopped 2 m off the plan (the planner's corridor is gone), never
    faster than the plan; ``leafgate sim`` names the turn no car can follow."""
    csv = _write(name, tmp_path)
    assert (
        main(["sim", "--trajectory", str(csv), "--out", str(tmp_path / "out"), "--no-plots"]) == 1
    )
    err = capsys.readouterr().err
    assert "not finished: STOPPING at t = " in err and "off the plan: 2.0" in err
    x, y = where
    assert f"the plan turns tighter than the car can: radius {tight:.2f} m at ({x}, {y}) m" in err
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert route_goal_misses(metrics, "kinematic", feasible=False) == []


@pytest.mark.slow
@pytest.mark.parametrize("name", ["switch-back", "forward"])
def test_with_room_to_leave_the_plan_they_are_driven_to_their_goal(
    name: str, tmp_path: Path
) -> None:
    """Where the user allows it (an empty test ground), the car cuts the turn and drives the
    whole course, through the switch-back's cusp, onto the goal."""
    scenario = file_scenario(str(_write(name, tmp_path)))
    config = load_config(
        None, {"sim.plant.kind": "kinematic", "gateway.watchdog.max_path_deviation": 10.0}
    )
    metrics = run(config, scenario).metrics
    assert metrics["finished"], metrics.get("not_finished_reason")
    assert metrics["progress_m"] == pytest.approx(metrics["route_length_m"], abs=0.1)
    assert metrics["final_position_error_m"] <= GOAL_FINAL_POSITION
    # never faster than the plan, where the plan stands at the cusp included
    assert route_goal_misses(metrics, "kinematic", feasible=False) == []
