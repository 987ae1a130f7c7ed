"""``leafgate run``: the daemon on the in-vehicle computer.

Assembles the parts from one config: the CAN codec (DBCs), the buses, the controller, the
gateway core, the Zenoh transport and the runtime; installs SIGINT/SIGTERM/SIGHUP handlers
first, so that a stop at any moment disengages cleanly (during start-up: exits 0 with nothing
left open); tells systemd when the loop runs. Every start-up problem (bad config, bus
unavailable, DBC missing, Zenoh endpoint refused) raises a :class:`~leafgate.errors.LeafgateError`
with one line naming it, before anything is sent.
"""

from __future__ import annotations

import dataclasses
import functools
import gc
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

import can
import numpy as np

from leafgate.can.bus import discard_queued, open_buses
from leafgate.can.codec import CanCodec
from leafgate.can.profile import Profile
from leafgate.config.transport import ZenohConfig
from leafgate.control import make_controller, plan_rules
from leafgate.control.base import Controller
from leafgate.control.reference import prebuild
from leafgate.gateway.core import Gateway, StepResult
from leafgate.gateway.watchdog import CHECK_ORDER, Check, Status
from leafgate.journal import ERR, NOTICE, WARNING
from leafgate.messages import GatewayState, Pose, Stamped, Trajectory
from leafgate.runtime.loop import InputSource, RequestBox, Runtime
from leafgate.runtime.receiver import CanReceiver
from leafgate.runtime.signals import StopRequest, signals_set
from leafgate.runtime.systemd import sd_notify
from leafgate.settings import LeafgateConfig

log = logging.getLogger(__name__)


def tool_view(cfg: ZenohConfig) -> ZenohConfig:
    """The Zenoh settings a tool (engage, status, sim-ecu …) uses to reach the daemon.

    The daemon listens on ``listen``; a tool started with the same config must not bind the
    same port, so it connects to the daemon's endpoints, as a peer (it waits for a daemon
    that is not up yet), and listens on a port of the system's choosing on the same
    interface: the daemon's gossip tells the tools about each other and they connect directly,
    so every tool receives what any other publishes (rmw_zenoh's topology, with the daemon
    in the router's place).
    """
    if cfg.config_file is not None:
        return cfg
    listen = tuple(
        dict.fromkeys(e.rsplit(":", 1)[0] + ":0" for e in cfg.listen if e.startswith("tcp/"))
    )
    mode = "peer" if cfg.mode == "router" else cfg.mode
    return dataclasses.replace(
        cfg, mode=mode, listen=listen, connect=tuple(cfg.listen) + tuple(cfg.connect)
    )


def same_plan(a: Trajectory, b: Trajectory) -> bool:
    """Whether two trajectories hold the same waypoints (a planner re-publishing its plan)."""
    return len(a) == len(b) and all(
        np.array_equal(getattr(a, f), getattr(b, f)) for f in ("x", "y", "heading", "speed")
    )


class StablePlan:
    """Passes inputs through, but keeps one Trajectory object while the plan is unchanged.

    Planners re-publish their plan (the gateway refuses a stale one); every decoded copy is a
    new object, and a new object tells the controller to restart its search. Identical
    waypoints therefore keep the first object, with the new receive time.
    """

    def __init__(self, source: InputSource) -> None:
        self._source = source
        self._plan: Trajectory | None = None

    def latest_pose(self) -> Stamped[Pose] | None:
        return self._source.latest_pose()

    def latest_trajectory(self) -> Stamped[Trajectory] | None:
        stamped = self._source.latest_trajectory()
        if stamped is None:
            return None
        plan = self._plan
        if plan is not None and stamped.value is not plan and same_plan(stamped.value, plan):
            return Stamped(plan, stamped.received, stamped.valid)
        self._plan = stamped.value
        return stamped


