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
from leafgate.errors import ConfigError, LeafgateError
from leafgate.settings import LeafgateConfig, load_config

log = logging.getLogger("leafgate")

EXIT_ERROR = 1
EXIT_USAGE = 2


def _replace_path(cfg: Any, dotted: str, value: Any) -> Any:
    """Return a copy of a nested frozen dataclass with one dotted field replaced."""
    head, _, rest = dotted.partition(".")
    if not rest:
        return dataclasses.replace(cfg, **{head: value})
    return dataclasses.replace(cfg, **{head: _replace_path(getattr(cfg, head), rest, value)})


def _with_overrides(cfg: LeafgateConfig, overrides: dict[str, Any]) -> LeafgateConfig:
    for dotted, value in overrides.items():
        if value is not None:
            try:
                cfg = _replace_path(cfg, dotted, value)
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"command line: {dotted}: {exc}") from None
    return cfg


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


def cmd_sim(args: argparse.Namespace) -> int:
    from leafgate.sim.plots import plot_drive
    from leafgate.sim.runner import run
    from leafgate.sim.scenarios import get_scenario

    cfg = load_config(args.config)
    cfg = _with_overrides(
        cfg,
        {
            "controller.kind": args.controller,
            "controller.mpc.solver": args.solver,
            "controller.mpc.mode": args.mode,
            "sim.plant.kind": args.plant,
        },
    )
    scenario_name = args.scenario or cfg.sim.scenario
    try:
        scenario = get_scenario(scenario_name)
    except KeyError as exc:
        raise ConfigError(str(exc.args[0])) from None
    result = run(cfg, scenario)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for t, event in result.timeline:
        print(f"  t={t:7.2f} s  {event}")
    print(
        f"scenario {scenario.name}: controller {cfg.controller.kind}, "
        f"solver {cfg.controller.mpc.solver}, mode {cfg.controller.mpc.mode}, "
        f"plant {cfg.sim.plant.kind}"
    )
    print(format_metrics(result.metrics))
    metrics = dict(result.metrics)
    metrics.update(
        {
            "scenario": scenario.name,
            "controller": cfg.controller.kind,
            "solver": cfg.controller.mpc.solver,
            "mode": cfg.controller.mpc.mode,
            "plant": cfg.sim.plant.kind,
            "timeline": [{"t": t, "event": e} for t, e in result.timeline],
        }
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    if not args.no_plots:
        plot_drive(out, scenario.trajectory, [result.trace], title=f"— {scenario.name}")
    print(
        f"wrote {out / 'metrics.json'}"
        + ("" if args.no_plots else ", path.png, steering.png, speed.png")
    )
    return 0


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

    p = sub.add_parser(
        "sim", help="closed-loop simulation on a simulated clock (the embedded default)"
    )
    p.add_argument("--config", help="YAML config (default: the embedded simulation defaults)")
    p.add_argument("--scenario", help="maneuver to drive (default: s-curve)")
    p.add_argument("--plant", choices=("kinematic", "steer-lag", "dynamic"))
    p.add_argument("--controller", choices=("mpc", "pure-pursuit", "stanley"))
    p.add_argument("--solver", choices=("hildreth", "osqp"))
    p.add_argument("--mode", choices=("acceleration", "velocity"))
    p.add_argument(
        "--out", default="leafgate-sim", help="output directory (default: ./leafgate-sim/)"
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=cmd_sim)
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
