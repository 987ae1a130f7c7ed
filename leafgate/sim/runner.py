"""The closed-loop simulator on a simulated clock.

One thread, one simulated clock: a 30 s maneuver runs in well under a second of wall time and
gives the same numbers every run.

:func:`run` is the full loop of the real system: plant → simulated ECU → CAN report frames →
the daemon's runtime (its ``CanReceiver``: decode, echo filter, foreign-frame and error counts;
``Runtime.tick``: ``Gateway.step`` with watchdogs, state machine, controller, safety gate, then
encode and send) → CAN command frames → ECU, over a python-can ``virtual`` bus, with
localization from the plant and the trajectory from the scenario, engaged by a scripted
operator request. :func:`run_direct` is the paper's Simulink check: the controller drives the
plant with nothing in between.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import math
import re
import secrets
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import can
import numpy as np

from leafgate.can.codec import CanCodec, Decoded, EncodeError
from leafgate.can.secoc import KEY_BYTES
from leafgate.config.sim import SimConfig
from leafgate.control import make_controller
from leafgate.control.reference import MIN_POINTS, split_segments
from leafgate.errors import ConfigError
from leafgate.gateway.core import END_REACHED, Gateway, GatewayInputs, StepResult
from leafgate.gateway.watchdog import off_plan
from leafgate.messages import (
    GatewayState,
    Gear,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SystemReport,
    Trajectory,
)
from leafgate.runtime.loop import Runtime
from leafgate.runtime.receiver import CanReceiver
from leafgate.settings import LeafgateConfig
from leafgate.sim.ecu import SimulatedEcu
from leafgate.sim.metrics import Projector, clearance_metrics, path_errors, tracking_metrics
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

# Injections the gateway's inputs perform (localization faults) …
LOCALIZATION_INJECTIONS = {"localization-dropout", "position-jump"}
# … and the bus: the gateway's frames stop reaching the ECU; another node sends on its IDs.
BUS_INJECTIONS = {"command-dropout", "foreign-command"}
GATEWAY_INJECTIONS = LOCALIZATION_INJECTIONS | BUS_INJECTIONS  # the rest: the simulated ECU
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
    in time order and in its direction of travel), or ``behind`` metres before it within the
    move the car drives (Autoware's planners keep a few metres behind the car), and is a new
    object with a new receive time, as from a planner over Zenoh (the transport makes a new
    object of every message). With ``resample``, every plan is re-sampled as a planner does on
    each cycle: every waypoint but the plan's ends and its cusps moves along its chord by a new
    fraction, so that no waypoint repeats the last plan's.
    """

    length: float = 30.0  # m
    period: float = 0.5  # s
    behind: float = 0.0  # m
    resample: bool = False

    def __post_init__(self) -> None:
        if not (self.length > 0.0 and self.period > 0.0 and self.behind >= 0.0):
            raise ConfigError(
                f"rolling window: length and period must be positive and behind not negative, "
                f"got {self.length!r} m every {self.period!r} s, {self.behind!r} m behind"
            )


RESAMPLE_STEP = 0.37  # the fraction of a chord each re-sampled plan moves on from the last


class _Planner:
    """Cuts the rolling windows out of the whole route, following the car along it."""

    def __init__(self, route: Trajectory, window: RollingWindow) -> None:
        self.route = route
        self.window = window
        self.projector = Projector(route)
        self.last_sent: float | None = None
        self.plan: Stamped[Trajectory] | None = None
        self.sent = 0  # plans sent

    def plan_at(self, now: float, pose: Pose) -> Stamped[Trajectory]:
        """The plan the gateway holds at ``now`` (a new one every period)."""
        if self.plan is None:  # the car's start, as the controller takes it
            self.projector.start_at(pose.x, pose.y, pose.heading)
        k, _, _, _, _ = self.projector.project(pose.x, pose.y, pose.speed)  # every tick: in order
        due = self.last_sent is None or now - self.last_sent >= self.window.period - 1e-9
        if self.plan is not None and not due:
            return self.plan
        route, proj = self.route, self.projector
        n = len(route)
        first = k
        if self.window.behind > 0.0:  # back along the route, not over the cusp before
            move_start = int(np.argmax(proj.move == proj.move[k]))
            back = int(np.searchsorted(proj.s, proj.s[k] - self.window.behind, side="left"))
            first = max(back, move_start)
        first = min(first, n - MIN_POINTS)  # a plan has at least four waypoints
        end_s = proj.s[k] + self.window.length
        last = max(int(np.searchsorted(proj.s, end_s, side="right")), first + MIN_POINTS)
        cut = slice(first, min(last, n))
        plan = Trajectory(
            x=route.x[cut], y=route.y[cut], heading=route.heading[cut], speed=route.speed[cut]
        )
        if self.window.resample:
            plan = resampled(plan, (0.1 + RESAMPLE_STEP * self.sent) % 1.0)
        self.sent += 1
        self.plan, self.last_sent = Stamped(plan, now), now
        return self.plan


