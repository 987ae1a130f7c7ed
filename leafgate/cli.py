"""The ``leafgate`` command and its subcommands.

Errors a user can cause (bad config, missing file, unknown scenario) end with one readable line
on stderr and a non-zero exit status, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from leafgate import __version__
from leafgate.config import parse_overrides
from leafgate.errors import ConfigError, LeafgateError
from leafgate.settings import LeafgateConfig, load_config, with_profile
from leafgate.sim.scenarios import Scenario

log = logging.getLogger("leafgate")

EXIT_ERROR = 1
EXIT_USAGE = 2


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
    ("progress_m", "progress along the route [m]", "{:.2f}"),
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
) -> Any:
    """Run the simulated loop while recording it as the daemon would (CAN log + session)."""
    from leafgate.replay.recorder import open_recording
    from leafgate.sim.runner import run

    rec_cfg = dataclasses.replace(cfg.recording, enabled=True, directory=str(directory))
    # Simulated time everywhere: frames keep the simulator's timestamps (no wall clock).
    recording = open_recording(rec_cfg, cfg, clock=None, wall_clock=None)
    try:
        result = run(cfg, scenario, injections=injections, recorder=recording, window=window)
    finally:
        recording.close()
    if recording.fault:
        print(f"leafgate: warning: recording fault: {recording.fault}", file=sys.stderr)
    for path in sorted(directory.iterdir()):
        print(f"recorded {path}")
    return result


TRAJECTORY_FORMAT = """\
trajectory files (--trajectory, publish-trajectory):
  CSV with the header x,y,heading,speed, one waypoint per line; or YAML, either a list of
  {x, y, heading, speed} mappings or a mapping of those four keys to lists of equal length.
  x, y: m, rear-axle centre; heading: rad, the vehicle's heading (also when reversing);
  speed: m/s, signed (negative = reverse; where the sign changes is a cusp, speed 0 there).
  At least 4 waypoints, 0.5-1.0 m apart as a planner sends them, no point repeated; the last
  waypoint is the goal (speed 0). Example CSV:
    x,y,heading,speed
    0.0,0.0,0.0,0.3
    0.5,0.0,0.0,0.6
    1.0,0.0,0.0,0.6
    1.5,0.0,0.0,0.0
