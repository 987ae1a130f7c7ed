"""Gateway.step end to end with a fake controller and a small fake ECU, in simulated time.

The :class:`Rig` here is also used by ``test_state_machine.py`` and ``test_watchdog.py``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from leafgate.config import VehicleConfig
from leafgate.config.gateway import GatewayConfig
from leafgate.gateway.core import EngagePhase, Gateway, GatewayInputs, StepResult
from leafgate.gateway.safety import Measured, check, gear_sign
from leafgate.messages import (
    ControlOutput,
    EcuState,
    GatewayState,
    Gear,
    LongCommand,
    LongMode,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerCommand,
    SteerReport,
    SystemReport,
    Trajectory,
)

PERIOD = 0.02  # s, default control period (50 Hz)


def straight_trajectory(n: int = 40, spacing: float = 0.5, speed: float = 1.0) -> Trajectory:
    """Waypoints along +x from x = −2 m."""
    x = -2.0 + spacing * np.arange(n)
    return Trajectory(x=x, y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, speed))


Script = Callable[["FakeController", Pose, float], ControlOutput]


def cruise(accel: float = 0.5, angle: float = 0.0, gear: Gear = Gear.D) -> Script:
    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        return ControlOutput(steer_angle=angle, accel=accel, speed=1.0, gear=gear, iterations=3)

    return script


class FakeController:
    """A scripted controller: ``script(self, pose, steer_angle) -> ControlOutput``."""

    period = PERIOD

    def __init__(self, script: Script | None = None) -> None:
        self.script = script or cruise()
        self.calls = 0
        self.resets = 0
        self.last_trajectory: Trajectory | None = None

    def reset(self) -> None:
        self.resets += 1
        self.calls = 0

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        self.calls += 1
        self.last_trajectory = trajectory
        return self.script(self, pose, steer_angle)


@dataclass
class FakeEcu:
    """Enables on a 0→1 ENABLE edge, latches override until CLEAR_OVERRIDE, shifts at rest,
    and moves a one-dimensional car along +x."""

    speed: float = 0.0  # m/s, signed
    x: float = 0.0  # m
    angle: float = 0.0  # rad
    gear: Gear = Gear.D
    enabled: bool = False
    override: bool = False
    state: EcuState = EcuState.READY
    fault: bool = False
    follow_enable: bool = True  # False: never enables (a broken ECU)
    prev_enable: bool | None = None  # None: no frame seen yet (the first ENABLE=1 is no edge)
    sent: list[tuple[float, SteerCommand, LongCommand]] = field(default_factory=list)

    def command(self, now: float, steer: SteerCommand, long: LongCommand) -> None:
        self.sent.append((now, steer, long))
        if steer.clear_override or long.clear_override:
            self.override = False
        edge = steer.enable and self.prev_enable is False
        self.prev_enable = steer.enable
        if not steer.enable:
            self.enabled = False
        elif edge and self.follow_enable and not self.override and not self.fault:
            self.enabled = True
        if self.enabled:
            self.angle = steer.angle
            if long.gear != Gear.NONE and abs(self.speed) < 0.05:
                self.gear = long.gear
            sign = gear_sign(self.gear)
            if long.accel < 0.0:  # brake towards rest, never reverse
                mag = max(abs(self.speed) + long.accel * PERIOD, 0.0)
                self.speed = math.copysign(mag, self.speed)
            else:
                self.speed += sign * long.accel * PERIOD
        else:  # the driver brakes to rest
            mag = max(abs(self.speed) - 3.0 * PERIOD, 0.0)
            self.speed = math.copysign(mag, self.speed)
        self.x += self.speed * PERIOD

    def steer_report(self) -> SteerReport:
        return SteerReport(self.angle, 0.0, 0.0, self.enabled, self.override, self.fault, False)

    def long_report(self) -> LongReport:
        return LongReport(
            self.speed, 0.0, self.gear, 0.0, 0.0, self.enabled, self.override, self.fault, False
        )

    def system_report(self) -> SystemReport:
        if self.fault:
            state = EcuState.FAULT
        elif self.override:
            state = EcuState.OVERRIDE
        elif self.enabled:
            state = EcuState.ENGAGED
        else:
            state = self.state
        return SystemReport(state, False, False, False, self.fault, 0)


class Rig:
    """A gateway stepped at 50 Hz of simulated time with fresh inputs unless told otherwise.

    Withheld inputs keep their last sample (as the runtime's latest-value slots do).
    """

    def __init__(
        self,
        controller: FakeController | None = None,
        config: GatewayConfig | None = None,
        mode: LongMode = LongMode.ACCELERATION,
        trajectory: Trajectory | None = None,
    ) -> None:
        self.controller = controller or FakeController()
        self.config = config or GatewayConfig()
        self.gw = Gateway(self.config, VehicleConfig(), self.controller, mode)
        self.ecu = FakeEcu()
        self.trajectory = trajectory or straight_trajectory()
        self.k = 0
        self.send = {"pose": True, "trajectory": True, "steer": True, "long": True, "system": True}
        self.pose_offset = (0.0, 0.0)  # m, added to the localization (jumps, off-path starts)
        self.heading = 0.0  # rad
        self.slots: dict[str, Stamped | None] = dict.fromkeys(self.send)
        self.results: list[StepResult] = []
        self.measured: list[tuple[float, Gear]] = []  # the ECU's speed and gear at each step

    @property
    def now(self) -> float:
        return self.k * PERIOD

    def step(self, request: OperatorRequest | None = None, **kw: object) -> StepResult:
        now = self.now
        values = {
            "pose": Pose(
                self.ecu.x + self.pose_offset[0],
                self.pose_offset[1],
                self.heading,
                self.ecu.speed,
                stamp=now,
            ),
            "trajectory": self.trajectory,
            "steer": self.ecu.steer_report(),
            "long": self.ecu.long_report(),
            "system": self.ecu.system_report(),
        }
        for name, value in values.items():
            if self.send[name]:
                self.slots[name] = Stamped(value, now)
        inputs = GatewayInputs(
            pose=self.slots["pose"],
            trajectory=self.slots["trajectory"],
            steer_report=self.slots["steer"],
            long_report=self.slots["long"],
            system_report=self.slots["system"],
            good_report_frames=3,
            request=request,
        )
        if kw:
            inputs = replace(inputs, **kw)  # type: ignore[arg-type]
        self.measured.append((self.ecu.speed, self.ecu.gear))
        result = self.gw.step(now, inputs)
        self.ecu.command(now, result.commands.steer, result.commands.long)
        self.results.append(result)
        self.k += 1
        return result

    def run(self, seconds: float, **kw: object) -> StepResult:
        result = self.step(**kw)  # type: ignore[arg-type]
        for _ in range(round(seconds / PERIOD) - 1):
            result = self.step()
        return result

    def engage(self) -> StepResult:
        """Warm up the inputs, engage, and let the ECU confirm."""
        self.run(0.1)
        result = self.step(OperatorRequest.ENGAGE)
        assert result.reply is not None and result.reply.accepted, result.reply
        self.run(0.1)
        assert self.gw.state == GatewayState.ENGAGED
        return result

    @property
    def state(self) -> GatewayState:
        return self.gw.state


# --- a whole maneuver ----------------------------------------------------------------------------


def test_engage_drive_to_trajectory_end_returns_to_standby() -> None:
    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        if ctl.calls <= 50:  # accelerate for 1 s, then brake
            return ControlOutput(steer_angle=0.05, accel=0.8, speed=0.8)
        at_rest = abs(pose.speed) < 0.01
        return ControlOutput(steer_angle=0.05, accel=-1.0, speed=0.0, finished=at_rest)

    rig = Rig(FakeController(script))
    rig.run(0.1)
    assert rig.state == GatewayState.STANDBY
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and reply.accepted and reply.state == GatewayState.ENGAGED
    seen = {rig.state}
    for _ in range(300):
        result = rig.step()
        seen.add(rig.state)
        if rig.state == GatewayState.STANDBY:
            break
    assert rig.state == GatewayState.STANDBY
    assert GatewayState.FAULT not in seen and GatewayState.STOPPING not in seen
    assert result.diagnostics.reason == "trajectory end reached"
    assert not result.commands.steer.enable and not result.commands.long.enable
    assert rig.ecu.x > 0.3  # the car moved
    enabled = [r for r in rig.results if r.commands.steer.enable]
    assert len(enabled) > 50
    assert rig.controller.resets == 1


def test_standby_frames_mirror_the_measured_angle_with_enable_off() -> None:
    rig = Rig()
    rig.ecu.angle = 0.2
    result = rig.run(0.1)
    assert result.commands.steer == SteerCommand(angle=0.2, enable=False)
    assert result.commands.long == LongCommand(mode=LongMode.ACCELERATION, enable=False)
    assert rig.controller.calls == 0


def test_engaged_frames_carry_enable_and_the_gated_controller_command() -> None:
    rig = Rig(FakeController(cruise(accel=10.0, angle=1.0)))
    rig.engage()
    result = rig.step()
    steer, long = result.commands.steer, result.commands.long
    assert steer.enable and long.enable
    limits = rig.gw.limits
    assert 0.0 < steer.angle < 1.0 and 0.0 < long.accel <= limits.max_accel
    assert {"angle_rate", "jerk"} <= set(result.diagnostics.clamped)
    assert result.diagnostics.clamps["angle_rate"] > 0


def test_engage_sends_an_enable_edge_after_standby_frames() -> None:
    rig = Rig()
    rig.run(0.1)
    assert not rig.results[-1].commands.steer.enable
    rig.step(OperatorRequest.ENGAGE)
    assert rig.results[-1].commands.steer.enable and rig.results[-1].commands.long.enable
    rig.run(0.1)
    assert rig.ecu.enabled
    assert rig.results[-1].diagnostics.engage_phase is EngagePhase.ACTIVE


def test_an_engage_on_the_first_tick_sends_enable_0_before_the_edge() -> None:
    # CI: an engage queued while the daemon started ran on its first tick, whose frames carried
    # ENABLE=1; the ECU had seen no ENABLE=0 before it, so there was no edge and it never engaged
    # ("ECU did not report ENABLED", or with a profile without an ECU state report, a car left
    # standing until the no-progress watchdog).
    rig = Rig()
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and reply.accepted and rig.state == GatewayState.ENGAGED
    first = rig.results[0].commands
    assert not first.steer.enable and not first.long.enable
    assert rig.controller.calls == 0  # nothing of the controller's went out, nor was computed
    rig.run(0.1)
    assert rig.results[1].commands.steer.enable and rig.results[1].commands.long.enable
    assert rig.ecu.enabled and rig.state == GatewayState.ENGAGED
    assert rig.results[-1].diagnostics.engage_phase is EngagePhase.ACTIVE


@pytest.mark.parametrize("gear, sign", [(Gear.D, 1.0), (Gear.R, -1.0)])
def test_wire_accel_is_gear_relative_and_speed_a_magnitude(gear: Gear, sign: float) -> None:
    # The controller's accel is d(signed v)/dt: in R, −0.3 means speeding up backwards.
    rig = Rig(FakeController(lambda c, p, s: ControlOutput(0.0, 0.3 * sign, 1.2 * sign, gear=gear)))
    rig.ecu.gear = gear
    rig.engage()
    long = rig.step().commands.long
    assert long.accel == pytest.approx(0.3)
    assert long.speed == pytest.approx(1.2)


def test_gear_change_brakes_then_shifts_at_standstill_then_drives_on() -> None:
    rig = Rig(FakeController(cruise(accel=0.5, gear=Gear.D)))
    rig.engage()
    rig.run(1.0)
    assert rig.ecu.speed > 0.3
    rig.controller.script = cruise(accel=-0.5, gear=Gear.R)
    requested_while_moving = False
    shifted_at = None
    last_accel = rig.results[-1].commands.long.accel
    for _ in range(200):
        speed_before = rig.ecu.speed
        result = rig.step()
        if rig.ecu.gear == Gear.D:  # braking builds up (jerk-limited) and is held
            assert result.diagnostics.gear_change
            assert result.commands.long.accel <= last_accel
            last_accel = result.commands.long.accel
        if result.commands.long.gear == Gear.R:
            requested_while_moving |= abs(speed_before) >= 0.05
        if rig.ecu.gear == Gear.R and shifted_at is None:
            shifted_at = rig.k
        if shifted_at is not None and rig.k > shifted_at + 5:
            break
    assert shifted_at is not None
    assert not requested_while_moving
    assert rig.state == GatewayState.ENGAGED
    after = rig.run(0.6)  # the jerk bound releases the brake over 0.4 s
    assert not after.diagnostics.gear_change
    assert after.commands.long.accel == pytest.approx(0.5)  # gear-relative: faster backwards
    assert rig.ecu.speed < 0.0


def test_gear_request_while_moving_is_refused_by_the_gate() -> None:
    rig = Rig(FakeController(cruise(accel=1.0)))
    rig.engage()
    rig.run(1.0)
    # A controller bypassing the brake phase: ask for R in D at speed.
    gate = rig.gw.gate
    _, long = gate.apply(
        SteerCommand(gate.last_steer.angle, enable=True),
        LongCommand(accel=gate.last_long.accel, gear=Gear.R, enable=True),
        Measured(rig.ecu.speed, Gear.D),
    )
    assert long.gear == Gear.NONE and "gear" in gate.last_clamped


def test_system_command_every_100_ms_and_at_once_on_reset() -> None:
    rig = Rig()
    times = []
    for _ in range(50):
        result = rig.step()
        if result.commands.system is not None:
            times.append(round(rig.now - PERIOD, 6))
    assert times == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    rig.step()
    result = rig.step(OperatorRequest.RESET)
    assert result.commands.system is not None and result.commands.system.clear_faults
    assert result.commands.system.state == GatewayState.STANDBY
    nxt = [rig.step().commands.system for _ in range(5)]
    assert [s is not None for s in nxt] == [False, False, False, False, True]
    assert not any(s.clear_faults for s in nxt if s is not None)


def test_system_command_carries_the_gateway_state() -> None:
    rig = Rig()
    rig.engage()
    systems = [rig.step().commands.system for _ in range(10)]
    assert any(s is not None and s.state == GatewayState.ENGAGED for s in systems)


def test_diagnostics_to_dict_is_json() -> None:
    rig = Rig(FakeController(lambda c, p, s: ControlOutput(0.0, 0.1, 1.0, cost=math.nan)))
    rig.engage()
    d = rig.step().diagnostics.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    assert back["state"] == "ENGAGED"
    assert back["controller"]["cost"] is None and back["controller"]["iterations"] == 0
    assert set(back["watchdogs"]) == {
        "localization",
        "trajectory",
        "steer_report",
        "long_report",
        "system_report",
        "report_errors",
        "overrun",
        "progress",
    }
    assert back["watchdogs"]["localization"]["status"] == "ok"
    assert set(back["clamps"]) >= {"angle", "angle_rate", "lateral_accel", "accel", "jerk"}


def test_controller_exception_holds_steering_and_stops() -> None:
    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        if ctl.calls > 30:
            raise RuntimeError("solver blew up")
        return ControlOutput(0.1, 0.5, 1.0)

    rig = Rig(FakeController(script))
    rig.engage()
    rig.run(0.5)
    assert rig.state == GatewayState.STOPPING
    assert "RuntimeError" in rig.results[-1].diagnostics.reason


def test_every_engaged_frame_passes_the_safety_check() -> None:
    rng = np.random.default_rng(7)

    def script(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
        return ControlOutput(
            steer_angle=float(rng.uniform(-1, 1)),
            accel=float(rng.uniform(-8, 8)),
            speed=float(rng.uniform(-5, 5)),
        )

    rig = Rig(FakeController(script))
    rig.engage()
    rig.run(3.0)
    checked = 0
    for k in range(1, len(rig.results)):
        cmds, prev = rig.results[k].commands, rig.results[k - 1].commands
        if not cmds.steer.enable:
            continue
        measured = Measured(rig.measured[k][0], rig.measured[k][1])
        assert check(cmds.steer, cmds.long, prev.steer, prev.long, measured, rig.gw.limits) == ()
        checked += 1
    assert checked > 100


def test_diagnostics_to_dict_keys_and_controller_figures() -> None:
    out = ControlOutput(0.0, 0.1, 1.0, iterations=4, solve_time=0.002, clips=1, nearest_index=7)
    rig = Rig(FakeController(lambda c, p, s: out))
    rig.engage()
    d = rig.step().diagnostics.to_dict()
    assert list(d) == [
        "time",
        "state",
        "reason",
        "fault",
        "fault_causes",
        "engage_phase",
        "watchdogs",
        "error_counter",
        "overruns_in_row",
        "ecu_state",
        "controller",
        "gear_change",
        "clamps",
        "clamped",
        "transitions",
    ]
    assert d["controller"] == {
        "converged": True,
        "iterations": 4,
        "solve_time": 0.002,
        "clips": 1,
        "cost": None,
        "nearest_index": 7,
        "finished": False,
        "gear": "D",
        "status": "ok",
    }
    assert d["ecu_state"] == "ENGAGED" and d["overruns_in_row"] == 0
    assert d["watchdogs"]["report_errors"] == {
        "status": "ok",
        "age": None,
        "limit": 5,
        "reaction": "NONE",
        "detail": "",
        "value": 0,
    }


def test_earlier_diagnostics_keep_their_clamp_counts() -> None:
    rig = Rig(FakeController(cruise(accel=10.0, angle=1.0)))  # clamped every tick
    rig.engage()
    first = rig.step().diagnostics
    counts = dict(first.clamps)
    later = rig.run(0.2).diagnostics
    assert first.clamps == counts
    assert later.clamps["jerk"] > counts["jerk"]


def test_a_disengage_from_a_stop_signal_names_the_signal_not_the_operator() -> None:
    """The daemon's shutdown ticks disengage with the signal as the reason (docs/state-machine.md)."""
    rig = Rig()
    rig.engage()
    result = rig.step(OperatorRequest.DISENGAGE, request_reason="SIGTERM received")
    assert rig.state == GatewayState.STANDBY
    (transition,) = result.diagnostics.transitions
    assert transition.reason == "SIGTERM received"
    rig.engage()
    (transition,) = rig.step(OperatorRequest.DISENGAGE).diagnostics.transitions
    assert transition.reason == "operator disengage"
