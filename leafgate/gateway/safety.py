"""The safety gate: the last word on every command, whatever produced it.

Limits are pure functions of (desired value, last sent value, measured state, limits), in the
manner of opendbc's ``apply_std_steer_angle_limits``, so they can be tested like a safety model
with tables of boundary values. :class:`SafetyGate` is the small stateful wrapper that remembers
the last sent command and counts every clamp by kind. :func:`check` tells whether a command
(with the previous one and the measured state) violates any limit; the log-replay checker uses it.

Everything is in wire terms: ``LongCommand.accel`` is *gear-relative* (positive speeds up in the
gear's direction, negative brakes) and ``LongCommand.speed`` is a magnitude.

Each limit is an interval ``[lo, hi]`` for the next value, built by intersecting an *envelope*
(amplitude limits: angle, lateral acceleration, accel bounds, speed limit) with a *rate* interval
(angle rate, jerk) around the last sent value. Where the two do not overlap — the envelope moved,
e.g. the speed limit was reached — the envelope wins: safety over smoothness.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

from leafgate.config import VehicleConfig
from leafgate.config.gateway import SafetyConfig
from leafgate.messages import Gear, LongCommand, LongMode, SteerCommand

#: Kinds of clamp, in the order they are reported.
CLAMP_KINDS: tuple[str, ...] = (
    "angle",
    "angle_rate",
    "lateral_accel",
    "accel",
    "jerk",
    "speed",
    "gear",
    "non_finite",
)


@dataclass(frozen=True)
class SafetyLimits:
    """The resolved limits the gate enforces (config and vehicle numbers combined)."""

    period: float  # s, time between two sent commands (rates are per second)
    max_angle: float  # rad, road-wheel angle amplitude
    rate_speeds: tuple[float, ...]  # m/s, breakpoints of the rate tables
    rate_up: tuple[float, ...]  # rad/s, wind-up (|angle| increasing)
    rate_down: tuple[float, ...]  # rad/s, unwind (|angle| decreasing)
    max_lateral_accel: float  # m/s²
    wheelbase: float  # m
    max_accel: float  # m/s², gear-relative
    min_accel: float  # m/s², gear-relative, negative (braking)
    max_jerk: float  # m/s³
    max_speed: float  # m/s
    standstill_speed: float  # m/s

    @functools.cached_property
    def speed_bounds(self) -> Bounds:
        """Allowed speed command (a magnitude), m/s (constant)."""
        return Bounds(0.0, self.max_speed, "speed", "speed")

    @classmethod
    def from_config(
        cls, safety: SafetyConfig, vehicle: VehicleConfig, period: float
    ) -> SafetyLimits:
        """Combine the gate's section with the vehicle's hard limits; a configured limit can only
        be tighter than the vehicle's."""
        max_angle = vehicle.max_steer_angle
        if safety.max_steer_angle is not None:
            max_angle = min(max_angle, safety.max_steer_angle)
        max_accel = vehicle.max_accel
        if safety.max_accel is not None:
            max_accel = min(max_accel, safety.max_accel)
        min_accel = vehicle.min_accel
        if safety.min_accel is not None:
            min_accel = max(min_accel, safety.min_accel)
        return cls(
            period=period,
            max_angle=max_angle,
            rate_speeds=safety.rate_speeds,
            rate_up=safety.rate_up,
            rate_down=safety.rate_down,
            max_lateral_accel=safety.max_lateral_accel,
            wheelbase=vehicle.wheelbase,
            max_accel=max_accel,
            min_accel=min_accel,
            max_jerk=safety.max_jerk,
            max_speed=safety.max_speed,
            standstill_speed=safety.standstill_speed,
        )


@dataclass(frozen=True, slots=True)
class Measured:
    """What the gate needs of the vehicle's measured state."""

    speed: float  # m/s, signed
    gear: Gear


