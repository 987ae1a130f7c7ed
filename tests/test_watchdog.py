"""Rows of docs/watchdogs.md's watchdog table: the watchdog alone, then its reaction in the gateway —
input withheld, late or corrupted → the stated reaction within one control period of the
threshold."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_gateway_core import PERIOD, FakeController, Rig, cruise, straight_trajectory

from leafgate.config.gateway import GatewayConfig, WatchdogConfig
from leafgate.control.reference import trajectory_problem
from leafgate.gateway.watchdog import (
    CHECK_ORDER,
    Check,
    ErrorCounter,
    OverrunWatchdog,
    PoseWatchdog,
    ProgressWatchdog,
    Reaction,
    ReportWatchdog,
    Status,
    WatchdogReport,
    freshness,
    position_jump,
    update_error_counter,
)
from leafgate.messages import (
    ControlOutput,
    GatewayState,
    OperatorRequest,
    Pose,
    Stamped,
    SteeringWheelAngle,
    Trajectory,
    WheelSpeeds,
)

CFG = WatchdogConfig()


# --- the watchdogs alone -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "age, status",
    [
        (None, Status.MISSING),
        (0.0, Status.OK),
        (0.100, Status.OK),
        (0.1001, Status.STALE),
        (0.500, Status.STALE),
        (0.5001, Status.LOST),
    ],
)
def test_freshness_thresholds_are_strictly_greater(age: float | None, status: Status) -> None:
    assert freshness(age, 0.1, 0.5) is status


def test_pose_watchdog_stale_then_lost_from_the_last_valid_sample() -> None:
    wd = PoseWatchdog(CFG)
    sample = Stamped(Pose(0.0, 0.0, 0.0, 0.0), 1.0)
    assert wd.update(1.0, sample).reaction is Reaction.NONE
    assert wd.update(1.1, sample).status is Status.OK
    check = wd.update(1.1 + 1e-6, sample)
    assert check.status is Status.STALE and check.reaction is Reaction.STOP
    check = wd.update(1.5 + 1e-6, sample)
    assert check.status is Status.LOST and check.reaction is Reaction.FAULT
    assert check.age == pytest.approx(0.5 + 1e-6)


def test_pose_watchdog_ignores_invalid_and_non_finite_samples() -> None:
    wd = PoseWatchdog(CFG)
    assert wd.update(0.0, Stamped(Pose(0.0, 0.0, 0.0, 0.0), 0.0, valid=False)).status is (
        Status.INVALID
    )
    good = Stamped(Pose(0.0, 0.0, 0.0, 0.0), 0.1)
    wd.update(0.1, good)
    check = wd.update(0.3, Stamped(Pose(math.nan, 0.0, 0.0, 0.0), 0.3))
    assert check.status is Status.STALE and check.age == pytest.approx(0.2)
    assert wd.last is good


@pytest.mark.parametrize("jump, faults", [(0.9, False), (0.999, False), (1.001, True), (3.0, True)])
def test_pose_jump_over_one_metre_in_one_sample_faults(jump: float, faults: bool) -> None:
    wd = PoseWatchdog(CFG)
    wd.update(0.0, Stamped(Pose(5.0, 5.0, 0.3, 0.0), 0.0))
    check = wd.update(0.02, Stamped(Pose(5.0, 5.0 + jump, 0.3, 0.0), 0.02))
    assert (check.status is Status.JUMP) is faults
    assert (check.reaction is Reaction.FAULT) is faults
    assert check.value == pytest.approx(jump)


def test_pose_jump_discounts_the_distance_driven() -> None:
    # 3 m/s for 0.4 s (missed samples) is 1.2 m of motion, not a jump.
    prev = Stamped(Pose(0.0, 0.0, math.pi / 2, 3.0), 0.0)
    cur = Stamped(Pose(0.0, 1.2, math.pi / 2, 3.0), 0.4)
    assert position_jump(prev, cur) == pytest.approx(0.0, abs=1e-9)
    sideways = Stamped(Pose(1.2, 1.2, math.pi / 2, 3.0), 0.4)
    assert position_jump(prev, sideways) == pytest.approx(1.2)


@pytest.mark.parametrize("period", [0.010, 0.020, 0.100])
def test_report_watchdog_faults_after_three_periods(period: float) -> None:
    wd: ReportWatchdog[int] = ReportWatchdog("r", period, 3.0)
    assert wd.update(0.0, None).status is Status.MISSING
    sample = Stamped(1, 0.0)
    assert wd.update(3 * period, sample).ok
    check = wd.update(3 * period + 1e-6, sample)
    assert check.status is Status.LOST and check.reaction is Reaction.FAULT


def test_error_counter_counts_like_panda() -> None:
    counter = ErrorCounter(5)
    assert counter.update(good=0, bad=4).ok and counter.count == 4
    assert counter.update(good=10, bad=0).ok and counter.count == 0  # floor 0
    assert counter.update(good=0, bad=-3).ok and counter.count == 0
    # Order within a tick unknown: bad first for the peak, good first for the value after.
    assert counter.update(good=1, bad=2).ok and counter.count == 2  # peak 2
    assert counter.update(good=1, bad=2).ok and counter.count == 3  # peak 4
    check = counter.update(good=1, bad=2)  # peak 5
    assert check.status is Status.ERRORS and check.reaction is Reaction.FAULT


def test_error_counter_five_bad_frames_in_one_tick_faults() -> None:
    assert not ErrorCounter(5).update(good=100, bad=5).ok
    assert ErrorCounter(5).update(good=100, bad=4).ok


@given(
    st.lists(
        st.lists(st.booleans(), max_size=12),  # one tick's frames in arrival order (True = bad)
        max_size=40,
    )
)
def test_error_counter_never_lags_the_frame_by_frame_counter(ticks: list[list[bool]]) -> None:
    count = panda = 0
    for frames in ticks:
        bad = sum(frames)
        peak, count = update_error_counter(count, len(frames) - bad, bad)
        panda_peak = panda
        for is_bad in frames:
            panda = panda + 1 if is_bad else max(panda - 1, 0)
            panda_peak = max(panda_peak, panda)
        assert peak >= panda_peak
        assert count >= panda


def test_overrun_three_ticks_in_a_row_faults() -> None:
    wd = OverrunWatchdog(3)
    assert [wd.update(o).ok for o in (True, True, False, True, True)] == [True] * 5
    assert wd.update(True).reaction is Reaction.FAULT


def test_one_long_stall_faults_although_it_is_one_overrun() -> None:
    # issue 17, finding 5: a 4.36 s tick counted as one overrun and never faulted
    wd = OverrunWatchdog(3, stall_limit=0.1)
    assert wd.update(True, 0.09).ok
    check = wd.update(True, 4.36)
    assert check.reaction is Reaction.FAULT and "stalled 4.360 s > 0.1 s" in check.detail


def test_gateway_faults_on_a_stalled_tick() -> None:
    rig = Rig()
    rig.engage()
    limit = GatewayConfig().watchdog.max_stall_periods * PERIOD
    rig.step(overrun=True, lateness=limit * 0.9)
    assert rig.state == GatewayState.ENGAGED
    rig.step(overrun=True, lateness=4.36)
    assert rig.state == GatewayState.FAULT
    assert "control loop stalled" in rig.gw.machine.fault_reason


# --- the reactions in the gateway, in simulated time -------------------------------------------


def assert_within_one_period(delay: float, threshold: float) -> None:
    """The reaction came at the first tick past the threshold."""
    assert threshold < delay <= threshold + PERIOD + 1e-9


def _first_state(rig: Rig, state: GatewayState, seconds: float) -> float:
    """Step until the gateway reaches ``state``; the time of that tick."""
    for _ in range(round(seconds / PERIOD)):
        now = rig.now
        rig.step()
        if rig.state == state:
            return now
    raise AssertionError(f"no {state.name} within {seconds} s (state {rig.state.name})")


def test_localization_withheld_stops_after_100_ms_then_faults_after_500_ms() -> None:
    rig = Rig()
    rig.engage()
    rig.step()
    last = rig.now - PERIOD  # the last pose sent
    rig.send["pose"] = False
    t_stop = _first_state(rig, GatewayState.STOPPING, 1.0)
    assert_within_one_period(t_stop - last, 0.100)
    t_fault = _first_state(rig, GatewayState.FAULT, 1.0)
    assert_within_one_period(t_fault - last, 0.500)
    assert "localization age" in rig.results[-1].diagnostics.fault


def test_localization_corrupted_counts_as_withheld() -> None:
    rig = Rig()
    rig.engage()
    rig.step()
    last = rig.now - PERIOD
    rig.pose_offset = (math.nan, 0.0)
    t_stop = _first_state(rig, GatewayState.STOPPING, 1.0)
    assert_within_one_period(t_stop - last, 0.100)


def test_position_jump_faults_in_the_same_tick() -> None:
    rig = Rig()
    rig.engage()
    rig.pose_offset = (0.0, 1.2)
    rig.step()
    assert rig.state == GatewayState.FAULT
    assert "jumped" in rig.results[-1].diagnostics.fault


def test_small_position_correction_is_no_jump() -> None:
    rig = Rig()
    rig.engage()
    rig.pose_offset = (0.0, 0.15)  # below localization_max_drift as well
    rig.run(0.2)
    assert rig.state == GatewayState.ENGAGED


def test_a_correction_below_the_jump_limit_still_disagrees_with_dead_reckoning() -> None:
    rig = Rig()
    rig.engage()
    rig.pose_offset = (0.0, 0.8)  # no jump (< 1 m), but the wheels did not move the car 0.8 m
    rig.step()
    assert rig.state == GatewayState.FAULT
    assert "dead reckoning" in rig.results[-1].diagnostics.fault


def test_localization_drifting_2_cm_per_sample_faults_before_0_3_m() -> None:
    # issue 17, finding 3: a second publisher drifting 2 cm per sample moved the car 3.9 m
    rig = Rig(FakeController(cruise(accel=0.5)))
    rig.engage()
    rig.run(1.0)
    assert rig.state == GatewayState.ENGAGED
    drift = 0.0
    while rig.state == GatewayState.ENGAGED and drift < 1.0:
        drift += 0.02
        rig.pose_offset = (0.0, drift)
        rig.step()
    assert rig.state == GatewayState.FAULT
    assert "dead reckoning" in rig.results[-1].diagnostics.fault
    assert drift < 0.3


def test_second_localization_source_half_a_metre_off_faults_within_half_a_second() -> None:
    # issue 17, finding 3: a constant 0.5 m second source was never detected
    rig = Rig(FakeController(cruise(accel=0.5)))
    rig.engage()
    rig.run(1.0)
    started = rig.now
    for k in range(50):
        rig.pose_offset = (0.0, 0.5 * (k % 2))
        rig.step()
        if rig.state == GatewayState.FAULT:
            break
    assert rig.state == GatewayState.FAULT
    assert "dead reckoning" in rig.results[-1].diagnostics.fault
    assert rig.now - started <= 0.5


def test_localization_agreeing_with_dead_reckoning_is_no_drift() -> None:
    rig = Rig(FakeController(cruise(accel=0.5)))
    rig.engage()
    rig.run(3.0)
    assert rig.state == GatewayState.ENGAGED
    assert rig.gw.watchdogs.pose.drift < 0.01


@pytest.mark.parametrize("report, period", [("steer", 0.010), ("long", 0.020), ("system", 0.100)])
def test_ecu_report_withheld_faults_after_three_periods(report: str, period: float) -> None:
    rig = Rig()
    rig.engage()
    rig.step()
    last = rig.now - PERIOD
    rig.send[report] = False
    t_fault = _first_state(rig, GatewayState.FAULT, 1.0)
    assert_within_one_period(t_fault - last, 3 * period)
    assert f"{report}_report age" in rig.results[-1].diagnostics.fault


def test_report_crc_errors_fault_at_five() -> None:
    rig = Rig()
    rig.engage()
    for _ in range(4):
        rig.step(good_report_frames=0, bad_report_frames=1)
    assert rig.state == GatewayState.ENGAGED
    rig.step(good_report_frames=0, bad_report_frames=1)
    assert rig.state == GatewayState.FAULT
    assert rig.results[-1].diagnostics.error_counter == 5


def test_report_errors_balanced_by_good_frames_do_not_fault() -> None:
    rig = Rig()
    rig.engage()
    for _ in range(100):
        rig.step(good_report_frames=2, bad_report_frames=1)
    assert rig.state == GatewayState.ENGAGED


def test_override_hands_back_to_standby() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.override = True
    rig.ecu.enabled = False
    rig.step()
    assert rig.state == GatewayState.STANDBY
    assert not rig.results[-1].commands.steer.enable
    assert "override" in rig.results[-1].diagnostics.reason


@pytest.mark.parametrize(
    "bad",
    [
        ControlOutput(0.3, 0.5, 1.0, converged=False, status="max iterations"),
        ControlOutput(math.nan, 0.5, 1.0),
        ControlOutput(0.0, math.inf, 1.0),
        ControlOutput(0.0, 0.5, -math.nan),
    ],
)
def test_solver_failure_holds_last_safe_command_and_stops(bad: ControlOutput) -> None:
    outputs = iter([ControlOutput(0.1, 0.5, 1.0)] * 40)

    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        return next(outputs, bad)

    rig = Rig(FakeController(script))
    rig.engage()
    rig.run(0.7)
    held = [r for r in rig.results if r.diagnostics.state == GatewayState.STOPPING]
    assert held, "no STOPPING"
    last_good = rig.results[len(rig.results) - len(held) - 1].commands.steer.angle
    assert last_good == pytest.approx(0.1)
    for r in held:
        assert r.commands.steer.enable and r.commands.steer.angle == last_good
        assert math.isfinite(r.commands.long.accel) and r.commands.long.accel <= 0.5


def test_three_overruns_in_a_row_fault_two_do_not() -> None:
    rig = Rig()
    rig.engage()
    rig.step(overrun=True)
    rig.step(overrun=True)
    rig.step()
    rig.step(overrun=True)
    rig.step(overrun=True)
    assert rig.state == GatewayState.ENGAGED
    rig.step(overrun=True)
    assert rig.state == GatewayState.FAULT
    assert "overran" in rig.results[-1].diagnostics.fault


def test_stale_inputs_in_standby_refuse_engage_but_do_not_fault() -> None:
    rig = Rig()
    rig.send["pose"] = False
    rig.send["long"] = False
    rig.run(1.0)
    assert rig.state == GatewayState.STANDBY
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and not reply.accepted


def test_thresholds_come_from_config() -> None:
    cfg = GatewayConfig(watchdog=WatchdogConfig(localization_stop_age=0.3))
    rig = Rig(config=cfg)
    rig.engage()
    rig.step()
    last = rig.now - PERIOD
    rig.send["pose"] = False
    t_stop = _first_state(rig, GatewayState.STOPPING, 1.0)
    assert_within_one_period(t_stop - last, 0.3)


def test_ok_verdicts_of_counters_follow_the_count() -> None:
    counter = ErrorCounter(5)
    first = counter.update(good=0, bad=2)
    assert first.ok and first.value == 2
    assert counter.update(good=0, bad=0) == first  # unchanged count: the same verdict
    assert counter.update(good=1, bad=0).value == 1
    overruns = OverrunWatchdog(3)
    assert overruns.update(False).value == 0
    assert overruns.update(True).value == 1
    assert overruns.update(False).value == 0


def test_report_get_finds_checks_in_any_order() -> None:
    checks = (
        Check("overrun", Status.OK, None, 3, Reaction.NONE, "", 0),
        Check("localization", Status.STALE, 0.2, 0.1, Reaction.STOP, "stale"),
    )
    report = WatchdogReport(checks, None, None, None, None, None)
    assert report.get("localization") is checks[1] and report.get("overrun") is checks[0]
    with pytest.raises(KeyError):
        report.get("trajectory")
    assert report.failing(Reaction.STOP) == (checks[1],)


def test_diagnostics_list_every_watchdog_in_check_order() -> None:
    rig = Rig()
    names = [c.name for c in rig.step().diagnostics.watchdogs]
    assert names == list(CHECK_ORDER)
    assert rig.step().diagnostics.watchdogs[CHECK_ORDER.index("long_report")].ok


# --- ECU reports judged (issue 17, finding 4) ---------------------------------------------------


def _forged_long(rig: Rig, speed: float) -> Stamped:
    genuine = rig.ecu.long_report()
    return Stamped(dataclasses.replace(genuine, speed=speed), rig.now)


def test_forged_speed_disagreeing_with_the_wheel_speeds_faults() -> None:
    # 20 m/s forged while the car does 2 m/s: never detected before, the gate took it for truth
    rig = Rig(FakeController(cruise(accel=0.5)))
    rig.engage()
    rig.run(1.0)
    wheels = Stamped(WheelSpeeds(rig.ecu.speed, rig.ecu.speed, "rear"), rig.now)
    rig.step(wheel_speeds=wheels)
    assert rig.state == GatewayState.ENGAGED  # genuine reports agree
    wheels = Stamped(WheelSpeeds(rig.ecu.speed, rig.ecu.speed, "rear"), rig.now)
    rig.step(wheel_speeds=wheels, long_report=_forged_long(rig, 20.0))
    assert rig.state == GatewayState.FAULT
    assert "disagrees with the rear wheel speeds" in rig.results[-1].diagnostics.fault


def test_forged_angle_disagreeing_with_the_steering_wheel_faults() -> None:
    rig = Rig()
    rig.run(0.2)
    steer = Stamped(dataclasses.replace(rig.ecu.steer_report(), angle=math.radians(20)), rig.now)
    wheel = Stamped(SteeringWheelAngle(0.0), rig.now)
    rig.step(steer_report=steer, steering_wheel=wheel)
    assert rig.state == GatewayState.FAULT  # in any state, like report errors
    assert "disagrees with the steering wheel" in rig.results[-1].diagnostics.fault


def test_angle_beyond_the_mechanical_limit_is_never_taken_as_measured() -> None:
    # 40° forged in STANDBY seeded the gate at 31°: the first engaged command was 30.3°
    rig = Rig()
    rig.run(0.2)
    forged = Stamped(dataclasses.replace(rig.ecu.steer_report(), angle=math.radians(40)), rig.now)
    result = rig.step(steer_report=forged)
    assert abs(result.commands.steer.angle) < math.radians(1.0)  # mirrors the last good angle
    for _ in range(10):  # the same forged report, tick after tick, counts once
        result = rig.step(steer_report=forged)
    assert rig.state == GatewayState.STANDBY


def test_speed_beyond_the_physical_limit_is_invalid() -> None:
    rig = Rig()
    rig.engage()
    for _ in range(6):  # 120 ms of forged reports: none refreshes the long report's age
        rig.step(long_report=_forged_long(rig, 60.0))
    assert rig.state == GatewayState.FAULT
    assert "long_report age" in rig.results[-1].diagnostics.fault


# --- plans that cannot be driven (issue 17, finding 10) -----------------------------------------


def _refusal(trajectory: Trajectory) -> str:
    rig = Rig(trajectory=trajectory)
    rig.run(0.1)
    result = rig.step(OperatorRequest.ENGAGE)
    assert result.reply is not None and not result.reply.accepted
    assert rig.state == GatewayState.STANDBY
    return result.reply.reason


@pytest.mark.parametrize("speed", [4.0, 50.0])
def test_engage_refused_for_a_plan_faster_than_the_maneuver_limit(speed: float) -> None:
    reason = _refusal(straight_trajectory(speed=speed))
    assert f"speed {speed:.2f} m/s above the maneuver limit 3 m/s" in reason


def test_engage_refused_for_a_plan_with_a_heading_flip() -> None:
    plan = straight_trajectory()
    heading = np.array(plan.heading)
    heading[20:] = math.pi  # the path goes on along +x, the heading turns round
    flipped = Trajectory(x=plan.x, y=plan.y, heading=heading, speed=plan.speed)
    assert "heading turns 180° from the waypoint before (a flip)" in _refusal(flipped)


def test_reversing_plan_keeps_its_heading_and_is_no_flip() -> None:
    from leafgate.sim.scenarios import get_scenario

    rig = Rig(trajectory=get_scenario("parallel-park").trajectory)
    assert trajectory_problem(rig.trajectory, max_speed=3.0) is None


def test_report_ages_count_up_to_where_the_bus_was_read() -> None:
    # issue 17, finding 7: a starved receive thread faulted 11 of 71 runs on "steer_report age"
    rig = Rig()
    rig.engage()
    rig.send["steer"] = False  # nothing new read for 60 ms: the thread is behind, frames wait
    for _ in range(3):
        rig.step(reports_as_of=rig.now - 3 * PERIOD + 0.001)
    assert rig.state == GatewayState.ENGAGED
    limit = GatewayConfig().watchdog.max_receive_lag
    rig.step(reports_as_of=rig.now - limit - 0.01)  # … but not for ever
    assert rig.state == GatewayState.FAULT
    assert "CAN receive thread" in rig.results[-1].diagnostics.fault


def test_a_late_receive_thread_at_start_up_latches_no_fault() -> None:
    # frames queue before the thread first reads them (seen in the README's bench block)
    rig = Rig()
    limit = GatewayConfig().watchdog.max_receive_lag
    rig.step(reports_as_of=rig.now - limit - 0.05)
    assert rig.state == GatewayState.STANDBY


# --- no progress along the plan (issue 13) ------------------------------------------------------


def _feed(
    wd: ProgressWatchdog,
    seconds: float,
    t0: float = 0.0,
    speed: float = 0.0,
    plan: object = "plan",
    steer_rate: float = 0.0,
    gear_change: bool = False,
    progress0: float = 0.0,
    route_length: float = 50.0,
    stop_distance: float = math.nan,
) -> tuple[float | None, float]:
    """Feed ticks at 50 Hz; return when the first STOP came (or None) and the end time."""
    t = t0
    for k in range(round(seconds / PERIOD)):
        t = t0 + k * PERIOD
        check = wd.update(
            t,
            plan,
            progress0 + speed * (t - t0),
            route_length,
            steer_rate * (t - t0),
            standstill=abs(speed) < 0.05,
            gear_change=gear_change,
            stop_distance=stop_distance,
        )
        if check.reaction is Reaction.STOP:
            assert check.detail.startswith("no progress")
            return t, t
    return None, t


def test_progress_watchdog_stalled_car_stops_after_the_configured_time() -> None:
    stop_at, _ = _feed(ProgressWatchdog(CFG), 10.0)
    assert stop_at is not None and stop_at == pytest.approx(CFG.no_progress_time, abs=PERIOD)
    cfg = WatchdogConfig(no_progress_time=1.0)
    stop_at, _ = _feed(ProgressWatchdog(cfg), 10.0)
    assert stop_at == pytest.approx(1.0, abs=PERIOD)


def test_progress_watchdog_slow_but_true_progress_is_no_stop() -> None:
    # 0.05 m/s: 0.15 m in every 3 s, above the 0.1 m asked for
    assert _feed(ProgressWatchdog(CFG), 30.0, speed=0.05)[0] is None


def test_progress_watchdog_creeping_below_the_threshold_stops() -> None:
    # 0.02 m/s: 0.06 m in 3 s; the car moves, yet it gets nowhere
    assert _feed(ProgressWatchdog(CFG), 30.0, speed=0.02)[0] is not None


def test_progress_watchdog_waiting_at_rest_for_a_gear_change_is_no_stop() -> None:
    wd = ProgressWatchdog(CFG)
    assert _feed(wd, 10.0, gear_change=True)[0] is None
    # the gear is in: now the car must move within the time
    stop_at, _ = _feed(wd, 10.0, t0=10.0)
    assert stop_at == pytest.approx(10.0 + CFG.no_progress_time, abs=PERIOD)


def test_progress_watchdog_standing_at_the_plans_stop_point_is_no_stop() -> None:
    # the plan comes to rest 20 m into its 50 (a planner's stop line): the car waits there
    # for a plan that moves on, for as long as it takes
    assert _feed(ProgressWatchdog(CFG), 30.0, progress0=20.0, stop_distance=0.03)[0] is None
    assert _feed(ProgressWatchdog(CFG), 30.0, progress0=20.0, stop_distance=-0.2)[0] is None
    # still short of it, or with no stop point ahead, a car at rest gets nowhere
    assert _feed(ProgressWatchdog(CFG), 30.0, progress0=20.0, stop_distance=0.5)[0] is not None
    assert _feed(ProgressWatchdog(CFG), 30.0, progress0=20.0)[0] is not None


def test_progress_watchdog_turning_the_wheel_at_rest_is_no_stop_but_a_stuck_wheel_is() -> None:
    wd = ProgressWatchdog(CFG)
    # at a cusp: the wheel swings 60° at 0.5 rad/s (2.1 s) before the car drives off, which
    # together with the stop before and the pull away takes longer than 3 s
    assert _feed(wd, 2.0, speed=0.02)[0] is None
    assert _feed(wd, 2.1, t0=2.0, steer_rate=0.5, progress0=0.04)[0] is None
    assert _feed(wd, 10.0, t0=4.1, speed=0.3, progress0=0.04)[0] is None
    # an actuator that does not move is no reason to wait
    assert _feed(ProgressWatchdog(CFG), 10.0, steer_rate=0.0)[0] is not None


def test_progress_watchdog_braking_to_a_commanded_stop_is_no_stall_but_resting_after_is() -> None:
    # Past a segment's end (an overshoot) progress stands still while the car brakes to rest.
    wd = ProgressWatchdog(CFG)
    for k in range(250):  # 5 s braking from 2.5 m/s at 0.5 m/s²
        check = wd.update(k * PERIOD, "plan", 6.8, 8.6, 0.0, False, False, commanded_speed=0.0)
        assert check.ok, k
    # at rest, nothing pending, the target still zero: that is a stall
    t0 = 250 * PERIOD
    stop_at = None
    for k in range(300):
        check = wd.update(t0 + k * PERIOD, "plan", 6.8, 8.6, 0.0, True, False, commanded_speed=0.0)
        if check.reaction is Reaction.STOP:
            stop_at = (k + 1) * PERIOD  # since the last braking tick
            break
    assert stop_at == pytest.approx(CFG.no_progress_time, abs=PERIOD)


def test_progress_watchdog_leaves_the_last_stretch_to_the_goal_check() -> None:
    wd = ProgressWatchdog(CFG)
    for k in range(500):  # creeping onto the goal, progress saturated at the plan's end
        check = wd.update(k * PERIOD, "plan", 27.85, 27.9, 0.0, False, False, commanded_speed=0.1)
        assert check.ok
    # at rest on the goal and still not finished: the goal check had its time
    stop_at, _ = _feed(wd, 10.0, t0=10.0, progress0=27.85, route_length=27.9)
    assert stop_at == pytest.approx(10.0 + CFG.no_progress_time, abs=2 * PERIOD)


def test_progress_watchdog_counts_progress_across_re_sent_plans() -> None:
    # A planner's rolling window: a new plan object every 0.5 s, progress counted from its start.
    def rolling(speed: float) -> float | None:
        wd = ProgressWatchdog(CFG)
        for i in range(40):
            stop_at, _ = _feed(wd, 0.5, t0=0.5 * i, speed=speed, plan=object(), progress0=0.3)
            if stop_at is not None:
                return stop_at
        return None

    assert rolling(speed=0.0) == pytest.approx(CFG.no_progress_time, abs=PERIOD)
    assert rolling(speed=0.1) is None


def test_progress_watchdog_ignores_controllers_without_a_route() -> None:
    wd = ProgressWatchdog(CFG)
    for k in range(500):
        check = wd.update(k * PERIOD, "plan", 0.0, 0.0, 0.0, True, False)
        assert check.ok


def test_progress_watchdog_stops_a_car_off_the_plan_at_once() -> None:
    """Farther from the plan than max_path_deviation: a controlled stop on that tick, naming
    the distance; at the limit, or with the distance unknown (NaN), no verdict."""
    wd = ProgressWatchdog(CFG)
    limit = CFG.max_path_deviation
    for k, d in enumerate((0.0, 0.9, limit, math.nan)):
        assert wd.update(k * PERIOD, "plan", 0.1 * k, 30.0, 0.0, False, False, 1.0, d).ok
    check = wd.update(0.1, "plan", 12.0, 30.0, 0.0, False, False, 1.0, limit + 0.01)
    assert check.reaction is Reaction.STOP and check.status is Status.OFF_PLAN
    assert check.detail == f"off the plan: {limit + 0.01:.2f} m from it at 12.0 of 30.0 m " + (
        f"(limit {limit:g} m)"
    )
    assert check.value == pytest.approx(limit + 0.01)


def test_the_deviation_limit_must_exceed_the_engage_envelope() -> None:
    with pytest.raises(ValueError, match=r"max_path_deviation must exceed engage\.max_distance"):
        GatewayConfig(watchdog=WatchdogConfig(max_path_deviation=1.0))
    GatewayConfig(watchdog=WatchdogConfig(max_path_deviation=1.5))


def _progress_rig(progress: Callable[[FakeController, Pose], float], accel: float) -> Rig:
    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        return ControlOutput(
            steer_angle=0.0,
            accel=accel,
            speed=1.0,
            progress=progress(ctl, pose),
            route_length=17.5,
        )

    return Rig(FakeController(script))


def test_gateway_stops_a_car_that_makes_no_progress() -> None:
    # The cusp deadlock of issue 13: status ok, the car at rest, the gateway ENGAGED for good.
    rig = _progress_rig(lambda ctl, pose: 3.0, accel=0.0)
    rig.engage()
    t0 = rig.now
    t_stop = _first_state(rig, GatewayState.STOPPING, 10.0)
    assert t_stop - t0 == pytest.approx(CFG.no_progress_time, abs=0.2)
    reason = rig.results[-1].diagnostics.reason
    assert "no progress" in reason and "3.0 of 17.5 m" in reason
    assert _first_state(rig, GatewayState.STANDBY, 5.0) > 0.0
    check = rig.results[-1].diagnostics.watchdogs[CHECK_ORDER.index("progress")]
    assert check.ok  # forgotten once the gateway no longer drives


def test_gateway_stops_a_car_that_leaves_the_plan() -> None:
    """The controller's deviation beyond the limit: a controlled stop, the reason in the
    diagnostics, then STANDBY."""

    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        off = 1.0 + pose.x  # m from the plan, growing as the car drives on
        return ControlOutput(0.0, 0.5, 1.0, progress=pose.x, route_length=17.5, deviation=off)

    rig = Rig(FakeController(script))
    rig.engage()
    _first_state(rig, GatewayState.STOPPING, 10.0)
    reason = rig.results[-1].diagnostics.reason
    assert reason.startswith("off the plan: 2.0") and "(limit 2 m)" in reason
    assert _first_state(rig, GatewayState.STANDBY, 10.0) > 0.0


def test_gateway_keeps_driving_a_car_that_progresses() -> None:
    rig = _progress_rig(lambda ctl, pose: 2.0 + pose.x, accel=0.05)  # 0.225 m in the first 3 s
    rig.engage()
    rig.run(10.0)
    assert rig.gw.state == GatewayState.ENGAGED