def build_gateway(
    cfg: LeafgateConfig, wrap_controller: Callable[[Controller], Controller] | None = None
) -> Gateway:
    """The pure core with its controller, as the config says.

    :param wrap_controller: e.g. the session recorder's tap on the controller's internals
    """
    controller = make_controller(cfg.controller, cfg.vehicle, cfg.gateway.period)
    if wrap_controller is not None:
        controller = wrap_controller(controller)
    return Gateway(cfg.gateway, cfg.vehicle, controller, cfg.long_mode)


SWITCH_INTERVAL = 0.001  # s, how long a thread may hold the GIL while another waits (default 5 ms)


def prepare_for_real_time() -> None:
    """Keep the interpreter's own pauses out of the control loop's deadlines.

    - Everything built at start-up (codec tables, DBCs, Zenoh and rosbags type stores, the
      controller's matrices) moves to the permanent generation (:func:`gc.freeze`), so a full
      collection in the loop no longer walks it: such a collection took tens of milliseconds
      in the 30-minute soak, longer than a tick.
    - The control thread waits at most ``SWITCH_INTERVAL`` for the GIL when a Zenoh or CAN
      receive thread holds it, instead of the interpreter's default 5 ms.
    """
    gc.collect()
    gc.freeze()
    sys.setswitchinterval(SWITCH_INTERVAL)


def log_profile(profile: Profile) -> None:
    """Say what protects the frames of the chosen vehicle; a warning when nothing does."""
    caps = profile.capabilities
    lacks = [name for name in ("lateral", "longitudinal", "gear") if not getattr(caps, name)]
    if lacks:
        log.info("vehicle profile %s cannot command: %s", profile.name, ", ".join(lacks))
    if profile.protection.upper().startswith("NONE"):
        log.warning("vehicle profile %s: frame protection %s", profile.name, profile.protection)
    else:
        log.info("vehicle profile %s: frame protection: %s", profile.name, profile.protection)


def recording_refusal(cfg: LeafgateConfig, fault: str) -> str | None:
    """Why an engage is refused for want of a recording (``recording.required``), or None."""
    if not cfg.recording.required:
        return None
    if not cfg.recording.enabled:
        return "recording is required (recording.required) but not enabled"
    if fault:
        return f"recording is required but failing: {fault}"
    return None


#: the watchdogs that watch an input (the others watch the error counter and the loop)
INPUT_CHECKS = frozenset(CHECK_ORDER[:5])

#: syslog priority of entering each state (the journal files the line at it)
STATE_PRIORITY = {
    GatewayState.FAULT: ERR,
    GatewayState.STOPPING: WARNING,
    GatewayState.ENGAGED: NOTICE,
    GatewayState.STANDBY: NOTICE,
}


