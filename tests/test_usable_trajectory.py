"""Issue 13: one rule for a usable trajectory — transport, engage check and controllers.

Old code: the transport needed ≥ 1 point, the watchdog (engage) ≥ 2, the controller ≥ 4 and no
repeated point; an Autoware plan with overlapping points was accepted at engage and then
refused by the controller ("controller: bad-trajectory"), its reason never shown.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.control.baselines import PurePursuit, PurePursuitConfig
from leafgate.control.mpc import MpcController
from leafgate.control.reference import remove_overlap_points, trajectory_problem
from leafgate.gateway import watchdog
from leafgate.messages import GatewayState, OperatorRequest, Pose, Trajectory
from leafgate.runtime import node
from tests.test_gateway_core import PERIOD, Rig


def _line(n: int, spacing: float = 0.5) -> Trajectory:
    x = spacing * np.arange(n, dtype=np.float64)
    return Trajectory(x=x, y=np.zeros(n), heading=np.zeros(n), speed=np.ones(n))


def _with_overlaps(traj: Trajectory, at: list[int], gap: float = 0.004) -> Trajectory:
    """``traj`` with a second waypoint ``gap`` m after each waypoint in ``at`` (as planners
    emit them at a stop point or where two path pieces join)."""
    keep = np.repeat(np.arange(len(traj)), [2 if i in at else 1 for i in range(len(traj))])
    x = traj.x[keep].copy()
    dup = np.flatnonzero(np.diff(keep) == 0) + 1
    x[dup] += gap
    return Trajectory(x=x, y=traj.y[keep], heading=traj.heading[keep], speed=traj.speed[keep])


def _arc(radius: float = 30.0, n: int = 30, spacing: float = 0.5) -> Trajectory:
    """A left turn of ``radius`` m, the vehicle's heading along it, in radians."""
    heading = spacing / radius * np.arange(n)
    return Trajectory(
        x=radius * np.sin(heading),
        y=radius * (1.0 - np.cos(heading)),
        heading=heading,
        speed=np.ones(n),
    )


def _reversed(traj: Trajectory, tangent: bool = False) -> Trajectory:
    """``traj``'s waypoints driven in reverse: the vehicle faces away from where it moves (or,
    ``tangent``, the heading is the way it moves, as a path's tangent is)."""
    heading = traj.heading if tangent else traj.heading + math.pi
    return Trajectory(x=traj.x, y=traj.y, heading=heading, speed=-traj.speed)


CASES = {
    "one point": _line(1),
    "two points": _line(2),
    "three points": _line(3),
    "four points": _line(4),
    "a NaN": Trajectory(
        x=[0.0, 0.5, math.nan, 1.5], y=[0.0] * 4, heading=[0.0] * 4, speed=[1.0] * 4
    ),
    "overlapping points": _with_overlaps(_line(20), [0, 7, 19]),
    "exact repeats": _with_overlaps(_line(20), [5, 6], gap=0.0),
    "four points, one overlapping": _with_overlaps(_line(3), [2]),
    "a huge finite x": Trajectory(
        x=[0.0, 1e300, 1.0, 1.5], y=[0.0] * 4, heading=[0.0] * 4, speed=[1.0] * 4
    ),
    "an arc": _arc(),
    "an arc, headings in degrees": Trajectory(
        x=_arc().x, y=_arc().y, heading=np.degrees(_arc().heading), speed=_arc().speed
    ),
    "an arc in reverse": _reversed(_arc()),
    "an arc in reverse, the path's tangent as heading": _reversed(_arc(), tangent=True),
    "a sparse arc (7 m between waypoints)": _arc(n=8, spacing=7.0),
}


def _controller_accepts(traj: Trajectory) -> bool:
    out = MpcController(MpcConfig(), VehicleConfig(), PERIOD).step(
        Pose(0.0, 0.0, 0.0, 0.0), 0.0, traj
    )
    return not out.status.startswith("bad-trajectory")


@pytest.mark.parametrize("name", sorted(CASES))
def test_transport_engage_check_and_controller_use_one_rule(name: str) -> None:
    traj = CASES[name]
    usable = trajectory_problem(traj) is None
    assert node.trajectory_is_valid(traj) == usable
    assert watchdog.trajectory_is_valid(traj) == usable
    assert _controller_accepts(traj) == usable


def test_overlapping_points_are_removed_not_refused() -> None:
    traj = CASES["overlapping points"]
    assert trajectory_problem(traj) is None
    cleaned = remove_overlap_points(traj)
    assert len(cleaned) == 20
    assert float(np.hypot(np.diff(cleaned.x), np.diff(cleaned.y)).min()) >= 0.01
    assert remove_overlap_points(_line(5)) is not None


def test_the_reason_names_the_problem() -> None:
    assert trajectory_problem(_line(3)) == ("trajectory: 3 waypoint(s), at least 4 are needed")
    assert trajectory_problem(CASES["four points, one overlapping"]) == (
        "trajectory: 3 waypoint(s) (1 overlapping removed), at least 4 are needed"
    )
    assert trajectory_problem(CASES["a NaN"]) == "trajectory: row 3: x is not finite"
    # old code: accepted, engaged, and numpy overflowed in the reference's arithmetic
    assert trajectory_problem(CASES["a huge finite x"]) == (
        "trajectory: row 2: x 1e+300 m is beyond ±1e+08 m"
    )


