"""A plan that comes to rest before its end: the car stops there and waits.

Autoware's planners stop a car at a stop line or before an obstacle by setting the speeds to
zero from the stop point on, for as far as the trajectory reaches. Old code: the reference
placed its points past the stop at the creep speed and the speed bound allowed the plan's 0
plus the 0.15 m/s margin, so the car crept on through the stop point towards the plan's end
(18.8 m into a plan that stops at 10 m, in 70 s).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from leafgate import cli
from leafgate.control.reference import ReferencePath, stop_point
from leafgate.messages import Pose, Trajectory
from leafgate.settings import load_config
from leafgate.sim.runner import run
from leafgate.sim.scenarios import Scenario

STOP = 10.0  # m, where the plan comes to rest
LENGTH = 20.0  # m, how far it reaches


def _stopping_plan(start_speed: float = 1.0) -> Trajectory:
    s = np.arange(0.0, LENGTH + 0.01, 0.5)
    speed = np.where(s < STOP, 1.0, 0.0)
    speed[0] = start_speed
    return Trajectory(x=s, y=np.zeros_like(s), heading=np.zeros_like(s), speed=speed)


def test_the_stop_point_is_the_first_waypoint_at_rest_after_the_motion() -> None:
    assert stop_point(np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0])) == 4
    assert stop_point(np.array([0.0, 0.5, 1.0, 1.0, 0.0])) is None  # at rest only at the end
    assert stop_point(np.zeros(5)) == 0  # a plan that never moves stands where it starts


def test_the_reference_stops_at_the_stop_point_and_waits_there() -> None:
    path = ReferencePath(_stopping_plan(start_speed=0.0))
    seg = path.segments[0]
    assert path.stops[seg] == pytest.approx(STOP)
    s = np.linspace(0.0, LENGTH, 81)
    speed = path.reference_speed(s)
    assert (speed[s >= STOP] == 0.0).all()
    assert speed[(s > 1.0) & (s < STOP - 1.0)].min() > 0.5  # driven before it
    # a horizon of 10 s from 9 m: every point on or short of the stop point
    _, _ = path.horizon(seg, 9.0, np.arange(1, 101) * 0.1)
    reach = path.horizon_arclength(seg, 9.0, np.arange(1, 101) * 0.1)
    assert reach.max() == pytest.approx(STOP, abs=1e-6)
    # from rest at the start, the horizon still reaches ahead: the car pulls away
    assert path.horizon_arclength(seg, 0.0, np.array([3.0]))[0] > 1.0


@pytest.mark.slow
def test_the_car_stops_at_the_stop_point_and_the_gateway_waits_engaged() -> None:
    traj = _stopping_plan()
    scenario = Scenario("stop", "a plan that stops at 10 m", traj, Pose(0.0, 0.0, 0.0, 0.0), 25.0)
    result = run(load_config(None, {"sim.plant.kind": "kinematic"}), scenario)
    x = result.series["x"]
    assert x.max() < STOP + 0.1  # never past the stop point
    assert x[-1] == pytest.approx(STOP, abs=0.1)
    # at rest there for over 10 s, longer than the no-progress watchdog's 3 s, still engaged
    at_stop = np.flatnonzero(np.abs(x - STOP) < 0.1)
    assert result.series["t"][-1] - result.series["t"][at_stop[0]] > 10.0
    assert result.states[-1] == "ENGAGED"
    assert not any("no progress" in what for _, what in result.timeline)
    assert result.metrics["finished"] is False  # the route's end was not reached


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["pure-pursuit", "stanley"])
def test_the_baselines_stop_at_the_stop_point_too(controller: str) -> None:
    """Old code: the baselines' target speed never fell below the creep speed before the
    segment's end, so they rolled through a planner's stop line."""
    scenario = Scenario("stop", "a plan that stops at 10 m", _stopping_plan(), Pose(0, 0, 0, 0), 20)
    cfg = load_config(None, {"sim.plant.kind": "kinematic", "controller.kind": controller})
    result = run(cfg, scenario)
    x = result.series["x"]
    assert x.max() < STOP + 0.1, x.max()
    assert x[-1] == pytest.approx(STOP, abs=0.1)
    assert result.states[-1] == "ENGAGED"
    assert not any("no progress" in what for _, what in result.timeline)


def _write(path: Path, rows: list[tuple[float, float, float, float]]) -> Path:
    lines = ["x,y,heading,speed"] + [",".join(f"{v:.6f}" for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_sim_refuses_a_file_whose_plan_stops_short_naming_the_waypoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    traj = _stopping_plan()
    rows = list(zip(traj.x, traj.y, traj.heading, traj.speed, strict=True))
    route = _write(tmp_path / "stop.csv", rows)
    out = tmp_path / "out"
    assert cli.main(["sim", "--no-plots", "--trajectory", str(route), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "stop.csv: row 21: the plan comes to rest here" in err  # s = 10 m
    assert "Traceback" not in err and not (out / "metrics.json").exists()
    still = _write(tmp_path / "still.csv", [(0.5 * i, 0.0, 0.0, 0.0) for i in range(10)])
    assert cli.main(["sim", "--no-plots", "--trajectory", str(still), "--out", str(out)]) == 1
    assert "still.csv: row 1: the plan comes to rest here" in capsys.readouterr().err


def test_a_speed_against_the_leg_is_named_as_that_not_as_speed_0(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Reported from outside: a straight forward line with a speed of −1 m/s at row 2 was
    refused as "the plan comes to rest here … (speed 0 …)": the check clamps speeds against the
    leg to 0. The value the file has is named, and why it stops the car."""
    route = _write(
        tmp_path / "minus.csv",
        [(0.0, 0.0, 0.0, 1.0), (1.0, 0.0, 0.0, -1.0), (2.0, 0.0, 0.0, 1.0), (3.0, 0, 0, 0)],
    )
    out = tmp_path / "out"
    assert cli.main(["sim", "--no-plots", "--trajectory", str(route), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "minus.csv: row 2: speed -1 m/s runs against the forward leg" in err
    assert "speed 0" not in err


def test_publish_trajectory_refuses_the_file_sim_refuses_with_the_same_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: ``publish-trajectory`` read a file by the gateway's rule only and sent a plan
    that comes to rest half way, on which the car would wait for ever (the file is re-sent as
    it is); ``sim --trajectory`` refused it. Both read a file by one rule now (before any
    session opens)."""
    speeds = [0.3, 0.6, 0.8, 1.0, 1.0, 1.0, 0.6, 0.3, 0.0, 0.3, 0.6, 0.8, 1.0, 1.0, 0.6, 0.3, 0.0]
    midstop = _write(
        tmp_path / "midstop.csv", [(0.5 * i, 0.0, 0.0, v) for i, v in enumerate(speeds)]
    )
    config = tmp_path / "z.yaml"
    config.write_text("{}\n", encoding="utf-8")
    out = tmp_path / "out"
    assert cli.main(["sim", "--no-plots", "--trajectory", str(midstop), "--out", str(out)]) == 1
    sim_err = capsys.readouterr().err
    publish = ["publish-trajectory", str(midstop), "--config", str(config), "--count", "1"]
    assert cli.main([*publish, "--wait", "0"]) == 1
    out_text, publish_err = capsys.readouterr()
    assert "published" not in out_text
    reason = "midstop.csv: row 9: the plan comes to rest here, before the end of its forward leg"
    assert reason in sim_err and reason in publish_err
    assert publish_err.strip().splitlines() == sim_err.strip().splitlines()


def test_sim_refuses_at_load_what_the_gateway_would_refuse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: a plan too fast for the safety gate, or over the transport's point limit,
    was loaded, then refused at engage (the row counted without the file's blank lines), and
    the run went on for its whole time budget before exiting 1."""
    rows = [(0.5 * i, 0.0, 0.0, 4.5 if i == 6 else 1.0) for i in range(12)] + [(6.0, 0, 0, 0)]
    lines = ["x,y,heading,speed", ""] + [",".join(map(str, r)) for r in rows]
    fast = tmp_path / "fast.csv"
    fast.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "out"
    assert cli.main(["sim", "--no-plots", "--trajectory", str(fast), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    # row 1 is the line after the header, blank lines counted: line 9
    assert "fast.csv: row 8: speed 4.50 m/s above the maneuver limit 3 m/s" in err
    many = _write(tmp_path / "many.csv", [(0.1 * i, 0.0, 0.0, 1.0) for i in range(30)])
    args = ["sim", "--no-plots", "--trajectory", str(many), "--set", "zenoh.max_plan_points=20"]
    assert cli.main([*args, "--out", str(out)]) == 1
    assert "many.csv: 30 waypoints, at most 20 (zenoh.max_plan_points)" in capsys.readouterr().err
    assert not (out / "metrics.json").exists()
    # publish-trajectory neither sends a plan the gateway would drop (before any session opens)
    config = tmp_path / "z.yaml"
    config.write_text("zenoh: {max_plan_points: 20}\n", encoding="utf-8")
    assert cli.main(["publish-trajectory", str(many), "--config", str(config)]) == 1
    assert "many.csv: 30 waypoints, at most 20" in capsys.readouterr().err


def test_trace_csv_keeps_map_coordinates_to_the_millimetre(tmp_path: Path) -> None:
    """Old code: six significant digits, a metre in x and 10 m in y at UTM coordinates."""
    x0, y0 = 351234.567, 5601234.321
    n = 41
    rows = [(x0 + 0.5 * i, y0, 0.0, 0.0 if i in (0, n - 1) else 1.0) for i in range(n)]
    route = _write(tmp_path / "utm.csv", rows)
    out = tmp_path / "out"
    assert cli.main(["sim", "--no-plots", "--trajectory", str(route), "--out", str(out)]) == 0
    lines = (out / "trace.csv").read_text().splitlines()[1:]
    xy = np.array([[float(v) for v in line.split(",")[1:3]] for line in lines])
    assert xy[0] == pytest.approx([x0, y0], abs=1e-3)
    assert len(np.unique(xy[:, 0])) > 500  # the car's every step shows, not 1 m steps
    assert math.hypot(*(xy[-1] - [x0 + 20.0, y0])) < 0.1
