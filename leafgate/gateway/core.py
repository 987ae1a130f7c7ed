"""The gateway's decision core: ``Gateway.step(now, inputs) -> StepResult``.

Pure and clock-free: the runtime (daemon), the process tests and the simulator call ``step``
with the latest inputs and their receive times, and send what it returns. One tick:

1. the watchdogs judge every input (:mod:`leafgate.gateway.watchdog`);
2. their reactions move the engagement state (:mod:`leafgate.gateway.state`): faults latch,
   an override hands back, a stale localization starts a controlled stop;
3. the operator's request, if any, is answered (engage preconditions, reset when the fault's
   cause is gone);
4. the commands of the state are built — STANDBY/FAULT mirror the measured values with
   ENABLE=0, ENGAGED runs the controller (handling gear changes at standstill), STOPPING brakes
   to rest with the steering held — and every ENABLE=1 command passes the safety gate
   (:mod:`leafgate.gateway.safety`) last;
5. DBW_SYSTEM_CMD is added when due (every 100 ms of ``now``, and at once on a reset).

Decisions behind the tables of docs/watchdogs.md and docs/state-machine.md (the tests hold them):

- Staleness of localization and ECU reports acts only while the gateway drives (ENGAGED or
  STOPPING); in STANDBY it only refuses an engage, so a gateway started before its inputs does
  not latch a fault. Report frame errors, loop overruns and CAN send errors latch FAULT in any
  state.
- An operator ``disengage`` hands back at once (ENABLE=0), as Autoware's manual mode does; the
  ECU's own not-engaged behaviour takes over.
- A fault raised while the ECU is enabled keeps ENABLE=1 and brakes at ``stop.fault_decel``
  with the steering held until the car is at rest (or the long report is lost), then sends
  ENABLE=0 — a localization loss during a controlled stop must not release the car mid-stop.
- The controller's ``finished`` (end reached, at rest) goes straight to STANDBY when the measured
  speed is below the standstill speed, and through STOPPING otherwise.
- Reset is accepted in FAULT when every latched cause is gone (``ecu`` causes are what the
  CLEAR_FAULTS of the reset clears) and in STANDBY (to clear ECU faults); not while driving.
- Frames on the gateway's own command IDs that it did not send (another node commanding the
  ECU) latch FAULT in any state, as a command conflict; the cause is gone once no such frame
  was seen for ``FOREIGN_QUIET`` seconds.
- No progress: ENGAGED with the ECU following and the controller driving (not finished), the
  car must gain ``watchdog.no_progress_distance`` along the plan within every
  ``watchdog.no_progress_time``, or the gateway makes a controlled stop naming it
  (:class:`~leafgate.gateway.watchdog.ProgressWatchdog`; waiting at rest for a gear change or
  for the wheel to turn, braking to a stop the controller asked for, standing at the plan's
  stop point and the plan's last ``no_progress_distance`` do not count).
- A plan replaced while ENGAGED is judged like an engage: when the vehicle is outside the engage
  envelope of the new plan (``engage.max_distance``, ``engage.max_heading_error``) the gateway
  makes a controlled stop instead of chasing it; a plan within the envelope is followed.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

from leafgate.config import VehicleConfig
from leafgate.config.gateway import GatewayConfig
from leafgate.control.base import Controller
from leafgate.gateway.plausibility import MAX_SKEW, cross_check, report_range_error
from leafgate.gateway.safety import Measured, SafetyGate, SafetyLimits, gear_sign
from leafgate.gateway.state import (
    EngagementMachine,
    EngageReply,
    Event,
    Transition,
    engage_refusal,
    path_deviation,
)
from leafgate.gateway.watchdog import (
    Check,
    ProgressWatchdog,
    Reaction,
    Status,
    WatchdogReport,
    Watchdogs,
    ecu_fault,
    override_active,
)
from leafgate.jsonconv import to_json
from leafgate.messages import (
    Commands,
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
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    Trajectory,
    WheelSpeeds,
)

_EPS = 1e-9  # s, slack when comparing times built from sums of periods
END_REACHED = "trajectory end reached"  # the reason of an engagement that drove its plan
FOREIGN_QUIET = 1.0  # s without foreign command frames before a command conflict may be reset

#: The last valid ECU reports (steer, long, system), read from a tick's WatchdogReport.
_Reports = tuple[SteerReport | None, LongReport | None, SystemReport | None]


@dataclass(frozen=True)
class GatewayInputs:
    """The latest value of every input, with its receive time (gateway clock, s)."""

    pose: Stamped[Pose] | None
    trajectory: Stamped[Trajectory] | None
    steer_report: Stamped[SteerReport] | None
    long_report: Stamped[LongReport] | None
    system_report: Stamped[SystemReport] | None
    good_report_frames: int = 0  # valid DBW report frames received since the last step
    bad_report_frames: int = 0  # report frames with bad CRC/counter/length since the last step
    report_error_cause: str = ""  # what the receiver makes of them (a second sender), or ""
    request: OperatorRequest | None = None  # pending operator request
    # why the request came, when not from an operator ("SIGTERM received": the daemon stops)
    request_reason: str = ""
    overrun: bool = False  # this tick started late (the period was exceeded)
    lateness: float = 0.0  # s this tick started after its deadline (a stall when long)
    bus_errors: int = 0  # command frames that could not be encoded or sent since the last step
    foreign_command_frames: int = 0  # frames on our command IDs we did not send, since last step
    foreign_command_names: tuple[str, ...] = ()  # their DBC names (for the fault reason)
    # s, the gateway-clock time up to which the bus has been read (None: now, nothing waits)
    reports_as_of: float | None = None
    # CAR-CAN frames the reports are cross-checked with (None: the profile has none)
    wheel_speeds: Stamped[WheelSpeeds] | None = None  # 0x284/0x285
    steering_wheel: Stamped[SteeringWheelAngle] | None = None  # 0x002


class EngagePhase(enum.Enum):
    """Where an engagement is in its hand-shake with the ECU."""

    IDLE = "idle"  # not driving
    CLEARING_OVERRIDE = "clearing_override"  # sending CLEAR_OVERRIDE with ENABLE=0
    ENABLING = "enabling"  # ENABLE=1 sent, waiting for the ECU to report ENABLED
    ACTIVE = "active"  # the ECU follows the commands


class ControllerFigures(NamedTuple):
    """The controller's figures of one tick (from :class:`~leafgate.messages.ControlOutput`)."""

    converged: bool
    iterations: int
    solve_time: float  # s
    clips: int
    cost: float
    nearest_index: int
    finished: bool
    gear: Gear
    status: str

    @classmethod
    def of(cls, out: ControlOutput) -> ControllerFigures:
        return cls(
            out.converged,
            out.iterations,
            out.solve_time,
            out.clips,
            out.cost,
            out.nearest_index,
            out.finished,
            out.gear,
            out.status,
        )


