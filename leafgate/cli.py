"""The ``leafgate`` command and its subcommands.

Errors a user can cause (bad config, missing file, unknown scenario) end with one readable line
on stderr and a non-zero exit status, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import json
import logging
import math
import os
import re
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

if __name__ == "__main__":  # python -m leafgate.cli: hold the stop signals before the imports
    from leafgate.runtime.hold import hold

    hold()

try:  # Ctrl-C while Python loads leafgate (seconds on a busy machine): one line, as later
    from leafgate import __version__
    from leafgate.cliargs import (
        add_overrides,
        add_profile_options,
        non_negative_int,
        non_negative_number,
        non_negative_seconds,
        positive_number,
        positive_seconds,
        whole_number_between,
    )
    from leafgate.config import parse_overrides
    from leafgate.errors import ConfigError, LeafgateError, UsageError
    from leafgate.journal import setup_logging
    from leafgate.settings import MAX_BENCH, LeafgateConfig, load_config, with_profile
    from leafgate.sim.scenarios import Scenario
except KeyboardInterrupt:
    print("leafgate: interrupted", file=sys.stderr)
    raise SystemExit(130) from None

log = logging.getLogger("leafgate")

EXIT_ERROR = 1
#: the commands that stop in a controlled way on SIGINT, SIGTERM and SIGHUP (runtime.signals)
STOP_SIGNAL_COMMANDS = frozenset({"run", "sim-ecu", "publish-trajectory"})
#: the operator tools: the first Ctrl-C ends them through KeyboardInterrupt, closing their Zenoh
#: session on the way out; a second one exits at once (runtime.hold.interrupt_once)
INTERRUPT_ONCE_COMMANDS = frozenset({"status", "engage", "disengage", "reset"})
EXIT_USAGE = 2
ENGAGE_WAIT = 15.0  # s, how long `engage` waits for a starting gateway's inputs by default


def _load(path: str | None, flags: dict[str, Any], sets: Sequence[str] = ()) -> LeafgateConfig:
    """The config file with ``--set KEY=VALUE`` overrides, then the explicit flags on top."""
    overrides = parse_overrides(sets)
    overrides.update({k: v for k, v in flags.items() if v is not None})
    return load_config(path, overrides)


# --- sim ----------------------------------------------------------------------------------------

METRIC_ORDER = (
    ("lateral_error_max_m", "lateral error max [m]", "{:.4f}"),
    ("lateral_error_rms_m", "lateral error RMS [m]", "{:.4f}"),
    ("heading_error_max_rad", "heading error max [rad]", "{:.4f}"),
    ("final_position_error_m", "final position error [m]", "{:.4f}"),
    ("speed_error_rms_mps", "speed error RMS [m/s]", "{:.4f}"),
    ("steer_rate_max_radps", "steering rate max [rad/s]", "{:.4f}"),
    ("steer_rate_sign_changes", "steering rate sign changes", "{}"),
    ("solve_time_median_s", "solve time median [µs]", "µs"),
    ("solve_time_p99_s", "solve time p99 [µs]", "µs"),
    ("solver_not_converged", "solver not converged", "{}"),
    ("input_clips", "input clips", "{}"),
    ("start_progress_m", "start along the route [m]", "{:.2f}"),
    ("progress_m", "progress from the start [m]", "{:.2f}"),
    ("route_length_m", "route length [m]", "{:.2f}"),
    ("duration_s", "simulated duration [s]", "{:.2f}"),
    ("wall_time_s", "wall time [s]", "{:.3f}"),
)


def format_metrics(metrics: dict[str, Any]) -> str:
    lines = []
    for key, label, fmt in METRIC_ORDER:
        if key not in metrics:
            continue
        value = metrics[key]
        text = f"{value * 1e6:.0f}" if fmt == "µs" else fmt.format(value)
        lines.append(f"  {label:<32} {text:>10}")
    for key, value in metrics.items():
        if key not in {k for k, _, _ in METRIC_ORDER} and isinstance(value, (int, float, str)):
            lines.append(f"  {key:<32} {value!s:>10}")
    return "\n".join(lines)


def _run_recorded(
    cfg: LeafgateConfig, scenario: Scenario, injections: Any, directory: Path, window: Any
) -> tuple[Any, bool]:
    """Run the simulated loop while recording it as the daemon would (CAN log + session).

    :returns: the drive's result, and whether every recording file was written whole (a file
        given up after a write error, e.g. disk full, is said so and not called recorded)
    """
    from leafgate.record.recorder import open_recording
    from leafgate.sim.runner import run

    rec_cfg = dataclasses.replace(cfg.recording, enabled=True, directory=str(directory))
    # Simulated time everywhere: frames keep the simulator's timestamps (no wall clock).
    recording = open_recording(rec_cfg, cfg, clock=None, wall_clock=None)
    try:
        result = run(
            cfg,
            scenario,
            injections=injections,
            recorder=recording,
            window=window,
            epoch=recording.epoch,  # the recording's clock: freshness values of MACs match it
        )
    finally:
        recording.close()
    whole = True
    for recorder in recording.recorders:
        info = recorder.diagnostics()
        files = info.get("files", [info.get("file")])
        if not info["fault"]:
            for path in files:
                print(f"recorded {path}")
            continue
        whole = False
        written = [path for path in files if path and Path(path).exists()]
        print(
            f"leafgate: error: recording failed: {info['fault']}; "
            + (f"incomplete: {', '.join(written)}" if written else "nothing recorded"),
            file=sys.stderr,
        )
    return result, whole


TRAJECTORY_FORMAT = """\
trajectory files (--trajectory, publish-trajectory):
  CSV with the header x,y,heading,speed, one waypoint per line; or YAML, either a list of
  {x, y, heading, speed} mappings or a mapping of those four keys to lists of equal length.
  x, y: m, rear-axle centre; heading: rad, the vehicle's heading (also when reversing);
  speed: m/s, signed (negative = reverse; where the sign changes is a cusp, speed 0 there).
  Required: at least 4 waypoints once a point closer than 1 cm to the one before is dropped,
  speeds above 0 up to each cusp and the last waypoint (at a 0 before them the car would
  stop and wait for another plan), none above the safety gate's limit. Any spacing drives:
  the controller follows a curve through the waypoints; a planner sends them 0.5-1.0 m
  apart, and sim warns where they are so far apart in a turn that its lateral error,
  measured from the straight chords between them, is coarse. The last waypoint is the goal:
  the car stops on it whatever its speed (a planner gives it 0). Example CSV:
    x,y,heading,speed
    0.0,0.0,0.0,0.3
    0.5,0.0,0.0,0.6
    1.0,0.0,0.0,0.6
    1.5,0.0,0.0,0.0
