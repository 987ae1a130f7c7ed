"""Built-in maneuvers: reference trajectories and start poses for the simulator.

Every scenario is a path of the rear-axle centre sampled at equal arc length (0.5 m, the paper's
waypoint spacing) with a heading and a signed speed per waypoint, and a start pose at rest on the
first waypoint.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from leafgate.messages import FloatArray, Pose, Trajectory

SPACING = 0.5  # m, waypoint spacing (paper: 0.5–1.0 m)
START_SPEED = 0.3  # m/s, reference speed at the first waypoint: a standing start needs a pull


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    trajectory: Trajectory
    start: Pose
    duration: float  # s, simulated time limit


def _resample_path(
    xs: FloatArray, ys: FloatArray, spacing: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Resample a dense polyline at equal arc length; return x, y, heading, arc length."""
    seg = np.hypot(np.diff(xs), np.diff(ys))
    s_dense = np.concatenate(([0.0], np.cumsum(seg)))
    s = np.arange(0.0, s_dense[-1] + 1e-9, spacing)
    if s_dense[-1] - s[-1] > 1e-6:
        s = np.append(s, s_dense[-1])  # keep the exact end point
        if s[-1] - s[-2] < 0.5 * spacing:
            s = np.delete(s, -2)
    x = np.interp(s, s_dense, xs)
    y = np.interp(s, s_dense, ys)
    # Heading from the dense path's tangent, so it is exact rather than a chord direction.
    tangent = np.arctan2(np.gradient(ys), np.gradient(xs))
    heading = np.interp(s, s_dense, np.unwrap(tangent))
    return x, y, heading, s


def _speed_profile(s: FloatArray, v_max: float, accel: float, decel: float) -> FloatArray:
    """Trapezoid over arc length: pull away from START_SPEED, cruise, stop exactly at the end."""
    total = s[-1]
    up = np.sqrt(START_SPEED**2 + 2.0 * accel * s)
    down = np.sqrt(np.maximum(0.0, 2.0 * decel * (total - s)))
    return np.minimum(np.minimum(up, down), v_max)


def _forward(
    name: str,
    description: str,
    path: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    length: float,
    v_max: float,
) -> Scenario:
    u = np.linspace(0.0, length, int(length / 0.01) + 1)
    xs, ys = path(u)
    x, y, heading, s = _resample_path(xs, ys, SPACING)
    speed = _speed_profile(s, v_max, accel=0.5, decel=0.5)
    traj = Trajectory(x=x, y=y, heading=heading, speed=speed)
    start = Pose(x=float(x[0]), y=float(y[0]), heading=float(heading[0]), speed=0.0)
    travel_time = float(np.sum(np.diff(s) / np.maximum(0.5 * (speed[1:] + speed[:-1]), 0.2)))
    return Scenario(name, description, traj, start, duration=travel_time + 10.0)


def s_curve() -> Scenario:
    """The paper's maneuver: a 3.5 m lateral displacement over 25 m, 0 → 2 m/s → stop."""
    lead_in, curve, lead_out, offset = 3.0, 25.0, 4.0, 3.5  # m

    def path(u: FloatArray) -> tuple[FloatArray, FloatArray]:
        t = np.clip((u - lead_in) / curve, 0.0, 1.0)
        # Quintic smoothstep: continuous curvature at both ends of the S.
        return u, offset * (10 * t**3 - 15 * t**4 + 6 * t**5)

    return _forward(
        "s-curve",
        "lateral displacement of 3.5 m over 25 m at 2 m/s (the paper's maneuver)",
        path,
        lead_in + curve + lead_out,
        2.0,
    )


def straight() -> Scenario:
    """40 m straight ahead at up to 3 m/s."""
    return _forward(
        "straight", "40 m straight at 3 m/s", lambda u: (u, np.zeros_like(u)), 40.0, 3.0
    )


def slalom() -> Scenario:
    """Sinusoidal slalom ±1.5 m, 30 m wavelength, at 3 m/s."""
    lead, wave, amplitude, periods = 5.0, 30.0, 1.5, 2  # m, m, m, -

    def path(u: FloatArray) -> tuple[FloatArray, FloatArray]:
        span = wave * periods
        t = np.clip(u - lead, 0.0, span)
        # A smoothstep window over the first and last half wave: the sine then starts and ends
        # with zero slope and curvature, so there is no heading kink at the straights.
        ramp = np.clip(np.minimum(t, span - t) / (0.5 * wave), 0.0, 1.0)
        window = ramp * ramp * (3.0 - 2.0 * ramp)
        return u, amplitude * window * np.sin(2.0 * math.pi * t / wave)

    return _forward(
        "slalom", "slalom ±1.5 m, 30 m wavelength, at 3 m/s", path, 2 * lead + wave * periods, 3.0
    )


SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "s-curve": s_curve,
    "straight": straight,
    "slalom": slalom,
}


def get_scenario(name: str) -> Scenario:
    """Build the named scenario.

    :raises KeyError: naming the known scenarios when ``name`` is not one of them
    """
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise KeyError(
            f"unknown scenario {name!r} (known: {', '.join(sorted(SCENARIOS))})"
        ) from None
    return factory()