def resampled(plan: Trajectory, fraction: float) -> Trajectory:
    """``plan`` with every waypoint but its ends and its cusps moved ``fraction`` (0–1) of the
    way to the next one (x, y, heading and speed alike): the same route as a planner that
    re-samples its path each cycle sends it (``--window-resample``), no waypoint repeating."""
    keep = np.zeros(len(plan), dtype=bool)
    keep[[0, -1]] = True
    keep[[seg.end for seg in split_segments(plan)]] = True
    move = ~(keep | np.r_[keep[1:], True])  # neither kept nor just before a kept one
    nxt = np.r_[np.arange(1, len(plan)), len(plan) - 1]
    f = np.where(move, fraction, 0.0)
    turn = np.angle(np.exp(1j * (plan.heading[nxt] - plan.heading)))
    return Trajectory(
        x=plan.x + f * (plan.x[nxt] - plan.x),
        y=plan.y + f * (plan.y[nxt] - plan.y),
        heading=plan.heading + f * turn,
        speed=plan.speed + f * (plan.speed[nxt] - plan.speed),
    )


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
            # every value as the shortest text that reads back as the same float: at map
            # coordinates (x ≈ 350 000 m) six significant digits were a metre
            columns = [
                (np.degrees(self.series[key]) if name in degrees else self.series[key]).tolist()
                for name, key in TRACE_COLUMNS
            ]
            for i, state in enumerate(self.states):
                out.writerow([repr(col[i]) for col in columns] + [state])


FINISH_TOLERANCE = 0.5  # m: a run finished only when it ended this close to the route's end