@dataclass(frozen=True)
class Diagnostics:
    """Everything the gateway knows about one tick; published at 10 Hz and recorded."""

    time: float  # s, gateway clock
    state: GatewayState
    reason: str  # why the gateway is in its state
    fault: str  # the latched fault's reason, "" when none
    fault_causes: tuple[str, ...]  # what a reset waits for
    engage_phase: EngagePhase
    watchdogs: tuple[Check, ...]
    error_counter: int  # report frame error counter (+1 bad, −1 good)
    overruns_in_row: int
    ecu_state: EcuState | None  # last valid DBW_SYSTEM_RPT state
    controller: ControllerFigures | None  # None when the controller did not run this tick
    gear_change: bool  # holding the brake for a gear change
    clamps: dict[str, int] = field(default_factory=dict)  # safety clamps since start, by kind
    clamped: tuple[str, ...] = ()  # kinds clamped this tick
    transitions: tuple[Transition, ...] = ()  # state changes this tick

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (enums by name, NaN/inf as null)."""
        return {
            "time": to_json(self.time),
            "state": self.state.name,
            "reason": self.reason,
            "fault": self.fault,
            "fault_causes": list(self.fault_causes),
            "engage_phase": self.engage_phase.value,
            "watchdogs": {
                c.name: {
                    "status": c.status.value,
                    "age": to_json(c.age),
                    "limit": to_json(c.limit),
                    "reaction": c.reaction.name,
                    "detail": c.detail,
                    "value": to_json(c.value),
                }
                for c in self.watchdogs
            },
            "error_counter": self.error_counter,
            "overruns_in_row": self.overruns_in_row,
            "ecu_state": None if self.ecu_state is None else self.ecu_state.name,
            "controller": None
            if self.controller is None
            else {k: to_json(getattr(self.controller, k)) for k in ControllerFigures._fields},
            "gear_change": self.gear_change,
            "clamps": dict(self.clamps),
            "clamped": list(self.clamped),
            "transitions": [t.to_dict() for t in self.transitions],
        }


@dataclass(frozen=True)
class StepResult:
    """What one tick decided."""

    commands: Commands
    diagnostics: Diagnostics
    reply: EngageReply | None  # the answer to ``inputs.request``, None without a request


def _finite_output(out: ControlOutput) -> bool:
    isfinite = math.isfinite
    return isfinite(out.steer_angle) and isfinite(out.accel) and isfinite(out.speed)


def _ramp(value: float, target: float, step: float) -> float:
    """Move ``value`` towards ``target`` by at most ``step``."""
    return min(max(target, value - step), value + step)


class Gateway:
    """Watchdogs, engagement state machine, controller and safety gate, stepped by the caller.

    :param config: the ``gateway:`` section
    :param vehicle: the vehicle's numbers (hard limits, wheelbase)
    :param controller: the path/speed controller (MPC, pure pursuit, Stanley)
    :param mode: which longitudinal command the ECU receives (acceleration or target speed)
    """

    def __init__(
        self,
        config: GatewayConfig,
        vehicle: VehicleConfig,
        controller: Controller,
        mode: LongMode = LongMode.ACCELERATION,
    ) -> None:
        self.config = config
        self.vehicle = vehicle
        self.controller = controller
        self.mode = mode
        self.limits = SafetyLimits.from_config(config.safety, vehicle, config.period)
        self.gate = SafetyGate(self.limits)
        self.watchdogs = Watchdogs(config.watchdog, config.period, config.safety.max_speed)
        self.progress = ProgressWatchdog(config.watchdog)
        self.machine = EngagementMachine()
        self._phase = EngagePhase.IDLE
        self._phase_since = 0.0  # s, when the current engage phase began
        self._clear_sent = False  # a CLEAR_OVERRIDE frame went out in this engagement
        self._override_latched = False  # the ECU latched an override we have not cleared
        self._enable_sent = False  # the last commands carried ENABLE=1
        # commands went out on an earlier tick: before an engage they carry ENABLE=0 (STANDBY),
        # and the ECU engages only on a 0→1 edge it has seen, so an engage on the gateway's very
        # first tick waits one tick before ENABLE=1
        self._frames_sent = False
        self._fault_braking = False  # in FAULT, still braking with ENABLE=1
        self._rest_since: float | None = None  # s, since when |v| is below standstill speed
        self._stop_reason = ""
        self._plan: Trajectory | None = None  # the plan being followed (checked against the pose)
        self._foreign_seen: float | None = None  # s, when foreign command frames were last seen
        self._next_system: float | None = None  # s, when DBW_SYSTEM_CMD is due next
        # fault_causes of diagnostics, sorted: kept until the machine's (frozen) set changes
        self._causes_of: frozenset[str] = frozenset()
        self._causes_sorted: tuple[str, ...] = ()
        self._range_judged: dict[str, float] = {}  # receive time of the last report range-judged
        self._cross_check: list[str] = []  # this tick's disagreements with CAR-CAN
        self.gate.seed(SteerCommand(angle=0.0), LongCommand(mode=mode))

    @property
    def state(self) -> GatewayState:
        """The engagement state."""
        return self.machine.state

    # -- one tick --------------------------------------------------------------------------------

    def step(self, now: float, inputs: GatewayInputs) -> StepResult:
        """Decide one control tick. Pure: no clock, no I/O; never raises for bad inputs.

        :param now: the gateway clock at this tick, s (the clock that stamps ``received``)
        :param inputs: the latest inputs
        """
        inputs = self._judge_reports(inputs)
        m = self.machine
        m.begin_tick()
        wd = self.watchdogs.update(
            now,
            inputs.pose,
            inputs.trajectory,
            inputs.steer_report,
            inputs.long_report,
            inputs.system_report,
            inputs.good_report_frames,
            inputs.bad_report_frames,
            inputs.overrun,
            inputs.lateness,
            inputs.reports_as_of,
            inputs.report_error_cause,
        )
        reports = self._reports(wd)  # once per tick: several decisions below read the flags
        measured = self._measured(wd)
        standstill = abs(measured.speed) < self.limits.standstill_speed
        at_rest = self._update_rest(now, standstill)

        self._react_to_watchdogs(now, wd, reports, inputs)
        reply, clear_faults = self._handle_request(now, inputs, wd, reports, at_rest)
        self._advance_engagement(now, reports)

        output: ControlOutput | None = None
        progress: Check | None = None
        steer: SteerCommand
        long: LongCommand
        gear_change = False
        if m.state == GatewayState.STOPPING and at_rest:
            m.fire(Event.AT_REST, now, f"at rest after a controlled stop ({self._stop_reason})")
        driving = self._phase in (EngagePhase.ENABLING, EngagePhase.ACTIVE) and self._frames_sent
        if m.state == GatewayState.ENGAGED and driving:
            output = self._run_controller(wd)
            if not output.converged or not _finite_output(output):
                self._stop(now, f"controller: {output.status} (converged={output.converged})")
            elif output.finished:
                if standstill:
                    m.fire(Event.AT_REST, now, END_REACHED)
                else:
                    self._stop(now, END_REACHED)
            elif self._phase is EngagePhase.ACTIVE:
                progress = self._judge_progress(now, wd, output, measured, standstill)
                if progress.reaction >= Reaction.STOP:
                    self._stop(now, progress.detail)
        if progress is None or (m.state != GatewayState.ENGAGED and progress.ok):
            progress = self.progress.idle()
        elif m.state != GatewayState.ENGAGED:
            self.progress.reset()  # the stop it asked for: shown this tick, forgotten after
        if m.state == GatewayState.FAULT and self._fault_braking:
            long_fresh = wd.get("long_report").ok
            if at_rest or not long_fresh:
                self._fault_braking = False
        if m.state in (GatewayState.STANDBY, GatewayState.ENGAGED, GatewayState.STOPPING):
            self._fault_braking = False
        if m.state not in (GatewayState.ENGAGED, GatewayState.STOPPING):
            self._phase = EngagePhase.IDLE

        # -- commands of the state --
        if m.state == GatewayState.ENGAGED and self._phase is EngagePhase.CLEARING_OVERRIDE:
            steer, long = self._mirror(wd, clear_override=True)
            self._clear_sent = True
        elif m.state == GatewayState.ENGAGED and output is not None:
            steer, long, gear_change = self._drive(output, measured, standstill)
        elif m.state == GatewayState.STOPPING:
            steer, long = self._brake(self.config.stop.decel, self.config.stop.jerk)
        elif m.state == GatewayState.FAULT and self._fault_braking:
            steer, long = self._brake(self.config.stop.fault_decel, self.limits.max_jerk)
        else:
            steer, long = self._mirror(wd, clear_override=False)

        if steer.enable or long.enable:
            steer, long = self.gate.apply(steer, long, measured)
        else:
            self.gate.seed(steer, long)
        self._enable_sent = steer.enable or long.enable
        self._frames_sent = True

        system = self._system_command(now, clear_faults)
        if reply is not None and inputs.request is not None:
            reply = reply.after_tick(inputs.request, m.state, m.reason)
        if m.fault_causes is not self._causes_of:  # sort only when the latched causes change
            self._causes_of, self._causes_sorted = m.fault_causes, tuple(sorted(m.fault_causes))
        diagnostics = Diagnostics(
            time=now,
            state=m.state,
            reason=m.reason,
            fault=m.fault_reason,
            fault_causes=self._causes_sorted,
            engage_phase=self._phase,
            watchdogs=(*wd.checks, progress),  # in CHECK_ORDER: progress comes last
            error_counter=self.watchdogs.errors.count,
            overruns_in_row=self.watchdogs.overrun.in_row,
            ecu_state=None if reports[2] is None else reports[2].state,
            controller=None if output is None else ControllerFigures.of(output),
            gear_change=gear_change,
            clamps=self.gate.counts_snapshot(),
            clamped=self.gate.last_clamped,
            transitions=tuple(m.transitions),
        )
        return StepResult(Commands(steer=steer, long=long, system=system), diagnostics, reply)

    def _receive_lag(self, now: float, inputs: GatewayInputs) -> str | None:
        """Why the CAN receive thread is too far behind the bus, or None."""
        as_of = inputs.reports_as_of
        limit = self.config.watchdog.max_receive_lag
        if as_of is None or not now - as_of > limit:
            return None
        return f"CAN receive thread {now - as_of:.3f} s behind the bus (> {limit:g} s)"

    # -- report plausibility --------------------------------------------------------------------

    def _judge_reports(self, inputs: GatewayInputs) -> GatewayInputs:
        """Out-of-range reports made invalid (each counted once as a bad frame); this tick's
        cross-check against CAR-CAN in ``_cross_check``."""
        changes: dict[str, Any] = {}
        bad = 0
        for kind, stamped in (("steer", inputs.steer_report), ("long", inputs.long_report)):
            if stamped is None or not stamped.valid:
                continue
            error = report_range_error(stamped.value, self.vehicle)
            if error is None:
                continue
            changes[f"{kind}_report"] = Stamped(stamped.value, stamped.received, valid=False)
            if self._range_judged.get(kind) != stamped.received:
                self._range_judged[kind] = stamped.received
                bad += 1
        steer = None if "steer_report" in changes else inputs.steer_report
        long = None if "long_report" in changes else inputs.long_report
        self._cross_check = cross_check(
            _near(steer, inputs.steering_wheel),
            _near(long, inputs.wheel_speeds),
            _near(inputs.wheel_speeds, long),
            _near(inputs.steering_wheel, steer),
            self.vehicle,
        )
        if not changes:
            return inputs
        return replace(inputs, bad_report_frames=inputs.bad_report_frames + bad, **changes)

    # -- watchdog reactions ----------------------------------------------------------------------

    def _react_to_watchdogs(
        self, now: float, wd: WatchdogReport, reports: _Reports, inputs: GatewayInputs
    ) -> None:
        m = self.machine
        driving = m.state in (GatewayState.ENGAGED, GatewayState.STOPPING)
        causes: dict[str, str] = {}
        for name in ("report_errors", "overrun"):
            check = wd.get(name)
            if check.reaction >= Reaction.FAULT:
                causes[name] = check.detail
        if inputs.bus_errors > 0:
            causes["bus"] = f"{inputs.bus_errors} command frame(s) could not be encoded or sent"
        # Like the reports' own ages, a late receive thread faults only while the gateway
        # drives: at start-up frames already queue before the thread first reads them.
        lag = self._receive_lag(now, inputs)
        if lag is not None and driving:
            causes["receive"] = lag
        if self._cross_check:
            causes["report_cross_check"] = "ECU report implausible: " + "; ".join(self._cross_check)
        if inputs.foreign_command_frames > 0:
            # Another node sends on our IDs: the ECU cannot tell whose command it follows.
            self._foreign_seen = now
            names = ", ".join(inputs.foreign_command_names) or "command"
            causes["command_conflict"] = (
                f"command conflict: {inputs.foreign_command_frames} foreign {names} frame(s) "
                "on the bus"
            )
        if driving:
            for check in wd.failing(Reaction.FAULT):
                causes.setdefault(check.name, check.detail)
            steer, long, system = reports
            fault = ecu_fault(steer, long, system)
            if fault is not None:
                causes["ecu"] = fault
            elif (
                self._phase is EngagePhase.ACTIVE
                and steer is not None
                and long is not None
                and not (steer.enabled and long.enabled)
                and not override_active(steer, long, system)
            ):
                causes["ecu"] = "ECU disengaged without an override"
        if causes:
            self._fault(now, causes, wd)
            return
        if not driving:
            if override_active(*reports):
                self._override_latched = True
            return
        if self._phase is not EngagePhase.CLEARING_OVERRIDE and override_active(*reports):
            self._override_latched = True
            m.fire(Event.OVERRIDE, now, "driver override reported by the ECU")
            return
        if m.state == GatewayState.ENGAGED:
            stops = wd.failing(Reaction.STOP)
            if stops:
                self._stop(now, stops[0].detail)
                return
            replaced = self._plan_refusal(wd)
            if replaced is not None:
                self._stop(now, replaced)

    def _plan_refusal(self, wd: WatchdogReport) -> str | None:
        """Why a plan that replaced the followed one must not be chased, or None: it cannot be
        driven (:func:`~leafgate.control.reference.trajectory_problem`), or the car is outside
        its engage envelope.

        Called on every ENGAGED tick: the refused-plan test is one comparison of receive times;
        the envelope test (a path search) runs once per new plan object, as the runtime keeps
        one object while a planner re-publishes the same waypoints.
        """
        traj = wd.trajectory
        if traj is not None:
            # a newer plan that cannot be driven: the planner's latest word is not the plan
            # followed, and chasing the older one would ignore it
            refused = self.watchdogs.trajectory.refused_since(traj.received)
            if refused:
                return f"trajectory replaced by one that cannot be driven: {refused}"
        if traj is None or traj.value is self._plan or wd.pose is None:
            return None
        self._plan = traj.value
        limits = self.config.engage
        distance, heading_error = path_deviation(
            wd.pose.value, traj.value, within=limits.max_distance
        )
        if distance > limits.max_distance:
            return (
                f"trajectory replaced: vehicle {distance:.2f} m from the new plan "
                f"(limit {limits.max_distance:g} m)"
            )
        if heading_error > limits.max_heading_error:
            return (
                f"trajectory replaced: heading {math.degrees(heading_error):.1f}° off the new "
                f"plan (limit {math.degrees(limits.max_heading_error):g}°)"
            )
        return None

    def _fault(self, now: float, causes: dict[str, str], wd: WatchdogReport) -> None:
        m = self.machine
        if m.state != GatewayState.FAULT:
            # Keep braking if the ECU follows us and we can see the car's speed.
            self._fault_braking = self._enable_sent and wd.get("long_report").ok
        reason = "; ".join(causes[k] for k in sorted(causes))
        m.fire(Event.FAULT, now, reason, frozenset(causes))

    def _stop(self, now: float, reason: str) -> None:
        """A controlled stop; an engagement that never sent ENABLE=1 just ends."""
        m = self.machine
        if self._enable_sent:
            if m.fire(Event.STOP, now, reason):
                self._stop_reason = reason
        else:
            m.fire(Event.ABORT, now, f"engagement ended before the ECU was enabled: {reason}")

    # -- operator requests -----------------------------------------------------------------------

    def _handle_request(
        self,
        now: float,
        inputs: GatewayInputs,
        wd: WatchdogReport,
        reports: _Reports,
        at_rest: bool,
    ) -> tuple[EngageReply | None, bool]:
        """Answer the pending request; True as second value when CLEAR_FAULTS is to be sent."""
        request = inputs.request
        m = self.machine
        state = m.state
        if request is None:
            return None, False
        if request is OperatorRequest.ENGAGE:
            if state == GatewayState.ENGAGED:
                return EngageReply.unchanged(state, "already engaged"), False
            refusal = engage_refusal(state, m.fault_reason, wd, self.config.engage)
            if refusal is not None:
                return EngageReply(False, state, refusal), False
            clear = self._override_latched or override_active(*reports)
            m.fire(Event.ENGAGE, now, "operator engage")
            self._plan = None if wd.trajectory is None else wd.trajectory.value
            self.controller.reset()
            self._phase = EngagePhase.CLEARING_OVERRIDE if clear else EngagePhase.ENABLING
            self._phase_since = now
            self._clear_sent = False
            reason = "engaging after clearing the override" if clear else "engaged"
            return EngageReply.done(m.state, reason), False
        if request is OperatorRequest.DISENGAGE:
            if state in (GatewayState.ENGAGED, GatewayState.STOPPING):
                m.fire(Event.DISENGAGE, now, inputs.request_reason or "operator disengage")
                return EngageReply.done(m.state, "disengaged"), False
            if state == GatewayState.FAULT:
                braking, self._fault_braking = self._fault_braking, False
                handed = "stopped braking; " if braking else ""
                text = f"fault stays latched ({m.fault_reason}); {handed}reset to leave FAULT"
                return EngageReply(False, state, text, changed=braking), False
            return EngageReply.unchanged(state, "already in STANDBY"), False
        # RESET
        if state == GatewayState.STANDBY:
            fault = ecu_fault(*reports)
            if fault is None:  # CLEAR_FAULTS goes out all the same: it costs nothing
                return EngageReply.unchanged(state, "nothing to reset: no fault latched"), True
            return EngageReply.done(state, f"clearing the ECU's faults ({fault})"), True
        if state != GatewayState.FAULT:
            return EngageReply(
                False, state, f"reset only in STANDBY or FAULT (is {state.name})"
            ), False
        if self._fault_braking and not at_rest:
            return EngageReply(False, state, "vehicle still braking to rest"), False
        remaining = self._remaining_causes(now, wd, inputs.bus_errors)
        if remaining:
            return EngageReply(
                False, state, "fault cause still present: " + "; ".join(remaining)
            ), False
        m.fire(Event.RESET, now, f"reset after: {m.fault_reason}")
        self._fault_braking = False
        return EngageReply.done(m.state, "fault cleared"), True

    def _judge_progress(
        self,
        now: float,
        wd: WatchdogReport,
        out: ControlOutput,
        measured: Measured,
        standstill: bool,
    ) -> Check:
        """The no-progress watchdog for a tick in which the controller drives the car."""
        assert wd.trajectory is not None and wd.steer is not None  # the controller ran
        want = measured.gear if out.gear == Gear.NONE else out.gear
        return self.progress.update(
            now,
            wd.trajectory.value,
            out.progress,
            out.route_length,
            wd.steer.value.angle,
            standstill,
            gear_change=want != measured.gear,
            commanded_speed=out.speed,
            deviation=out.deviation,
            stop_distance=out.stop_distance,
        )

    def _remaining_causes(self, now: float, wd: WatchdogReport, bus_errors: int) -> list[str]:
        out = []
        for cause in sorted(self.machine.fault_causes):
            if cause == "ecu":
                continue  # cleared by the CLEAR_FAULTS this reset sends
            if cause == "command_conflict":
                seen = self._foreign_seen
                if seen is not None and now - seen < FOREIGN_QUIET - _EPS:
                    out.append(f"foreign command frames seen {now - seen:.2f} s ago")
                continue
            if cause == "report_cross_check":
                out.extend(self._cross_check)
                continue
            if cause == "receive":
                continue  # a thread that lagged once has caught up by the time of a reset
            if cause == "bus":
                if bus_errors > 0:
                    out.append(f"{bus_errors} command frame(s) could not be sent")
                continue
            check = wd.get(cause)
            if check.status is not Status.OK:
                out.append(check.detail or f"{cause} {check.status.value}")
        return out

    # -- engagement hand-shake -------------------------------------------------------------------

    def _advance_engagement(self, now: float, reports: _Reports) -> None:
        m = self.machine
        if m.state not in (GatewayState.ENGAGED, GatewayState.STOPPING):
            return
        timeout = self.config.engage.confirm_timeout
        steer, long, system = reports
        if self._phase is EngagePhase.CLEARING_OVERRIDE:
            if self._clear_sent and not override_active(steer, long, system):
                self._override_latched = False
                self._phase, self._phase_since = EngagePhase.ENABLING, now
            elif now - self._phase_since > timeout + _EPS:
                m.fire(Event.ABORT, now, f"override not cleared within {timeout:g} s")
                return
        if self._phase is EngagePhase.ENABLING and self._enable_sent:
            if steer is not None and long is not None and steer.enabled and long.enabled:
                self._phase = EngagePhase.ACTIVE
            elif now - self._phase_since > timeout + _EPS:
                if m.state == GatewayState.STOPPING:
                    m.fire(Event.AT_REST, now, f"ECU did not report ENABLED within {timeout:g} s")
                else:
                    m.fire(Event.ABORT, now, f"ECU did not report ENABLED within {timeout:g} s")

    # -- commands --------------------------------------------------------------------------------

    def _run_controller(self, wd: WatchdogReport) -> ControlOutput:
        """Call the controller; an exception becomes a not-converged output (never propagates)."""
        assert wd.pose is not None and wd.trajectory is not None and wd.steer is not None
        try:
            return self.controller.step(wd.pose.value, wd.steer.value.angle, wd.trajectory.value)
        except Exception as exc:  # the control loop must survive any controller bug
            return ControlOutput(
                steer_angle=math.nan,
                accel=math.nan,
                speed=math.nan,
                converged=False,
                status=f"exception {type(exc).__name__}: {exc}",
            )

    def _drive(
        self, out: ControlOutput, measured: Measured, standstill: bool
    ) -> tuple[SteerCommand, LongCommand, bool]:
        """The controller's command in wire terms, or the brake held for a gear change."""
        want = measured.gear if out.gear == Gear.NONE else out.gear
        steer = SteerCommand(angle=out.steer_angle, enable=True)
        if want != measured.gear:
            # Hold the brake; ask for the gear only at standstill; drive on once it is reported.
            last = self.gate.last_long
            dt = self.limits.period
            stop = self.config.stop
            long = LongCommand(
                mode=self.mode,
                accel=_ramp(last.accel, -stop.decel, stop.jerk * dt),
                speed=0.0,
                gear=want if standstill else Gear.NONE,
                enable=True,
            )
            return steer, long, True
        sign = gear_sign(measured.gear)  # the controller's accel is d(signed v)/dt
        long = LongCommand(
            mode=self.mode,
            accel=sign * out.accel,
            speed=abs(out.speed) if sign != 0.0 else 0.0,
            gear=Gear.NONE,
            enable=True,
        )
        return steer, long, False

    def _brake(self, decel: float, jerk: float) -> tuple[SteerCommand, LongCommand]:
        """Steering held at the last sent angle; deceleration built up at ``jerk``."""
        dt = self.limits.period
        last_steer, last_long = self.gate.last_steer, self.gate.last_long
        steer = SteerCommand(angle=last_steer.angle, enable=True)
        long = LongCommand(
            mode=self.mode,
            accel=_ramp(last_long.accel, -decel, jerk * dt),
            speed=max(0.0, last_long.speed - decel * dt),
            gear=Gear.NONE,
            enable=True,
        )
        return steer, long

    def _mirror(self, wd: WatchdogReport, clear_override: bool) -> tuple[SteerCommand, LongCommand]:
        """ENABLE=0 frames mirroring the measured angle (accel 0, speed 0, no gear request)."""
        angle = self.gate.last_steer.angle
        if wd.steer is not None and math.isfinite(wd.steer.value.angle):
            limit = self.limits.max_angle
            angle = min(max(wd.steer.value.angle, -limit), limit)
        steer = SteerCommand(angle=angle, enable=False, clear_override=clear_override)
        long = LongCommand(mode=self.mode, enable=False, clear_override=clear_override)
        return steer, long

    def _system_command(self, now: float, clear_faults: bool) -> SystemCommand | None:
        """DBW_SYSTEM_CMD every ``system_period`` of ``now``, and at once with CLEAR_FAULTS."""
        period = self.config.system_period
        due = self._next_system is None or now >= self._next_system - _EPS
        if not (due or clear_faults):
            return None
        if self._next_system is None or clear_faults or now - self._next_system >= period:
            self._next_system = now + period  # (re)anchor after a start, reset or long gap
        else:
            self._next_system += period
        return SystemCommand(state=self.machine.state, clear_faults=clear_faults)

    # -- measured state --------------------------------------------------------------------------

    @staticmethod
    def _reports(wd: WatchdogReport) -> _Reports:
        """The last valid reports (also when stale: their flags are the latest we know)."""
        return (
            None if wd.steer is None else wd.steer.value,
            None if wd.long is None else wd.long.value,
            None if wd.system is None else wd.system.value,
        )

    @staticmethod
    def _measured(wd: WatchdogReport) -> Measured:
        """Speed and gear: the ECU's long report when fresh, else localization; NaN if neither.

        A NaN speed makes the safety gate assume the maneuver speed limit and refuse gear changes.
        """
        gear = Gear.NONE if wd.long is None else wd.long.value.gear
        if wd.long is not None and wd.get("long_report").ok:
            return Measured(wd.long.value.speed, gear)
        if wd.pose is not None and wd.get("localization").ok:
            return Measured(wd.pose.value.speed, gear)
        return Measured(math.nan, gear)

    def _update_rest(self, now: float, standstill: bool) -> bool:
        """True once the car has stood still for ``stop.standstill_time``."""
        if not standstill:
            self._rest_since = None
            return False
        if self._rest_since is None:
            self._rest_since = now
        return now - self._rest_since >= self.config.stop.standstill_time - _EPS


def _near(stamped: Stamped[Any] | None, other: Stamped[Any] | None) -> Any:
    """The value of a valid ``stamped`` when ``other`` is valid and received within
    :data:`~leafgate.gateway.plausibility.MAX_SKEW` of it, else None (nothing to compare)."""
    if stamped is None or other is None or not (stamped.valid and other.valid):
        return None
    return stamped.value if abs(stamped.received - other.received) <= MAX_SKEW else None
