"""The simulator in real time: ``leafgate sim-ecu`` and ``leafgate sim --realtime``.

``sim-ecu`` is the hardware stand-in for process tests: the simulated drive-by-wire ECU and its
plant on a real bus (``udp_multicast`` here, ``socketcan`` where the kernel has it), publishing
the plant's pose as localization (nav_msgs/Odometry) over Zenoh with configurable rate, noise
and latency.

Faults for process tests (``sim-ecu --inject KIND@T[+DUR][:NAME=VALUE,...]``, repeatable): T is
counted from the moment the ECU first engages (the first accepted ENABLE edge), so a test can
say "3 s into the maneuver" without knowing how long start-up and engagement took. The ECU's own
injections (:data:`leafgate.sim.ecu.INJECTION_KINDS`) go to :meth:`SimulatedEcu.inject`; the
localization publisher performs :data:`LOCALIZATION_FAULTS`. Each start and end is logged with
its ``time.perf_counter`` value (CLOCK_MONOTONIC on Linux, the clock the gateway stamps its
transitions with, so times compare across processes) and listed at the end of the ``--trace``
CSV as ``# {json}`` comment lines.

``sim --realtime`` runs the daemon's own runtime (its threads, one in-process Zenoh session, a
python-can ``virtual`` bus) against the simulated ECU in the same process, drives a scenario
and reports the same metrics as the simulated-clock mode.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from leafgate.config.can import BusConfig, CanConfig
from leafgate.config.sim import LocalizationConfig
from leafgate.errors import ConfigError, LeafgateError
from leafgate.messages import GatewayState, Pose
from leafgate.settings import LeafgateConfig
from leafgate.sim.ecu import INJECTION_KINDS as ECU_INJECTION_KINDS
from leafgate.sim.ecu import RealtimeStats, SimulatedEcu, run_ecu_realtime
from leafgate.sim.metrics import clearance_metrics, path_errors, tracking_metrics
from leafgate.sim.names import TO_SIM_ECU
from leafgate.sim.plots import Trace
from leafgate.sim.scenarios import Scenario

log = logging.getLogger(__name__)

TRAJECTORY_REPUBLISH = 0.5  # s, planners re-publish their plan; the gateway refuses a stale one
_channels = itertools.count()
_EPS = 1e-9  # s, tolerance of "due at now" against sums of tick periods

#: Faults the localization publisher of ``sim-ecu`` performs: kind → parameters and defaults.
LOCALIZATION_FAULTS: Mapping[str, Mapping[str, float]] = {
    "localization-stop": {},  # nothing is published
    "localization-jump": {"lateral": 2.0, "longitudinal": 0.0},  # m, offset (left +, ahead +)
    "localization-delay": {"delay": 0.4},  # s, each sample is published this long after its stamp
}
#: Every ``sim-ecu --inject`` kind with its parameters' defaults.
SIM_ECU_INJECTIONS: Mapping[str, Mapping[str, float]] = {
    **ECU_INJECTION_KINDS,
    **LOCALIZATION_FAULTS,
}
_INJECT_SYNTAX = re.compile(
    r"(?P<kind>[a-z-]+)@(?P<at>[0-9.]+)s?(?:\+(?P<dur>[0-9.]+)s?)?(?::(?P<params>.*))?"
)


@dataclass(frozen=True)
class EngagedInjection:
    """A fault ``at`` seconds after the ECU first engages: ``KIND@T[s][+DUR[s]][:NAME=VALUE,...]``.

    ``params`` holds every parameter of the kind (defaults filled in).
    """

    kind: str
    at: float  # s after the first engagement
    duration: float | None = None  # s, None = until the end
    params: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str) -> EngagedInjection:
        """Parse ``localization-jump@3`` or ``override-torque@2+0.5:torque=5``.

        :raises ConfigError: one line naming the text and what is wrong
        """
        m = _INJECT_SYNTAX.fullmatch(text.strip())
        if not m:
            raise ConfigError(
                f"--inject {text!r}: expected KIND@TIME[s][+DURATION[s]][:NAME=VALUE,...], "
                "e.g. localization-stop@3s"
            )
        kind = TO_SIM_ECU.get(m.group("kind"), m.group("kind"))  # sim's name for the same fault
        defaults = SIM_ECU_INJECTIONS.get(kind)
        if defaults is None:
            raise ConfigError(
                f"--inject {text!r}: unknown kind {kind!r} "
                f"(known: {', '.join(sorted(SIM_ECU_INJECTIONS))})"
            )
        try:
            at = float(m.group("at"))
            duration = float(m.group("dur")) if m.group("dur") else None
        except ValueError:
            raise ConfigError(f"--inject {text!r}: bad time {m.group(0)!r}") from None
        if duration is not None and not duration > 0.0:
            raise ConfigError(f"--inject {text!r}: the duration must be positive")
        params = dict(defaults)
        for item in filter(None, (m.group("params") or "").split(",")):
            name, sep, value = item.partition("=")
            name = name.strip()
            if not sep or name not in defaults:
                known = ", ".join(sorted(defaults)) or "none"
                raise ConfigError(
                    f"--inject {text!r}: unknown parameter {name!r} for {kind} (known: {known})"
                )
            try:
                params[name] = float(value)
            except ValueError:
                raise ConfigError(f"--inject {text!r}: {name}={value!r} is not a number") from None
            if not math.isfinite(params[name]):
                raise ConfigError(f"--inject {text!r}: {name} must be finite")
        if kind == "localization-delay" and not params["delay"] > 0.0:
            raise ConfigError(f"--inject {text!r}: delay must be positive")
        return cls(kind, at, duration, params)

    def __str__(self) -> str:
        dur = "" if self.duration is None else f"+{self.duration:g}"
        return f"{self.kind}@{self.at:g}{dur}"


class InjectionSchedule:
    """Arms :class:`EngagedInjection` s at the ECU's first engagement and logs them.

    :meth:`on_tick` is called by the ECU loop after each step; ECU faults are handed to
    :meth:`SimulatedEcu.inject` once the engagement time is known, localization faults are
    asked for with :meth:`params`.

    :param clock: the monotonic clock logged with each event (the gateway's clock)
    """

    def __init__(
        self, injections: Iterable[EngagedInjection], clock: Callable[[], float] = time.perf_counter
    ) -> None:
        self.injections = tuple(injections)
        self.clock = clock
        self.engaged_at: float | None = None  # s, ECU time of the first engagement
        self.events: list[dict[str, Any]] = []
        self._started = [False] * len(self.injections)
        self._ended = [False] * len(self.injections)

    def _event(self, event: str, now: float, **extra: Any) -> dict[str, Any]:
        record = {"event": event, "t": now, "mono": self.clock(), **extra}
        self.events.append(record)
        return record

    def on_tick(self, now: float, ecu: SimulatedEcu) -> None:
        """Arm at the first engagement; log each injection's start and end."""
        if self.engaged_at is None:
            if not ecu.engaged:
                return
            self.engaged_at = now
            record = self._event("engaged", now)
            log.info(
                "ECU engaged at t=%.3f s (monotonic %.6f); %d injection(s) armed",
                now,
                record["mono"],
                len(self.injections),
            )
            for inj in self.injections:
                if inj.kind in ECU_INJECTION_KINDS:
                    ecu.inject(inj.kind, now + inj.at, inj.duration, **inj.params)
        if not self.injections:
            return
        engaged_at = self.engaged_at
        for i, inj in enumerate(self.injections):
            start = engaged_at + inj.at
            if not self._started[i] and now >= start - _EPS:
                self._started[i] = True
                record = self._event("injection-start", now, kind=inj.kind, after_engage=inj.at)
                log.info(
                    "injection %s started %.3f s after engage (t=%.3f s, monotonic %.6f) %s",
                    inj.kind,
                    now - engaged_at,
                    now,
                    record["mono"],
                    dict(inj.params),
                )
            end = start + inj.duration if inj.duration is not None else math.inf
            if self._started[i] and not self._ended[i] and now >= end - _EPS:
                self._ended[i] = True
                record = self._event("injection-end", now, kind=inj.kind)
                log.info(
                    "injection %s ended (t=%.3f s, monotonic %.6f)", inj.kind, now, record["mono"]
                )

    def params(self, now: float, kind: str) -> Mapping[str, float] | None:
        """The parameters of the last-given injection of ``kind`` active at ``now``, or None."""
        if self.engaged_at is None:
            return None
        for inj in reversed(self.injections):
            if inj.kind != kind:
                continue
            start = self.engaged_at + inj.at
            end = start + inj.duration if inj.duration is not None else math.inf
            if start - _EPS <= now < end - _EPS:
                return inj.params
        return None

    def never_started(self) -> list[EngagedInjection]:
        """The injections whose time had not come when the run ended."""
        return [
            inj for inj, started in zip(self.injections, self._started, strict=True) if not started
        ]


#: ``faults(now, kind)``: the active localization fault's parameters, or None.
FaultLookup = Callable[[float, str], Mapping[str, float] | None]


class LocalizationFeed:
    """Publishes the plant's pose at a fixed rate, with noise and latency, from the ECU loop.

    ``on_tick`` is called by the ECU loop at its 1 kHz tick; it keeps a short history so the pose
    published is the one ``latency`` seconds old.

    :param wall_clock: stamp samples with the wall clock (a live run); False stamps them with
        the simulated ``now`` of :meth:`on_tick` (the simulated-clock loop)
    :param faults: asked each sample for the :data:`LOCALIZATION_FAULTS` that act now:
        ``localization-stop`` publishes nothing, ``localization-jump`` offsets the position
        (``lateral`` to the left of the heading, ``longitudinal`` ahead, m),
        ``localization-delay`` publishes each sample ``delay`` s after its stamp (samples stay in
        order: while delayed ones wait, later ones queue behind them)
    """

    def __init__(
        self,
        publish: Any,
        cfg: LocalizationConfig,
        faults: FaultLookup | None = None,
        *,
        wall_clock: bool = True,
    ) -> None:
        self._publish = publish  # callable(Pose)
        self._wall_clock = wall_clock  # stamps from time.time(), else from the tick's ``now``
        self.cfg = cfg
        self.period = 1.0 / cfg.rate_hz
        self._next = 0.0
        self._history: deque[tuple[float, Pose]] = deque()
        self._rng = np.random.default_rng(cfg.seed)
        self._faults = faults
        self._delayed: deque[tuple[float, Pose]] = deque()  # (due, pose with its stamp)
        self.published = 0
        self.suppressed = 0  # samples not published (localization-stop)
        self.errors = 0

    def on_tick(self, now: float, ecu: SimulatedEcu) -> None:
        self._history.append((now, ecu.plant.pose()))
        delayed = self._delayed
        while delayed and delayed[0][0] <= now + _EPS:
            self._send(delayed.popleft()[1])
        if now + 1e-9 < self._next:
            return
        self._next = max(self._next + self.period, now)
        while len(self._history) > 1 and self._history[1][0] <= now - self.cfg.latency + 1e-9:
            self._history.popleft()
        pose = self._history[0][1]
        if self.cfg.position_noise > 0 or self.cfg.heading_noise > 0:
            nx, ny = self._rng.normal(0.0, self.cfg.position_noise, 2)
            nh = self._rng.normal(0.0, self.cfg.heading_noise)
            pose = dataclasses.replace(
                pose, x=pose.x + nx, y=pose.y + ny, heading=pose.heading + nh
            )
        stamp = (time.time() if self._wall_clock else now) - self.cfg.latency
        pose = dataclasses.replace(pose, stamp=stamp)
        faults = self._faults
        if faults is not None:
            if faults(now, "localization-stop") is not None:
                self.suppressed += 1
                return
            jump = faults(now, "localization-jump")
            if jump is not None:
                c, s = math.cos(pose.heading), math.sin(pose.heading)
                ahead, left = jump["longitudinal"], jump["lateral"]
                pose = dataclasses.replace(
                    pose, x=pose.x + ahead * c - left * s, y=pose.y + ahead * s + left * c
                )
            delay = faults(now, "localization-delay")
            if delay is not None or delayed:
                delayed.append((now + (delay["delay"] if delay is not None else 0.0), pose))
                return
        self._send(pose)

    def _send(self, pose: Pose) -> None:
        try:
            self._publish(pose)
            self.published += 1
        except LeafgateError as exc:  # a publication problem must not stop the ECU loop
            self.errors += 1
            log.warning("localization not published: %s", exc)


def run_sim_ecu(
    cfg: LeafgateConfig,
    scenario: Scenario,
    stop: threading.Event,
    trace_path: str | None = None,
    injections: Sequence[EngagedInjection] = (),
) -> int:
    """The body of ``leafgate sim-ecu``: ECU + plant on the configured bus, localization on Zenoh.

    :param trace_path: write the plant's states (t, x, y, heading, speed, steer_angle; SI, and
        mono, the ``time.perf_counter`` of the tick) as CSV there on exit, every 20 ms, followed
        by the injection events and the ECU's counters as ``# {json}`` comment lines
    :param injections: faults armed at the ECU's first engagement
    """
    from leafgate.runtime.daemon import tool_view
    from leafgate.runtime.signals import signals_set
    from leafgate.transport.client import OdometryPublisher
    from leafgate.transport.session import open_session

    zcfg = tool_view(cfg.zenoh)
    session = open_session(zcfg)
    try:
        with OdometryPublisher(session, zcfg) as odom:
            schedule = InjectionSchedule(injections)
            feed = LocalizationFeed(odom.publish, cfg.sim.localization, schedule.params)
            trace = _PlantTrace()
            ecus: list[SimulatedEcu] = []

            def on_tick(now: float, ecu: SimulatedEcu) -> None:
                if not ecus:
                    ecus.append(ecu)
                    # lateral-only vehicles: the simulated driver holds the planned speed
                    ecu.set_driver_path(scenario.trajectory)
                schedule.on_tick(now, ecu)
                feed.on_tick(now, ecu)
                if trace_path is not None:
                    trace.on_tick(now, ecu)

            log.info(
                "simulated ECU on %s:%s, plant %s at %s; localization on %r at %.0f Hz",
                cfg.can.dbw.interface,
                cfg.can.dbw.channel,
                cfg.sim.plant.kind,
                scenario.name,
                zcfg.prefix,
                cfg.sim.localization.rate_hz,
            )
            with signals_set(stop):
                try:
                    stats = run_ecu_realtime(cfg, stop, start=scenario.start, on_tick=on_tick)
                finally:
                    if trace_path is not None:
                        footer = [*schedule.events]
                        if ecus:
                            footer.append({"counters": dataclasses.asdict(ecus[0].counters)})
                        trace.write_csv(trace_path, footer)
            c = stats.counters
            log.info(
                "simulated ECU stopped: %d ticks, %d frames sent, %d received, %d overruns; "
                "%d command frames rejected (bad CRC %d, bad counter %d, length %d, "
                "bad MAC %d, stale freshness %d); "
                "%d timeouts, %d overrides; %d poses published, %d suppressed",
                stats.ticks,
                stats.frames_sent,
                stats.frames_received,
                stats.overruns,
                c.rx_errors,
                c.bad_crc,
                c.bad_counter,
                c.wrong_length,
                c.bad_mac,
                c.stale_freshness,
                c.timeouts,
                c.overrides,
                feed.published,
                feed.suppressed,
            )
            for inj in schedule.never_started():
                why = "the ECU never engaged" if schedule.engaged_at is None else "run ended first"
                log.warning("injection %s never started (%s)", inj, why)
    finally:
        session.close()
    return 0


@dataclass
class _PlantTrace:
    """The plant's states, sampled by the ECU loop every 20 ms."""

    period: float = 0.02
    rows: list[tuple[float, float, float, float, float, float, float]] = field(default_factory=list)
    _next: float = 0.0

    def on_tick(self, now: float, ecu: SimulatedEcu) -> None:
        if now + 1e-9 >= self._next:
            self._next = now + self.period
            p = ecu.plant
            mono = time.perf_counter()  # s, compares with the gateway's clock
            self.rows.append((now, p.x, p.y, p.heading, p.speed, p.steer_angle, mono))

    def write_csv(self, path: str, footer: Iterable[Mapping[str, Any]] = ()) -> None:
        """The rows, then each ``footer`` record as a ``# {json}`` line (numpy skips them)."""
        with open(path, "w", encoding="utf-8") as f:
            f.write("t,x,y,heading,speed,steer_angle,mono\n")
            for row in self.rows:
                f.write(",".join(f"{v:.6f}" for v in row) + "\n")
            for record in footer:
                f.write("# " + json.dumps(record) + "\n")


def run_realtime(
    cfg: LeafgateConfig,
    scenario: Scenario,
    progress: Callable[[float, str], None] | None = None,
) -> dict[str, Any]:
    """Drive ``scenario`` in real time through the daemon's runtime; return metrics and trace.

    Everything runs in this process: the ECU loop and the gateway runtime on their own threads,
    one Zenoh session (no network endpoints) and a python-can ``virtual`` bus.
    """
    import zenoh

    from leafgate.runtime.daemon import run_daemon
    from leafgate.runtime.loop import Runtime
    from leafgate.runtime.signals import interrupt_deferred
    from leafgate.transport.client import OdometryPublisher, TrajectoryPublisher, request

    channel = f"leafgate-realtime-{next(_channels)}"
    cfg = dataclasses.replace(
        cfg,
        can=CanConfig(
            dbw=BusConfig(interface="virtual", channel=channel),
            car=None,
            auth_key_file=cfg.can.auth_key_file,  # an authenticated profile's key
        ),
        zenoh=dataclasses.replace(cfg.zenoh, listen=(), connect=(), config_file=None, mode="peer"),
    )
    zconf = zenoh.Config()
    zconf.insert_json5("scouting/multicast/enabled", "false")
    zconf.insert_json5("scouting/delay", "0")
    session = zenoh.open(zconf)
    stop_ecu, stop_gw = threading.Event(), threading.Event()
    runtime_box: list[Runtime] = []
    trace = _PlantTrace()
    errors: list[BaseException] = []
    timeline: list[tuple[float, str]] = []
    wall0 = time.perf_counter()

    ecu_stats: list[RealtimeStats] = []

    def guarded(fn: Any, *args: Any, **kwargs: Any) -> Any:
        def body() -> None:
            try:
                result = fn(*args, **kwargs)
                if isinstance(result, RealtimeStats):
                    ecu_stats.append(result)
            except BaseException as exc:  # surfaced to the caller after the join
                errors.append(exc)
                stop_ecu.set()
                stop_gw.set()

        return body

    try:
        with (
            OdometryPublisher(session, cfg.zenoh) as odom,
            TrajectoryPublisher(session, cfg.zenoh) as plan,
        ):
            feed = LocalizationFeed(odom.publish, cfg.sim.localization)

            driving: list[SimulatedEcu] = []

            def on_tick(now: float, ecu: SimulatedEcu) -> None:
                if not driving:  # lateral-only vehicles: the driver holds the planned speed
                    driving.append(ecu)
                    ecu.set_driver_path(scenario.trajectory)
                feed.on_tick(now, ecu)
                trace.on_tick(now, ecu)

            ecu_thread = threading.Thread(
                target=guarded(
                    run_ecu_realtime, cfg, stop_ecu, start=scenario.start, on_tick=on_tick
                ),
                name="leafgate-sim-ecu",
                daemon=True,
            )
            gw_thread = threading.Thread(
                target=guarded(
                    run_daemon, cfg, stop_gw, on_runtime=runtime_box.append, session=session
                ),
                name="leafgate-gateway",
                daemon=True,
            )
            try:
                with interrupt_deferred():  # both started, or Ctrl-C after: the finally joins
                    ecu_thread.start()
                    gw_thread.start()
                deadline = time.perf_counter() + scenario.duration + 5.0
                engaged = drove = False
                next_plan = 0.0
                last_state: GatewayState | None = None
                engage_after = time.perf_counter() + 0.5
                while time.perf_counter() < deadline and not errors:
                    t = time.perf_counter()
                    if t >= next_plan:
                        plan.publish(scenario.trajectory)
                        next_plan = t + TRAJECTORY_REPUBLISH
                    runtime = runtime_box[0] if runtime_box else None
                    state = runtime.gateway.state if runtime is not None else None
                    if state is not None and state != last_state:
                        timeline.append((t - wall0, f"gateway {state.name}"))
                        last_state = state
                    if runtime is not None and not engaged and t >= engage_after:
                        reply = request(cfg.zenoh, "engage", timeout=2.0, session=session)
                        timeline.append((t - wall0, f"operator engage: {reply}"))
                        if reply.get("accepted"):
                            engaged = True
                        else:
                            engage_after = t + 0.5
                    if progress is not None:  # wall s since start, and the gateway's state
                        progress(t - wall0, "" if state is None else state.name)
                    drove |= state in (GatewayState.ENGAGED, GatewayState.STOPPING)
                    idle = state in (GatewayState.STANDBY, GatewayState.FAULT)
                    if drove and idle and trace.rows and abs(trace.rows[-1][4]) < 0.01:
                        break
                    time.sleep(0.02)
            finally:  # also on Ctrl-C: the threads stop before the session closes,
                # and a second Ctrl-C waits for that: a thread left inside Zenoh when the
                # interpreter exits aborts it (SIGABRT, see interrupt_deferred)
                with interrupt_deferred():
                    stop_gw.set()
                    gw_thread.join(timeout=5.0)
                    stop_ecu.set()
                    ecu_thread.join(timeout=5.0)
    finally:
        session.close()
    if errors:
        raise errors[0]
    rows = np.asarray(trace.rows, dtype=np.float64)
    ts, x, y, heading, speed, steer = (rows[:, i].copy() for i in range(6))
    metrics: dict[str, Any] = tracking_metrics(scenario.trajectory, ts, x, y, heading, speed, steer)
    metrics.update(clearance_metrics(scenario.name, ts, x, y, heading))
    runtime = runtime_box[0]
    loop = runtime.stats.summary()
    metrics.update(
        {
            "final_state": runtime.gateway.state.name,
            "final_reason": runtime.gateway.machine.reason,
            "duration_s": float(ts[-1] - ts[0]) if len(ts) else 0.0,
            "wall_time_s": time.perf_counter() - wall0,
            "loop_compute_median_s": loop["compute_median_s"],
            "loop_compute_p99_s": loop["compute_p99_s"],
            "loop_start_lateness_p99_s": loop["start_lateness_p99_s"],
            "loop_overruns": loop["overruns"],
            "localization_published": feed.published,
            # the simulator shares this machine: a late ECU loop is a late report to the gateway
            "ecu_loop_max_lateness_s": ecu_stats[0].max_lateness if ecu_stats else math.nan,
        }
    )
    speed_ref = path_errors(scenario.trajectory, x, y, heading, speed).speed_ref
    plot_trace = Trace("mpc, real time", ts, x, y, speed, steer, steer, speed_ref)
    return {"metrics": metrics, "trace": plot_trace, "timeline": timeline}