def finish_verdict(metrics: dict[str, Any], claimed: bool, why_not: str) -> tuple[bool, str]:
    """Did the run finish the maneuver? Checked against the route, not only taken from the
    gateway: the car must have driven the route from where its start projects
    (``start_progress_m``; 0 from the first waypoint) to the end, within
    :data:`FINISH_TOLERANCE`, and stopped on the end.

    A start within :data:`FINISH_TOLERANCE` of the route's end leaves nothing to drive: such a
    run is not finished (a car that never moved would pass every other check). So a finished
    run always made progress.
    """
    length, start = metrics["route_length_m"], metrics["start_progress_m"]
    progress, final = metrics["progress_m"], metrics["final_position_error_m"]
    left = length - start  # m, the route from the start's projection to the end
    if not claimed:
        return False, why_not
    if left <= FINISH_TOLERANCE:
        return False, (
            f"the gateway reported the end reached, but the car started {left:.2f} m before "
            f"the route's end (at {start:.1f} of {length:.1f} m), within the "
            f"{FINISH_TOLERANCE:g} m that counts as there: nothing was left to drive"
        )
    if progress < left - FINISH_TOLERANCE or final > FINISH_TOLERANCE:
        started = f" from its start at {start:.1f} m" if start >= 0.05 else ""
        return False, (
            f"the gateway reported the end reached, but the car got {progress:.1f} of "
            f"{left:.1f} m along the route{started} and stopped {final:.2f} m from its end"
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
    metrics.update(clearance_metrics(scenario.name, arr["t"], arr["x"], arr["y"], arr["heading"]))
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
    limit = config.gateway.watchdog.max_path_deviation
    left_plan = ""  # where the car first went farther off the plan than the gateway allows
    for k in range(steps):
        t = k * period
        pose = plant.pose()
        out = controller.step(pose, plant.steer_angle, traj)
        off = None if left_plan else off_plan(out.deviation, out.progress, out.route_length, limit)
        if off is not None:  # the watchdog's rule and words
            left_plan = (
                f"{off} at t = {t:.2f} s: the gateway (watchdog.max_path_deviation) would have "
                "stopped the car there; --direct has no gateway and drove on"
            )
            timeline.append((t, left_plan))
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
    if left_plan:  # the end was reached where the car would not have been let drive
        extra["finished"], why_not = False, left_plan
    return _finish(config, scenario, rec, solve_times, extra, timeline, label, why_not)


class _SimClock:
    """Simulated time, s: the clock of the runtime and its receiver, and of every stamp."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class _SimBus:
    """The simulated CAN bus: one python-can ``virtual`` channel, with the gateway's end, the
    ECU's end and, for ``foreign-command``, a third node's.

    The gateway's end hears its own frames back, as the daemon's ``udp_multicast`` bus does:
    the receiver's echo filter works on every drive as it does on the bench.
    """

    def __init__(self, codec: CanCodec) -> None:
        self.channel = f"leafgate-sim-{next(_channel_ids)}"
        report_ids = codec.receive_ids("reports") | codec.receive_ids("car")
        self.gateway = can.Bus(  # the runtime widens the filter by its command IDs
            interface="virtual",
            channel=self.channel,
            preserve_timestamps=True,
            receive_own_messages=True,
            can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in sorted(report_ids)],
        )
        self.ecu = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self.command_ids = sorted(codec.receive_ids("commands"))
        self._foreign: can.BusABC | None = None  # opened at the first foreign frame

    def send_foreign(self, now: float) -> None:
        """Another node commands the ECU: one all-zero frame on each of our command IDs."""
        if self._foreign is None:
            self._foreign = can.Bus(
                interface="virtual", channel=self.channel, preserve_timestamps=True
            )
        while self._foreign.recv(timeout=0.0) is not None:
            pass  # it hears the whole bus; nobody reads it
        for frame_id in self.command_ids:
            frame = can.Message(
                arbitration_id=frame_id, is_extended_id=False, data=bytes(8), timestamp=now
            )
            self._foreign.send(frame)

    def close(self) -> None:
        for bus in (self.gateway, self.ecu, self._foreign):
            if bus is not None:
                bus.shutdown()


class _Vehicle:
    """The car's side of the bus: the plant, driven by the simulated ECU, which sends its
    reports and takes the command frames (the ECU's own injections armed)."""

    def __init__(
        self,
        config: LeafgateConfig,
        scenario: Scenario,
        injections: tuple[Injection, ...],
        bus: can.BusABC,
        codec: CanCodec,
    ) -> None:
        self.plant = make_plant(config.sim.plant, config.vehicle, start_pose(scenario, config.sim))
        ecu = SimulatedEcu(config.sim.ecu, self.plant, config.vehicle, codec)
        ecu.set_driver_path(scenario.trajectory)  # lateral-only: the driver holds the speed
        for inj in injections:
            if inj.kind in ECU_INJECTIONS:
                ecu_kind, kwargs, default_duration = ECU_INJECTIONS[inj.kind]
                ecu.inject(ecu_kind, at=inj.at, duration=inj.duration or default_duration, **kwargs)
        self.ecu = ecu
        self.bus = bus

    def step(self, now: float, dt: float) -> None:
        """Actuate the plant for one ECU tick and send the reports due now."""
        self.ecu.step(now, dt)
        errors = self.ecu.counters.encode_errors
        for msg in self.ecu.reports(now):
            self.bus.send(msg)
        if self.ecu.counters.encode_errors > errors:  # a report the gateway would miss: say why
            raise EncodeError(f"simulated ECU: report frame not sent: {self.ecu.last_encode_error}")

    def take_commands(self, now: float, lost: bool) -> None:
        """Hand the frames on the bus to the ECU; ``lost``: none reach it (command-dropout)."""
        while (frame := self.bus.recv(timeout=0.0)) is not None:
            if not lost:
                self.ecu.receive_frame(now, frame)


class _SimInputs:
    """Localization and trajectory as the runtime reads them (its ``InputSource``).

    Localization is the plant's pose each tick, or, with noise or latency configured
    (``sim.localization``; the seed makes it repeatable), the newest sample of the same feed as
    sim-ecu's, on the simulated clock. The trajectory is the scenario's route, whole or as a
    planner's rolling window. ``localization-dropout`` and ``position-jump`` act here.
    """

    def __init__(
        self,
        config: LeafgateConfig,
        route: Trajectory,
        injections: tuple[Injection, ...],
        window: RollingWindow | None,
    ) -> None:
        loc = config.sim.localization
        self._samples: list[Pose] = []  # published by the feed since the last control tick
        self.feed = None
        if loc.position_noise > 0 or loc.heading_noise > 0 or loc.latency > 0:
            self.feed = LocalizationFeed(self._samples.append, loc, wall_clock=False)
        self._planner = None if window is None else _Planner(route, window)
        self._whole = Stamped(route, 0.0)
        self._injections = [i for i in injections if i.kind in LOCALIZATION_INJECTIONS]
        self._pose: Stamped[Pose] | None = None
        self._plan: Stamped[Trajectory] | None = None

    def latest_pose(self) -> Stamped[Pose] | None:
        return self._pose

    def latest_trajectory(self) -> Stamped[Trajectory] | None:
        return self._plan

    def on_ecu_tick(self, now: float, ecu: SimulatedEcu) -> None:
        if self.feed is not None:
            self.feed.on_tick(now, ecu)

    def update(self, now: float, truth: Pose) -> None:
        """The inputs of the control tick at ``now``; ``truth`` is the plant's pose."""
        pose: Pose | None
        if self.feed is None:
            pose = dataclasses.replace(truth, stamp=now)
        else:  # the newest sample published since the last tick, if any
            pose = self._samples[-1] if self._samples else None
            self._samples.clear()
        active = {i.kind for i in self._injections if i.active(now)}
        if pose is not None and "position-jump" in active:
            pose = dataclasses.replace(pose, x=pose.x + 2.0)
        if pose is not None and "localization-dropout" not in active:
            self._pose = Stamped(pose, now)
        self._plan = self._whole if self._planner is None else self._planner.plan_at(now, truth)


class _GatewaySide:
    """The gateway as the daemon runs it: ``Runtime.tick`` with its ``CanReceiver``, on the
    simulated clock, and what the drive's metrics and timeline need from each frame and tick.

    No Notifier thread: :meth:`receive` feeds the receiver each frame the gateway's end of the
    bus holds, synchronously, so the drive stays deterministic. The frames carry simulated
    timestamps and the receiver's wall clock is the simulated one, so a frame is received at
    the time it was sent.
    """

    def __init__(
        self,
        config: LeafgateConfig,
        codec: CanCodec,
        bus: can.BusABC,
        inputs: _SimInputs,
        recorder: Recorder | None,
        timeline: list[tuple[float, str]],
        clock: _SimClock,
    ) -> None:
        period = config.gateway.period
        controller = make_controller(config.controller, config.vehicle, period)
        if recorder is not None:  # recording: a transparent wrapper lets it see the predicted path
            controller = recorder.wrap_controller(controller)
        self.gateway = Gateway(config.gateway, config.vehicle, controller, config.long_mode)
        self.codec = codec
        self.clock = clock
        self.receiver = CanReceiver(self.codec, self.clock, wall_clock=self.clock)
        self.receiver.on_frame = self._on_frame
        self.runtime = Runtime(
            self.gateway,
            self.codec,
            bus,
            self.receiver,
            inputs,
            period,
            clock=self.clock,
            on_tick=self._on_tick,
            receive_buses=(),  # fed synchronously: no frame ever waits unread
        )
        self.bus = bus
        self.recorder = recorder
        self.timeline = timeline
        self.transitions: list[dict[str, Any]] = []
        self.solve_times: list[float] = []
        self.not_converged = self.clips = 0
        self.frames_sent = self.frames_received = self.frames_rejected = 0
        self.engaged_once = False
        self.commands_lost = False  # command-dropout: the tick's frames do not reach the ECU
        self._state = self.gateway.state  # before the tick
        self._gear: Gear | None = None
        self._ecu_state: str | None = None

    @property
    def state(self) -> GatewayState:
        return self.gateway.state

    def receive(self, now: float) -> None:
        """The receiver reads what arrived on the gateway's end of the bus."""
        self.clock.now = now
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self.receiver.on_message_received(msg)

    def tick(self, now: float, request: OperatorRequest | None) -> StepResult:
        self.clock.now = now
        return self.runtime.tick(now, request=request)

    def _on_frame(self, msg: can.Message, decoded: Decoded) -> None:
        """Every frame received but our own echoes (the daemon's recorder hook, too)."""
        self.frames_received += 1
        if self.recorder is not None:
            self.recorder.on_can_frame(msg, "rx")
        if decoded.counts_for_reports and not decoded.valid:
            self.frames_rejected += 1
        if not decoded.valid:
            return
        now = self.clock.now
        for value in decoded.values:
            if isinstance(value, LongReport) and value.gear != self._gear:
                self._gear = value.gear
                self.timeline.append((now, f"gear {value.gear.name}"))
            elif isinstance(value, SystemReport) and value.state.name != self._ecu_state:
                self._ecu_state = value.state.name
                self.timeline.append((now, f"ECU {self._ecu_state}"))

    def _on_tick(
        self, now: float, inputs: GatewayInputs, result: StepResult, frames: Sequence[can.Message]
    ) -> None:
        """After each tick: its figures, its transitions, its frames to the recorder."""
        if self.runtime.stats.encode_errors:  # the gate keeps values in range: a bug, say so
            raise EncodeError(next(iter(self.codec.last_errors), "see the log"))
        if result.reply is not None:
            verdict = "accepted" if result.reply.accepted else "refused"
            self.timeline.append((now, f"operator engage: {verdict} ({result.reply.reason})"))
        ctl = result.diagnostics.controller
        # Every tick the controller ran while engaged, including the one whose failure moved
        # the gateway to STOPPING.
        if ctl is not None and self._state == GatewayState.ENGAGED:
            self.solve_times.append(ctl.solve_time)
            self.not_converged += 0 if ctl.converged else 1
            self.clips += ctl.clips
        for tr in result.diagnostics.transitions:  # an engagement may begin and end in one tick
            self.transitions.append(
                {
                    "t": round(now, 6),
                    "from": tr.source.name,
                    "to": tr.target.name,
                    "reason": tr.reason,
                }
            )
            self.timeline.append((now, f"gateway {tr.source.name} → {tr.target.name}: {tr.reason}"))
            self.engaged_once |= tr.target == GatewayState.ENGAGED
        self._state = self.gateway.state
        self.frames_sent += len(frames)
        if self.recorder is not None:  # the tick's inputs, result and the frames on the bus
            self.recorder.on_tick(now, inputs, result, [] if self.commands_lost else frames)

    def figures(self) -> dict[str, Any]:
        """The gateway's part of the drive's metrics."""
        last = self.runtime.last_result
        clamps = {} if last is None else last.diagnostics.clamps
        return {
            "solver_not_converged": self.not_converged,
            "input_clips": self.clips,
            "final_state": self.gateway.state.name,
            "transitions": self.transitions,
            "safety_clamps": {name: int(count) for name, count in clamps.items()},
            "can_frames_sent": self.frames_sent,
            "can_frames_received": self.frames_received,
            "can_frames_rejected": self.frames_rejected,
            # the receiver's echo filter: our own frames heard back, others' on our IDs
            "can_own_echoes": self.receiver.own_echoes,
            "can_foreign_frames": self.receiver.foreign_total,
        }


class _EndCondition:
    """A drive is done once the gateway has engaged and let go again, and the car has been at
    rest for :data:`REST_BEFORE_END`."""

    def __init__(self) -> None:
        self.rest_since: float | None = None

    def reached(self, now: float, gateway: _GatewaySide, speed: float) -> bool:
        at_rest = abs(speed) <= STANDSTILL_SPEED
        idle = gateway.state in (GatewayState.STANDBY, GatewayState.FAULT)
        if not (gateway.engaged_once and idle and at_rest):
            self.rest_since = None
            return False
        self.rest_since = now if self.rest_since is None else self.rest_since
        return now - self.rest_since >= REST_BEFORE_END


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

    The gateway runs as in the daemon (``Runtime.tick`` and its ``CanReceiver`` with the echo
    filter and the foreign-frame and error counts), on the simulated clock.

    :param recorder: records the drive (``leafgate.record.recorder``): every frame the gateway
        receives and sends, stamped with the simulated time, and every tick's inputs and result
    :param window: send the route as a planner's rolling window instead of whole, once
    :param epoch: Unix time of t = 0 for authenticated frames' freshness values (the
        recording's, so a recorded log verifies against its timestamps); None: now
    :raises EncodeError: a command frame could not be encoded (the safety gate keeps every
        value in range, so this is a bug)
    """
    period = config.gateway.period
    ticks_per_control = max(1, round(period / ECU_TICK))
    ecu_dt = period / ticks_per_control
    timeline: list[tuple[float, str]] = [
        (0.0, f"start {scenario.name}: gateway {GatewayState.STANDBY.name}")
    ]
    inputs = _SimInputs(config, scenario.trajectory, injections, window)
    # Authenticated frames: the configured key, or a throwaway one; their freshness values come
    # from the simulated clock as Unix time from the start (as the recording stamps frames).
    key = sim_key(config)
    start = time.time() if epoch is None else epoch
    clock = _SimClock()

    def unix_time() -> float:
        return start + clock.now

    codec = CanCodec.for_config(config, clock=unix_time, key=key)  # the gateway's
    bus = _SimBus(codec)
    try:
        ecu_codec = CanCodec.for_config(config, clock=unix_time, key=key)
        vehicle = _Vehicle(config, scenario, injections, bus.ecu, ecu_codec)
        gateway = _GatewaySide(config, codec, bus.gateway, inputs, recorder, timeline, clock)
        end = _EndCondition()
        trace = _Recorder()
        plant = vehicle.plant
        wall0 = time.perf_counter()
        now = 0.0
        for k in range(round(scenario.duration / ecu_dt)):
            now = k * ecu_dt
            clock.now = now
            control = k % ticks_per_control == 0
            active = {i.kind for i in injections if i.active(now)}
            vehicle.step(now, ecu_dt)
            inputs.on_ecu_tick(now, vehicle.ecu)
            if control and "foreign-command" in active:
                bus.send_foreign(now)
            gateway.receive(now)
            if not control:
                continue
            inputs.update(now, plant.pose())
            gateway.commands_lost = "command-dropout" in active
            request = OperatorRequest.ENGAGE if abs(now - engage_at) < ecu_dt / 2 else None
            cmds = gateway.tick(now, request).commands
            vehicle.take_commands(now, lost=gateway.commands_lost)
            accel_target = cmds.long.accel if cmds.long.enable else 0.0
            state = gateway.state.name
            trace.add(now, plant.pose(), plant.steer_angle, cmds.steer.angle, accel_target, state)
            if end.reached(now, gateway, plant.speed):
                break
        wall_time = time.perf_counter() - wall0
    finally:
        bus.close()
    ecu_rejected = vehicle.ecu.rejected_frames
    return _result(config, scenario, label, window, gateway, trace, ecu_rejected, now, wall_time)


def _result(
    config: LeafgateConfig,
    scenario: Scenario,
    label: str,
    window: RollingWindow | None,
    gateway: _GatewaySide,
    trace: _Recorder,
    ecu_rejected: int,
    duration: float,
    wall_time: float,
) -> SimResult:
    """The drive's metrics, trace and timeline, and whether it finished (and why not)."""
    figures = gateway.figures()
    extra = {
        "solver_not_converged": figures.pop("solver_not_converged"),
        "input_clips": figures.pop("input_clips"),
        "duration_s": float(duration),
        "wall_time_s": wall_time,
        "finished": False,  # decided below
        "rolling_window": None
        if window is None
        else {
            "length_m": window.length,
            "period_s": window.period,
            "behind_m": window.behind,
            "resample": window.resample,
        },
        **figures,
        "ecu_frames_rejected": ecu_rejected,
    }
    why_not = _why_not(gateway, scenario)
    extra["finished"] = not why_not
    return _finish(
        config, scenario, trace, gateway.solve_times, extra, gateway.timeline, label, why_not
    )


def _why_not(gateway: _GatewaySide, scenario: Scenario) -> str:
    """Why the gateway did not finish the drive ("" when it reported the end reached)."""
    transitions = gateway.transitions
    ended = [tr for tr in transitions if tr["to"] in ("FAULT", "STOPPING", "STANDBY")]
    if not gateway.engaged_once:
        refusal = _refusal(gateway.timeline)
        return "the gateway never engaged" + (f": {refusal}" if refusal else "")
    if ended and (ended[0]["to"] != "STANDBY" or ended[0]["reason"] != END_REACHED):
        first = ended[0]
        return f"{first['to']} at t = {first['t']:.2f} s: {first['reason']}"
    if gateway.state != GatewayState.STANDBY:
        return f"time limit {scenario.duration:.0f} s reached in {gateway.state.name}"
    return ""


def _refusal(timeline: list[tuple[float, str]]) -> str:
    """The operator engage refusal of a run, if any."""
    return next((event for _, event in timeline if "engage: refused" in event), "")