class Bounds(NamedTuple):
    """The allowed interval for the next value and what bounds each side."""

    lo: float
    hi: float
    lo_kind: str
    hi_kind: str

    def clamp(self, value: float) -> tuple[float, str | None]:
        """The value inside the bounds and the kind of the bound applied (None: untouched)."""
        if value < self.lo:
            return self.lo, self.lo_kind
        if value > self.hi:
            return self.hi, self.hi_kind
        return value, None


@dataclass(frozen=True, slots=True)
class Violation:
    """A limit a command breaks (from :func:`check`)."""

    kind: str  # one of CLAMP_KINDS
    value: float  # the offending value (rad, m/s², m/s, or the gear number)
    bound: float  # the bound it exceeds (same unit; NaN for gear/non-finite)


@dataclass(frozen=True)
class GateResult:
    """The gated command and the kinds clamped on the way."""

    steer: SteerCommand
    long: LongCommand
    clamped: tuple[str, ...]


# --- pure limit functions ---------------------------------------------------------------------


def interp(x: float, xp: Sequence[float], fp: Sequence[float]) -> float:
    """Piecewise-linear interpolation, constant beyond the ends (as ``numpy.interp``).

    Plain Python: called a few times per tick on short tables, where numpy's call overhead
    dominates.
    """
    if x <= xp[0]:
        return float(fp[0])
    for i in range(1, len(xp)):
        if x <= xp[i]:
            t = (x - xp[i - 1]) / (xp[i] - xp[i - 1])
            return float(fp[i - 1] + t * (fp[i] - fp[i - 1]))
    return float(fp[-1])


def angle_rate_limits(speed: float, limits: SafetyLimits) -> tuple[float, float]:
    """(wind-up, unwind) angle-rate limits at the measured speed, rad/s."""
    v = abs(speed)
    return (
        interp(v, limits.rate_speeds, limits.rate_up),
        interp(v, limits.rate_speeds, limits.rate_down),
    )


def lateral_angle_limit(speed: float, limits: SafetyLimits) -> float:
    """Largest road-wheel angle with ``|tan δ / L| v² ≤ a_lat``, rad (π/2 at standstill)."""
    v2 = speed * speed
    if v2 <= 0.0:
        return math.pi / 2
    return math.atan(limits.max_lateral_accel * limits.wheelbase / v2)


def angle_rate_bounds(last: float, speed: float, limits: SafetyLimits) -> tuple[float, float]:
    """Interval reachable from ``last`` in one period under the wind-up and unwind rates.

    Moving towards zero is unwinding (``rate_down``), away from zero winding up (``rate_up``); a
    move across zero unwinds to zero first and winds up for the rest of the period.
    """
    up, down = angle_rate_limits(speed, limits)
    dt = limits.period

    def reach(a: float) -> float:
        # the most positive value reachable from a
        if a >= 0.0:
            return a + up * dt
        if a + down * dt <= 0.0:
            return a + down * dt
        return up * (dt + a / down)  # a < 0: the time left after reaching zero, at wind-up rate

    return -reach(-last), reach(last)


def _intersect(
    env_lo: float,
    env_hi: float,
    env_lo_kind: str,
    env_hi_kind: str,
    rate_lo: float,
    rate_hi: float,
    rate_kind: str,
) -> Bounds:
    """Intersect an envelope with a rate interval; the envelope wins where they are disjoint."""
    if rate_hi < env_lo:
        return Bounds(env_lo, env_lo, env_lo_kind, env_lo_kind)
    if rate_lo > env_hi:
        return Bounds(env_hi, env_hi, env_hi_kind, env_hi_kind)
    lo, lo_kind = (rate_lo, rate_kind) if rate_lo > env_lo else (env_lo, env_lo_kind)
    hi, hi_kind = (rate_hi, rate_kind) if rate_hi < env_hi else (env_hi, env_hi_kind)
    return Bounds(lo, hi, lo_kind, hi_kind)