class StateLog:
    """Logs every state transition with its reason, and each input lost and regained.

    Called on the control thread after every tick; it only compares a few enums per tick and
    logs (through the queued handler) when something changed.

    - ``state STANDBY → ENGAGED: operator engage`` at notice, → STOPPING at warning, → FAULT at
      err; JSON lines carry ``event``, ``from``, ``to``, ``reason``.
    - ``input localization lost: …`` (warning) when a watchdog leaves OK, ``input localization
      back after 0.62 s`` (notice) when it returns; a first sample is ``… received`` (info).
    """

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self._log = logger or log
        self._status: dict[str, Status] = {}
        self._since: dict[str, float] = {}  # last good sample of each watchdog not OK

    def on_tick(
        self, now: float, _inputs: Any, result: StepResult, _frames: Sequence[can.Message]
    ) -> None:
        diagnostics = result.diagnostics
        for tr in diagnostics.transitions:
            self._log.log(
                logging.ERROR if tr.target == GatewayState.FAULT else logging.INFO,
                "state %s → %s: %s",
                tr.source.name,
                tr.target.name,
                tr.reason,
                extra={
                    "priority": STATE_PRIORITY.get(tr.target, NOTICE),
                    "fields": {"event": "transition", **tr.to_dict()},
                },
            )
        for check in diagnostics.watchdogs:
            previous = self._status.get(check.name)
            if previous is check.status:
                continue
            self._status[check.name] = check.status
            self._input_changed(now, check, previous)

    def _input_changed(self, now: float, check: Check, previous: Status | None) -> None:
        name, status, detail = check.name, check.status, check.detail
        kind = "input" if name in INPUT_CHECKS else "watchdog"
        fields = {"event": kind, kind: name, "status": status.value}
        if status is Status.OK:
            if previous in (None, Status.MISSING, Status.INVALID):
                if kind == "input":
                    self._log.info("input %s received", name, extra={"fields": fields})
                return
            away = now - self._since.pop(name, now)
            self._log.info(
                "%s %s back after %.2f s",
                kind,
                name,
                away,
                extra={"priority": NOTICE, "fields": {**fields, "away_s": away}},
            )
            return
        if previous is None and status is Status.MISSING:
            return  # nothing yet at start: not a loss
        # from the last good sample: the watchdog notices only once its age passed the limit
        self._since.setdefault(name, now - (check.age or 0.0))
        verb = "lost" if kind == "input" and previous is Status.OK else status.value
        self._log.warning(
            "%s %s %s: %s", kind, name, verb, detail or status.value, extra={"fields": fields}
        )


class VehicleView:
    """What ``leafgate status`` shows of the car: speed, road-wheel angle, progress on the plan.

    Updated on the control thread at most every ``period`` s; read by the diagnostics
    publisher (one dict replaced whole, so a reader never sees half of one).
    """

    def __init__(self, period: float = 0.1) -> None:
        self.period = period
        self.latest: dict[str, Any] = {}
        self._next = -float("inf")

    def on_tick(
        self, now: float, inputs: Any, result: StepResult, _frames: Sequence[can.Message]
    ) -> None:
        if now < self._next:
            return
        self._next = now + self.period
        long, steer, plan = inputs.long_report, inputs.steer_report, inputs.trajectory
        figures = result.diagnostics.controller
        waypoints = len(plan.value) if plan is not None else 0
        index = figures.nearest_index if figures is not None else None
        self.latest = {
            "speed": None if long is None else long.value.speed,  # m/s
            "steer_angle": None if steer is None else steer.value.angle,  # rad, road wheel
            "plan_waypoints": waypoints,
            "plan_index": index,
            "plan_progress": index / (waypoints - 1)
            if index is not None and waypoints > 1
            else None,
        }


class SystemdWatchdog:
    """Sends ``WATCHDOG=1`` from the control loop at half of systemd's ``WatchdogSec``.

    Kicked after every tick: a loop that stops ticking stops the kicks, and systemd restarts
    the daemon. Silent until :meth:`start` (called right after ``READY=1``): the first tick's
    kick comes before the ready call, and a ping before ``READY=1`` tells systemd the service
    is alive before it has said it is up. Outside systemd (no ``WATCHDOG_USEC``, or for another
    process) it does nothing.
    """

    def __init__(self, interval: float | None) -> None:
        self.interval = interval  # s between notifications; None: off
        self._last = -float("inf")
        self._started = False
        self.sent = 0

    @classmethod
    def from_environment(cls) -> SystemdWatchdog:
        usec = os.environ.get("WATCHDOG_USEC", "")
        pid = os.environ.get("WATCHDOG_PID", "")
        if not usec.isdigit() or int(usec) <= 0 or (pid and pid != str(os.getpid())):
            return cls(None)
        return cls(int(usec) * 1e-6 / 2.0)

    def start(self, now: float) -> None:
        """READY=1 has gone out: kick from now on (this first kick at once)."""
        self._started = True
        self.kick(now)

    def kick(self, now: float) -> None:
        if self.interval is None or not self._started or now - self._last < self.interval:
            return
        self._last = now
        if sd_notify("WATCHDOG=1"):
            self.sent += 1