def test_headings_that_disagree_with_the_path_are_refused_naming_the_row() -> None:
    """Old code: an arc whose headings were in degrees was engaged; the car left the plan and
    the off-the-plan watchdog stopped it 2 m off, naming a 0.5 m turn the path does not have."""
    assert trajectory_problem(CASES["an arc"]) is None
    assert trajectory_problem(CASES["an arc in reverse"]) is None
    assert trajectory_problem(CASES["a sparse arc (7 m between waypoints)"]) is None
    degrees = trajectory_problem(CASES["an arc, headings in degrees"])
    assert degrees is not None and degrees.startswith("trajectory: row 2: heading 0.955 rad is")
    assert degrees.endswith(
        "driven forward; headings are the vehicle's, in radians, and these look like degrees "
        "(read as degrees they run along the path; up to 27.69)"
    )
    tangent = trajectory_problem(CASES["an arc in reverse, the path's tangent as heading"])
    assert tangent is not None and tangent.startswith("trajectory: row 1: heading 0.000 rad is")
    assert "180° off the way the path runs from it to the next waypoint, driven backward" in (
        tangent
    )


@pytest.mark.parametrize("kind", ["mpc", "pure-pursuit"])
def test_a_plan_with_overlapping_points_is_driven(kind: str) -> None:
    traj = _with_overlaps(_line(30), [0, 10, 29])
    ctrl = (
        MpcController(MpcConfig(), VehicleConfig(), PERIOD)
        if kind == "mpc"
        else PurePursuit(PurePursuitConfig(), VehicleConfig(), PERIOD)
    )
    out = ctrl.step(Pose(0.0, 0.0, 0.0, 0.5), 0.0, traj)
    assert out.converged and not out.status.startswith("bad-trajectory")
    assert out.route_length == pytest.approx(14.5)


def test_engage_with_an_unusable_plan_is_refused_with_the_controllers_reason() -> None:
    """Old code: ``{"accepted": true}`` and the engagement ended at once with
    "controller: bad-trajectory"."""
    ctrl = MpcController(MpcConfig(), VehicleConfig(), PERIOD)
    rig = Rig(controller=ctrl, trajectory=_line(3))  # type: ignore[arg-type]
    rig.run(0.1)
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and not reply.accepted
    assert "3 waypoint(s), at least 4 are needed" in reply.reason
    assert rig.state == GatewayState.STANDBY


def test_engage_with_overlapping_points_starts_and_drives() -> None:
    ctrl = MpcController(MpcConfig(), VehicleConfig(), PERIOD)
    rig = Rig(controller=ctrl, trajectory=_with_overlaps(_line(30), [0, 3, 29]))  # type: ignore[arg-type]
    rig.engage()
    rig.run(1.0)
    assert rig.state == GatewayState.ENGAGED, rig.gw.machine.reason


def test_headings_in_degrees_that_flip_name_the_first_row_and_say_radians() -> None:
    """Old code: a 12 m arc of 10 m radius in degrees (2.9° a waypoint, a "flip" of 164° as
    radians at every step) was refused at the step whose flip was largest, row 22 or wherever
    rounding put it, and the hint that headings are radians never showed."""
    arc = _arc(radius=10.0, n=25)
    degrees = Trajectory(x=arc.x, y=arc.y, heading=np.degrees(arc.heading), speed=arc.speed)
    assert trajectory_problem(degrees) == (
        "trajectory: row 2: heading turns 164° from the waypoint before (a flip); headings are "
        "the vehicle's, in radians, and these look like degrees (read as degrees they run along "
        "the path; up to 68.75)"
    )
    # flips the plan has twice, headings in range: the first is named, not the larger
    turned = arc.heading + np.select([np.arange(25) >= 15, np.arange(25) >= 7], [-0.9, 2.0])
    flipped = Trajectory(x=arc.x, y=arc.y, heading=turned, speed=arc.speed)
    assert trajectory_problem(flipped) == (
        "trajectory: row 8: heading turns 117° from the waypoint before (a flip)"
    )


def test_unwrapped_headings_in_radians_with_one_flip_are_not_called_degrees() -> None:
    """Reported from outside: headings past 2π (PythonRobotics' ``smooth_yaw`` unwraps them)
    with one real flip read "these look like degrees": the size decided. Now the geometry does:
    read as degrees, 6.5° and 8.4° are near the path's 12°, but read as radians every chord but
    the flip's runs along them."""
    x = np.arange(6) * 0.9766
    y = np.arange(6) * 0.2151  # the path runs at 0.217 rad = 6.5 − 2π
    heading = np.array([6.5, 6.5, 6.5, 8.4, 6.5, 6.5])
    traj = Trajectory(x=x, y=y, heading=heading, speed=np.array([1.0, 1, 1, 1, 1, 0]))
    assert trajectory_problem(traj) == (
        "trajectory: row 4: heading turns 109° from the waypoint before (a flip)"
    )