"""


def _realtime_verdict(cfg: LeafgateConfig, metrics: dict[str, Any]) -> tuple[bool, str]:
    """Whether ``sim --realtime`` finished the route, and why not (with the simulator's own
    lateness when that explains a report fault).

    The gateway claims the end only by its reason: a controlled stop (stale localization, no
    progress) ends in STANDBY too, and was reported as "the gateway reported the end reached,
    but the car got 5.9 of 32.3 m", without the reason or the load hint.
    """
    from leafgate.gateway.core import END_REACHED
    from leafgate.sim.runner import finish_verdict

    final = metrics["final_state"]
    claimed = final == "STANDBY" and metrics["final_reason"] == END_REACHED
    finished, reason = finish_verdict(
        metrics, claimed, f"the gateway ended in {final}: {metrics['final_reason']}"
    )
    return finished, (reason + _realtime_starved(cfg, metrics)) if reason else ""


def _realtime_starved(cfg: LeafgateConfig, metrics: dict[str, Any]) -> str:
    """Why an ECU report was late in ``sim --realtime``, when the simulator itself was late.

    The simulated ECU shares this machine with the gateway; on a loaded one its loop wakes late
    and its reports reach the gateway late, which the report watchdog takes, as it must, for a
    late ECU. Said, with the figure, so the fault is not read as the gateway's.
    """
    watchdog = cfg.gateway.watchdog
    # s: later than this, the ECU missed a slot of its fastest report
    slot = min(watchdog.steer_report_period, watchdog.long_report_period)
    late = metrics.get("ecu_loop_max_lateness_s")
    if not (isinstance(late, float) and late > slot) or "report" not in metrics["final_reason"]:
        return ""
    periods = watchdog.report_timeout_periods
    return (
        f"; the simulated ECU's own loop woke up to {late * 1000:.0f} ms late on this machine "
        f"(load), so its reports were late: the gateway keeps the car's timeout "
        f"(gateway.watchdog.report_timeout_periods {periods:g}); on a loaded machine try "
        "--set gateway.watchdog.report_timeout_periods=10"
    )


def _warn_coarse_chords(scenario: Scenario) -> None:
    """Say when the plan's waypoints are too far apart for the lateral error to mean much."""
    from leafgate.control.reference import CHORD_SAGITTA_WARN, chord_sagitta

    traj = scenario.trajectory
    cut, i, gap = chord_sagitta(traj)
    if cut > CHORD_SAGITTA_WARN:
        print(
            f"leafgate: warning: {scenario.name}: waypoints {gap:.2f} m apart in a turn at "
            f"({traj.x[i]:.1f}, {traj.y[i]:.1f}) m: the car follows a curve through them, "
            f"the lateral error is measured from the straight chords, which cut it by up to "
            f"{cut * 100:.1f} cm (a planner sends 0.5-1.0 m)",
            file=sys.stderr,
        )


