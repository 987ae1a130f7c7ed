"""Tracking metrics of a closed-loop run, computed from the true (plant) states.

Errors are measured against the reference polyline, not against the waypoint the controller
happened to pick, so that every controller is judged the same way.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from leafgate.control.reference import (
    chord_directions,
    remove_overlap_points,
    split_segments,
    start_waypoint,
    tightest_turn,
)
from leafgate.geometry import wrap_angle
from leafgate.messages import FloatArray, Trajectory
from leafgate.sim.scenarios import clearance

STEER_RATE_DEADBAND = 0.01  # rad/s, rate changes smaller than this are not a sign change


@dataclass(frozen=True)
class PathErrors:
    lateral: FloatArray  # m, signed cross-track error (left of the path positive)
    heading: FloatArray  # rad, wrapped to (−π, π]
    speed_ref: FloatArray  # m/s, reference speed at the projection
    progress: FloatArray  # m, arc length of the projection along the route


PROJECTION_WINDOW = 40  # segments ahead the projection may move per sample (20 m at 0.5 m)
PROJECTION_SLACK = 2  # segments it may move back (noise around a waypoint)
DIRECTION_SPEED = 0.05  # m/s, above this the sign of the speed says which way the car drives


def _segment_distances(
    traj: Trajectory, x: float, y: float, lo: int, hi: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Squared distance, projection parameter and error vector to segments ``lo..hi-1``."""
    ax, ay = traj.x[lo:hi], traj.y[lo:hi]
    dx, dy = traj.x[lo + 1 : hi + 1] - ax, traj.y[lo + 1 : hi + 1] - ay
    rx, ry = x - ax, y - ay
    # A zero-length segment (a repeated point) projects onto its start.
    t = np.clip((rx * dx + ry * dy) / np.maximum(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
    ex, ey = rx - t * dx, ry - t * dy
    return ex * ex + ey * ey, t, ex, ey


class Projector:
    """Follows a vehicle along a reference polyline in time order: its projection, arc length.

    The projection starts at the trajectory's first segment, or, placed with :meth:`start_at`,
    where the controller starts a car on a new plan (a start mid-route is not a drive from the
    first waypoint, nor a jump to a later pass of the same place); it then only
    moves along the path (a little back for noise, up to a window ahead): routes double back on
    themselves at cusps, cross themselves and close on their start, and a plain nearest-segment
    search would jump to another part of the route. With a speed given, only segments planned
    in the vehicle's direction of travel are candidates (the two legs of a cusp have opposite
    speed signs). Nor does it skip a move: it reaches the move after next only through the next
    one (a parking maneuver's two reverse moves lie side by side, the forward move between them
    is short, and a car reversing off the first one is not on the last).
    """

    def __init__(self, traj: Trajectory) -> None:
        self.traj = traj
        self.n_seg = len(traj) - 1
        self.seg_dir = chord_directions(traj)  # the planned direction of each segment
        gaps = np.hypot(np.diff(traj.x), np.diff(traj.y))
        self.s = np.concatenate(([0.0], np.cumsum(gaps)))  # m, arc length at each waypoint
        # the move of each segment: a new one where the planned direction changes
        self.move = np.concatenate(([0], np.cumsum(self.seg_dir[1:] != self.seg_dir[:-1])))
        self.k = 0  # the segment of the last projection
        self.moving_dir = 0.0

    @property
    def length(self) -> float:
        """The route's length, m."""
        return float(self.s[-1])

    def start_at(self, x: float, y: float, heading: float) -> None:
        """Place the projection where a car at ``(x, y)``, heading ``heading`` (rad), starts on
        the route: the controller's rule (:func:`~leafgate.control.reference.start_waypoint`,
        on the first direction segment)."""
        i = start_waypoint(self.traj, split_segments(self.traj)[0], x, y, heading)
        self.k = min(i, self.n_seg - 1)

    def project(
        self, x: float, y: float, speed: float | None = None
    ) -> tuple[int, float, float, float, float]:
        """The next sample: segment ``k``, parameter ``t`` on it, squared distance, error."""
        lo, hi = max(0, self.k - PROJECTION_SLACK), min(self.n_seg, self.k + PROJECTION_WINDOW)
        dist2, t, ex, ey = _segment_distances(self.traj, x, y, lo, hi)
        dist2 = np.where(self.move[lo:hi] > self.move[self.k] + 1, np.inf, dist2)
        if speed is not None:
            if abs(speed) > DIRECTION_SPEED:
                self.moving_dir = math.copysign(1.0, speed)
            other_way = self.seg_dir[lo:hi] == -self.moving_dir
            if self.moving_dir != 0.0 and not np.all(other_way):
                dist2 = np.where(other_way, np.inf, dist2)
        j = int(np.argmin(dist2))
        self.k = lo + j
        return self.k, float(t[j]), float(dist2[j]), float(ex[j]), float(ey[j])

    def arc_length(self, k: int, t: float) -> float:
        """Arc length of the point ``t`` along segment ``k``, m."""
        return float(self.s[k] + t * (self.s[k + 1] - self.s[k]))


def path_errors(
    traj: Trajectory,
    x: FloatArray,
    y: FloatArray,
    heading: FloatArray,
    speed: FloatArray | None = None,
) -> PathErrors:
    """Project each sample onto the reference polyline, following the path in time order
    (:class:`Projector`) from where the first sample starts on it.

    For reversing segments the heading reference is the vehicle heading stored in the
    trajectory, so the same formula holds in both directions.
    """
    proj = Projector(traj)
    if x.shape[0]:
        proj.start_at(float(x[0]), float(y[0]), float(heading[0]))
    # the planned speed along each segment, and zero at a cusp (where the car stands) also
    # when the plan gives no waypoint at rest there (the same rule as the controller's)
    v_from, v_to = traj.speed[:-1].copy(), traj.speed[1:].copy()
    cusps = np.flatnonzero(proj.seg_dir[1:] != proj.seg_dir[:-1]) + 1
    v_to[cusps - 1] = 0.0
    v_from[cusps] = 0.0
    lateral = np.empty(x.shape[0])
    heading_err = np.empty(x.shape[0])
    speed_ref = np.empty(x.shape[0])
    progress = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        k, tk, dist2, ex, ey = proj.project(
            float(x[i]), float(y[i]), None if speed is None else float(speed[i])
        )
        dx, dy = traj.x[k + 1] - traj.x[k], traj.y[k + 1] - traj.y[k]
        cross = dx * ey - dy * ex
        lateral[i] = math.copysign(math.sqrt(dist2), cross) if cross != 0 else 0.0
        ref_heading = traj.heading[k] + tk * float(
            wrap_angle(traj.heading[k + 1] - traj.heading[k])
        )
        heading_err[i] = float(wrap_angle(heading[i] - ref_heading))
        speed_ref[i] = v_from[k] + tk * (v_to[k] - v_from[k])
        progress[i] = proj.arc_length(k, tk)
    return PathErrors(lateral=lateral, heading=heading_err, speed_ref=speed_ref, progress=progress)


def sign_changes(rate: FloatArray, deadband: float = STEER_RATE_DEADBAND) -> int:
    """Count reversals of a rate signal, ignoring excursions inside the deadband."""
    signs = np.sign(rate[np.abs(rate) > deadband])
    return int(np.count_nonzero(np.diff(signs)))


PATH_CURVATURE_RATE_DEADBAND = 2e-3  # 1/m², curvature changes slower than this are no reversal
PATH_TURN_WINDOW = 1.0  # m, the path's curvature is its turn over this much arc length
PATH_CURVATURE_SWING = 2e-3  # 1/m, a smaller change of the curvature is no reversal (0.3° of wheel)


def path_steer_sign_changes(traj: Trajectory) -> int:
    """Reversals of the steering the path itself asks for, over its arc length.

    The steering follows the curvature the vehicle drives, ``direction · dθ/ds`` (reversing,
    the heading turns the other way for the same wheel angle); its reversals are those of the
    curvature's rate. At a cusp the car stands while the wheel turns, so the curvature on
    either side of it counts as one profile. The yardstick for a run's
    ``steer_rate_sign_changes``.

    Measured on the plan the controller drives, without overlapping points
    (:func:`~leafgate.control.reference.remove_overlap_points`), and so that the precision a
    file was written with does not count:

    - the curvature is the turn over :data:`PATH_TURN_WINDOW` of arc length, every half
      window: the headings' rounding errors do not add up over a window, they cancel but at its
      ends. Per waypoint chord, headings written to 4 decimals 0.1 m apart read as 1543
      reversals on a PythonRobotics course that asks for 5;
    - a reversal is a swing of the curvature by at least :data:`PATH_CURVATURE_SWING` between
      two turning points (hysteresis), and a swing counts only if somewhere its rate reaches
      :data:`PATH_CURVATURE_RATE_DEADBAND` (the slow drift of a long bend is no reversal, as
      the run's steering is counted with a rate deadband).

    On the route library, and on 120 generated routes, this gives the counts of the chord by
    chord measure; with 3 decimals at 0.1 m, 7 instead of 5. A heading written to 2 decimals
    (0.6°) is coarser than any of it.
    """
    traj = remove_overlap_points(traj)
    if len(traj) < 2:
        return 0
    gaps = np.hypot(np.diff(traj.x), np.diff(traj.y))
    s = np.concatenate(([0.0], np.cumsum(gaps)))  # m, arc length at each waypoint
    turned = np.concatenate(  # rad, the turn the driven curvature has made by each waypoint
        ([0.0], np.cumsum(chord_directions(traj) * np.asarray(wrap_angle(np.diff(traj.heading)))))
    )
    half = 0.5 * PATH_TURN_WINDOW
    if s[-1] <= PATH_TURN_WINDOW:
        return 0
    grid = np.arange(half, s[-1] - half + 1e-9, half)
    curvature = (np.interp(grid + half, s, turned) - np.interp(grid - half, s, turned)) / (
        PATH_TURN_WINDOW
    )
    signs = [
        math.copysign(1.0, curvature[b] - curvature[a])
        for a, b in itertools.pairwise(_turning_points(curvature, PATH_CURVATURE_SWING))
        if np.max(np.abs(np.diff(curvature[a : b + 1]))) >= PATH_CURVATURE_RATE_DEADBAND * half
    ]
    return int(np.count_nonzero(np.diff(signs))) if len(signs) > 1 else 0


def _turning_points(values: FloatArray, swing: float) -> list[int]:
    """Indices of the extremes between which ``values`` moves by more than ``swing`` (the first
    and the last included): smaller wiggles are not turns."""
    points: list[int] = []
    trend, low, high, extreme = 0, 0, 0, 0
    for j in range(1, values.shape[0]):
        v = values[j]
        if trend == 0:  # no swing yet: from the lowest or the highest value so far
            low = j if v < values[low] else low
            high = j if v > values[high] else high
            if v - values[low] > swing:
                trend, points, extreme = 1, [low], j
            elif values[high] - v > swing:
                trend, points, extreme = -1, [high], j
        elif trend * (v - values[extreme]) >= 0.0:  # on in the same direction
            extreme = j
        elif abs(v - values[extreme]) > swing:  # turned back by more than a wiggle
            points.append(extreme)
            trend, extreme = -trend, j
    if trend:
        points.append(extreme)
    return points


def tracking_metrics(
    traj: Trajectory,
    t: FloatArray,
    x: FloatArray,
    y: FloatArray,
    heading: FloatArray,
    speed: FloatArray,
    steer_angle: FloatArray,
) -> dict[str, Any]:
    """Lateral/heading/speed errors and steering smoothness of a run (true plant states).

    ``start_progress_m`` is where the car's start projects on the route (0 from its first
    waypoint); ``progress_m`` how far along the route the car got from there: the farthest
    projection less the start's, so the part of the route before a start mid-route does not
    count, and a car that never moved made none.
    """
    errors = path_errors(traj, x, y, heading, speed)
    sampled = errors.progress.size > 0
    start_progress = float(errors.progress[0]) if sampled else 0.0
    steer_rate = np.gradient(steer_angle, t) if t.shape[0] > 1 else np.zeros_like(t)
    final_pos = math.hypot(x[-1] - traj.x[-1], y[-1] - traj.y[-1])
    final_heading = float(abs(wrap_angle(heading[-1] - traj.heading[-1])))
    route_length = float(np.sum(np.hypot(np.diff(traj.x), np.diff(traj.y))))
    tightest = tightest_turn(traj)
    return {
        "lateral_error_max_m": float(np.max(np.abs(errors.lateral))),
        "lateral_error_rms_m": float(np.sqrt(np.mean(errors.lateral**2))),
        "heading_error_max_rad": float(np.max(np.abs(errors.heading))),
        "final_position_error_m": final_pos,
        "final_heading_error_rad": final_heading,
        "speed_error_rms_mps": float(np.sqrt(np.mean((speed - errors.speed_ref) ** 2))),
        "steer_rate_max_radps": float(np.max(np.abs(steer_rate))),
        "steer_rate_rms_radps": float(np.sqrt(np.mean(steer_rate**2))),
        "steer_rate_sign_changes": sign_changes(steer_rate),
        "path_steer_sign_changes": path_steer_sign_changes(traj),
        # m/s, how far the speed ran above the plan's at the car's place on the route
        "overspeed_max_mps": float(np.max(np.abs(speed) - np.abs(errors.speed_ref))),
        # m, where the start projects on the route, and how far along it the car got from there
        "start_progress_m": start_progress,
        "progress_m": float(np.max(errors.progress)) - start_progress if sampled else 0.0,
        "route_length_m": route_length,
        # m, the radius of the plan's tightest turn (inf: straight), and where it starts
        "plan_min_turn_radius_m": tightest[0],
        "plan_min_turn_radius_at": [float(traj.x[tightest[1]]), float(traj.y[tightest[1]])],
    }


def clearance_metrics(
    scenario_name: str, t: FloatArray, x: FloatArray, y: FloatArray, heading: FloatArray
) -> dict[str, Any]:
    """How close the car's body came to the scene's obstacles (parked cars, kerb, walls): the
    smallest gap, m (negative: it went that deep into one), which obstacle and when; empty for a
    scene without obstacles."""
    near = clearance(scenario_name, x, y, heading)
    if near is None:
        return {}
    gap, box, i = near
    return {
        "clearance_min_m": gap,
        "clearance_min_obstacle": box.name,
        "clearance_min_t_s": float(t[i]),
    }


def collision(metrics: dict[str, Any]) -> str | None:
    """What the car's body hit, as a sentence, when :func:`clearance_metrics` says it went into
    an obstacle; None when it kept clear or the scene has none."""
    gap = metrics.get("clearance_min_m")
    if gap is None or gap >= 0.0:
        return None
    return (
        f"the car's body went {-gap:.2f} m into {metrics['clearance_min_obstacle']} at "
        f"t = {metrics['clearance_min_t_s']:.1f} s"
    )


# --- the goals of issue 13 for the route library -------------------------------------------------

GOAL_LATERAL_KINEMATIC = 0.05  # m, max lateral error on the kinematic plant
GOAL_FINAL_POSITION = 0.05  # m, kinematic plant
GOAL_FINAL_HEADING = math.radians(1.0)  # rad, kinematic plant
GOAL_LATERAL_LAG = 0.15  # m, max lateral error on the steer-lag and dynamic plants
GOAL_EXTRA_SIGN_CHANGES = 2  # steering reversals beyond the path's own, lag plants
GOAL_OVERSPEED = 0.2  # m/s above the plan's speed, on every route (the infeasible one too)


def route_goal_misses(metrics: dict[str, Any], plant: str, feasible: bool) -> list[str]:
    """Which goals a run missed (empty: all met), each naming the figure and its limit.

    Feasible routes must finish; on the kinematic plant within 5 cm laterally, 5 cm and 1° at
    the goal; on the steer-lag and dynamic plants within 15 cm with at most two steering
    reversals more than the path's. Every route, the infeasible one too, keeps the speed within
    0.2 m/s of the plan's, and in a scene with obstacles clear of them (:func:`collision`).
    """

    def num(key: str) -> float:
        value = metrics[key]
        assert isinstance(value, (int, float))
        return float(value)

    misses = []
    hit = collision(metrics)
    if hit is not None:
        misses.append(hit)
    if num("overspeed_max_mps") > GOAL_OVERSPEED:
        misses.append(f"overspeed {num('overspeed_max_mps'):.2f} m/s > {GOAL_OVERSPEED} m/s")
    if not feasible:
        return misses
    if not metrics.get("finished"):
        misses.append(f"not finished: {metrics.get('not_finished_reason', '?')}")
    lateral = num("lateral_error_max_m")
    if plant == "kinematic":
        if lateral > GOAL_LATERAL_KINEMATIC:
            misses.append(f"lateral error {lateral:.3f} m > {GOAL_LATERAL_KINEMATIC} m")
        if num("final_position_error_m") > GOAL_FINAL_POSITION:
            misses.append(
                f"final position {num('final_position_error_m'):.3f} m > {GOAL_FINAL_POSITION} m"
            )
        if num("final_heading_error_rad") > GOAL_FINAL_HEADING:
            misses.append(f"final heading {math.degrees(num('final_heading_error_rad')):.2f}° > 1°")
    else:
        if lateral > GOAL_LATERAL_LAG:
            misses.append(f"lateral error {lateral:.3f} m > {GOAL_LATERAL_LAG} m")
        allowed = num("path_steer_sign_changes") + GOAL_EXTRA_SIGN_CHANGES
        if num("steer_rate_sign_changes") > allowed:
            misses.append(
                f"steering sign changes {num('steer_rate_sign_changes'):.0f} > {allowed:.0f} "
                f"(the path's {num('path_steer_sign_changes'):.0f} + {GOAL_EXTRA_SIGN_CHANGES})"
            )
    return misses