def set_rt_priority(priority: int) -> bool:
    """Put the calling thread (only it: Linux schedules threads) under SCHED_FIFO ``priority``.

    0 leaves scheduling alone. A refusal (no ``LimitRTPRIO``/CAP_SYS_NICE) is logged as a
    warning and the loop runs at normal priority.

    :returns: True when the thread now runs at ``priority``
    """
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) else "not supported here"
        log.warning(
            "control thread stays at normal priority: SCHED_FIFO %d refused (%s)",
            priority,
            reason,
        )
        return False
    log.info("control thread runs under SCHED_FIFO priority %d", priority)
    return True


def run_daemon(
    cfg: LeafgateConfig,
    stop: threading.Event | None = None,
    *,
    on_runtime: Callable[[Runtime], None] | None = None,
    session: Any = None,
) -> int:
    """Run the gateway until ``stop`` is set or a signal arrives; return the exit status.

    :param on_runtime: called with the runtime once it exists (tests, recording)
    :param session: an open Zenoh session to declare the gateway on (the in-process
        simulation shares one); None opens one from ``cfg.zenoh``
    :raises LeafgateError: on any start-up problem (one line, nothing sent yet)
    """
    stop = stop or threading.Event()
    # The handlers first: a stop request during start-up ends it cleanly (exit 0, every part
    # opened so far closed) instead of the default action's kill (status 143, or 129).
    with signals_set(stop) as stopping:
        return _run_daemon(cfg, stop, stopping, on_runtime, session)


def _stopped_starting(stop: threading.Event, before: str) -> bool:
    """Whether a stop came during start-up; logs that the daemon ends before ``before``."""
    if stop.is_set():
        log.info("stop requested during start-up: exiting before %s", before)
    return stop.is_set()