"""


def cmd_sim(args: argparse.Namespace) -> int:
    from leafgate.sim.plots import plot_drive
    from leafgate.sim.runner import Injection, run, run_direct

    cfg = _load(
        args.config,
        {
            "controller.kind": args.controller,
            "controller.mpc.solver": args.solver,
            "controller.mpc.mode": args.mode,
            "sim.plant.kind": args.plant,
            # the seeded disturbances' random processes (a batch case's --seed)
            "sim.localization.seed": args.seed,
        },
        args.set,
    )
    if args.profile:
        cfg = with_profile(cfg, args.profile)
    if not _model_given(args.config, args.set):  # the steering-aware model where the wheel lags
        from leafgate.sim.runner import default_model

        mpc = dataclasses.replace(cfg.controller.mpc, model=default_model(cfg.sim.plant.kind))
        cfg = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, mpc=mpc))
    if args.trajectory and args.scenario:
        raise ConfigError("sim: give --scenario NAME or --trajectory FILE, not both")
    if args.start and not args.trajectory:
        raise ConfigError("sim: --start goes with --trajectory (a scenario has its own start)")
    if args.trajectory:
        from leafgate.sim.scenarios import file_scenario

        scenario = file_scenario(args.trajectory, _start_pose(args.start))
    else:
        scenario = _scenario(args.scenario or cfg.sim.scenario)
    injections = tuple(Injection.parse(text) for text in args.inject)
    window = None
    if args.rolling_window is not None:
        from leafgate.sim.runner import RollingWindow

        window = RollingWindow(args.rolling_window, args.window_period)
    if (injections or args.record or window) and (args.direct or args.realtime):
        raise ConfigError(
            "--inject, --record and --rolling-window need the full simulated loop "
            "(not --direct or --realtime)"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.realtime:
        from leafgate.sim.realtime import run_realtime
        from leafgate.sim.runner import finish_verdict

        outcome = run_realtime(cfg, scenario)
        metrics, trace, timeline = outcome["metrics"], outcome["trace"], outcome["timeline"]
        final = metrics["final_state"]
        metrics["finished"], reason = finish_verdict(
            metrics, final == "STANDBY", f"the gateway ended in {final}"
        )
        if reason:
            metrics["not_finished_reason"] = reason
        loop = "real time (daemon runtime, in-process Zenoh, virtual CAN)"
    else:
        if args.direct:
            result = run_direct(cfg, scenario)
        elif args.record:
            result = _run_recorded(cfg, scenario, injections, Path(args.record), window)
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
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
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
    if not metrics.get("finished"):
        reason = metrics.get("not_finished_reason") or "the maneuver did not finish"
        print(f"leafgate: {scenario.name}: not finished: {reason}", file=sys.stderr)
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
        raise ConfigError(
            f"--start {text!r}: expected X,Y,HEADING_DEG (m, m, degrees), e.g. 0,0,90"
        ) from None
    if not all(isfinite(v) for v in (x, y, heading_deg)):
        raise ConfigError(f"--start {text!r}: values must be finite")
    return Pose(x=x, y=y, heading=radians(heading_deg), speed=0.0)


# --- the daemon and its tools ------------------------------------------------------------------


def _scenario(name: str) -> Scenario:
    from leafgate.sim.scenarios import get_scenario

    try:
        return get_scenario(name)
    except KeyError as exc:
        raise ConfigError(str(exc.args[0])) from None


def cmd_run(args: argparse.Namespace) -> int:
    from leafgate.gateway.daemon import run_daemon

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


def cmd_request(args: argparse.Namespace) -> int:
    from leafgate.gateway.daemon import tool_view
    from leafgate.transport.client import request

    cfg = load_config(args.config)
    reply = request(tool_view(cfg.zenoh), args.command, timeout=args.timeout)
    print(json.dumps(reply))
    return 0 if reply.get("accepted") else EXIT_ERROR


def cmd_status(args: argparse.Namespace) -> int:
    from leafgate.gateway.daemon import tool_view
    from leafgate.transport.client import watch_diagnostics

    cfg = load_config(args.config)
    seen: list[dict[str, Any]] = []

    def show(diag: dict[str, Any]) -> None:
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
            f"loop {compute_text} median, {loop.get('overruns', 0)} overruns | {', '.join(parts)}",
            flush=True,
        )

    watch_diagnostics(tool_view(cfg.zenoh), show, args.duration)
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

    cfg = load_config(args.file)
    CanCodec.for_config(cfg)  # the profile and its DBCs load
    try:
        make_controller(cfg.controller, cfg.vehicle, cfg.gateway.period)
    except ConfigError as exc:  # a check across sections: name the file too
        raise ConfigError(f"{args.file}: {exc}") from None
    _scenario(cfg.sim.scenario)
    print(
        f"{args.file}: ok — controller {cfg.controller.kind} at {cfg.gateway.rate_hz:g} Hz, "
        f"dbw bus {cfg.can.dbw.interface}:{cfg.can.dbw.channel}, "
        f"car bus {'shared' if cfg.can.car is None else cfg.can.car.interface + ':' + cfg.can.car.channel}, "
        f"zenoh {cfg.zenoh.mode} prefix {cfg.zenoh.prefix!r}"
    )
    profile = cfg.profile
    caps = profile.capabilities
    can_do = [n for n in ("lateral", "longitudinal", "gear") if getattr(caps, n)]
    print(f"vehicle profile {profile.name} ({profile.where}): commands {', '.join(can_do)}")
    print(f"frame protection: {profile.protection}")
    return 0


def cmd_publish_trajectory(args: argparse.Namespace) -> int:
    import time

    from leafgate.gateway.daemon import tool_view
    from leafgate.transport.client import TrajectoryPublisher
    from leafgate.transport.session import open_session

    cfg = load_config(args.config)
    if (args.file is None) == (args.scenario is None):
        raise ConfigError("publish-trajectory: give a FILE or --scenario NAME (one of them)")
    if args.file is not None:
        from leafgate.control.reference import load_trajectory, validate

        trajectory = load_trajectory(args.file)
        spacing = validate(trajectory, args.file)
        print(f"{args.file}: {len(trajectory)} waypoints, spacing {spacing}")
    else:
        trajectory = _scenario(args.scenario).trajectory
    zcfg = tool_view(cfg.zenoh)
    session = open_session(zcfg)
    sent = 0
    try:
        with TrajectoryPublisher(session, zcfg) as publisher:
            if not publisher.wait_for_subscriber(args.wait):
                print(
                    f"leafgate: warning: no subscriber on {publisher.key} yet; publishing anyway",
                    file=sys.stderr,
                )
            next_t = time.monotonic()
            while args.count == 0 or sent < args.count:
                publisher.publish(trajectory)
                sent += 1
                next_t += args.period
                time.sleep(max(0.0, next_t - time.monotonic()))
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    print(f"published the trajectory {sent} times")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    if args.replay_command == "check":
        from leafgate.replay.check import main_check

        return main_check(
            args.log, config=args.config, as_json=args.json, gap_periods=args.gap_periods
        )
    if args.replay_command == "play":
        from leafgate.replay.play import main_play

        return main_play(
            args.log,
            interface=args.interface,
            channel=args.channel,
            speed=args.speed,
            start=args.start,
            ids=args.ids,
            bitrate=args.bitrate,
        )
    if args.replay_command == "rerun":
        from leafgate.replay.rerun import main_rerun

        return main_rerun(args.session, overrides=args.set, as_json=args.json)
    from leafgate.replay.plot import main_plot

    return main_plot(args.log, out=args.out)


def cmd_decode(args: argparse.Namespace) -> int:
    from leafgate.can.decode import decode_log

    return decode_log(args.log, summary=not args.no_summary)


# --- the command line -------------------------------------------------------------------------


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
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    from leafgate.sim.scenarios import SCENARIOS

    p = sub.add_parser(
        "sim",
        help="closed-loop simulation on a simulated clock (the embedded default)",
        description="Drive a built-in scenario or your own trajectory file through the whole "
        "gateway on a simulated clock. Writes metrics.json, trace.csv (one row per control "
        "tick) and plots to --out; exits 1 with the reason on stderr when the maneuver did "
        "not finish.",
        epilog=TRAJECTORY_FORMAT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", help="YAML config (default: the embedded simulation defaults)")
    p.add_argument(
        "--scenario",
        metavar="NAME",
        help=f"maneuver to drive (default: s-curve): {', '.join(SCENARIOS)}",
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
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. controller.mpc.weight_lateral=10 (repeatable)",
    )
    p.add_argument(
        "--rolling-window",
        type=float,
        metavar="M",
        help="send the route as a planner does: the next M metres (e.g. 30), re-sent",
    )
    p.add_argument(
        "--window-period",
        type=float,
        default=0.5,
        metavar="S",
        help="s between rolling-window plans (default 0.5)",
    )
    p.add_argument("--plant", choices=("kinematic", "steer-lag", "dynamic"))
    p.add_argument("--controller", choices=("mpc", "pure-pursuit", "stanley"))
    p.add_argument("--solver", choices=("daqp", "hildreth", "osqp"))
    p.add_argument("--mode", choices=("acceleration", "velocity"))
    p.add_argument(
        "--profile",
        help="vehicle profile: leafgate-dbw (default), sze-hlc, leaf-ze1-lkas, or a .yaml file",
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
        help="fault or driver action, e.g. localization-dropout@8s, override@10s (repeatable)",
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
        "sim-ecu", help="simulated drive-by-wire ECU and plant on a real bus, localization on Zenoh"
    )
    p.add_argument("--config", required=True, help="YAML config, e.g. config/sim.yaml")
    p.add_argument(
        "--scenario",
        help="start the plant on this scenario's first waypoint (default: sim.scenario)",
    )
    p.add_argument("--plant", choices=("kinematic", "steer-lag", "dynamic"))
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
        p = sub.add_parser(name, help=text)
        p.add_argument("--config", required=True, help="YAML config naming the Zenoh endpoints")
        p.add_argument("--timeout", type=float, default=None, help="s to wait for the gateway")
        p.set_defaults(func=cmd_request)

    p = sub.add_parser("status", help="live diagnostics of a running gateway")
    p.add_argument("--config", required=True)
    p.add_argument("--duration", type=float, default=1.0, help="s to watch (default 1)")
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
    r.add_argument("log", help="CAN log (.log/.asc/.blf/.trc/.csv) or session (.mcap)")
    r.add_argument("--config", help="the deployment config whose limits apply (default: built-in)")
    r.add_argument("--json", action="store_true", help="machine-readable report")
    r.add_argument(
        "--gap-periods", type=float, default=3.0, help="a gap is this many periods of silence"
    )
    r = rsub.add_parser("play", help="timed playback of a log onto a bus")
    r.add_argument("log")
    r.add_argument(
        "--interface", required=True, help="python-can interface (socketcan, udp_multicast, …)"
    )
    r.add_argument("--channel", required=True)
    r.add_argument("--speed", type=float, default=1.0, help="speed factor (0: as fast as possible)")
    r.add_argument("--start", type=float, default=0.0, help="s into the log to start at")
    r.add_argument("--ids", help="only these IDs, hex, comma-separated (e.g. 0A0,0A1)")
    r.add_argument("--bitrate", type=int, default=500_000)
    r = rsub.add_parser("rerun", help="re-run a recorded session through Gateway.step and compare")
    r.add_argument("session", help="session .mcap")
    r.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. controller.mpc.weight_lateral=10",
    )
    r.add_argument("--json", action="store_true")
    r = rsub.add_parser("plot", help="path, steering and speed plots of a recorded drive")
    r.add_argument("log", help="CAN log or session .mcap")
    r.add_argument("--out", required=True, help="output directory")
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
    p.add_argument("--period", type=float, default=0.5, help="s between publications (default 0.5)")
    p.add_argument(
        "--count", type=int, default=0, help="publications before exiting (0: until Ctrl-C)"
    )
    p.add_argument("--wait", type=float, default=5.0, help="s to wait for the gateway's subscriber")
    p.set_defaults(func=cmd_publish_trajectory)

    p = sub.add_parser(
        "decode", help="decode a CAN log (.log/.asc/.blf/.trc/.csv) with the leafgate DBCs"
    )
    p.add_argument("log")
    p.add_argument("--no-summary", action="store_true")
    p.set_defaults(func=cmd_decode)
    return parser


def setup_logging(fmt: str, verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stdout)
    if fmt == "json":

        class _Json(logging.Formatter):
            def format(self, record: logging.LogRecord) -> str:
                return json.dumps(
                    {
                        "t": record.created,
                        "level": record.levelname,
                        "logger": record.name,
                        "msg": record.getMessage(),
                    }
                )

        handler.setFormatter(_Json())
    else:
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args(["sim", *(argv or [])])
    setup_logging(args.log_format, args.verbose)
    try:
        return int(args.func(args))
    except LeafgateError as exc:
        print(f"leafgate: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, ConfigError) else EXIT_ERROR
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
