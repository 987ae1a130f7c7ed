"""Tracking metrics of a closed-loop run, computed from the true (plant) states.

Errors are measured against the reference polyline, not against the waypoint the controller
happened to pick, so that every controller is judged the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from leafgate.messages import FloatArray, Trajectory

STEER_RATE_DEADBAND = 0.01  # rad/s, rate changes smaller than this are not a sign change


@dataclass(frozen=True)
class PathErrors:
    lateral: FloatArray  # m, signed cross-track error (left of the path positive)
    heading: FloatArray  # rad, wrapped to (−π, π]
    speed_ref: FloatArray  # m/s, reference speed at the projection


def wrap_angle(angle: FloatArray | float) -> FloatArray:
    return (np.asarray(angle) + math.pi) % (2.0 * math.pi) - math.pi


def path_errors(traj: Trajectory, x: FloatArray, y: FloatArray, heading: FloatArray) -> PathErrors:
    """Project each sample onto the nearest segment of the reference polyline.

    For reversing segments the heading reference is the vehicle heading stored in the
    trajectory, so the same formula holds in both directions.
    """
    px, py = traj.x, traj.y
    ax, ay = px[:-1], py[:-1]
    dx, dy = np.diff(px), np.diff(py)
    seg_len2 = dx * dx + dy * dy
    # (samples × segments) projection parameters, clipped to the segments.
    rx = x[:, None] - ax[None, :]
    ry = y[:, None] - ay[None, :]
    t = np.clip((rx * dx + ry * dy) / seg_len2, 0.0, 1.0)
    ex = rx - t * dx
    ey = ry - t * dy
    dist2 = ex * ex + ey * ey
    k = np.argmin(dist2, axis=1)
    rows = np.arange(x.shape[0])
    tk = t[rows, k]
    cross = dx[k] * ey[rows, k] - dy[k] * ex[rows, k]
    lateral = np.sign(cross) * np.sqrt(dist2[rows, k])
    ref_heading = traj.heading[k] + tk * wrap_angle(traj.heading[k + 1] - traj.heading[k])
    speed_ref = traj.speed[k] + tk * (traj.speed[k + 1] - traj.speed[k])
    return PathErrors(
        lateral=lateral, heading=wrap_angle(heading - ref_heading), speed_ref=speed_ref
    )


def sign_changes(rate: FloatArray, deadband: float = STEER_RATE_DEADBAND) -> int:
    """Count reversals of a rate signal, ignoring excursions inside the deadband."""
    signs = np.sign(rate[np.abs(rate) > deadband])
    return int(np.count_nonzero(np.diff(signs)))


def tracking_metrics(
    traj: Trajectory,
    t: FloatArray,
    x: FloatArray,
    y: FloatArray,
    heading: FloatArray,
    speed: FloatArray,
    steer_angle: FloatArray,
) -> dict[str, float]:
    """Lateral/heading/speed errors and steering smoothness of a run (true plant states)."""
    errors = path_errors(traj, x, y, heading)
    steer_rate = np.gradient(steer_angle, t) if t.shape[0] > 1 else np.zeros_like(t)
    final_pos = math.hypot(x[-1] - traj.x[-1], y[-1] - traj.y[-1])
    final_heading = float(abs(wrap_angle(heading[-1] - traj.heading[-1])))
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
    }