def steer_bounds(last: float, speed: float, limits: SafetyLimits) -> Bounds:
    """Allowed road-wheel angle for the next command, rad."""
    lateral = lateral_angle_limit(speed, limits)
    if lateral < limits.max_angle:
        env, kind = lateral, "lateral_accel"
    else:
        env, kind = limits.max_angle, "angle"
    rate_lo, rate_hi = angle_rate_bounds(last, speed, limits)
    return _intersect(-env, env, kind, kind, rate_lo, rate_hi, "angle_rate")


def gear_sign(gear: Gear) -> float:
    """Direction of travel of a gear: D +1, R −1, anything else 0."""
    if gear == Gear.D:
        return 1.0
    if gear == Gear.R:
        return -1.0
    return 0.0


def speed_in_gear(measured: Measured) -> float:
    """Speed in the gear's direction of travel, m/s (|v| when the gear has no direction)."""
    sign = gear_sign(measured.gear)
    return sign * measured.speed if sign != 0.0 else abs(measured.speed)


def accel_bounds(last: float, measured: Measured, mode: LongMode, limits: SafetyLimits) -> Bounds:
    """Allowed gear-relative acceleration for the next command, m/s².

    In acceleration mode no positive acceleration is allowed above the speed limit.
    """
    env_hi, hi_kind = limits.max_accel, "accel"
    if mode == LongMode.ACCELERATION and speed_in_gear(measured) > limits.max_speed:
        env_hi, hi_kind = 0.0, "speed"
    step = limits.max_jerk * limits.period
    return _intersect(limits.min_accel, env_hi, "accel", hi_kind, last - step, last + step, "jerk")


def speed_bounds(limits: SafetyLimits) -> Bounds:
    """Allowed speed command (a magnitude), m/s."""
    return limits.speed_bounds


def gear_allowed(requested: Gear, measured: Measured, limits: SafetyLimits) -> bool:
    """A gear change may be requested only at standstill; NONE or the current gear always pass."""
    if requested in (Gear.NONE, measured.gear):
        return True
    return abs(measured.speed) < limits.standstill_speed


def apply_limits(
    steer: SteerCommand,
    long: LongCommand,
    last_steer: SteerCommand,
    last_long: LongCommand,
    measured: Measured,
    limits: SafetyLimits,
) -> GateResult:
    """Bring a desired command inside every limit.

    Non-finite values are replaced by the last sent ones (then limited as usual).

    :param steer: desired steering command
    :param long: desired longitudinal command (accel gear-relative, speed a magnitude)
    :param last_steer: the steering command sent last period
    :param last_long: the longitudinal command sent last period
    :param measured: measured speed (signed) and gear
    :param limits: the limits to enforce
    :returns: the command to send and the kinds clamped (each at most once, CLAMP_KINDS order)
    """
    kinds: set[str] = set()
    isfinite = math.isfinite
    # An unknown speed is taken as the maneuver limit: tighter rate tables, no gear change.
    v = measured.speed
    if not isfinite(v):
        v = limits.max_speed
        measured = Measured(v, measured.gear)

    # Non-finite values are replaced by the last sent ones.
    angle = steer.angle
    if not isfinite(angle):
        angle = last_steer.angle
        kinds.add("non_finite")
    angle, kind = steer_bounds(last_steer.angle, v, limits).clamp(angle)
    if kind:
        kinds.add(kind)

    accel = long.accel
    if not isfinite(accel):
        accel = last_long.accel
        kinds.add("non_finite")
    accel, kind = accel_bounds(last_long.accel, measured, long.mode, limits).clamp(accel)
    if kind:
        kinds.add(kind)

    speed = long.speed
    if not isfinite(speed):
        speed = last_long.speed
        kinds.add("non_finite")
    speed, kind = limits.speed_bounds.clamp(speed)
    if kind:
        kinds.add(kind)

    gear = long.gear
    if not gear_allowed(gear, measured, limits):
        gear = Gear.NONE
        kinds.add("gear")

    rate_limit = steer.rate_limit
    if not isfinite(rate_limit):
        rate_limit = 0.0
        kinds.add("non_finite")
    if not kinds and rate_limit >= 0.0:
        # Nothing clamped: every value above is the desired one, so the (frozen) desired
        # commands are the result.
        return GateResult(steer=steer, long=long, clamped=())
    return GateResult(
        steer=SteerCommand(angle, max(rate_limit, 0.0), steer.enable, steer.clear_override),
        long=LongCommand(long.mode, accel, speed, gear, long.enable, long.clear_override),
        clamped=tuple(k for k in CLAMP_KINDS if k in kinds) if kinds else (),
    )


