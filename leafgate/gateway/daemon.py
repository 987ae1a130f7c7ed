"""``leafgate run``: the daemon on the in-vehicle computer.

Assembles the parts from one config: the CAN codec (DBCs), the buses, the controller, the
gateway core, the Zenoh transport and the runtime; installs SIGINT/SIGTERM handlers that
disengage cleanly; tells systemd when the loop runs. Every start-up problem (bad config, bus
unavailable, DBC missing, Zenoh endpoint refused) raises a :class:`~leafgate.errors.LeafgateError`
with one line naming it, before anything is sent.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import can
import numpy as np

from leafgate.can.bus import open_buses
from leafgate.can.codec import CanCodec
from leafgate.can.profile import Profile
from leafgate.control import make_controller
from leafgate.control.base import Controller
from leafgate.gateway.core import Gateway
from leafgate.gateway.runtime import CanReceiver, InputSource, RequestBox, Runtime, sd_notify
from leafgate.messages import OperatorRequest, Pose, Stamped, Trajectory
from leafgate.settings import LeafgateConfig
from leafgate.transport.config import ZenohConfig

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


@contextmanager
def signals_set(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: Any) -> None:
        log.info("%s received: disengaging and shutting down", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


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
    clock = time.perf_counter
    codec = CanCodec.for_config(cfg)  # CanCodecError: a DBC missing/invalid
    requests = RequestBox()
    from leafgate.replay.recorder import open_recording
    from leafgate.transport.node import GatewayTransport  # zenoh loads only where it is used

    with ExitStack() as stack:
        # Recording never stops the loop: a file problem becomes a fault in diagnostics.
        recording = open_recording(cfg.recording, cfg, clock=clock)
        stack.callback(recording.close)
        gateway = build_gateway(cfg, wrap_controller=recording.wrap_controller)
        buses = stack.enter_context(
            open_buses(cfg.can, codec.receive_ids("reports"), codec.receive_ids("car"))
        )

        def answer(request: OperatorRequest) -> dict[str, Any]:
            if request is OperatorRequest.ENGAGE:
                refusal = recording_refusal(cfg, recording.fault)
                if refusal is not None:
                    return {
                        "accepted": False,
                        "state": runtime.gateway.state.name,
                        "reason": refusal,
                    }
            return requests.submit(request)

        if session is None:
            transport = GatewayTransport.open(cfg.zenoh, answer, clock=clock)
        else:
            transport = GatewayTransport(session, cfg.zenoh, answer, clock=clock)
        stack.enter_context(transport)
        transport.on_raw = recording.on_zenoh_input
        receiver = CanReceiver(codec, clock)
        receiver.on_frame = lambda msg, _decoded: recording.on_can_frame(msg, "rx")
        notifier = can.Notifier(
            [buses.dbw] if buses.shared else [buses.dbw, buses.car], [receiver], timeout=0.1
        )
        stack.callback(notifier.stop)
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
            on_tick=recording.on_tick,
            receive_buses=[buses.dbw] if buses.shared else [buses.dbw, buses.car],
            extra_diagnostics=lambda: {
                "zenoh_decode_errors": transport.decode_errors,
                "zenoh_last_errors": transport.last_errors,
                "engage_refused_unheard": transport.request_refusals,
                "zenoh_invalid_samples": transport.invalid_samples,
                "recording": recording.diagnostics(),
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

        def ready() -> None:
            sd_notify("READY=1")
            log.info("control loop running")

        prepare_for_real_time()
        with signals_set(stop):
            runtime.run(stop, on_ready=ready)
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