def cmd_sim(args: argparse.Namespace) -> int:
    from leafgate.control import plan_rules
    from leafgate.sim.metrics import collision
    from leafgate.sim.plots import plot_drive
    from leafgate.sim.runner import Injection, run, run_direct

    flags = {
        "controller.mpc.solver": args.solver,
        "controller.mpc.mode": args.mode,
        "sim.plant.kind": args.plant,
        # the seeded disturbances' random processes (a batch case's --seed)
        "sim.localization.seed": args.seed,
    }
    if args.controller:  # the names `compare` uses: mpc-steer is the MPC with the lag model
        from leafgate.sim.compare import CONTROLLERS

        flags["controller.kind"], flags["controller.mpc.model"] = CONTROLLERS[args.controller]
    cfg = _load(args.config, flags, args.set)
    if args.profile:
        cfg = with_profile(cfg, args.profile)
    # the steering-aware model where the wheel lags, unless the model was chosen
    if not args.controller and not _model_given(args.config, args.set):
        from leafgate.sim.runner import default_model

        mpc = dataclasses.replace(cfg.controller.mpc, model=default_model(cfg.sim.plant.kind))
        cfg = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, mpc=mpc))
    if args.trajectory and args.scenario:
        raise UsageError("sim: give --scenario NAME or --trajectory FILE, not both")
    if args.start and not args.trajectory:
        raise UsageError("sim: --start goes with --trajectory (a scenario has its own start)")
    if args.trajectory:
        from leafgate.sim.scenarios import file_scenario

        scenario = file_scenario(
            args.trajectory,
            _start_pose(args.start),
            max_speed=cfg.gateway.safety.max_speed,
            max_points=cfg.zenoh.max_plan_points,
        )
        _warn_coarse_chords(scenario)
    else:
        scenario = _scenario(args.scenario or cfg.sim.scenario)
    injections = tuple(Injection.parse(text) for text in args.inject)
    window = None
    if args.rolling_window is None and (args.window_behind or args.window_resample):
        raise UsageError("--window-behind and --window-resample need --rolling-window")
    if args.rolling_window is not None:
        from leafgate.sim.runner import RollingWindow

        window = RollingWindow(
            args.rolling_window, args.window_period, args.window_behind, args.window_resample
        )
    if (injections or args.record or window) and (args.direct or args.realtime):
        raise UsageError(
            "--inject, --record and --rolling-window need the full simulated loop "
            "(not --direct or --realtime)"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    recorded = True  # every --record file written whole (nothing to say without --record)
    if args.record or args.realtime:
        cfg = _sim_key_file(cfg, Path(args.record) if args.record else out)
    if args.realtime:
        from leafgate.progress import Progress
        from leafgate.sim.realtime import run_realtime

        with Progress(f"sim --realtime {scenario.name}", scenario.duration, "s") as shown:
            outcome = run_realtime(cfg, scenario, lambda t, state: shown.update(round(t), state))
        metrics, trace, timeline = outcome["metrics"], outcome["trace"], outcome["timeline"]
        metrics["finished"], reason = _realtime_verdict(cfg, metrics)
        if reason:
            metrics["not_finished_reason"] = reason
        loop = "real time (daemon runtime, in-process Zenoh, virtual CAN)"
    else:
        if args.direct:
            result = run_direct(cfg, scenario)
        elif args.record:
            result, recorded = _run_recorded(cfg, scenario, injections, Path(args.record), window)
        else:
            result = run(cfg, scenario, injections=injections, window=window)
        result.write_trace_csv(out / "trace.csv")
        metrics, trace, timeline = dict(result.metrics), result.trace, list(result.timeline)
        loop = (
            "direct (controller → plant)"
            if args.direct
            else "simulated clock through CAN, ECU and gateway"
        )
    for t, event in timeline:
        print(f"  t={t:7.2f} s  {event}")
    print(
        f"scenario {scenario.name}: controller {cfg.controller.kind}, "
        f"model {cfg.controller.mpc.model}, solver {cfg.controller.mpc.solver}, "
        f"mode {cfg.controller.mpc.mode}, "
        f"plant {cfg.sim.plant.kind}; {loop}"
    )
    print(format_metrics(metrics))
    metrics.update(
        {
            "scenario": scenario.name,
            "controller": cfg.controller.kind,
            "model": cfg.controller.mpc.model,
            "solver": cfg.controller.mpc.solver,
            "mode": cfg.controller.mpc.mode,
            "plant": cfg.sim.plant.kind,
            "loop": loop,
            "injections": list(args.inject),
            "timeline": [{"t": t, "event": e} for t, e in timeline],
        }
    )
    from leafgate.jsonconv import to_json  # one JSON convention: NaN as null, enums by name

    text = json.dumps(to_json(metrics), indent=2, allow_nan=False)
    (out / "metrics.json").write_text(text + "\n", encoding="utf-8")
    if not args.no_plots:
        from leafgate.sim.scenarios import OBSTACLES

        obstacles = OBSTACLES.get(scenario.name, ())
        plot_drive(
            out, scenario.trajectory, [trace], title=f"— {scenario.name}", obstacles=obstacles
        )
    print(
        f"wrote {out / 'metrics.json'}"
        + ("" if args.realtime else ", trace.csv")
        + ("" if args.no_plots else ", path.png, steering.png, speed.png")
    )
    finished = bool(metrics.get("finished"))
    if not finished:  # an injected fault too: the drive did not finish
        reason = metrics.get("not_finished_reason") or "the maneuver did not finish"
        print(f"leafgate: {scenario.name}: not finished: {reason}", file=sys.stderr)
    # the turn the controller slows for (its steer_max on this wheelbase)
    car = plan_rules(cfg.controller, cfg.vehicle).min_turn_radius
    section = cfg.controller.section_name
    plan = metrics["plan_min_turn_radius_m"]
    if plan < car:  # said whenever the plan itself cannot be driven as sent, finished or not
        x, y = metrics["plan_min_turn_radius_at"]
        off = (
            f"; the car was up to {metrics['lateral_error_max_m']:.2f} m off it" if finished else ""
        )
        print(
            f"leafgate: {scenario.name}: the plan turns tighter than the car can: "
            f"radius {plan:.2f} m at ({x:.1f}, {y:.1f}) m, the car's tightest "
            f"{car:.2f} m (vehicle.wheelbase, controller.{section}.steer_max){off}",
            file=sys.stderr,
        )
    if not finished:
        return EXIT_ERROR
    hit = collision(metrics)
    if hit is not None:  # the route was driven, through a parked car or over the kerb
        print(f"leafgate: {scenario.name}: collision: {hit}", file=sys.stderr)
        return EXIT_ERROR
    if not recorded:  # the drive finished, but --record's files are not whole
        print(
            f"leafgate: error: {scenario.name}: the drive finished, but --record "
            f"{args.record} failed (above)",
            file=sys.stderr,
        )
        return EXIT_ERROR
    return 0


def _model_given(path: str | None, sets: Sequence[str]) -> bool:
    """Whether the config file or a ``--set`` chooses ``controller.mpc.model``."""
    if "controller.mpc.model" in parse_overrides(sets):
        return True
    if path is None:
        return False
    from leafgate.config import load_yaml

    node: Any = load_yaml(path)
    for key in ("controller", "mpc", "model"):
        if not isinstance(node, dict) or key not in node:
            return False
        node = node[key]
    return True


def _start_pose(text: str | None) -> Any:
    """``X,Y,HEADING_DEG`` → a pose at rest (SI), or None."""
    if not text:
        return None
    from math import isfinite, radians

    from leafgate.messages import Pose

    parts = text.split(",")
    try:
        x, y, heading_deg = (float(p) for p in parts)
    except ValueError:
        raise UsageError(
            f"--start {text!r}: expected X,Y,HEADING_DEG (m, m, degrees), e.g. 0,0,90"
        ) from None
    if not all(isfinite(v) for v in (x, y, heading_deg)):
        raise UsageError(f"--start {text!r}: values must be finite")
    return Pose(x=x, y=y, heading=radians(heading_deg), speed=0.0)


# --- the daemon and its tools ------------------------------------------------------------------


def _scenario(name: str) -> Scenario:
    from leafgate.sim.scenarios import get_scenario

    try:
        return get_scenario(name)
    except KeyError as exc:
        raise ConfigError(str(exc.args[0])) from None


def cmd_run(args: argparse.Namespace) -> int:
    from leafgate.runtime.daemon import run_daemon

    return run_daemon(load_config(args.config))


def cmd_sim_ecu(args: argparse.Namespace) -> int:
    import threading

    from leafgate.sim.realtime import EngagedInjection, run_sim_ecu

    injections = [EngagedInjection.parse(text) for text in args.inject]
    cfg = _load(args.config, {"sim.plant.kind": args.plant})
    return run_sim_ecu(
        cfg,
        _scenario(args.scenario or cfg.sim.scenario),
        threading.Event(),
        args.trace,
        injections,
    )


EXIT_UNCHANGED = 3  # an operator request found nothing to do (already in the requested state)


def cmd_request(args: argparse.Namespace) -> int:
    """engage / disengage / reset: print the reply; exit 0 only when it was carried out."""
    from leafgate.runtime.daemon import tool_view
    from leafgate.transport.client import engage, request

    cfg = load_config(args.config)
    zcfg = tool_view(cfg.zenoh)
    wait = getattr(args, "wait", 0.0)
    if args.command == "engage" and wait > 0:

        def waiting(reason: str) -> None:
            print(f"leafgate: waiting (up to {wait:g} s): {reason}", file=sys.stderr, flush=True)

        reply = engage(zcfg, max(wait, args.timeout or 0.0), on_waiting=waiting)
    else:
        reply = request(zcfg, args.command, timeout=args.timeout)
    print(json.dumps(reply))
    for field, what in (
        ("ignored_replies", "replies from sessions that are not the gateway were ignored"),
        ("conflicting_replies", "more than one session claims to be the gateway"),
    ):
        if reply.get(field):
            print(f"leafgate: warning: {len(reply[field])} {what}", file=sys.stderr)
    if reply.get("accepted") and "conflicting_replies" not in reply:
        return 0
    return EXIT_UNCHANGED if reply.get("already") else EXIT_ERROR


def vehicle_text(vehicle: Any) -> str:
    """``1.23 m/s, wheel -2.1°, plan 42 % (120/285)``; ``?`` for what the gateway lacks."""
    if not isinstance(vehicle, dict):
        vehicle = {}
    speed, angle = vehicle.get("speed"), vehicle.get("steer_angle")
    progress, index = vehicle.get("plan_progress"), vehicle.get("plan_index")
    waypoints = vehicle.get("plan_waypoints")
    speed_text = f"{speed:5.2f} m/s" if isinstance(speed, (int, float)) else "  ? m/s"
    angle_deg = math.degrees(angle) if isinstance(angle, (int, float)) else None
    angle_text = f"wheel {angle_deg:+5.1f}°" if angle_deg is not None else "wheel ?"
    if isinstance(progress, (int, float)):
        plan_text = f"plan {progress * 100:3.0f} % ({index}/{waypoints})"
    elif waypoints:
        plan_text = f"plan of {waypoints} points"
    else:
        plan_text = "no plan"
    return f"{speed_text}, {angle_text}, {plan_text}"


def cmd_status(args: argparse.Namespace) -> int:
    from leafgate.runtime.daemon import tool_view
    from leafgate.transport.client import DiagnosticsWatch, watch_diagnostics

    cfg = load_config(args.config)
    seen: list[dict[str, Any]] = []

    closed: list[BrokenPipeError] = []
    watch = DiagnosticsWatch()

    def show(diag: dict[str, Any]) -> None:
        # On a Zenoh thread: a closed stdout is noted here and raised in the main thread, which
        # stops watching at once (it watched on for the whole --duration after `| head -1`).
        if closed:
            return
        try:
            _show(diag)
        except BrokenPipeError as exc:
            closed.append(exc)
            watch.done.set()

    def _show(diag: dict[str, Any]) -> None:
        seen.append(diag)
        if args.json:
            print(json.dumps(diag), flush=True)
            return
        loop = diag.get("loop", {})
        parts = []
        for name, wd in (diag.get("watchdogs") or {}).items():
            if not isinstance(wd, dict):
                continue
            age = wd.get("age")
            shown = f"{age * 1e3:.0f} ms" if isinstance(age, (int, float)) else str(wd.get("value"))
            flag = "" if wd.get("status") == "ok" else f" [{wd.get('status')}]"
            parts.append(f"{name} {shown}{flag}")
        compute = loop.get("compute_median_s")
        compute_text = f"{compute * 1e6:.0f} µs" if isinstance(compute, (int, float)) else "?"
        print(
            f"{diag.get('state', '?'):<9} {diag.get('reason', '')!s:<32} "
            f"{vehicle_text(diag.get('vehicle'))} | "
            f"loop {compute_text} median, {loop.get('overruns', 0)} overruns | {', '.join(parts)}",
            flush=True,
        )

    watch_diagnostics(tool_view(cfg.zenoh), show, args.duration, watch=watch)
    if closed:
        raise closed[0]
    foreign = watch.foreign()
    if foreign:  # someone else publishes on the gateway's key: shown, never believed
        named = ", ".join(f"{who} ({n})" for who, n in sorted(foreign.items()))
        print(
            f"leafgate: warning: ignored {sum(foreign.values())} diagnostics record(s) from "
            f"publishers without the gateway's liveliness token: {named}",
            file=sys.stderr,
        )
    if len(watch.gateways) > 1:
        print(
            f"leafgate: error: diagnostics from {len(watch.gateways)} sessions holding the "
            f"gateway's liveliness token (conflicting): {', '.join(sorted(watch.gateways))}",
            file=sys.stderr,
        )
        return EXIT_ERROR
    if not seen:
        print(
            f"leafgate: error: no diagnostics from a gateway within {args.duration:g} s",
            file=sys.stderr,
        )
        return EXIT_ERROR
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    from leafgate.can.codec import CanCodec
    from leafgate.control import make_controller

    if Path(args.file).suffix.lower() == ".dbc":  # a common slip: not a YAML syntax error
        raise ConfigError(
            f"{args.file}: a DBC file, not a leafgate config: name it in a vehicle profile's "
            "dbc: list, or as can.dbw_dbc / can.car_dbc in a config"
        )
    cfg = load_config(args.file)
    codec = CanCodec.for_config(cfg)  # the profile and its DBCs load
    for line in codec.dbc_warnings():  # frames not to be trusted (overlaps, hidden)
        print(f"leafgate: warning: {line}", file=sys.stderr)
    for why in codec.unsendable_reports():  # the gateway runs with them; sim and sim-ecu not
        print(
            f"leafgate: warning: the simulated ECU (sim, sim-ecu) cannot send {why}",
            file=sys.stderr,
        )
    try:
        make_controller(cfg.controller, cfg.vehicle, cfg.gateway.period)
    except ConfigError as exc:  # a check across sections: name the file too
        raise ConfigError(f"{args.file}: {exc}") from None
    _scenario(cfg.sim.scenario)
    from leafgate.runtime.checks import offline_checks

    report = offline_checks(cfg)  # the daemon's start-up runs the same checks
    for line in report.warnings:
        print(f"leafgate: warning: {line}", file=sys.stderr)
    port = f" port {cfg.can.dbw.kwargs['port']}" if "port" in cfg.can.dbw.kwargs else ""
    unchecked = "; ".join(report.unchecked) or "nothing"
    print(
        f"{args.file}: ok offline (not checked here: {unchecked}) — controller {cfg.controller.kind} at {cfg.gateway.rate_hz:g} Hz, "
        f"dbw bus {cfg.can.dbw.interface}:{cfg.can.dbw.channel}{port}, "
        f"car bus {'shared' if cfg.can.car is None else cfg.can.car.interface + ':' + cfg.can.car.channel}, "
        f"zenoh {cfg.zenoh.mode} prefix {cfg.zenoh.prefix!r}"
        + (f" on {', '.join(cfg.zenoh.listen)}" if cfg.zenoh.listen else "")
    )
    profile = cfg.profile
    caps = profile.capabilities
    can_do = [n for n in ("lateral", "longitudinal", "gear") if getattr(caps, n)]
    print(f"vehicle profile {profile.name} ({profile.where}): commands {', '.join(can_do)}")
    print(f"frame protection: {' '.join(profile.protection.split())}")
    if profile.authenticated:  # for_config above loaded it: mode, owner, length checked
        print(f"authentication key: {cfg.can.auth_key_file} (mode, owner and length checked)")
    print(f"profile adjustments: {len(cfg.adjustments) or 'none'}")
    for line in cfg.adjustments:
        print(f"  {line}")
    z = cfg.zenoh
    if z.ros == "rmw_zenoh":
        print(
            f"ROS 2: rmw_zenoh node {z.node_namespace.rstrip('/')}/{z.node_name}, "
            f"domain {z.domain_id}, {z.ros_distro} type hashes"
        )
    else:
        print(f"ROS 2: through zenoh-bridge-ros2dds -n {z.ros_namespace}")
    return 0


def cmd_publish_trajectory(args: argparse.Namespace) -> int:
    """Publish until --count or a stop signal (SIGINT, SIGTERM, SIGHUP), then close in order.

    A stop signal sets an event (runtime.signals) instead of raising KeyboardInterrupt: a Ctrl-C
    that came while Python ran a finaliser (an import's lock, on the first publication) was
    swallowed there ("Exception ignored in … KeyboardInterrupt") and the command published on,
    and a second one could cut the closing of the publisher and session short.
    """
    import threading
    import time

    from leafgate.runtime.daemon import tool_view
    from leafgate.runtime.signals import signals_set
    from leafgate.transport.client import TrajectoryPublisher
    from leafgate.transport.session import open_session

    cfg = load_config(args.config)
    if (args.file is None) == (args.scenario is None):
        raise UsageError("publish-trajectory: give a FILE or --scenario NAME (one of them)")
    if args.file is not None:
        from leafgate.control.reference import load_plan_file, validate

        # the rule for a file (as `sim --trajectory` reads it), with the gateway's limits: a
        # plan it would drop, or one the car would wait on forever, is not sent
        trajectory = load_plan_file(
            args.file,
            max_speed=cfg.gateway.safety.max_speed,
            max_points=cfg.zenoh.max_plan_points,
        )
        spacing = validate(trajectory, args.file)
        print(f"{args.file}: {len(trajectory)} waypoints, {spacing} apart")
    else:
        trajectory = _scenario(args.scenario).trajectory
    zcfg = tool_view(cfg.zenoh)
    stop = threading.Event()
    sent = 0
    with signals_set(stop):
        session = open_session(zcfg)
        try:
            with TrajectoryPublisher(session, zcfg) as publisher:
                if not publisher.wait_for_subscriber(args.wait, stop=stop) and not stop.is_set():
                    print(
                        f"leafgate: warning: no subscriber on {publisher.key} yet; "
                        "publishing anyway",
                        file=sys.stderr,
                    )
                next_t = time.monotonic()
                while not stop.is_set() and (args.count == 0 or sent < args.count):
                    publisher.publish(trajectory)
                    sent += 1
                    next_t += args.period
                    stop.wait(max(0.0, next_t - time.monotonic()))
        finally:
            session.close()
    print(f"published the trajectory {sent} times")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    if args.replay_command == "check":
        from leafgate.replay.check import main_check

        # a rotated log's parts are checked as one log; other files each alone, one verdict
        return main_check(
            args.log,
            config=args.config,
            profile=args.profile,
            as_json=args.json,
            gap_periods=args.gap_periods,
            key_file=args.key_file,
        )
    if args.replay_command == "play":
        from leafgate.replay.play import play_from_args

        return play_from_args(args)
    if args.replay_command == "rerun":
        from leafgate.replay.rerun import main_rerun

        return main_rerun(args.session, overrides=args.set, as_json=args.json)
    from leafgate.replay.plot import main_plot

    return main_plot(args.log, out=args.out, config=args.config, profile=args.profile)


def cmd_decode(args: argparse.Namespace) -> int:
    from leafgate.can.secoc import tool_key
    from leafgate.record.logs import recording_context
    from leafgate.replay.decode import decode_log

    context = recording_context(args.log[0], config=args.config, profile=args.profile)
    return decode_log(
        args.log,
        summary=not args.no_summary,
        profile=context.profile,
        dbw_dbc=context.config.can.dbw_dbc,
        car_dbc=context.config.can.car_dbc,
        key=tool_key(args.key_file, context.config if args.config else None),
    )


def cmd_keygen(args: argparse.Namespace) -> int:
    from leafgate.can.secoc import write_key

    path = write_key(args.path)
    print(f"wrote a new 256-bit key to {path} (mode 0600); set can.auth_key_file: {path}")
    return 0


def _sim_key_file(cfg: LeafgateConfig, directory: Path) -> LeafgateConfig:
    """For a recorded or real-time drive of a profile that authenticates its frames and has no
    key configured: a throwaway key in ``directory/auth.key`` (mode 0600; an earlier run's is
    reused), so the processes share it and `replay check --key-file` can verify the log."""
    from leafgate.can.secoc import write_key

    if not cfg.profile.authenticated or cfg.can.auth_key_file is not None:
        return cfg
    path = directory / "auth.key"
    directory.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        write_key(path)
    print(f"authenticated frames: throwaway key {path}")
    return dataclasses.replace(cfg, can=dataclasses.replace(cfg.can, auth_key_file=str(path)))


# --- the command line -------------------------------------------------------------------------


KEY_FILE_HELP = (
    "key file verifying authenticated frames (leafgate-dbw-auth); default: the --config's "
    "can.auth_key_file; without a key their MACs are reported as not verified"
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="leafgate",
        description="Drive-by-wire gateway for automated low-speed driving of a Nissan Leaf.",
    )
    parser.add_argument("--version", action="version", version=f"leafgate {__version__}")
    parser.add_argument(
        "--log-format", choices=("text", "json"), default="text", help="log line format on stdout"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument(
        "--bench",
        # checked here: passed on as LEAFGATE_BENCH, a bad N would be blamed on the variable
        type=whole_number_between(0, MAX_BENCH, "a bench number"),
        metavar="N",
        help="simulation bench N: a config with `bench:` takes its CAN and Zenoh ports from N "
        "(same as LEAFGATE_BENCH=N)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    from leafgate.record.logs import readable_suffixes_text
    from leafgate.sim.compare import CONTROLLERS, PLANTS
    from leafgate.sim.names import TO_SIM, TO_SIM_ECU, injection_names, only_here
    from leafgate.sim.realtime import SIM_ECU_INJECTIONS
    from leafgate.sim.runner import INJECTION_KINDS
    from leafgate.sim.scenarios import SCENARIOS

    p = sub.add_parser(
        "sim",
        help="closed-loop simulation on a simulated clock (the embedded default)",
        description="Drive a built-in scenario or your own trajectory file through the whole "
        "gateway on a simulated clock. Writes metrics.json, trace.csv (one row per control "
        "tick) and plots to --out; exits 1 with the reason on stderr when the maneuver did "
        "not finish, or when the car's body went into a parked car, kerb or wall of the scene.",
        epilog=f"scenarios: {', '.join(SCENARIOS)}.\n"
        f"controllers: {', '.join(CONTROLLERS)}.\n"
        f"injections: {injection_names(INJECTION_KINDS, TO_SIM)}.\n"
        "Scenarios and controllers have the same names in `compare`; a fault `sim-ecu` "
        "takes too has the same name there.\n"
        f"Only `sim` injects: {only_here(INJECTION_KINDS, SIM_ECU_INJECTIONS, TO_SIM)}.\n\n"
        + TRAJECTORY_FORMAT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", help="YAML config (default: the embedded simulation defaults)")
    p.add_argument(
        "--scenario",
        metavar="NAME",
        help=f"maneuver to drive: {', '.join(SCENARIOS)} (default: the config's, s-curve)",
    )
    p.add_argument(
        "--trajectory",
        metavar="FILE",
        help="drive your own path from a .csv or .yaml trajectory file (format below)",
    )
    p.add_argument(
        "--start",
        metavar="X,Y,HEADING_DEG",
        help="start pose for --trajectory, at rest (default: the first waypoint)",
    )
    add_overrides(p)
    p.add_argument(
        "--rolling-window",
        type=positive_number,
        metavar="M",
        help="send the route as a planner does: the next M metres (e.g. 30), re-sent",
    )
    p.add_argument(
        "--window-period",
        type=positive_seconds,
        default=0.5,
        metavar="S",
        help="s between rolling-window plans (default 0.5)",
    )
    p.add_argument(
        "--window-behind",
        type=non_negative_number,
        default=0.0,
        metavar="M",
        help="each rolling-window plan also keeps M metres behind the car, as Autoware's "
        "planners do (default 0)",
    )
    p.add_argument(
        "--window-resample",
        action="store_true",
        help="re-sample every rolling-window plan, as a planner does on each cycle: no "
        "waypoint repeats the last plan's",
    )
    p.add_argument("--plant", choices=PLANTS)
    p.add_argument(
        "--controller",
        choices=tuple(CONTROLLERS),
        help="mpc-steer: the MPC with the steering-lag model (as in `compare`)",
    )
    p.add_argument("--solver", choices=("daqp", "hildreth", "osqp"))
    p.add_argument("--mode", choices=("acceleration", "velocity"))
    p.add_argument(
        "--profile",
        metavar="NAME|FILE",
        help="vehicle profile: leafgate-dbw (default), leafgate-dbw-auth, sze-hlc, "
        "leaf-ze1-lkas, or a .yaml file",
    )
    p.add_argument(
        "--out", default="leafgate-sim", help="output directory (default: ./leafgate-sim/)"
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument(
        "--seed",
        type=int,
        help="seed of the simulated disturbances (localization noise): `leafgate batch sim` "
        "prints each case's --seed and --set so it can be run alone",
    )
    p.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="KIND@T[+DUR]",
        help="fault or driver action, e.g. localization-dropout@8s, override@10s (repeatable): "
        + injection_names(INJECTION_KINDS, TO_SIM),
    )
    p.add_argument(
        "--record", metavar="DIR", help="record the drive (CAN log and session .mcap) into DIR"
    )
    loop = p.add_mutually_exclusive_group()
    loop.add_argument(
        "--direct",
        action="store_true",
        help="controller drives the plant directly (no CAN, no gateway)",
    )
    loop.add_argument(
        "--realtime", action="store_true", help="the daemon's runtime in real time, in this process"
    )
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("run", help="the gateway daemon (vehicle or simulated ECU)")
    p.add_argument("--config", required=True, help="deployment YAML, e.g. config/leafgate.yaml")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "sim-ecu",
        help="simulated drive-by-wire ECU and plant on a real bus, localization on Zenoh",
        epilog=f"scenarios: {', '.join(SCENARIOS)}. "
        f"injections: {injection_names(SIM_ECU_INJECTIONS, TO_SIM_ECU)}. "
        "A fault `sim` takes too has the same name there. Only `sim-ecu` injects: "
        f"{only_here(SIM_ECU_INJECTIONS, INJECTION_KINDS, TO_SIM_ECU)}.",
    )
    p.add_argument("--config", required=True, help="YAML config, e.g. config/sim.yaml")
    p.add_argument(
        "--scenario",
        metavar="NAME",
        help="start the plant on this scenario's first waypoint (default: sim.scenario): "
        + ", ".join(SCENARIOS),
    )
    p.add_argument("--plant", choices=PLANTS)
    p.add_argument(
        "--trace", metavar="CSV", help="write the plant's states there on exit (every 20 ms)"
    )
    p.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="KIND@T[+DUR][:NAME=VALUE,...]",
        help="fault T s after the ECU first engages, e.g. localization-stop@3s, "
        "localization-jump@2:lateral=2, corrupt-crc@3+0.5 (repeatable)",
    )
    p.set_defaults(func=cmd_sim_ecu)

    for name, text in (
        ("engage", "ask the gateway to engage"),
        ("disengage", "ask the gateway to disengage"),
        ("reset", "ask the gateway to clear a latched fault"),
    ):
        p = sub.add_parser(
            name,
            help=text,
            description=f"{text[0].upper()}{text[1:]}. Prints the JSON reply. Exit status: 0 "
            "carried out, 1 refused, 3 nothing to do (already so).",
        )
        p.add_argument("--config", required=True, help="YAML config naming the Zenoh endpoints")
        p.add_argument(
            "--timeout", type=positive_seconds, default=None, help="s to wait for the gateway"
        )
        if name == "engage":
            p.add_argument(
                "--wait",
                type=non_negative_seconds,
                default=ENGAGE_WAIT,
                metavar="SECONDS",
                help="while the gateway refuses for want of its inputs (just started, no plan "
                "yet), ask again for up to this long, saying what it waits for "
                f"(default {ENGAGE_WAIT:g}; 0: ask once)",
            )
        p.set_defaults(func=cmd_request)

    p = sub.add_parser("status", help="live diagnostics of a running gateway")
    p.add_argument("--config", required=True)
    p.add_argument("--duration", type=positive_seconds, default=1.0, help="s to watch (default 1)")
    p.add_argument("--json", action="store_true", help="print the raw JSON records")
    p.set_defaults(func=cmd_status)

    p = sub.add_parser(
        "compare", help="every controller × plant × scenario: report.md, report.json and plots"
    )
    from leafgate.sim.compare import add_arguments, cmd_compare

    add_arguments(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser(
        "batch", help="simulation sweeps, log checks and session re-runs on Dask (many inputs)"
    )
    from leafgate.batch.cli import add_arguments as add_batch_arguments
    from leafgate.batch.cli import cmd_batch

    add_batch_arguments(p)
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("replay", help="check, play back, re-run and plot recorded drives")
    rsub = p.add_subparsers(dest="replay_command", metavar="ACTION", required=True)
    r = rsub.add_parser(
        "check", help="offline safety check of a CAN log or session (exit 1 on any finding)"
    )
    r.add_argument(
        "log",
        nargs="+",
        help=f"CAN log or session ({readable_suffixes_text()}); a rotated log's parts "
        "(checked as one log, a missing part reported), or several logs (one verdict)",
    )
    add_profile_options(r, "the deployment config whose limits and profile apply")
    r.add_argument("--json", action="store_true", help="machine-readable report")
    from leafgate.replay.check import add_gap_periods

    add_gap_periods(r)
    r.add_argument("--key-file", metavar="FILE", help=KEY_FILE_HELP)
    r = rsub.add_parser(
        "play",
        help="timed playback of a log onto a bus (the gateway's command IDs left out by default)",
    )
    from leafgate.replay.play import add_arguments as add_play_arguments

    add_play_arguments(r)
    r = rsub.add_parser("rerun", help="re-run a recorded session through Gateway.step and compare")
    r.add_argument("session", help="session .mcap")
    add_overrides(r)
    r.add_argument("--json", action="store_true")
    r = rsub.add_parser("plot", help="path, steering and speed plots of a recorded drive")
    r.add_argument("log", help="CAN log or session .mcap")
    r.add_argument("--out", required=True, help="output directory")
    add_profile_options(r, "the deployment config naming the vehicle profile")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("check-config", help="load and check a config file")
    p.add_argument("file")
    p.set_defaults(func=cmd_check_config)

    p = sub.add_parser(
        "publish-trajectory", help="publish a trajectory (re-published, as a planner does)"
    )
    p.add_argument("file", nargs="?", help="CSV or YAML trajectory")
    p.add_argument("--scenario", help="a built-in scenario's trajectory instead of a file")
    p.add_argument("--config", required=True)
    p.add_argument(
        "--period", type=positive_seconds, default=0.5, help="s between publications (default 0.5)"
    )
    p.add_argument(
        "--count",
        type=non_negative_int,
        default=0,
        help="publications before exiting (0: until Ctrl-C)",
    )
    p.add_argument(
        "--wait",
        type=non_negative_seconds,
        default=5.0,
        help="s to wait for the gateway's subscriber",
    )
    p.set_defaults(func=cmd_publish_trajectory)

    p = sub.add_parser("decode", help="decode a CAN log or session with the leafgate DBCs")
    p.add_argument(
        "log",
        nargs="+",
        help=f"CAN log or session ({readable_suffixes_text()}); a rotated log's parts are "
        "decoded in order as one",
    )
    add_profile_options(p, "the deployment config naming the vehicle profile and DBCs")
    p.add_argument("--no-summary", action="store_true")
    p.add_argument("--key-file", metavar="FILE", help=KEY_FILE_HELP)
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser(
        "keygen", help="write a new key for authenticated frames (hex, mode 0600, never overwrites)"
    )
    p.add_argument("path", help="the key file to create (then set can.auth_key_file to it)")
    p.set_defaults(func=cmd_keygen)
    return parser


def _naming_the_file(exc: ConfigError, args: argparse.Namespace) -> ConfigError:
    """A config error that names the config file of the command (every entry point); a usage
    error names the options, as it is."""
    path = getattr(args, "config", None) or getattr(args, "file", None)
    text = str(exc)
    sources = (str(path), "command line", "--profile", "--config")
    if path is None or isinstance(exc, UsageError) or any(text.startswith(s) for s in sources):
        return exc
    return ConfigError(f"{path}: {text}")


EXIT_PIPE = 141  # 128 + SIGPIPE, as a shell reports a command killed by a closed pipe
EXIT_INTERRUPTED = 130  # 128 + SIGINT


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # stdout has no file descriptor (tests capture it)
        pass


def _closed_standard_streams() -> int:
    """Refuse to start with stdout closed (``>&-``: ``sys.stdout`` is None); 0 when it is open.

    Every command's product or log goes to stdout: discarding it silently would let a command
    look as if it had done its work. A closed stderr is pointed at /dev/null (there is nowhere
    to tell about it), and the exit status still says how the command ended.
    """
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 (for the process)
    if sys.stdout is None:
        sys.stdout = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 (for the process)
        print(
            "leafgate: error: standard output is closed; nothing to write to "
            "(redirect it to a file or to /dev/null instead)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    return 0


def _one_line(exc: OSError) -> str:
    """``Permission denied: 'out/x'``: the reason and the path, without the errno prefix."""
    what = exc.strerror or str(exc)
    if exc.filename is not None:
        return f"{what}: {os.fsdecode(exc.filename)}"
    return what


#: errors only a write raises (disk full, quota, file too large): the output being written
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def _written(exc: OSError, args: argparse.Namespace) -> str:
    """``" (writing --out DIR)"`` for a write error that names no file (``file.write`` raises
    ENOSPC without a path): the output options this command writes; "" otherwise."""
    if exc.filename is not None or exc.errno not in _WRITE_ERRNOS:
        return ""
    names = (*OUTPUT_FOLDERS, *OUTPUT_FILES)
    given = [f"--{n} {getattr(args, n)}" for n in names if getattr(args, n, None)]
    return f" (writing {' / '.join(given)})" if given else ""


#: options naming a folder the command writes into, checked before any work starts
OUTPUT_FOLDERS = ("out", "record")
#: options naming a file the command writes, whose folder is checked the same way
OUTPUT_FILES = ("trace",)


def output_folder(path: str | Path, option: str) -> Path:
    """Create ``path`` (and its parents) for ``option``; one line naming both when impossible.

    :raises LeafgateError: the folder cannot be created or is not a folder
    """
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LeafgateError(
            f"{option} {path}: cannot create the output folder: {_one_line(exc)}"
        ) from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise LeafgateError(f"{option} {path}: the output folder is not writable")
    return folder


def _prepare_outputs(args: argparse.Namespace) -> None:
    """Fail before any work when an output folder cannot be made (not after a long run)."""
    for name in OUTPUT_FOLDERS:
        value = getattr(args, name, None)
        if isinstance(value, str) and value:
            output_folder(value, f"--{name}")
    for name in OUTPUT_FILES:
        value = getattr(args, name, None)
        if isinstance(value, str) and value:
            output_folder(Path(value).parent, f"--{name}")


def _from_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` was raised because of a Ctrl-C: a native module whose initialisation a
    KeyboardInterrupt broke says "ImportError: initialization failed" (scipy's HiGHS, loaded
    when the MPC is built), with the KeyboardInterrupt as its cause."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def _negative_start(argv: Sequence[str]) -> list[str]:
    """``argv`` with ``--start -5,2,90`` joined into ``--start=-5,2,90``.

    argparse (before Python 3.13) takes a value that starts with ``-`` and is not a plain
    number for an option, so a start pose with a negative X was "expected one argument".
    """
    out: list[str] = []
    args = iter(argv)
    for arg in args:
        if arg == "--start":
            value = next(args, None)
            if value is not None and re.match(r"-\.?\d", value):
                out.append(f"--start={value}")
                continue
            out.append(arg)
            if value is not None:
                out.append(value)
            continue
        out.append(arg)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``leafgate`` command; every way it can end is one line and an exit status.

    - a :class:`LeafgateError` (bad config, file, bus …): its line, status 1 (2 for config);
    - a file or folder that cannot be written: the reason and the path, status 1;
    - stdout closed by the reader (``leafgate decode … | head``): status 141, quietly on
      stdout, one line on stderr;
    - Ctrl-C: "interrupted", status 130;
    - stdout closed before the start (``leafgate decode … >&-``): one line, status 2.
    """
    closed = _closed_standard_streams()
    if closed:
        return closed
    previous_sigint: Any = None  # SIGINT's handler before the command's own (restored after)
    try:  # Ctrl-C before the command runs (a traceback of argparse's, once): one line too
        parser = build_parser()  # imports what the subcommands' options list
        argv = _negative_start(sys.argv[1:] if argv is None else argv)
        args = parser.parse_args(argv)
        if args.command is None:
            args = parser.parse_args(["sim", *argv])
        if args.command not in STOP_SIGNAL_COMMANDS:
            from leafgate.runtime.signals import release

            release()  # the default actions back (a signal held meanwhile acts now)
        if args.command in INTERRUPT_ONCE_COMMANDS:
            from leafgate.runtime.hold import interrupt_once

            previous_sigint = signal.signal(signal.SIGINT, interrupt_once)
        if args.bench is not None:
            from leafgate.settings import BENCH_ENV

            os.environ[BENCH_ENV] = str(args.bench)  # every config this process loads
        # The daemon logs from its control thread: through a queue, so stdout never delays a
        # tick.
        setup_logging(args.log_format, args.verbose, queued=args.command == "run")
    except KeyboardInterrupt:
        print("leafgate: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    try:
        _prepare_outputs(args)
        try:
            return int(args.func(args))
        except ConfigError as exc:
            raise _naming_the_file(exc, args) from None
    except LeafgateError as exc:
        print(f"leafgate: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, ConfigError) else EXIT_ERROR
    except KeyboardInterrupt:
        print("leafgate: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        _silence_stdout()
        print("leafgate: output closed by the reader; stopped", file=sys.stderr)
        return EXIT_PIPE
    except OSError as exc:
        print(f"leafgate: error: {_one_line(exc)}{_written(exc, args)}", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:
        if not _from_interrupt(exc):
            raise
        print("leafgate: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous_sigint is not None:  # main() may be called again (tests): as it was
            signal.signal(signal.SIGINT, previous_sigint)


if __name__ == "__main__":
    sys.exit(main())