def check(
    steer: SteerCommand,
    long: LongCommand,
    last_steer: SteerCommand,
    last_long: LongCommand,
    measured: Measured,
    limits: SafetyLimits,
    tolerance: float = 1e-9,
) -> tuple[Violation, ...]:
    """Every limit a sent command breaks; empty when it is within all of them.

    The same bounds as :func:`apply_limits`, so ``check(apply_limits(x)) == ()``. A log replay
    should pass a tolerance of at least the frame's quantisation (1e-4 rad, 1e-3 m/s², 1e-3 m/s)
    and the measured state at the time the frame was sent.

    :param tolerance: slack allowed on every bound (in the bound's unit)
    """
    out: list[Violation] = []
    for value in (steer.angle, long.accel, long.speed):
        if not math.isfinite(value):
            out.append(Violation("non_finite", value, math.nan))
    if not math.isfinite(measured.speed):
        return tuple(out)

    def within(value: float, bounds: Bounds) -> None:
        if not math.isfinite(value):
            return
        if value < bounds.lo - tolerance:
            out.append(Violation(bounds.lo_kind, value, bounds.lo))
        elif value > bounds.hi + tolerance:
            out.append(Violation(bounds.hi_kind, value, bounds.hi))

    within(steer.angle, steer_bounds(last_steer.angle, measured.speed, limits))
    within(long.accel, accel_bounds(last_long.accel, measured, long.mode, limits))
    within(long.speed, speed_bounds(limits))
    if not gear_allowed(long.gear, measured, limits):
        out.append(Violation("gear", float(long.gear), math.nan))
    return tuple(out)


# --- the stateful wrapper ----------------------------------------------------------------------


class SafetyGate:
    """Holds the last sent command and counts clamps by kind.

    :param limits: the limits to enforce
    """

    def __init__(self, limits: SafetyLimits) -> None:
        self.limits = limits
        self.last_steer = SteerCommand(angle=0.0)
        self.last_long = LongCommand()
        self.counts: dict[str, int] = dict.fromkeys(CLAMP_KINDS, 0)
        self.last_clamped: tuple[str, ...] = ()
        self._snapshot: dict[str, int] | None = None  # copy of counts, None after a change

    def counts_snapshot(self) -> dict[str, int]:
        """A copy of :attr:`counts` (CLAMP_KINDS order) that this gate never changes.

        The same copy is returned until a clamp is counted, so a per-tick record can hold the
        counts without copying them every tick. Callers must not mutate it.
        """
        if self._snapshot is None:
            self._snapshot = {k: self.counts[k] for k in CLAMP_KINDS}
        return self._snapshot

    def apply(
        self, steer: SteerCommand, long: LongCommand, measured: Measured
    ) -> tuple[SteerCommand, LongCommand]:
        """Gate a command that will be sent with ENABLE=1 and remember it as the last sent."""
        result = apply_limits(steer, long, self.last_steer, self.last_long, measured, self.limits)
        for kind in result.clamped:
            self.counts[kind] += 1
            self._snapshot = None
        self.last_clamped = result.clamped
        self.last_steer, self.last_long = result.steer, result.long
        return result.steer, result.long

    def seed(self, steer: SteerCommand, long: LongCommand) -> None:
        """Remember a command sent without passing the gate (ENABLE=0 frames mirroring the
        measured state), so the rate limits start from what the ECU saw last."""
        if math.isfinite(steer.angle):
            self.last_steer = steer  # frozen: kept as is
        else:
            self.last_steer = replace(steer, angle=self.last_steer.angle)
        self.last_long = long
        self.last_clamped = ()
