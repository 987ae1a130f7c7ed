"""The closed-loop simulator on a simulated clock.

One thread, one simulated clock: a 30 s maneuver runs in well under a second of wall time and
gives the same numbers every run.

:func:`run` is the full loop of the real system: plant → simulated ECU → CAN report frames →
gateway codec → ``Gateway.step`` (watchdogs, state machine, controller, safety gate) → CAN command
frames → ECU, over a python-can ``virtual`` bus, with localization from the plant and the
trajectory from the scenario, engaged by a scripted operator request. :func:`run_direct` is the
paper's Simulink check: the controller drives the plant with nothing in between.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import re
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import can
import numpy as np

from leafgate.can.codec import CanCodec, EncodeError
from leafgate.can.secoc import KEY_BYTES
from leafgate.config.sim import SimConfig
from leafgate.control import make_controller
from leafgate.control.reference import MIN_POINTS
from leafgate.errors import ConfigError
from leafgate.gateway.core import END_REACHED, Gateway, GatewayInputs
from leafgate.messages import (
    GatewayState,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerReport,
    SystemReport,
    Trajectory,
)
from leafgate.settings import LeafgateConfig
from leafgate.sim.ecu import SimulatedEcu
from leafgate.sim.metrics import Projector, path_errors, tracking_metrics
from leafgate.sim.names import TO_SIM
from leafgate.sim.plant import STANDSTILL_SPEED, SpeedController, gear_direction, make_plant
from leafgate.sim.plots import Trace
from leafgate.sim.realtime import LocalizationFeed
from leafgate.sim.scenarios import Scenario

if TYPE_CHECKING:  # recording is optional: leafgate.replay is imported only by its callers
    from leafgate.record.recorder import Recorder

ECU_TICK = 0.01  # s, simulated ECU step (its fastest report period)
ENGAGE_AT = 0.5  # s, when the scripted operator asks to engage (reports are fresh by then)
REST_BEFORE_END = 1.0  # s at rest, disengaged, before the run ends
_channel_ids = itertools.count()

# Injections the gateway side handles (localization faults); the rest go to the simulated ECU.
GATEWAY_INJECTIONS = {"localization-dropout", "position-jump", "command-dropout"}
ECU_INJECTIONS = {
    "override": (
        "override-torque",
        {"torque": 5.0},
        0.5,
    ),  # N·m for 0.5 s: a driver grabs the wheel
    "brake-pedal": ("brake-pedal", {}, 0.5),
    "report-dropout": ("report-dropout", {}, None),
    "corrupt-crc": ("corrupt-crc", {}, None),
    "stuck-counter": ("stuck-counter", {}, None),
    "actuator-fault": ("actuator-fault", {}, None),
}
INJECTION_KINDS = sorted(GATEWAY_INJECTIONS | set(ECU_INJECTIONS))
#: Metrics measured on the wall clock: they differ between runs of the same drive.
WALL_CLOCK_METRICS = frozenset({"wall_time_s", "solve_time_median_s", "solve_time_p99_s"})


def start_pose(scenario: Scenario, sim: SimConfig) -> Pose:
    """The plant's start: the scenario's, moved by ``sim.start_lateral_offset`` (left of its
    heading) and turned by ``sim.start_heading_offset``."""
    start = scenario.start
    if not (sim.start_lateral_offset or sim.start_heading_offset):
        return start
    left = sim.start_lateral_offset
    return dataclasses.replace(
        start,
        x=start.x - left * math.sin(start.heading),
        y=start.y + left * math.cos(start.heading),
        heading=start.heading + sim.start_heading_offset,
    )


def default_model(plant: str) -> Literal["kinematic", "kinematic_steer_lag"]:
    """The MPC prediction model the simulator uses on ``plant`` unless told otherwise: the
    steering-aware one wherever the wheel lags (as on the car), the paper's kinematic one on
    the kinematic plant."""
    return "kinematic" if plant == "kinematic" else "kinematic_steer_lag"


@dataclass(frozen=True)
class Injection:
    """A fault or driver action at a simulated time: ``KIND@T[s][+DURATION[s]]``."""

    kind: str
    at: float  # s
    duration: float | None = None  # s, None = until the end

    def active(self, t: float) -> bool:
        return t >= self.at and (self.duration is None or t < self.at + self.duration)

    @classmethod
    def parse(cls, text: str) -> Injection:
        """Parse ``localization-dropout@8s`` or ``override@10+0.5``.

        :raises ConfigError: naming the text and what is wrong
        """
        m = re.fullmatch(r"([a-z-]+)@([0-9.]+)s?(?:\+([0-9.]+)s?)?", text.strip())
        if not m:
            raise ConfigError(
                f"--inject {text!r}: expected KIND@TIME[s][+DURATION[s]], e.g. override@10s"
            )
        kind = TO_SIM.get(m.group(1), m.group(1))  # sim-ecu's name for the same fault
        if kind not in INJECTION_KINDS:
            raise ConfigError(
                f"--inject {text!r}: unknown kind {kind!r} (known: {', '.join(INJECTION_KINDS)})"
            )
        duration = float(m.group(3)) if m.group(3) else None
        return cls(kind, float(m.group(2)), duration)


@dataclass
class _Recorder:
    """Per-tick time series, kept as lists while running."""

    t: list[float] = field(default_factory=list)
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    heading: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    steer_actual: list[float] = field(default_factory=list)
    steer_target: list[float] = field(default_factory=list)
    accel_target: list[float] = field(default_factory=list)
    state: list[str] = field(default_factory=list)

    def add(
        self,
        t: float,
        pose: Pose,
        steer_actual: float,
        steer_target: float,
        accel_target: float,
        state: str,
    ) -> None:
        self.t.append(t)
        self.x.append(pose.x)
        self.y.append(pose.y)
        self.heading.append(pose.heading)
        self.speed.append(pose.speed)
        self.steer_actual.append(steer_actual)
        self.steer_target.append(steer_target)
        self.accel_target.append(accel_target)
        self.state.append(state)

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            k: np.asarray(v, dtype=np.float64) for k, v in self.__dict__.items() if k != "state"
        }


#: ``trace.csv`` columns (name with its unit) and the recorder's series behind each (SI inside;
#: degrees only in the file).
TRACE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("t_s", "t"),
    ("x_m", "x"),
    ("y_m", "y"),
    ("heading_deg", "heading"),
    ("speed_mps", "speed"),
    ("steer_cmd_deg", "steer_target"),
    ("steer_deg", "steer_actual"),
    ("accel_cmd_mps2", "accel_target"),
)


@dataclass(frozen=True)
class RollingWindow:
    """A planner's rolling plan: the next ``length`` of the route, re-sent every ``period``.

    Each plan starts at the waypoint the car last passed (its projection on the route, followed
    in time order and in its direction of travel) and is a new object with a new receive time,
    as from a planner over Zenoh (the transport makes a new object of every message).
    """

    length: float = 30.0  # m
    period: float = 0.5  # s

    def __post_init__(self) -> None:
        if not (self.length > 0.0 and self.period > 0.0):
            raise ConfigError(
                f"rolling window: length and period must be positive, got {self.length!r} m "
                f"every {self.period!r} s"
            )


class _Planner:
    """Cuts the rolling windows out of the whole route, following the car along it."""

    def __init__(self, route: Trajectory, window: RollingWindow) -> None:
        self.route = route
        self.window = window
        self.projector = Projector(route)
        self.last_sent: float | None = None
        self.plan: Stamped[Trajectory] | None = None

    def plan_at(self, now: float, pose: Pose) -> Stamped[Trajectory]:
        """The plan the gateway holds at ``now`` (a new one every period)."""
        k, _, _, _, _ = self.projector.project(pose.x, pose.y, pose.speed)  # every tick: in order
        due = self.last_sent is None or now - self.last_sent >= self.window.period - 1e-9
        if self.plan is not None and not due:
            return self.plan
        route, proj = self.route, self.projector
        n = len(route)
        first = min(k, n - MIN_POINTS)  # a plan has at least four waypoints
        end_s = proj.s[first] + self.window.length
        last = max(int(np.searchsorted(proj.s, end_s, side="right")), first + MIN_POINTS)
        cut = slice(first, min(last, n))
        plan = Trajectory(
            x=route.x[cut], y=route.y[cut], heading=route.heading[cut], speed=route.speed[cut]
        )
        self.plan, self.last_sent = Stamped(plan, now), now
        return self.plan


@dataclass(frozen=True)
class SimResult:
    scenario: Scenario
    metrics: dict[str, Any]
    trace: Trace
    timeline: tuple[tuple[float, str], ...]
    series: dict[str, np.ndarray] = field(default_factory=dict)  # per control tick, SI
    states: tuple[str, ...] = ()  # the gateway state at each control tick

    def write_trace_csv(self, path: Path) -> None:
        """``trace.csv``: one row per control tick (:data:`TRACE_COLUMNS` and the state)."""
        degrees = {"heading_deg", "steer_cmd_deg", "steer_deg"}
        with path.open("w", encoding="utf-8", newline="") as f:
            out = csv.writer(f)
            out.writerow([name for name, _ in TRACE_COLUMNS] + ["state"])
            columns = [
                np.degrees(self.series[key]) if name in degrees else self.series[key]
                for name, key in TRACE_COLUMNS
            ]
            for i, state in enumerate(self.states):
                out.writerow([f"{col[i]:.6g}" for col in columns] + [state])


FINISH_TOLERANCE = 0.5  # m: a run finished only when it ended this close to the route's end


def finish_verdict(metrics: dict[str, Any], claimed: bool, why_not: str) -> tuple[bool, str]:
    """Did the run finish the maneuver? Checked against the route, not only taken from the
    gateway: the car must have got along the whole route and stopped on its end."""
    length, progress = metrics["route_length_m"], metrics["progress_m"]
    final = metrics["final_position_error_m"]
    if not claimed:
        return False, why_not
    if progress < length - FINISH_TOLERANCE or final > FINISH_TOLERANCE:
        return False, (
            f"the gateway reported the end reached, but the car got {progress:.1f} of "
            f"{length:.1f} m along the route and stopped {final:.2f} m from its end"
        )
    return True, ""


def _finish(
    config: LeafgateConfig,
    scenario: Scenario,
    rec: _Recorder,
    solve_times: list[float],
    extra: dict[str, Any],
    timeline: list[tuple[float, str]],
    label: str,
    why_not: str,
) -> SimResult:
    arr = rec.arrays()
    traj = scenario.trajectory
    metrics: dict[str, Any] = tracking_metrics(
        traj, arr["t"], arr["x"], arr["y"], arr["heading"], arr["speed"], arr["steer_actual"]
    )
    solve = np.asarray(solve_times or [0.0])
    metrics["solve_time_median_s"] = float(np.median(solve))
    metrics["solve_time_p99_s"] = float(np.percentile(solve, 99))
    metrics.update(extra)
    metrics["finished"], reason = finish_verdict(metrics, bool(extra["finished"]), why_not)
    if reason:
        metrics["not_finished_reason"] = reason
    speed_ref = path_errors(traj, arr["x"], arr["y"], arr["heading"], arr["speed"]).speed_ref
    trace = Trace(
        label=label or f"{config.controller.kind}, {config.sim.plant.kind} plant",
        t=arr["t"],
        x=arr["x"],
        y=arr["y"],
        speed=arr["speed"],
        steer_actual=arr["steer_actual"],
        steer_target=arr["steer_target"],
        speed_ref=speed_ref,
    )
    return SimResult(
        scenario=scenario,
        metrics=metrics,
        trace=trace,
        timeline=tuple(timeline),
        series=arr,
        states=tuple(rec.state),
    )


def run_direct(config: LeafgateConfig, scenario: Scenario, label: str = "") -> SimResult:
    """Drive ``scenario`` with the controller commanding the plant directly (no CAN, no gateway)."""
    period = config.gateway.period
    traj = scenario.trajectory
    controller = make_controller(config.controller, config.vehicle, period)
    plant = make_plant(config.sim.plant, config.vehicle, start_pose(scenario, config.sim))
    velocity_mode = config.controller.mpc.mode == "velocity"
    speed_ctl = SpeedController(min_accel=-3.0, max_accel=config.vehicle.max_accel)
    rec = _Recorder()
    solve_times: list[float] = []
    timeline: list[tuple[float, str]] = [
        (0.0, f"start {scenario.name} (direct: controller → plant)")
    ]
    not_converged = clips = 0
    steps = round(scenario.duration / period)
    wall0 = time.perf_counter()
    t = 0.0
    finished = False
    for k in range(steps):
        t = k * period
        pose = plant.pose()
        out = controller.step(pose, plant.steer_angle, traj)
        not_converged += 0 if out.converged else 1
        clips += out.clips
        solve_times.append(out.solve_time)
        gear = plant.gear
        if out.gear != gear and abs(plant.speed) <= STANDSTILL_SPEED:
            if plant.set_gear(out.gear):
                timeline.append((t, f"gear {out.gear.name}"))
            gear = plant.gear
        direction = gear_direction(gear)
        if out.gear != gear:
            accel_rel = -3.0  # hold the brake until the gear change is done
        elif velocity_mode:
            accel_rel = speed_ctl.step(period, abs(out.speed), direction * plant.speed)
        else:
            accel_rel = direction * out.accel
        rec.add(t, pose, plant.steer_angle, out.steer_angle, accel_rel, "DIRECT")
        if out.finished:
            timeline.append((t, "trajectory end reached, at rest"))
            finished = True
            break
        plant.step(period, out.steer_angle, accel_rel, gear)
    extra = {
        "solver_not_converged": not_converged,
        "input_clips": clips,
        "duration_s": float(t),
        "wall_time_s": time.perf_counter() - wall0,
        "finished": finished,
    }
    why_not = (
        "" if finished else f"the controller did not reach the end within {scenario.duration:.0f} s"
    )
    return _finish(config, scenario, rec, solve_times, extra, timeline, label, why_not)


class _Slots:
    """The gateway's latest-value inputs, filled from decoded CAN frames on the simulated clock."""

    def __init__(self) -> None:
        self.steer: Stamped[SteerReport] | None = None
        self.long: Stamped[LongReport] | None = None
        self.system: Stamped[SystemReport] | None = None
        self.good = 0
        self.bad = 0

    def take_counts(self) -> tuple[int, int]:
        counts = (self.good, self.bad)
        self.good = self.bad = 0
        return counts


