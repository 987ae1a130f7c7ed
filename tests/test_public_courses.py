"""The path-tracking courses of PythonRobotics, driven as a user drives their own route.

The five courses of PythonRobotics' MPC example are written as trajectory files by
``tools/public_courses.py`` (its waypoints, scipy's natural spline, its speed rule) and read back
by ``leafgate sim --trajectory``'s loader. Before the cusp rule of
:func:`leafgate.control.reference.chord_directions`, the switch-back course stopped at its cusp:
"no progress … at 106.5 of 167.8 m". The two long courses turn tighter than any car can at one
point: R = 0.57 m at (30, −1) on the switch-back and 0.37 m at (75, 30) on the forward course,
where the Leaf turns no tighter than 4.5 m. The reference slows to 1 m/s before them; by
default the car is stopped off the plan there, and the sim names the turn; where the user
allows the car to leave the plan, it drives them as well as it can, never faster than the
plan, and ends on the goal.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from leafgate.cli import main
from leafgate.control.reference import split_segments
from leafgate.settings import load_config
from leafgate.sim.metrics import GOAL_FINAL_POSITION, route_goal_misses
from leafgate.sim.runner import run
from leafgate.sim.scenarios import file_scenario
from tools.public_courses import write_course as _write


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
    "name, tight, where", [("switch-back", 0.57, (29.8, -0.9)), ("forward", 0.37, (75.0, 29.9))]
)
def test_a_course_tighter_than_the_car_turns_is_stopped_off_the_plan_and_said_why(
    name: str, tight: float, where: tuple[float, float], tmp_path: Path, capsys: Any
) -> None:
    """By default the car is stopped 2 m off the plan (the planner's corridor is gone), never
    faster than the plan; ``leafgate sim`` names the turn no car can follow.

    The car reaches the turn slowly (the reference's ``TIGHT_TURN_SPEED``), so the stop keeps
    it near the plan: before, it came at the plan's 2.9 m/s and braked to 5.0 m (switch-back)
    and 5.7 m (forward) off the plan; now 2.8 m."""
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
    assert metrics["lateral_error_max_m"] < 3.2


@pytest.mark.slow
@pytest.mark.parametrize("name", ["switch-back", "forward"])
def test_with_room_to_leave_the_plan_they_are_driven_to_their_goal(
    name: str, tmp_path: Path, capsys: Any
) -> None:
    """Where the user allows it (an empty test ground), the car cuts the turn and drives the
    whole course, through the switch-back's cusp, onto the goal; ``leafgate sim`` still says
    that the plan turns tighter than the car can, and how far off it the car went (old code:
    exit 0 and nothing said, the car 6.2 m off the plan)."""
    csv, out = _write(name, tmp_path), tmp_path / "out"
    room = "gateway.watchdog.max_path_deviation=10"
    args = ["sim", "--trajectory", str(csv), "--plant", "kinematic", "--set", room]
    assert main([*args, "--out", str(out), "--no-plots"]) == 0
    err = capsys.readouterr().err
    assert "the plan turns tighter than the car can: radius" in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert f"the car was up to {metrics['lateral_error_max_m']:.2f} m off it" in err
    assert metrics["finished"], metrics.get("not_finished_reason")
    assert metrics["progress_m"] == pytest.approx(metrics["route_length_m"], abs=0.1)
    assert metrics["final_position_error_m"] <= GOAL_FINAL_POSITION
    # never faster than the plan, where the plan stands at the cusp included
    assert route_goal_misses(metrics, "kinematic", feasible=False) == []
