"""Built-in scenarios and the path-error metrics every controller is judged by."""

from __future__ import annotations

import numpy as np
import pytest

from leafgate.messages import Trajectory
from leafgate.sim.metrics import path_errors, sign_changes
from leafgate.sim.scenarios import SCENARIOS, get_scenario


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_waypoints_equidistant_and_stop_at_end(name: str) -> None:
    sc = get_scenario(name)
    traj = sc.trajectory
    spacing = np.hypot(np.diff(traj.x), np.diff(traj.y))
    assert np.all(spacing > 0.25) and np.all(spacing <= 1.0)  # paper: 0.5–1.0 m apart
    assert traj.speed[-1] == 0.0
    assert sc.start.speed == 0.0
    assert (sc.start.x, sc.start.y) == (traj.x[0], traj.y[0])


def test_s_curve_is_the_papers_maneuver() -> None:
    traj = get_scenario("s-curve").trajectory
    assert traj.y[-1] - traj.y[0] == pytest.approx(3.5)
    assert np.max(traj.speed) == pytest.approx(2.0)
    assert np.median(np.hypot(np.diff(traj.x), np.diff(traj.y))) == pytest.approx(0.5, abs=0.01)


def test_unknown_scenario_lists_known_ones() -> None:
    with pytest.raises(KeyError, match="known: "):
        get_scenario("hairpin")


def test_lateral_error_is_signed_distance_to_polyline() -> None:
    traj = Trajectory(x=[0.0, 1.0, 2.0, 3.0], y=[0.0] * 4, heading=[0.0] * 4, speed=[1.0] * 4)
    err = path_errors(
        traj, np.array([0.5, 2.5, 1.0]), np.array([0.2, -0.3, 0.0]), np.array([0.1, 0.0, -0.2])
    )
    np.testing.assert_allclose(err.lateral, [0.2, -0.3, 0.0])
    np.testing.assert_allclose(err.heading, [0.1, 0.0, -0.2])


def test_sign_changes_ignores_deadband() -> None:
    rate = np.array([0.1, 0.2, -0.1, 0.005, -0.005, 0.3, 0.2])
    assert sign_changes(rate, deadband=0.01) == 2


def test_projection_follows_a_path_that_doubles_back() -> None:
    """Forward along y = 0, cusp, then reverse along y = 0.4 back over the same x: the
    projection must stay on the segment being driven, not jump to the nearer other leg."""
    xs = np.concatenate([np.arange(0.0, 5.01, 0.5), np.arange(5.0, -0.01, -0.5)])
    ys = np.concatenate([np.zeros(11), np.linspace(0.0, 0.4, 3), np.full(8, 0.4)])
    traj = Trajectory(
        x=xs, y=ys, heading=np.zeros(22), speed=np.concatenate([np.ones(11), -np.ones(11)])
    )
    # Out on the first leg 0.25 m to its left (0.15 m from the second leg, which is nearer),
    # then back along the second leg 0.15 m to its right.
    x = np.concatenate([np.linspace(0.2, 4.8, 20), np.linspace(4.0, 0.5, 20)])
    y = np.concatenate([np.full(20, 0.25), np.full(20, 0.25)])
    speed = np.concatenate([np.full(20, 1.0), np.full(20, -1.0)])
    err = path_errors(traj, x, y, np.zeros(40), speed)
    np.testing.assert_allclose(err.lateral[:20], 0.25, atol=1e-9)  # left of the first leg
    np.testing.assert_allclose(np.abs(err.lateral[25:]), 0.15, atol=1e-9)  # on the second leg
    # the plan stands at its cusp (5, 0): on the last chord into it, from x = 4.5, the planned
    # speed falls to zero
    np.testing.assert_allclose(err.speed_ref[:20], np.minimum(1.0, (5.0 - x[:20]) / 0.5))
    np.testing.assert_allclose(err.speed_ref[25:], -1.0)


def test_projection_does_not_skip_the_move_between_two_reverse_moves() -> None:
    """Parallel parking: reverse, a 1.15 m pull forward, reverse 0.65 m into the slot. The last
    move lies beside the end of the first, so a car still reversing at the end of the first
    move, a little off it, is nearer the last one: the projection stays on the first move (it
    gets to the last only through the forward one), and the planned speed there is the first
    move's, not the goal's 0 (which judged a reversing car 0.5 m/s too fast)."""
    traj = get_scenario("parallel-park").trajectory
    first_end = int(np.flatnonzero(np.diff(np.sign(traj.speed)) != 0)[0])  # the first cusp
    n = first_end + 1
    # along the first move, 0.15 m to the side of its waypoints (towards the last move), reversing
    x = traj.x[:n] + 0.15 * np.sin(traj.heading[:n])
    y = traj.y[:n] - 0.15 * np.cos(traj.heading[:n])
    err = path_errors(traj, x, y, traj.heading[:n], np.full(n, -0.5))
    first_length = float(np.sum(np.hypot(np.diff(traj.x[:n]), np.diff(traj.y[:n]))))
    assert err.progress.max() <= first_length + 1e-9
    assert np.all(err.speed_ref[: n - 4] <= -0.2)  # reversing as planned, not at rest


def test_the_planned_speed_is_zero_at_a_cusp_without_a_waypoint_at_rest() -> None:
    """PythonRobotics' speeds (+v up to the waypoint before the cusp, −v from the cusp on) read
    linearly would cross zero half-way along the chord into the cusp, and a car braking to it
    as planned read as overspeeding; the plan stands at its cusp, as the controller's does."""
    x = np.array([0.0, 1.0, 2.0, 3.0, 2.0, 1.0, 0.0])
    n = len(x)
    speed = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0, 0.0])
    traj = Trajectory(x, np.zeros(n), np.zeros(n), speed)
    errors = path_errors(traj, np.array([2.5, 3.0]), np.zeros(2), np.zeros(2))
    assert errors.speed_ref.tolist() == [0.5, 0.0]  # read linearly: [0.0, -1.0]
