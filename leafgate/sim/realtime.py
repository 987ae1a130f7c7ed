"""The simulator in real time: ``leafgate sim-ecu`` and ``leafgate sim --realtime``.

``sim-ecu`` is the hardware stand-in for process tests: the simulated drive-by-wire ECU and its
plant on a real bus (``udp_multicast`` here, ``socketcan`` where the kernel has it), publishing
the plant's pose as localization (nav_msgs/Odometry) over Zenoh with configurable rate, noise
and latency.

``sim --realtime`` runs the daemon's own runtime (its threads, one in-process Zenoh session, a
python-can ``virtual`` bus) against the simulated ECU in the same process, drives a scenario
and reports the same metrics as the simulated-clock mode.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from leafgate.can.config import BusConfig, CanConfig
from leafgate.errors import LeafgateError
from leafgate.messages import GatewayState, Pose
from leafgate.settings import LeafgateConfig
from leafgate.sim.config import LocalizationConfig
from leafgate.sim.ecu import SimulatedEcu, run_ecu_realtime
from leafgate.sim.metrics import path_errors, tracking_metrics
from leafgate.sim.plots import Trace
from leafgate.sim.scenarios import Scenario

log = logging.getLogger(__name__)

TRAJECTORY_REPUBLISH = 0.5  # s, planners re-publish their plan; the gateway refuses a stale one
_channels = itertools.count()


class LocalizationFeed:
    """Publishes the plant's pose at a fixed rate, with noise and latency, from the ECU loop.

    ``on_tick`` is called by the ECU loop at its 1 kHz tick; it keeps a short history so the pose
    published is the one ``latency`` seconds old.
    """

    def __init__(self, publish: Any, cfg: LocalizationConfig) -> None:
        self._publish = publish  # callable(Pose)
        self.cfg = cfg
        self.period = 1.0 / cfg.rate_hz
        self._next = 0.0
        self._history: deque[tuple[float, Pose]] = deque()
        self._rng = np.random.default_rng(cfg.seed)
        self.published = 0
        self.errors = 0

    def on_tick(self, now: float, ecu: SimulatedEcu) -> None:
        self._history.append((now, ecu.plant.pose()))
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
        try:
            self._publish(dataclasses.replace(pose, stamp=time.time() - self.cfg.latency))
            self.published += 1
        except LeafgateError as exc:  # a publication problem must not stop the ECU loop
            self.errors += 1
            log.warning("localization not published: %s", exc)


def run_sim_ecu(
    cfg: LeafgateConfig, scenario: Scenario, stop: threading.Event, trace_path: str | None = None
) -> int:
    """The body of ``leafgate sim-ecu``: ECU + plant on the configured bus, localization on Zenoh.

    :param trace_path: write the plant's states (t, x, y, heading, speed, steer_angle; SI) as CSV
        there on exit, every 20 ms
    """
    from leafgate.gateway.daemon import signals_set, tool_view
    from leafgate.transport.client import OdometryPublisher
    from leafgate.transport.session import open_session

    zcfg = tool_view(cfg.zenoh)
    session = open_session(zcfg)
    try:
        with OdometryPublisher(session, zcfg) as odom:
            feed = LocalizationFeed(odom.publish, cfg.sim.localization)
            trace = _PlantTrace()

            def on_tick(now: float, ecu: SimulatedEcu) -> None:
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
                        trace.write_csv(trace_path)
            log.info(
                "simulated ECU stopped: %d ticks, %d frames sent, %d received, %d overruns; "
                "%d poses published",
                stats.ticks,
                stats.frames_sent,
                stats.frames_received,
                stats.overruns,
                feed.published,
            )
    finally:
        session.close()
    return 0


@dataclass
class _PlantTrace:
    """The plant's states, sampled by the ECU loop every 20 ms."""

    period: float = 0.02
    rows: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)
    _next: float = 0.0

    def on_tick(self, now: float, ecu: SimulatedEcu) -> None:
        if now + 1e-9 >= self._next:
            self._next = now + self.period
            p = ecu.plant
            self.rows.append((now, p.x, p.y, p.heading, p.speed, p.steer_angle))

    def write_csv(self, path: str) -> None:
        with open(path, "w", encoding="utf-8") as f:
            f.write("t,x,y,heading,speed,steer_angle\n")
            for row in self.rows:
                f.write(",".join(f"{v:.6f}" for v in row) + "\n")


def run_realtime(cfg: LeafgateConfig, scenario: Scenario) -> dict[str, Any]:
    """Drive ``scenario`` in real time through the daemon's runtime; return metrics and trace.

    Everything runs in this process: the ECU loop and the gateway runtime on their own threads,
    one Zenoh session (no network endpoints) and a python-can ``virtual`` bus.
    """
    import zenoh

    from leafgate.gateway.daemon import run_daemon
    from leafgate.gateway.runtime import Runtime
    from leafgate.transport.client import OdometryPublisher, TrajectoryPublisher, request

    channel = f"leafgate-realtime-{next(_channels)}"
    cfg = dataclasses.replace(
        cfg,
        can=CanConfig(dbw=BusConfig(interface="virtual", channel=channel), car=None),
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

    def guarded(fn: Any, *args: Any, **kwargs: Any) -> Any:
        def body() -> None:
            try:
                fn(*args, **kwargs)
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

            def on_tick(now: float, ecu: SimulatedEcu) -> None:
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
                drove |= state in (GatewayState.ENGAGED, GatewayState.STOPPING)
                idle = state in (GatewayState.STANDBY, GatewayState.FAULT)
                if drove and idle and trace.rows and abs(trace.rows[-1][4]) < 0.01:
                    break
                time.sleep(0.02)
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
    runtime = runtime_box[0]
    loop = runtime.stats.summary()
    metrics.update(
        {
            "final_state": runtime.gateway.state.name,
            "duration_s": float(ts[-1] - ts[0]) if len(ts) else 0.0,
            "wall_time_s": time.perf_counter() - wall0,
            "loop_compute_median_s": loop["compute_median_s"],
            "loop_compute_p99_s": loop["compute_p99_s"],
            "loop_start_lateness_p99_s": loop["start_lateness_p99_s"],
            "loop_overruns": loop["overruns"],
            "localization_published": feed.published,
        }
    )
    speed_ref = path_errors(scenario.trajectory, x, y, heading, speed).speed_ref
    plot_trace = Trace("mpc, real time", ts, x, y, speed, steer, steer, speed_ref)
    return {"metrics": metrics, "trace": plot_trace, "timeline": timeline}
