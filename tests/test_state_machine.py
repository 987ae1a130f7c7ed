"""The engagement state machine: the transition table, every refusal of an engage request, and
every transition driven through the gateway in simulated time."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from test_gateway_core import PERIOD, FakeController, Rig, cruise, straight_trajectory

from leafgate.config.gateway import EngageConfig, GatewayConfig, StopConfig, WatchdogConfig
from leafgate.gateway.state import (
    TRANSITIONS,
    EngagementMachine,
    Event,
    next_state,
    path_deviation,
)
from leafgate.messages import (
    ControlOutput,
    EcuState,
    GatewayState,
    Gear,
    OperatorRequest,
    Pose,
    Trajectory,
)

S = GatewayState
E = Event

# The specification, written out: (state, event) → state; every pair not listed is ignored.
EXPECTED = {
    (S.STANDBY, E.ENGAGE): S.ENGAGED,
    (S.STANDBY, E.FAULT): S.FAULT,
    (S.ENGAGED, E.DISENGAGE): S.STANDBY,
    (S.ENGAGED, E.STOP): S.STOPPING,
    (S.ENGAGED, E.AT_REST): S.STANDBY,
    (S.ENGAGED, E.ABORT): S.STANDBY,
    (S.ENGAGED, E.OVERRIDE): S.STANDBY,
    (S.ENGAGED, E.FAULT): S.FAULT,
    (S.STOPPING, E.DISENGAGE): S.STANDBY,
    (S.STOPPING, E.AT_REST): S.STANDBY,
    (S.STOPPING, E.OVERRIDE): S.STANDBY,
    (S.STOPPING, E.FAULT): S.FAULT,
    (S.FAULT, E.RESET): S.STANDBY,
}


@pytest.mark.parametrize("state", list(S))
@pytest.mark.parametrize("event", list(E))
def test_transition_table(state: GatewayState, event: Event) -> None:
    assert next_state(state, event) == EXPECTED.get((state, event))


def test_fault_is_left_only_by_reset() -> None:
    assert [e for (s, e) in TRANSITIONS if s == S.FAULT] == [E.RESET]


def test_machine_records_transitions_and_latches_fault_causes() -> None:
    m = EngagementMachine()
    assert m.fire(E.ENGAGE, 1.0, "operator engage")
    assert not m.fire(E.ENGAGE, 1.1, "again")
    assert m.fire(E.FAULT, 1.2, "lost", frozenset({"localization"}))
    assert not m.fire(E.FAULT, 1.3, "errors", frozenset({"report_errors"}))
    assert m.fault_causes == {"localization", "report_errors"}
    assert m.fault_reason == "lost"
    assert [(t.source, t.target) for t in m.transitions] == [
        (S.STANDBY, S.ENGAGED),
        (S.ENGAGED, S.FAULT),
    ]
    m.begin_tick()
    assert m.fire(E.RESET, 2.0, "reset")
    assert m.state == S.STANDBY and m.fault_causes == frozenset() and m.fault_reason == ""
    assert m.transitions[0].to_dict() == {
        "time": 2.0,
        "from": "FAULT",
        "to": "STANDBY",
        "reason": "reset",
    }


# --- path deviation ----------------------------------------------------------------------------


def test_path_deviation_uses_the_nearest_point_of_the_polyline() -> None:
    traj = Trajectory(
        x=np.array([0.0, 1.0, 1.0]),
        y=np.array([0.0, 0.0, 1.0]),
        heading=np.array([0.0, math.pi / 2, math.pi / 2]),
        speed=np.ones(3),
    )
    d, h = path_deviation(Pose(0.5, 0.3, 0.0, 0.0), traj)
    assert d == pytest.approx(0.3)  # between the waypoints, not to one of them
    assert h == pytest.approx(math.pi / 4)  # heading interpolated along the segment
    d, h = path_deviation(Pose(1.4, 0.6, math.pi / 2, 0.0), traj)
    assert d == pytest.approx(0.4) and h == pytest.approx(0.0)


def test_path_deviation_wraps_heading() -> None:
    traj = Trajectory(
        x=np.array([0.0, 1.0]), y=np.zeros(2), heading=np.full(2, math.pi - 0.1), speed=np.ones(2)
    )
    _, h = path_deviation(Pose(0.5, 0.0, -math.pi + 0.1, 0.0), traj)
    assert h == pytest.approx(0.2)


# --- refusals, table-driven, in simulated time -------------------------------------------------

Setup = Callable[[Rig], None]


def _withhold(name: str, seconds: float) -> Setup:
    def setup(rig: Rig) -> None:
        rig.run(0.1)
        rig.send[name] = False
        rig.run(seconds)

    return setup


def _never(name: str) -> Setup:
    def setup(rig: Rig) -> None:
        rig.send[name] = False
        rig.slots[name] = None
        rig.run(0.1)

    return setup


def _set(**attrs: object) -> Setup:
    def setup(rig: Rig) -> None:
        for key, value in attrs.items():
            target = rig.ecu if hasattr(rig.ecu, key) else rig
            setattr(target, key, value)
        rig.run(0.1)

    return setup


def _trajectory(traj: Trajectory) -> Setup:
    def setup(rig: Rig) -> None:
        rig.trajectory = traj
        rig.run(0.1)

    return setup


def _fault(rig: Rig) -> None:
    rig.step(overrun=True)
    rig.step(overrun=True)
    rig.step(overrun=True)
    assert rig.state == S.FAULT


def _stopping(rig: Rig) -> None:
    rig.engage()
    rig.run(1.0)
    rig.send["pose"] = False
    rig.run(0.12)
    assert rig.state == S.STOPPING


_NAN_TRAJ = straight_trajectory()
_NAN_TRAJ = Trajectory(
    x=np.where(np.arange(len(_NAN_TRAJ)) == 3, np.nan, _NAN_TRAJ.x),
    y=_NAN_TRAJ.y,
    heading=_NAN_TRAJ.heading,
    speed=_NAN_TRAJ.speed,
)

REFUSALS: list[tuple[str, Setup, str]] = [
    ("pose_stale", _withhold("pose", 0.2), "localization not fresh"),
    ("pose_missing", _never("pose"), "localization not fresh and valid: localization missing"),
    ("pose_invalid", _set(pose_offset=(math.inf, 0.0)), "localization invalid"),
    ("trajectory_missing", _never("trajectory"), "trajectory missing"),
    ("trajectory_stale", _withhold("trajectory", 1.2), "trajectory age"),
    ("trajectory_non_finite", _trajectory(_NAN_TRAJ), "trajectory invalid"),
    ("trajectory_one_point", _trajectory(straight_trajectory(n=1)), "trajectory invalid"),
    ("steer_report_stale", _withhold("steer", 0.1), "steer_report age"),
    ("long_report_stale", _withhold("long", 0.1), "long_report age"),
    ("system_report_stale", _withhold("system", 0.4), "system_report age"),
    ("system_report_missing", _never("system"), "system_report missing"),
    ("ecu_fault", _set(fault=True), "ECU reports state FAULT, actuator fault; reset first"),
    ("ecu_not_ready", _set(state=EcuState.NOT_READY), "ECU not ready (state NOT_READY)"),
    # the car has sent no gear yet (issue 15: no plausible default before it does)
    ("gear_unknown", _set(gear=Gear.NONE), "gear unknown: no gear received from the car yet"),
    ("off_path", _set(pose_offset=(0.0, 1.05)), "1.05 m from the trajectory"),
    ("off_heading", _set(heading=math.radians(31.0)), "heading 31.0° off the trajectory"),
    ("fault_latched", _fault, "fault latched (control loop overran 3 ticks in a row)"),
    ("stopping", _stopping, "stopping"),
]


@pytest.mark.parametrize(
    "setup, reason", [(s, r) for _, s, r in REFUSALS], ids=[n for n, _, _ in REFUSALS]
)
def test_engage_refused(setup: Setup, reason: str) -> None:
    rig = Rig()
    setup(rig)
    before = rig.state
    result = rig.step(OperatorRequest.ENGAGE)
    assert result.reply is not None and not result.reply.accepted
    assert reason in result.reply.reason
    assert rig.state == before and result.reply.state == before
    assert not result.commands.steer.enable or before == S.STOPPING


@pytest.mark.parametrize(
    "setup",
    [
        _set(pose_offset=(0.0, 0.95)),
        _set(heading=math.radians(29.0)),
        _withhold("pose", 0.08),
    ],  # 100 ms old at the engage tick
    ids=["0.95_m_off", "29_deg_off", "pose_100_ms_old"],
)
def test_engage_accepted_just_inside_the_limits(setup: Setup) -> None:
    rig = Rig()
    setup(rig)
    result = rig.step(OperatorRequest.ENGAGE)
    assert result.reply is not None and result.reply.accepted, result.reply


def test_engage_limits_come_from_config() -> None:
    cfg = GatewayConfig(engage=EngageConfig(max_distance=0.5))
    rig = Rig(config=cfg)
    rig.pose_offset = (0.0, 0.6)
    rig.run(0.1)
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and not reply.accepted and "limit 0.5 m" in reply.reason


# --- transitions in simulated time -------------------------------------------------------------


def test_disengage_hands_back_at_once() -> None:
    rig = Rig()
    rig.engage()
    result = rig.step(OperatorRequest.DISENGAGE)
    assert result.reply is not None and result.reply.accepted
    assert rig.state == S.STANDBY and not result.commands.steer.enable
    assert not result.commands.long.enable
    assert [(t.source, t.target) for t in result.diagnostics.transitions] == [
        (S.ENGAGED, S.STANDBY)
    ]


def test_disengage_in_standby_and_reset_while_engaged() -> None:
    rig = Rig()
    reply = rig.step(OperatorRequest.DISENGAGE).reply
    assert reply is not None and not reply.accepted and not reply.changed
    assert rig.state == S.STANDBY
    rig.engage()
    reply = rig.step(OperatorRequest.RESET).reply
    assert reply is not None and not reply.accepted and rig.state == S.ENGAGED
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and not reply.accepted and reply.reason == "already engaged"
    assert not reply.changed and reply.state == S.ENGAGED


def test_controlled_stop_brakes_within_comfort_limits_holds_steering_then_standby() -> None:
    cfg = GatewayConfig(watchdog=WatchdogConfig(localization_fault_age=5.0))
    rig = Rig(FakeController(cruise(accel=1.0, angle=0.05)), config=cfg)
    rig.engage()
    rig.run(2.0)
    assert rig.ecu.speed > 1.5
    rig.send["pose"] = False
    while rig.state == S.ENGAGED:
        rig.step()
    assert rig.state == S.STOPPING
    held = rig.results[-1].commands.steer.angle
    stop = StopConfig()
    prev_accel = rig.results[-1].commands.long.accel
    while rig.state == S.STOPPING:
        result = rig.step()
        if rig.state != S.STOPPING:
            break
        long = result.commands.long
        assert result.commands.steer.enable and result.commands.steer.angle == held
        assert long.accel >= -stop.decel - 1e-12
        assert abs(long.accel - prev_accel) <= stop.jerk * PERIOD + 1e-12
        prev_accel = long.accel
        assert rig.k < 1000
    assert rig.state == S.STANDBY
    assert abs(rig.ecu.speed) < 0.05
    assert "at rest after a controlled stop (localization age" in rig.results[-1].diagnostics.reason
    assert not rig.results[-1].commands.steer.enable


def test_disengage_during_stop_hands_back() -> None:
    rig = Rig()
    _stopping(rig)
    reply = rig.step(OperatorRequest.DISENGAGE).reply
    assert reply is not None and reply.accepted and rig.state == S.STANDBY


def test_fault_while_driving_keeps_braking_until_at_rest_then_enable_off() -> None:
    rig = Rig(FakeController(cruise(accel=1.0)))
    rig.engage()
    rig.run(2.0)
    rig.send["pose"] = False
    while rig.state != S.FAULT:
        rig.step()
    assert rig.ecu.speed > 0.2
    braking = 0
    while rig.results[-1].commands.steer.enable:
        result = rig.step()
        braking += 1
        assert result.commands.long.accel <= 0.0 and rig.k < 1000
    assert braking > 5 and abs(rig.ecu.speed) < 0.05 and rig.state == S.FAULT


def test_reset_refused_while_cause_present_then_accepted_with_clear_faults() -> None:
    rig = Rig()
    rig.engage()
    rig.send["long"] = False
    rig.run(0.1)
    assert rig.state == S.FAULT
    result = rig.step(OperatorRequest.RESET)
    assert result.reply is not None and not result.reply.accepted
    assert "long_report" in result.reply.reason and rig.state == S.FAULT
    assert result.commands.system is None or not result.commands.system.clear_faults
    rig.send["long"] = True
    rig.step()
    result = rig.step(OperatorRequest.RESET)
    assert result.reply is not None and result.reply.accepted and rig.state == S.STANDBY
    assert result.commands.system is not None and result.commands.system.clear_faults
    assert rig.step(OperatorRequest.ENGAGE).reply.accepted  # type: ignore[union-attr]


def test_override_then_engage_clears_override_before_the_enable_edge() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.override, rig.ecu.enabled = True, False
    rig.step()
    assert rig.state == S.STANDBY
    rig.run(0.2)
    result = rig.step(OperatorRequest.ENGAGE)
    assert result.reply is not None and result.reply.accepted
    assert "clearing the override" in result.reply.reason
    first = result.commands
    assert first.steer.clear_override and first.long.clear_override
    assert not first.steer.enable and not first.long.enable
    rig.run(0.2)
    cmds = [r.commands for r in rig.results[-11:]]
    # ENABLE only after CLEAR_OVERRIDE went out with ENABLE=0: the ECU sees a clean edge.
    first_enable = next(i for i, c in enumerate(cmds) if c.steer.enable)
    assert first_enable > 0 and not cmds[first_enable - 1].steer.enable
    assert rig.ecu.enabled and rig.state == S.ENGAGED


def test_override_not_cleared_aborts_engage() -> None:
    rig = Rig()
    rig.run(0.1)
    rig.ecu.override = True
    rig.step()
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and reply.accepted
    for _ in range(40):
        rig.ecu.override = True  # the driver still holds the wheel
        rig.step()
    assert rig.state == S.STANDBY
    reasons = [t.reason for r in rig.results for t in r.diagnostics.transitions]
    assert reasons[-1] == "override not cleared within 0.5 s"
    assert not any(r.commands.steer.enable for r in rig.results)


def test_ecu_not_enabling_aborts_engage() -> None:
    rig = Rig()
    rig.ecu.follow_enable = False
    rig.run(0.1)
    rig.step(OperatorRequest.ENGAGE)
    rig.run(0.6)
    assert rig.state == S.STANDBY
    reasons = [t.reason for r in rig.results for t in r.diagnostics.transitions]
    assert any("did not report ENABLED within 0.5 s" in r for r in reasons)


def test_ecu_dropping_engagement_faults_and_reset_clears_it() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.enabled = False  # e.g. its command timeout, without an override
    rig.step()
    assert rig.state == S.FAULT and "ECU disengaged" in rig.results[-1].diagnostics.fault
    result = rig.step(OperatorRequest.RESET)
    assert result.reply is not None and result.reply.accepted
    assert result.commands.system is not None and result.commands.system.clear_faults


def test_ecu_fault_flag_while_engaged_faults() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.fault = True
    rig.step()
    assert rig.state == S.FAULT and "ECU reports" in rig.results[-1].diagnostics.fault
    assert rig.results[-1].diagnostics.fault_causes == ("ecu",)


@pytest.mark.parametrize(
    "kw, cause",
    [
        ({"overrun": True}, "overrun"),
        ({"bus_errors": 1}, "bus"),
        ({"bad_report_frames": 5}, "report_errors"),
    ],
)
def test_faults_latch_in_standby(kw: dict[str, object], cause: str) -> None:
    rig = Rig()
    rig.run(0.1)
    for _ in range(3):
        rig.step(**kw)
    assert rig.state == S.FAULT and cause in rig.results[-1].diagnostics.fault_causes
    assert not rig.results[-1].commands.steer.enable


def test_stopping_escalates_to_fault() -> None:
    rig = Rig()
    _stopping(rig)
    rig.step(bus_errors=2)
    assert rig.state == S.FAULT


def test_trajectory_end_while_moving_goes_through_stopping() -> None:
    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        return ControlOutput(0.0, 1.0, 1.0, finished=ctl.calls > 30)

    rig = Rig(FakeController(script))
    rig.engage()
    rig.run(1.0)
    states = [r.diagnostics.state for r in rig.results]
    assert S.STOPPING in states
    rig.run(2.0)
    assert rig.state == S.STANDBY


def test_fault_causes_in_diagnostics_follow_causes_added_while_in_fault() -> None:
    # Diagnostics keep the sorted causes between ticks: a cause added in FAULT must show.
    rig = Rig()
    rig.run(0.1)
    rig.step(bus_errors=1)
    assert rig.state == S.FAULT and rig.results[-1].diagnostics.fault_causes == ("bus",)
    rig.step(bad_report_frames=5)
    assert rig.results[-1].diagnostics.fault_causes == ("bus", "report_errors")
    rig.run(0.1)
    assert rig.step(OperatorRequest.RESET).reply is not None
    assert rig.state == S.STANDBY and rig.results[-1].diagnostics.fault_causes == ()
