"""Route shapes for the controller tests (issue 13): built from straights and arcs.

Waypoints 0.5 m apart with the vehicle heading and a signed speed (trapezoid, zero at each
segment's end), as a planner sends them. Shared by the tests; not a route library.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from leafgate.messages import FloatArray, Pose, Trajectory
from leafgate.sim.scenarios import Scenario

SPACING = 0.5  # m

Piece = tuple[float, float]  # (length m, curvature 1/m): a straight has curvature 0


def polyline(
    pieces: Sequence[Piece], x0: float = 0.0, y0: float = 0.0, h0: float = 0.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Points 0.5 m apart (exactly on the arcs) and the travel direction at each."""
    xs, ys, hs = [x0], [y0], [h0]
    x, y, h = x0, y0, h0
    carry = 0.0  # m of the current spacing already travelled
    for length, kappa in pieces:
        s = 0.0
        while s < length - 1e-9:
            ds = min(SPACING - carry, length - s)
            if kappa == 0.0:
                x += ds * math.cos(h)
                y += ds * math.sin(h)
            else:
                h1 = h + kappa * ds
                x += (math.sin(h1) - math.sin(h)) / kappa
                y += (math.cos(h) - math.cos(h1)) / kappa
                h = h1
            s += ds
            carry += ds
            if carry >= SPACING - 1e-9:
                xs.append(x)
                ys.append(y)
                hs.append(h)
                carry = 0.0
    if carry > 0.05:  # keep the exact end point
        xs.append(x)
        ys.append(y)
        hs.append(h)
    return np.array(xs), np.array(ys), np.array(hs)


def profile(n: int, v_max: float, accel: float = 0.5) -> FloatArray:
    """Speed magnitudes of ``n`` waypoints: pull away from 0.3 m/s, cruise, stop at the end."""
    s = SPACING * np.arange(n, dtype=np.float64)
    up = np.sqrt(0.09 + 2.0 * accel * s)
    down = np.sqrt(np.maximum(0.0, 2.0 * accel * (s[-1] - s)))
    return np.minimum(np.minimum(up, down), v_max)


def leg(pieces: Sequence[Piece], v_max: float = 1.0, pose: Pose | None = None) -> Trajectory:
    """One forward leg from ``pose`` (default the origin, heading +x)."""
    p = pose or Pose(0.0, 0.0, 0.0, 0.0)
    x, y, h = polyline(pieces, p.x, p.y, p.heading)
    return Trajectory(x=x, y=y, heading=h, speed=profile(x.size, v_max))


def with_reverse(forward: Trajectory, reverse_pieces: Sequence[Piece] | None, v: float = 0.8):
    """``forward``, a cusp at its end, then a reverse leg: along ``reverse_pieces`` (curvature
    of the reversing path, travel frame) or, with None, back over the forward leg's own
    waypoints (the reverse leg retraces the forward one exactly)."""
    if reverse_pieces is None:
        x, y, h = forward.x[::-1], forward.y[::-1], forward.heading[::-1]
    else:
        end = Pose(
            float(forward.x[-1]), float(forward.y[-1]), float(forward.heading[-1]) + math.pi, 0
        )
        x, y, travel = polyline(reverse_pieces, end.x, end.y, end.heading)
        h = travel - math.pi  # the car faces away from its travel
    speed = -profile(x.size, v)
    return Trajectory(
        x=np.concatenate((forward.x, x[1:])),
        y=np.concatenate((forward.y, y[1:])),
        heading=np.concatenate((forward.heading, np.unwrap(h[1:]))),
        speed=np.concatenate((forward.speed, speed[1:])),
    )


def scenario(
    name: str, traj: Trajectory, start: Pose | None = None, slack: float = 25.0
) -> Scenario:
    """A scenario starting at rest on the first waypoint, with time to drive it at 0.5 m/s."""
    length = float(np.hypot(np.diff(traj.x), np.diff(traj.y)).sum())
    if start is None:
        start = Pose(float(traj.x[0]), float(traj.y[0]), float(traj.heading[0]), 0.0)
    return Scenario(name, name, traj, start, duration=2.0 * length + slack)


R_MIN = 2.70 / math.tan(math.radians(30.0))  # m, the MPC's turning radius (≈ 4.7 m)


def closed_loop() -> Trajectory:
    """A 10 m × 10 m rounded square (corners r = 6 m) that ends on its start."""
    r = 6.0
    pieces = [(10.0, 0.0), (r * math.pi / 2, 1 / r)] * 4
    return leg(pieces)


def figure_eight() -> Trajectory:
    """Two 8 m circles, left then right, crossing at the start: ≈ 100 m."""
    r = 8.0
    return leg([(2 * math.pi * r, 1 / r), (2 * math.pi * r, -1 / r), (3.0, 0.0)])


def u_turn_short() -> Trajectory:
    """20 m out, a U-turn of 6 m radius, 15 m back: ends 5 m short of its start, 12 m aside."""
    return leg([(20.0, 0.0), (6.0 * math.pi, 1 / 6.0), (15.0, 0.0)])


def corner() -> Trajectory:
    """10 m, a 90° corner of 5 m radius, 10 m."""
    return leg([(10.0, 0.0), (5.0 * math.pi / 2, 1 / 5.0), (10.0, 0.0)])


def switch_back() -> Trajectory:
    """25 m forward through a U-turn hairpin (r = 6 m), a cusp, 15 m in reverse."""
    fwd = leg([(8.0, 0.0), (6.0 * math.pi, 1 / 6.0), (5.0, 0.0)])
    return with_reverse(fwd, [(15.0, 0.0)])


def retraced_cusp() -> Trajectory:
    """15 m forward on a gentle curve, then back over exactly the same waypoints."""
    return with_reverse(leg([(5.0, 0.0), (10.0, 1 / 20.0)]), None)


def infeasible_hairpin() -> Trajectory:
    """A 180° hairpin of 2 m radius — far tighter than the car turns (≈ 4.7 m) — at 1 m/s."""
    return leg([(8.0, 0.0), (2.0 * math.pi, 1 / 2.0), (8.0, 0.0)])
