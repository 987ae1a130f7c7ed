"""``leafgate sim`` never reports progress the car did not make.

An outside tester found ``progress_m`` 51 m for a car that never moved: its start projected 51 m
along the route, and the progress was the farthest projection. Now ``start_progress_m`` says
where the start projects (by the controller's rule for where a drive starts) and
``progress_m`` is how far along the route the car got from there; a run that left nothing to
drive is not finished.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from leafgate import cli
from leafgate.messages import Trajectory
from leafgate.sim.metrics import tracking_metrics
from leafgate.sim.runner import FINISH_TOLERANCE, finish_verdict
from tests.routes import closed_loop, figure_eight, leg

# 6 m straight, 90° to the left of 6 m radius, 4 m straight: 19.4 m, waypoints 0.5 m apart
L_PIECES = [(6.0, 0.0), (6.0 * math.pi / 2, 1.0 / 6.0), (4.0, 0.0)]
L_LENGTH = 10.0 + 3.0 * math.pi  # m


def _write_csv(path: Path, traj: Trajectory) -> Path:
    rows = zip(traj.x, traj.y, traj.heading, traj.speed, strict=True)
    lines = ["x,y,heading,speed"] + [f"{a:.6f},{b:.6f},{c:.6f},{d:.6f}" for a, b, c, d in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _standing(traj: Trajectory, x: float, y: float, heading: float, n: int = 50) -> dict:
    """The metrics of a car that stood at ``(x, y)`` for ``n`` control ticks."""
    t = np.arange(n) * 0.02
    return tracking_metrics(
        traj, t, np.full(n, x), np.full(n, y), np.full(n, heading), np.zeros(n), np.zeros(n)
    )


def test_a_car_standing_mid_route_made_no_progress() -> None:
    """Old code: 12 m of progress on this 20 m straight (the start's projection)."""
    traj = leg([(20.0, 0.0)])
    m = _standing(traj, 12.0, 0.3, 0.0)
    assert m["progress_m"] == 0.0
    assert m["start_progress_m"] == pytest.approx(12.0, abs=1e-9)
    assert m["route_length_m"] == pytest.approx(20.0)
    assert m["lateral_error_max_m"] == pytest.approx(0.3)  # measured where the car stands


def test_a_start_on_a_later_pass_of_the_same_place_projects_on_the_first() -> None:
    """A closed loop ends on its start, a figure-eight passes its start again half-way: a car
    standing 0.3 m behind the start, nearer a waypoint of the later pass than the first
    waypoint, starts at the route's beginning (the controller's rule), not 77 or 50 m along."""
    for traj in (closed_loop(), figure_eight()):
        h = float(traj.heading[0])
        x, y = float(traj.x[0]) - 0.3 * math.cos(h), float(traj.y[0]) - 0.3 * math.sin(h)
        m = _standing(traj, x, y, h)
        assert m["progress_m"] == 0.0
        assert m["start_progress_m"] == pytest.approx(0.0, abs=1e-9)


def test_a_start_within_the_tolerance_of_the_end_is_not_finished() -> None:
    """The gateway reports the end reached for a car that stood on it: no drive was checked."""
    metrics = {
        "route_length_m": 20.0,
        "start_progress_m": 20.0 - FINISH_TOLERANCE,
        "progress_m": 0.0,
        "final_position_error_m": FINISH_TOLERANCE,
    }
    finished, reason = finish_verdict(metrics, True, "")
    assert not finished
    assert "nothing was left to drive" in reason and "at 19.5 of 20.0 m" in reason
    # just beyond it, the car must drive what is left
    drove = {**metrics, "start_progress_m": 19.4, "progress_m": 0.6, "final_position_error_m": 0.0}
    assert finish_verdict(drove, True, "") == (True, "")
    stood = {**drove, "progress_m": 0.0, "final_position_error_m": 0.6}
    assert finish_verdict(stood, True, "")[0] is False


def test_a_mid_route_start_is_judged_on_the_route_left_to_drive() -> None:
    metrics = {
        "route_length_m": 60.0,
        "start_progress_m": 30.0,
        "progress_m": 20.0,
        "final_position_error_m": 10.0,
    }
    finished, reason = finish_verdict(metrics, True, "")
    assert not finished
    assert "the car got 20.0 of 30.0 m along the route from its start at 30.0 m" in reason
    done = {**metrics, "progress_m": 29.7, "final_position_error_m": 0.05}
    assert finish_verdict(done, True, "") == (True, "")


def _sim(route: Path, out: Path, *args: str) -> tuple[int, dict]:
    rc = cli.main(["sim", "--no-plots", "--trajectory", str(route), "--out", str(out), *args])
    return rc, json.loads((out / "metrics.json").read_text(encoding="utf-8"))


@pytest.mark.slow
def test_sim_from_the_first_waypoint_progresses_the_whole_route(tmp_path: Path) -> None:
    route = _write_csv(tmp_path / "L.csv", leg(L_PIECES))
    rc, m = _sim(route, tmp_path / "out")
    assert rc == 0 and m["finished"] is True
    assert m["route_length_m"] == pytest.approx(L_LENGTH, abs=0.01)
    assert m["start_progress_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["progress_m"] == pytest.approx(L_LENGTH, abs=0.1)


@pytest.mark.slow
def test_sim_from_mid_route_counts_only_what_the_car_drove(tmp_path: Path) -> None:
    """Old code: progress 19.4 m, the whole route, for a car that drove the last 13.4 m."""
    route = _write_csv(tmp_path / "L.csv", leg(L_PIECES))
    rc, m = _sim(route, tmp_path / "out", "--start", "6,0,0")  # where the bend begins
    assert rc == 0 and m["finished"] is True
    assert m["progress_m"] == pytest.approx(L_LENGTH - 6.0, abs=0.1)
    assert m["start_progress_m"] == pytest.approx(6.0, abs=0.01)


@pytest.mark.slow
def test_sim_with_a_car_that_never_moved_reports_no_progress(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: 8 m of progress for a start 3 m beside the route that the gateway refused."""
    route = _write_csv(tmp_path / "straight.csv", leg([(12.0, 0.0)]))
    rc, m = _sim(route, tmp_path / "out", "--start", "8,3,0")
    assert rc == 1 and m["finished"] is False
    assert "the gateway never engaged" in capsys.readouterr().err
    assert m["progress_m"] == 0.0
    assert m["start_progress_m"] == pytest.approx(8.0, abs=0.01)


@pytest.mark.slow
def test_sim_started_on_the_routes_end_is_not_finished(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: finished, exit 0, 12 m of progress: the gateway engaged, found the car on the
    end at rest and reported the end reached; the car never moved."""
    route = _write_csv(tmp_path / "straight.csv", leg([(12.0, 0.0)]))
    rc, m = _sim(route, tmp_path / "out", "--start", "12,0,0")
    err = capsys.readouterr().err
    assert rc == 1 and m["finished"] is False
    assert "nothing was left to drive" in err and "nothing was left" in m["not_finished_reason"]
    assert m["progress_m"] == pytest.approx(0.0, abs=0.01)
    assert m["start_progress_m"] == pytest.approx(12.0, abs=0.01)
