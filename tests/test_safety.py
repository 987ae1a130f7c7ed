"""The safety gate, tested like a safety model: values packed densely around every limit at
several speeds, random sweeps, and the checker that the log replay reuses."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.config import VehicleConfig, from_mapping
from leafgate.config.gateway import GatewayConfig, SafetyConfig
from leafgate.errors import ConfigError
from leafgate.gateway.safety import (
    CLAMP_KINDS,
    Measured,
    SafetyGate,
    SafetyLimits,
    angle_rate_bounds,
    apply_limits,
    check,
    lateral_angle_limit,
)
from leafgate.messages import Gear, LongCommand, LongMode, SteerCommand

PERIOD = 0.02  # s
VEHICLE = VehicleConfig()
LIMITS = SafetyLimits.from_config(SafetyConfig(), VEHICLE, PERIOD)
SPEEDS = [0.0, 1.0, 3.0, 5.0, 10.0]  # m/s
# The brief's tables, written out independently of the config defaults.
UP = (0.6, 0.5, 0.2)  # rad/s at 0/3/10 m/s
DOWN = (0.6, 0.6, 0.3)  # rad/s
BP = (0.0, 3.0, 10.0)  # m/s
DELTAS = [-1e-3, -1e-6, 0.0, 1e-6, 1e-3]  # packed around each limit
MAX_ANGLE = math.radians(31.0)  # rad


def gate(
    angle: float = 0.0,
    last_angle: float = 0.0,
    speed: float = 0.0,
    accel: float = 0.0,
    last_accel: float = 0.0,
    speed_cmd: float = 0.0,
    gear: Gear = Gear.NONE,
    measured_gear: Gear = Gear.D,
    mode: LongMode = LongMode.ACCELERATION,
    limits: SafetyLimits = LIMITS,
) -> tuple[float, LongCommand, tuple[str, ...]]:
    """Gate one command; returns (angle, long command, kinds clamped)."""
    result = apply_limits(
        SteerCommand(angle, enable=True),
        LongCommand(mode=mode, accel=accel, speed=speed_cmd, gear=gear, enable=True),
        SteerCommand(last_angle, enable=True),
        LongCommand(mode=mode, accel=last_accel, enable=True),
        Measured(speed, measured_gear),
        limits,
    )
    return result.steer.angle, result.long, result.clamped


def lateral_accel(angle: float, speed: float) -> float:
    return abs(math.tan(angle) / VEHICLE.wheelbase) * speed * speed


# --- steering angle ----------------------------------------------------------------------------


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_angle_never_leaves_the_amplitude_or_lateral_limit(
    speed: float, delta: float, sign: float
) -> None:
    limit = min(MAX_ANGLE, math.atan(3.0 * VEHICLE.wheelbase / speed**2) if speed else MAX_ANGLE)
    desired = sign * (limit + delta)
    angle, _, clamped = gate(angle=desired, last_angle=desired, speed=speed)  # rate not binding
    assert abs(angle) <= limit + 1e-12
    assert lateral_accel(angle, speed) <= 3.0 + 1e-9
    if delta > 0:
        assert angle == pytest.approx(sign * limit, abs=1e-12)
        kind = "lateral_accel" if limit < MAX_ANGLE else "angle"
        assert kind in clamped
    else:
        assert angle == desired and clamped == ()


def test_lateral_limit_binds_only_above_about_3_6_m_per_s() -> None:
    assert lateral_angle_limit(3.0, LIMITS) > MAX_ANGLE
    assert lateral_angle_limit(3.7, LIMITS) < MAX_ANGLE
    assert lateral_angle_limit(0.0, LIMITS) == pytest.approx(math.pi / 2)
    assert lateral_angle_limit(10.0, LIMITS) == pytest.approx(math.atan(3.0 * 2.7 / 100.0))


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("last", [0.05, -0.05])
def test_wind_up_rate_limit_by_speed(speed: float, delta: float, last: float) -> None:
    up = float(np.interp(speed, BP, UP))
    step = up * PERIOD
    desired = last + math.copysign(step + delta, last)  # away from zero
    angle, _, clamped = gate(angle=desired, last_angle=last, speed=speed)
    assert abs(angle - last) <= step + 1e-12
    if delta > 0:
        assert "angle_rate" in clamped and abs(angle - last) == pytest.approx(step)
    else:
        assert angle == desired


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("last", [0.06, -0.06])  # inside the lateral limit at 10 m/s (0.081)
def test_unwind_rate_limit_by_speed(speed: float, delta: float, last: float) -> None:
    down = float(np.interp(speed, BP, DOWN))
    step = down * PERIOD
    desired = last - math.copysign(step + delta, last)  # towards zero
    angle, _, clamped = gate(angle=desired, last_angle=last, speed=speed)
    assert abs(angle - last) <= step + 1e-12
    if delta > 0:
        assert "angle_rate" in clamped and abs(angle - last) == pytest.approx(step)
    else:
        assert angle == desired


@pytest.mark.parametrize("speed", [3.0, 5.0, 10.0])
def test_wind_up_and_unwind_tables_are_distinguished(speed: float) -> None:
    # Above 0 m/s the unwind rate is higher: the same step is allowed towards zero only.
    up = float(np.interp(speed, BP, UP)) * PERIOD
    down = float(np.interp(speed, BP, DOWN)) * PERIOD
    assert down > up
    step = (up + down) / 2
    last = 0.05  # rad, inside the lateral-acceleration limit at 10 m/s
    away, _, _ = gate(angle=last + step, last_angle=last, speed=speed)
    towards, _, _ = gate(angle=last - step, last_angle=last, speed=speed)
    assert away == pytest.approx(last + up)
    assert towards == pytest.approx(last - step)


def test_rate_tables_at_their_breakpoints() -> None:
    for speed, up, down in zip(BP, UP, DOWN, strict=True):
        lo, hi = angle_rate_bounds(0.1, speed, LIMITS)
        assert hi == pytest.approx(0.1 + up * PERIOD)
        assert lo == pytest.approx(0.1 - down * PERIOD)
    lo, hi = angle_rate_bounds(0.1, 20.0, LIMITS)  # beyond the table: its last value
    assert hi == pytest.approx(0.1 + 0.2 * PERIOD)


def test_move_across_zero_unwinds_then_winds_up() -> None:
    speed = 10.0  # up 0.2, down 0.3 rad/s
    last = 0.003  # rad: reaches zero after 0.01 s of unwinding, then winds up for 0.01 s
    lo, _ = angle_rate_bounds(last, speed, LIMITS)
    assert lo == pytest.approx(-0.2 * (PERIOD - last / 0.3))
    angle, _, clamped = gate(angle=-1.0, last_angle=last, speed=speed)
    assert angle == pytest.approx(lo) and clamped == ("angle_rate",)


def test_configured_angle_limit_can_only_be_lower() -> None:
    low = SafetyLimits.from_config(SafetyConfig(max_steer_angle=math.radians(20)), VEHICLE, PERIOD)
    assert low.max_angle == pytest.approx(math.radians(20))
    angle, _, _ = gate(angle=0.5, last_angle=0.5, limits=low)
    assert angle == pytest.approx(math.radians(20))
    high = SafetyLimits.from_config(SafetyConfig(max_steer_angle=math.radians(40)), VEHICLE, PERIOD)
    assert high.max_angle == pytest.approx(MAX_ANGLE)


# --- longitudinal ------------------------------------------------------------------------------


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("bound", [3.0, -6.0])
def test_accel_amplitude_limits(speed: float, delta: float, bound: float) -> None:
    desired = bound + math.copysign(1.0, bound) * delta
    mode = LongMode.SPEED  # no speed-limit rule on accel in speed mode
    _, long, clamped = gate(accel=desired, last_accel=desired, speed=speed, mode=mode)
    assert -6.0 <= long.accel <= 3.0
    if delta > 0:
        assert long.accel == bound and "accel" in clamped
    else:
        assert long.accel == desired


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_jerk_limit(speed: float, delta: float, direction: float) -> None:
    step = 5.0 * PERIOD  # m/s², default max jerk 5 m/s³
    desired = -1.0 + direction * (step + delta)
    _, long, clamped = gate(accel=desired, last_accel=-1.0, speed=speed, mode=LongMode.SPEED)
    assert abs(long.accel + 1.0) <= step + 1e-12
    assert ("jerk" in clamped) is (delta > 0)


@pytest.mark.parametrize("delta", DELTAS)
def test_speed_command_clamped_to_maneuver_limit(delta: float) -> None:
    _, long, clamped = gate(speed_cmd=3.0 + delta, speed=1.0, mode=LongMode.SPEED)
    assert 0.0 <= long.speed <= 3.0
    assert ("speed" in clamped) is (delta > 0)
    _, long, clamped = gate(speed_cmd=-0.1, mode=LongMode.SPEED)
    assert long.speed == 0.0 and "speed" in clamped


@pytest.mark.parametrize(
    "speed, gear, allowed",
    [
        (2.99, Gear.D, True),
        (3.0, Gear.D, True),
        (3.001, Gear.D, False),
        (5.0, Gear.D, False),
        (-3.001, Gear.R, False),
        (3.0, Gear.R, True),  # rolling forward in R: speeding up backwards brakes the roll
        (-5.0, Gear.D, True),
    ],
)
def test_no_positive_accel_at_the_speed_limit_in_accel_mode(
    speed: float, gear: Gear, allowed: bool
) -> None:
    _, long, clamped = gate(accel=0.05, last_accel=0.05, speed=speed, measured_gear=gear)
    assert (long.accel == 0.05) is allowed
    assert ("speed" in clamped) is not allowed
    _, long, _ = gate(accel=-0.05, last_accel=-0.05, speed=speed, measured_gear=gear)
    assert long.accel == -0.05  # braking always allowed
    _, long, _ = gate(accel=0.05, last_accel=0.05, speed=speed, mode=LongMode.SPEED)
    assert long.accel == 0.05


# --- gear ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "speed, requested, measured, allowed",
    [
        (0.0, Gear.R, Gear.D, True),
        (0.049, Gear.R, Gear.D, True),
        (-0.049, Gear.P, Gear.R, True),
        (0.05, Gear.R, Gear.D, False),
        (1.0, Gear.R, Gear.D, False),
        (-1.0, Gear.D, Gear.R, False),
        (10.0, Gear.P, Gear.D, False),
        (1.0, Gear.D, Gear.D, True),  # no change
        (1.0, Gear.NONE, Gear.D, True),  # no request
    ],
)
def test_gear_change_only_at_standstill(
    speed: float, requested: Gear, measured: Gear, allowed: bool
) -> None:
    _, long, clamped = gate(gear=requested, speed=speed, measured_gear=measured)
    assert long.gear == (requested if allowed else Gear.NONE)
    assert ("gear" in clamped) is not allowed


def test_gear_refused_when_speed_unknown() -> None:
    _, long, clamped = gate(gear=Gear.R, speed=math.nan)
    assert long.gear == Gear.NONE and "gear" in clamped


# --- non-finite ----------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_hold_the_last_command(bad: float) -> None:
    result = apply_limits(
        SteerCommand(bad, rate_limit=bad, enable=True),
        LongCommand(accel=bad, speed=bad, enable=True),
        SteerCommand(0.1, enable=True),
        LongCommand(accel=-0.5, speed=1.5, enable=True),
        Measured(1.0, Gear.D),
        LIMITS,
    )
    assert result.steer.angle == 0.1 and result.steer.rate_limit == 0.0
    assert result.long.accel == -0.5 and result.long.speed == 1.5
    assert result.clamped == ("non_finite",)


# --- random sweeps -------------------------------------------------------------------------------

finite = st.floats(min_value=-20.0, max_value=20.0, allow_nan=False)
anything = st.one_of(finite, st.sampled_from([math.nan, math.inf, -math.inf]))
angles = st.floats(min_value=-0.6, max_value=0.6, allow_nan=False)


@settings(max_examples=400, deadline=None)
@given(
    angle=anything,
    last_angle=angles,
    speed=st.floats(min_value=-12.0, max_value=12.0, allow_nan=False),
    accel=anything,
    last_accel=st.floats(min_value=-6.0, max_value=3.0),
    speed_cmd=anything,
    gear=st.sampled_from(list(Gear)),
    measured_gear=st.sampled_from(list(Gear)),
    mode=st.sampled_from(list(LongMode)),
)
def test_nothing_outside_the_limits_ever_leaves(
    angle: float,
    last_angle: float,
    speed: float,
    accel: float,
    last_accel: float,
    speed_cmd: float,
    gear: Gear,
    measured_gear: Gear,
    mode: LongMode,
) -> None:
    last_steer = SteerCommand(last_angle, enable=True)
    last_long = LongCommand(mode=mode, accel=last_accel, enable=True)
    measured = Measured(speed, measured_gear)
    desired_steer = SteerCommand(angle, enable=True)
    desired_long = LongCommand(mode=mode, accel=accel, speed=speed_cmd, gear=gear, enable=True)
    out = apply_limits(desired_steer, desired_long, last_steer, last_long, measured, LIMITS)
    assert check(out.steer, out.long, last_steer, last_long, measured, LIMITS) == ()
    # Independent restatement of the hard limits.
    assert all(math.isfinite(v) for v in (out.steer.angle, out.long.accel, out.long.speed))
    assert abs(out.steer.angle) <= MAX_ANGLE + 1e-12
    assert lateral_accel(out.steer.angle, speed) <= 3.0 + 1e-9 or abs(out.steer.angle) <= abs(
        last_angle
    )
    assert -6.0 <= out.long.accel <= 3.0 and 0.0 <= out.long.speed <= 3.0
    if out.long.gear not in (Gear.NONE, measured_gear):
        assert abs(speed) < 0.05
    # A command already within the limits passes untouched.
    if check(desired_steer, desired_long, last_steer, last_long, measured, LIMITS, 0.0) == ():
        assert out.steer.angle == angle and out.long.accel == accel
        assert out.long.speed == speed_cmd and out.long.gear == gear and out.clamped == ()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(angles, finite, st.floats(0.0, 3.5)), min_size=1, max_size=60))
def test_a_gated_sequence_is_always_within_rate_and_jerk_bounds(
    steps: list[tuple[float, float, float]],
) -> None:
    g = SafetyGate(LIMITS)
    for angle, accel, speed in steps:
        prev_steer, prev_long = g.last_steer, g.last_long
        measured = Measured(speed, Gear.D)
        steer, long = g.apply(SteerCommand(angle, enable=True), LongCommand(accel=accel), measured)
        assert check(steer, long, prev_steer, prev_long, measured, LIMITS) == ()
        assert abs(long.accel - prev_long.accel) <= 5.0 * PERIOD + 1e-12 or long.accel == 0.0


# --- the checker -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "steer, long, measured, kinds",
    [
        (0.6, 0.0, 0.0, {"angle"}),
        (0.05, 0.0, 0.0, {"angle_rate"}),  # from 0.0 in one period: > 0.6 rad/s
        (0.3, 0.0, 8.0, {"lateral_accel"}),
        (0.0, 0.2, 1.0, {"jerk"}),
        (0.0, 0.05, 3.5, {"speed"}),
    ],
)
def test_check_names_the_violated_limit(
    steer: float, long: float, measured: float, kinds: set[str]
) -> None:
    last_angle = steer if kinds != {"angle_rate"} else 0.0
    violations = check(
        SteerCommand(steer, enable=True),
        LongCommand(accel=long, enable=True),
        SteerCommand(last_angle, enable=True),
        LongCommand(accel=0.0),
        Measured(measured, Gear.D),
        LIMITS,
    )
    assert {v.kind for v in violations} == kinds


def test_check_flags_gear_and_non_finite() -> None:
    violations = check(
        SteerCommand(math.nan),
        LongCommand(gear=Gear.R),
        SteerCommand(0.0),
        LongCommand(),
        Measured(1.0, Gear.D),
        LIMITS,
    )
    assert {v.kind for v in violations} == {"non_finite", "gear"}


def test_check_tolerance_for_quantised_frames() -> None:
    cmd = SteerCommand(MAX_ANGLE + 5e-5, enable=True)  # 1e-4 rad resolution on the wire
    args = (LongCommand(), SteerCommand(MAX_ANGLE), LongCommand(), Measured(0.0, Gear.D), LIMITS)
    assert check(cmd, *args) != ()
    assert check(cmd, *args, tolerance=1e-4) == ()


# --- the stateful gate ---------------------------------------------------------------------------


def test_gate_counts_clamps_by_kind_and_remembers_the_last_sent() -> None:
    g = SafetyGate(LIMITS)
    measured = Measured(0.0, Gear.D)
    g.apply(SteerCommand(1.0, enable=True), LongCommand(accel=1.0, enable=True), measured)
    assert g.last_clamped == ("angle_rate", "jerk")
    g.apply(
        SteerCommand(math.nan, enable=True),
        LongCommand(accel=-1.0, gear=Gear.R),
        Measured(1.0, Gear.D),
    )
    assert g.counts["angle_rate"] == 1 and g.counts["jerk"] == 2
    assert g.counts["non_finite"] == 1 and g.counts["gear"] == 1
    assert set(g.counts) == set(CLAMP_KINDS)
    g.seed(SteerCommand(0.4), LongCommand())
    assert g.last_steer.angle == 0.4 and g.last_clamped == ()


# --- configuration -------------------------------------------------------------------------------


def test_gateway_config_from_yaml_mapping_with_units() -> None:
    cfg = from_mapping(
        GatewayConfig,
        {
            "safety": {"max_steer_angle_deg": 25, "rate_up_degps": [30, 20, 10], "max_speed": 2.0},
            "engage": {"max_heading_error_deg": 20},
            "watchdog": {"trajectory_max_age": None},
        },
        "gw.yaml",
    )
    assert cfg.safety.max_steer_angle == pytest.approx(math.radians(25))
    assert cfg.safety.rate_up[0] == pytest.approx(math.radians(30))
    assert cfg.engage.max_heading_error == pytest.approx(math.radians(20))
    assert cfg.watchdog.trajectory_max_age is None


@pytest.mark.parametrize(
    "mapping, message",
    [
        ({"safety": {"rate_up": [0.5, 0.4]}}, "equal length"),
        ({"safety": {"rate_speeds": [0.0, 5.0, 3.0]}}, "strictly increasing"),
        ({"safety": {"min_accel": 1.0}}, "min_accel must be negative"),
        ({"safety": {"max_jerk": 1.0}}, "stop.jerk must not exceed"),
        ({"watchdog": {"localization_fault_age": 0.05}}, "localization_fault_age"),
        ({"safety": {"max_speeed": 1.0}}, "safety.max_speeed: unknown key"),
    ],
)
def test_bad_gateway_config_names_the_problem(mapping: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        from_mapping(GatewayConfig, mapping, "gw.yaml")


def test_limits_from_config_tighten_accel() -> None:
    limits = SafetyLimits.from_config(SafetyConfig(max_accel=1.5, min_accel=-3.0), VEHICLE, PERIOD)
    assert (limits.max_accel, limits.min_accel) == (1.5, -3.0)
    _, long, _ = gate(accel=2.0, last_accel=2.0, limits=replace(limits), mode=LongMode.SPEED)
    assert long.accel == 1.5


def test_counts_snapshot_of_an_earlier_tick_is_not_changed_by_later_clamps() -> None:
    # Diagnostics hold the snapshot instead of a per-tick copy: it must never change afterwards.
    g = SafetyGate(LIMITS)
    measured = Measured(0.0, Gear.D)
    before = g.counts_snapshot()
    assert before == dict.fromkeys(CLAMP_KINDS, 0) and list(before) == list(CLAMP_KINDS)
    g.apply(SteerCommand(0.0, enable=True), LongCommand(enable=True), measured)  # no clamp
    assert g.counts_snapshot() is before  # unchanged counts: no new copy
    g.apply(SteerCommand(1.0, enable=True), LongCommand(accel=1.0, enable=True), measured)
    after = g.counts_snapshot()
    assert before == dict.fromkeys(CLAMP_KINDS, 0)
    assert after["angle_rate"] == 1 and after["jerk"] == 1 and after == g.counts


def test_unclamped_command_passes_with_every_field_unchanged() -> None:
    steer = SteerCommand(0.001, rate_limit=0.2, enable=True, clear_override=False)
    long = LongCommand(LongMode.SPEED, accel=0.01, speed=1.0, gear=Gear.D, enable=True)
    result = apply_limits(
        steer, long, SteerCommand(0.0), LongCommand(LongMode.SPEED), Measured(1.0, Gear.D), LIMITS
    )
    assert result.clamped == ()
    assert result.steer == steer and result.long == long


@pytest.mark.parametrize("rate_limit, sent", [(-0.5, 0.0), (math.nan, 0.0), (0.3, 0.3)])
def test_steer_rate_limit_is_never_negative_or_non_finite(rate_limit: float, sent: float) -> None:
    result = apply_limits(
        SteerCommand(0.0, rate_limit=rate_limit, enable=True),
        LongCommand(enable=True),
        SteerCommand(0.0),
        LongCommand(),
        Measured(0.0, Gear.D),
        LIMITS,
    )
    assert result.steer.rate_limit == sent
    assert result.clamped == (("non_finite",) if math.isnan(rate_limit) else ())


def test_seed_keeps_the_last_angle_when_the_mirrored_angle_is_not_finite() -> None:
    g = SafetyGate(LIMITS)
    g.seed(SteerCommand(0.25), LongCommand())
    g.seed(SteerCommand(math.nan, clear_override=True), LongCommand())
    assert g.last_steer == SteerCommand(0.25, clear_override=True)


def test_speed_limit_of_replaced_limits_is_their_own() -> None:
    # The speed interval is cached per SafetyLimits: a replaced copy must not reuse the cache.
    assert gate(speed_cmd=10.0)[1].speed == LIMITS.max_speed  # fills LIMITS' cache
    slower = replace(LIMITS, max_speed=1.0)
    assert gate(speed_cmd=10.0, limits=slower)[1].speed == 1.0