def _run_daemon(
    cfg: LeafgateConfig,
    stop: threading.Event,
    stopping: StopRequest,
    on_runtime: Callable[[Runtime], None] | None,
    session: Any,
) -> int:
    """The body of :func:`run_daemon`, under its signal handlers."""
    clock = time.perf_counter
    codec = CanCodec.for_config(cfg)  # CanCodecError: a DBC missing/invalid
    for line in codec.dbc_warnings():  # frames not to be trusted (overlaps, hidden)
        log.warning("%s", line)
    # what `leafgate check-config` checks offline, checked the same way before anything opens
    from leafgate.runtime.checks import offline_checks

    for line in offline_checks(cfg, zenoh=session is None).warnings:
        log.warning("%s", line)
    requests = RequestBox()
    from leafgate.record.recorder import open_recording
    from leafgate.runtime.node import GatewayTransport  # zenoh loads only where it is used
    from leafgate.transport.session import CONNECT_WAIT, unanswered_connect

    if _stopped_starting(stop, "opening the buses"):
        return 0
    with ExitStack() as stack:
        buses = stack.enter_context(
            open_buses(cfg.can, codec.receive_ids("reports"), codec.receive_ids("car"))
        )
        if _stopped_starting(stop, "opening Zenoh"):
            return 0
        if session is None:
            transport = GatewayTransport.open(cfg.zenoh, requests.submit, clock=clock)
        else:
            transport = GatewayTransport(session, cfg.zenoh, requests.submit, clock=clock)
        stack.enter_context(transport)
        if session is None and (unanswered := unanswered_connect(transport.session, cfg.zenoh)):
            log.warning(
                "zenoh: no answer from %s within %.0f s: no localization or plan until one "
                "answers (Zenoh goes on trying); is the router (rmw_zenohd, the bridge) running?",
                ", ".join(unanswered),
                CONNECT_WAIT,
            )
        if _stopped_starting(stop, "opening the recording"):
            return 0
        # Opened only now that the bus and Zenoh are up: a start that fails on either leaves
        # no empty recording behind (with Restart=on-failure they would pile up).
        # Recording never stops the loop: a file problem becomes a fault in diagnostics.
        recording = open_recording(cfg.recording, cfg, clock=clock)
        stack.callback(recording.close)
        gateway = build_gateway(cfg, wrap_controller=recording.wrap_controller)
        transport.on_raw = recording.on_zenoh_input
        # a new plan's reference is built on Zenoh's thread as it arrives, not in a tick
        rules = plan_rules(cfg.controller, cfg.vehicle)  # as the controller builds them
        transport.on_plan = functools.partial(prebuild, rules=rules)
        receiver = CanReceiver(codec, clock)
        receiver.on_frame = lambda msg, _decoded: recording.on_can_frame(msg, "rx")
        receive_buses = [buses.dbw] if buses.shared else [buses.dbw, buses.car]
        # what queued while Zenoh and the recording opened: stale, and cut by the queue's drops
        queued_at_start = sum(discard_queued(bus) for bus in receive_buses)
        if queued_at_start:
            log.info("discarded %d CAN frames queued during start-up", queued_at_start)
        notifier = can.Notifier(receive_buses, [receiver], timeout=0.1)
        stack.callback(notifier.stop)
        state_log = StateLog()
        vehicle = VehicleView()
        watchdog = SystemdWatchdog.from_environment()

        def on_tick(
            now: float, inputs: Any, result: StepResult, frames: Sequence[can.Message]
        ) -> None:
            recording.on_tick(now, inputs, result, frames)
            state_log.on_tick(now, inputs, result, frames)
            vehicle.on_tick(now, inputs, result, frames)
            watchdog.kick(now)

        runtime = Runtime(
            gateway,
            codec,
            buses.dbw,
            receiver,
            StablePlan(transport),
            cfg.gateway.period,
            publisher=transport,
            requests=requests,
            clock=clock,
            on_tick=on_tick,
            # on the control thread, after the state check: FAULT's reason comes first
            engage_veto=lambda: recording_refusal(cfg, recording.fault),
            receive_buses=receive_buses,
            extra_diagnostics=lambda: {
                "zenoh_decode_errors": transport.decode_errors,
                "zenoh_last_errors": transport.last_errors,
                "engage_refused_unheard": transport.request_refusals,
                "zenoh_invalid_samples": transport.invalid_samples,
                "zenoh_input_sources": transport.input_sources,
                # counter skips after a receive stall: lost frames, not report errors
                "can_stall_skips": receiver.stall_skips,
                "can_discarded_at_start": queued_at_start,
                "recording": recording.diagnostics(),
                "vehicle": vehicle.latest,
            },
        )
        if on_runtime is not None:
            on_runtime(runtime)
        log.info(
            "leafgate running at %.0f Hz: vehicle profile %s, dbw %s:%s, zenoh prefix %r",
            cfg.gateway.rate_hz,
            codec.profile.name,
            cfg.can.dbw.interface,
            cfg.can.dbw.channel,
            cfg.zenoh.prefix,
        )
        log_profile(codec.profile)
        for line in cfg.adjustments:  # what the profile changed in the configuration
            log.info("config adjusted: %s", line)

        def ready() -> None:  # on the control thread, after its first tick
            set_rt_priority(cfg.gateway.rt_priority)
            sd_notify("READY=1")
            watchdog.start(clock())  # WATCHDOG=1 only after READY=1
            log.info("control loop running")

        prepare_for_real_time()
        runtime.run(stop, on_ready=ready, stop_reason=lambda: stopping.reason)
        sd_notify("STOPPING=1")
        summary = runtime.stats.summary()
        log.info(
            "stopped after %d ticks: %d overruns, compute median %.0f µs p99 %.0f µs",
            summary["ticks"],
            summary["overruns"],
            summary["compute_median_s"] * 1e6,
            summary["compute_p99_s"] * 1e6,
        )
    return 0