def sim_key(config: LeafgateConfig) -> bytes | None:
    """A throwaway random key for a simulated drive whose profile authenticates its frames and
    whose config names no key file (None: the codecs read ``can.auth_key_file``, or need none).
    It lives in memory only; ``leafgate sim --record`` writes one to a file instead."""
    if config.profile.authenticated and config.can.auth_key_file is None:
        return secrets.token_bytes(KEY_BYTES)
    return None


def run(
    config: LeafgateConfig,
    scenario: Scenario,
    label: str = "",
    injections: tuple[Injection, ...] = (),
    engage_at: float = ENGAGE_AT,
    recorder: Recorder | None = None,
    window: RollingWindow | None = None,
    epoch: float | None = None,
) -> SimResult:
    """Drive ``scenario`` through the whole gateway: CAN codec, ECU, watchdogs, safety gate.

    :param recorder: records the drive (``leafgate.record.recorder``): every frame the gateway
        receives and sends, stamped with the simulated time, and every tick's inputs and result
    :param window: send the route as a planner's rolling window instead of whole, once
    :param epoch: Unix time of t = 0 for authenticated frames' freshness values (the
        recording's, so a recorded log verifies against its timestamps); None: now
    """
    period = config.gateway.period
    ticks_per_control = max(1, round(period / ECU_TICK))
    ecu_dt = period / ticks_per_control
    traj = scenario.trajectory
    controller = make_controller(config.controller, config.vehicle, period)
    if recorder is not None:  # recording: a transparent wrapper lets it see the predicted path
        controller = recorder.wrap_controller(controller)
    gateway = Gateway(config.gateway, config.vehicle, controller, config.long_mode)
    plant = make_plant(config.sim.plant, config.vehicle, start_pose(scenario, config.sim))
    # Authenticated frames: the configured key, or a throwaway one; their freshness values come
    # from the simulated clock as Unix time from the start (as the recording stamps frames).
    key = sim_key(config)
    epoch = time.time() if epoch is None else epoch
    now = 0.0

    def sim_clock() -> float:
        return epoch + now

    ecu_codec = CanCodec.for_config(config, clock=sim_clock, key=key)
    ecu = SimulatedEcu(config.sim.ecu, plant, config.vehicle, ecu_codec)
    ecu.set_driver_path(traj)  # lateral-only vehicles: the driver holds the planned speed
    gw_codec = CanCodec.for_config(config, clock=sim_clock, key=key)
    report_ids = gw_codec.receive_ids("reports") | gw_codec.receive_ids("car")
    channel = f"leafgate-sim-{next(_channel_ids)}"
    gw_bus = can.Bus(
        interface="virtual",
        channel=channel,
        preserve_timestamps=True,
        can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in sorted(report_ids)],
    )
    ecu_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)

    for inj in injections:
        if inj.kind in ECU_INJECTIONS:
            ecu_kind, kwargs, default_duration = ECU_INJECTIONS[inj.kind]
            ecu.inject(ecu_kind, at=inj.at, duration=inj.duration or default_duration, **kwargs)
    gw_injections = [i for i in injections if i.kind in GATEWAY_INJECTIONS]
    # Localization with noise or latency (sim.localization; the seed makes it repeatable): the
    # same feed as sim-ecu's, on the simulated clock; without either, the plant's pose each tick.
    loc = config.sim.localization
    localized: list[Pose] = []  # samples the feed published since the last control tick
    feed = None
    if loc.position_noise > 0 or loc.heading_noise > 0 or loc.latency > 0:
        feed = LocalizationFeed(localized.append, loc, wall_clock=False)
    planner = None if window is None else _Planner(traj, window)
    whole_plan = Stamped(traj, 0.0)

    slots = _Slots()
    rec = _Recorder()
    solve_times: list[float] = []
    timeline: list[tuple[float, str]] = [
        (0.0, f"start {scenario.name}: gateway {GatewayState.STANDBY.name}")
    ]
    transitions: list[dict[str, Any]] = []
    frames_sent = frames_received = frames_rejected = 0
    not_converged = clips = 0
    clamps: dict[str, int] = {}
    last_pose: Stamped[Pose] | None = None
    last_state = gateway.state
    ecu_state_seen: str | None = None
    engaged_once = False
    rest_since: float | None = None
    steer_target = 0.0
    wall0 = time.perf_counter()
    steps = round(scenario.duration / ecu_dt)
    try:
        for k in range(steps):
            now = k * ecu_dt
            # 1. The ECU actuates the plant for one ECU tick and sends the reports due now.
            ecu.step(now, ecu_dt)
            if feed is not None:
                feed.on_tick(now, ecu)
            for msg in ecu.reports(now):
                ecu_bus.send(msg)
            # 2. The gateway's receive side decodes what arrived.
            while (rx := gw_bus.recv(timeout=0.0)) is not None:
                frames_received += 1
                if recorder is not None:  # recording: every frame the gateway receives
                    recorder.on_can_frame(rx, "rx")
                decoded = gw_codec.decode(rx)
                if decoded.counts_for_reports:
                    if decoded.valid:
                        slots.good += 1
                    else:
                        slots.bad += 1
                        frames_rejected += 1
                if not decoded.valid:
                    continue
                for value in decoded.values:
                    if isinstance(value, SteerReport):
                        slots.steer = Stamped(value, now)
                    elif isinstance(value, LongReport):
                        if slots.long is None or slots.long.value.gear != value.gear:
                            timeline.append((now, f"gear {value.gear.name}"))
                        slots.long = Stamped(value, now)
                    elif isinstance(value, SystemReport):
                        slots.system = Stamped(value, now)
                        if value.state.name != ecu_state_seen:
                            ecu_state_seen = value.state.name
                            timeline.append((now, f"ECU {ecu_state_seen}"))
            if k % ticks_per_control:
                continue
            # 3. Localization from the plant (unless a fault is injected), the scripted operator.
            pose: Pose | None
            if feed is None:
                pose = plant.pose()
                pose = Pose(pose.x, pose.y, pose.heading, pose.speed, pose.yaw_rate, stamp=now)
            else:  # the newest sample published since the last tick, if any
                pose = localized[-1] if localized else None
                localized.clear()
            dropout = pose is None
            jump = command_dropout = False
            for inj in gw_injections:
                if inj.active(now):
                    dropout |= inj.kind == "localization-dropout"
                    jump |= inj.kind == "position-jump"
                    command_dropout |= inj.kind == "command-dropout"
            if jump and pose is not None:
                pose = dataclasses.replace(pose, x=pose.x + 2.0)
            if not dropout and pose is not None:
                last_pose = Stamped(pose, now)
            request = OperatorRequest.ENGAGE if abs(now - engage_at) < ecu_dt / 2 else None
            good, bad = slots.take_counts()
            plan = whole_plan if planner is None else planner.plan_at(now, plant.pose())
            inputs = GatewayInputs(
                pose=last_pose,
                trajectory=plan,
                steer_report=slots.steer,
                long_report=slots.long,
                system_report=slots.system,
                good_report_frames=good,
                bad_report_frames=bad,
                report_error_cause=gw_codec.second_senders() if bad else "",
                request=request,
            )
            result = gateway.step(now, inputs)
            if result.reply is not None:
                verdict = "accepted" if result.reply.accepted else "refused"
                timeline.append((now, f"operator engage: {verdict} ({result.reply.reason})"))
            diag = result.diagnostics
            ctl = diag.controller
            # Count every tick the controller ran while engaged, including the one whose
            # failure moved the gateway to STOPPING.
            if ctl is not None and last_state == GatewayState.ENGAGED:
                solve_times.append(ctl.solve_time)
                not_converged += 0 if ctl.converged else 1
                clips += ctl.clips
            # Every transition of the tick: an engagement may begin and end within one.
            for tr in diag.transitions:
                transitions.append(
                    {
                        "t": round(now, 6),
                        "from": tr.source.name,
                        "to": tr.target.name,
                        "reason": tr.reason,
                    }
                )
                timeline.append((now, f"gateway {tr.source.name} → {tr.target.name}: {tr.reason}"))
                engaged_once |= tr.target == GatewayState.ENGAGED
            last_state = gateway.state
            # 4. Command frames out, through the codec, to the ECU.
            cmds = result.commands
            steer_target = cmds.steer.angle
            sent: list[can.Message] = []  # recording: the frames that went onto the bus
            frames = gw_codec.encode_commands(cmds, timestamp=now)
            if gw_codec.last_errors:  # the gate keeps values in range: this is a bug, say so
                raise EncodeError(gw_codec.last_errors[0])
            for frame in frames:
                frames_sent += 1
                if not command_dropout:
                    gw_bus.send(frame)
                    sent.append(frame)
            if recorder is not None:  # recording: the tick's inputs, result and sent frames
                recorder.on_tick(now, inputs, result, sent)
            while (cmd_frame := ecu_bus.recv(timeout=0.0)) is not None:
                ecu.receive_frame(now, cmd_frame)
            accel_target = cmds.long.accel if cmds.long.enable else 0.0
            rec.add(
                now, plant.pose(), plant.steer_angle, steer_target, accel_target, gateway.state.name
            )
            # 5. Done once the gateway has let go and the car has been at rest for a while.
            at_rest = abs(plant.speed) <= STANDSTILL_SPEED
            idle = gateway.state in (GatewayState.STANDBY, GatewayState.FAULT)
            if engaged_once and idle and at_rest:
                rest_since = now if rest_since is None else rest_since
                if now - rest_since >= REST_BEFORE_END:
                    break
            else:
                rest_since = None
        for name, count in diag.clamps.items():
            clamps[name] = int(count)
    finally:
        gw_bus.shutdown()
        ecu_bus.shutdown()
    extra = {
        "solver_not_converged": not_converged,
        "input_clips": clips,
        "duration_s": float(now),
        "wall_time_s": time.perf_counter() - wall0,
        "finished": False,  # decided below
        "rolling_window": None
        if window is None
        else {"length_m": window.length, "period_s": window.period},
        "final_state": gateway.state.name,
        "transitions": transitions,
        "safety_clamps": clamps,
        "can_frames_sent": frames_sent,
        "can_frames_received": frames_received,
        "can_frames_rejected": frames_rejected,
        "ecu_frames_rejected": ecu.rejected_frames,
    }
    why_not = ""
    ended = [tr for tr in transitions if tr["to"] in ("FAULT", "STOPPING", "STANDBY")]
    if not engaged_once:
        why_not = "the gateway never engaged" + (f": {r}" if (r := _refusal(timeline)) else "")
    elif ended and (ended[0]["to"] != "STANDBY" or ended[0]["reason"] != END_REACHED):
        first = ended[0]
        why_not = f"{first['to']} at t = {first['t']:.2f} s: {first['reason']}"
    elif gateway.state != GatewayState.STANDBY:
        why_not = f"time limit {scenario.duration:.0f} s reached in {gateway.state.name}"
    extra["finished"] = not why_not
    return _finish(config, scenario, rec, solve_times, extra, timeline, label, why_not)


def _refusal(timeline: list[tuple[float, str]]) -> str:
    """The operator engage refusal of a run, if any."""
    return next((event for _, event in timeline if "engage: refused" in event), "")
