"""``leafgate compare``: every controller on every plant and scenario, in one report.

Controllers: the paper's MPC (``mpc``, kinematic prediction model), the steering-aware MPC
(``mpc-steer``, model ``kinematic_steer_lag``), Pure Pursuit and Stanley. Plants: kinematic,
steer-lag and dynamic (:mod:`leafgate.sim.plant`). Scenarios: all built-in ones
(:data:`leafgate.sim.scenarios.SCENARIOS`). Every drive goes through the full loop
(:func:`leafgate.sim.runner.run`: CAN codec, simulated ECU, gateway, safety gate) unless
``direct`` asks for the controller-drives-plant loop (:func:`~leafgate.sim.runner.run_direct`).
Drives are independent and deterministic, so they run in parallel processes.

Written into the output directory:

- ``report.md`` — per scenario, a table of lateral error RMS and max, heading error max, final
  position and heading error, steering-rate RMS and max, steering-rate sign changes, controller
  time median and p99; the best lateral error per plant in bold; a summary of where the MPC
  is not the most accurate; links to the plots.
- ``report.json`` — the same numbers (SI units), one record per drive.
- ``plots/<scenario>/<plant>/{path,steering,speed}.png`` — all controllers overlaid.
- ``paper-fig2-4/<scenario>/`` — the paper's Figs. 2–4 pair: the plain MPC and the
  steering-aware MPC on the full vehicle (dynamic) plant.
- ``plots/<scenario>/layout.png`` for the parking scenarios: slot or bay, kerb, parked cars,
  the planned path and each controller's path on the steer-lag plant, the car at its goal.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from leafgate.cliargs import positive_int
from leafgate.errors import ConfigError
from leafgate.jsonconv import to_json
from leafgate.progress import Progress
from leafgate.settings import LeafgateConfig, load_config
from leafgate.sim.plots import Trace, plot_drive
from leafgate.sim.runner import SimResult, run, run_direct
from leafgate.sim.scenarios import OBSTACLES, SCENARIOS, footprint, get_scenario

#: Controllers of the comparison: name → (controller kind, MPC prediction model).
CONTROLLERS: dict[str, tuple[str, str]] = {
    "mpc": ("mpc", "kinematic"),
    "mpc-steer": ("mpc", "kinematic_steer_lag"),
    "pure-pursuit": ("pure-pursuit", "kinematic"),
    "stanley": ("stanley", "kinematic"),
}
PLANTS: tuple[str, ...] = ("kinematic", "steer-lag", "dynamic")
MPC_NAMES = ("mpc", "mpc-steer")
BASELINE_NAMES = ("pure-pursuit", "stanley")
PAPER_SCENARIOS = ("s-curve", "slalom")  # the paper's manoeuvre, and where the lag shows most
PAPER_PLANT = "dynamic"  # the full vehicle model (the paper used LGSVL)
TIE = 1e-3  # m: max lateral errors this small (a straight line) rank no controller above another

#: Table columns: metric key, heading, unit conversion factor, format.
COLUMNS: tuple[tuple[str, str, float, str], ...] = (
    ("lateral_error_rms_m", "lat. RMS [m]", 1.0, "{:.3f}"),
    ("lateral_error_max_m", "lat. max [m]", 1.0, "{:.3f}"),
    ("heading_error_max_rad", "heading max [°]", 180.0 / math.pi, "{:.2f}"),
    ("final_position_error_m", "final pos. [m]", 1.0, "{:.3f}"),
    ("final_heading_error_rad", "final heading [°]", 180.0 / math.pi, "{:.2f}"),
    ("steer_rate_rms_radps", "steer rate RMS [rad/s]", 1.0, "{:.3f}"),
    ("steer_rate_max_radps", "steer rate max [rad/s]", 1.0, "{:.3f}"),
    ("steer_rate_sign_changes", "steer sign changes", 1.0, "{:d}"),
    ("solve_time_median_s", "time median [µs]", 1e6, "{:.0f}"),
    ("solve_time_p99_s", "time p99 [µs]", 1e6, "{:.0f}"),
)


def drive_config(base: LeafgateConfig, controller: str, plant: str) -> LeafgateConfig:
    """``base`` with the controller (and MPC model) of the comparison and the plant set.

    :raises ConfigError: for an unknown controller or plant name
    """
    if controller not in CONTROLLERS:
        raise ConfigError(f"unknown controller {controller!r} (known: {', '.join(CONTROLLERS)})")
    if plant not in PLANTS:
        raise ConfigError(f"unknown plant {plant!r} (known: {', '.join(PLANTS)})")
    kind, model = CONTROLLERS[controller]
    mpc = dataclasses.replace(base.controller.mpc, model=model)  # type: ignore[arg-type]
    ctl = dataclasses.replace(base.controller, kind=kind, mpc=mpc)  # type: ignore[arg-type]
    plant_cfg = dataclasses.replace(base.sim.plant, kind=plant)  # type: ignore[arg-type]
    sim = dataclasses.replace(base.sim, plant=plant_cfg)
    return dataclasses.replace(base, controller=ctl, sim=sim)


def _drive(task: tuple[LeafgateConfig, str, str, str, bool]) -> tuple[str, str, str, SimResult]:
    """One drive (runs in a worker process)."""
    config, scenario, plant, controller, direct = task
    runner = run_direct if direct else run
    result = runner(config, get_scenario(scenario), label=controller)
    return scenario, plant, controller, result


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the parent (which stops the comparison with one line)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _select(names: Sequence[str] | None, known: Sequence[str], what: str) -> list[str]:
    if not names:
        return list(known)
    selected: list[str] = []
    for name in names:
        for part in name.split(","):
            part = part.strip()
            if part not in known:
                raise ConfigError(f"unknown {what} {part!r} (known: {', '.join(known)})")
            if part not in selected:
                selected.append(part)
    return selected


def run_compare(
    config: LeafgateConfig,
    out_dir: Path | str,
    scenarios: Sequence[str] | None = None,
    plants: Sequence[str] | None = None,
    controllers: Sequence[str] | None = None,
    direct: bool = False,
    workers: int | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """Drive every selected controller × plant × scenario and write the report.

    :param config: the base configuration (controller and plant are set per drive)
    :param out_dir: directory for ``report.md``, ``report.json`` and the plots (created)
    :param scenarios: scenario names (default: all built-in ones); items may be comma-separated
    :param plants: plant kinds (default: kinematic, steer-lag, dynamic)
    :param controllers: controller names of :data:`CONTROLLERS` (default: all four)
    :param direct: drive the plant from the controller directly (no CAN, ECU or gateway)
    :param workers: parallel processes (default: the CPU count, at most 4; 1 runs in-process)
    :param plots: write the PNG plots
    :returns: the content of ``report.json``
    :raises ConfigError: naming an unknown scenario, plant or controller
    """
    scenario_names = _select(scenarios, list(SCENARIOS), "scenario")
    plant_names = _select(plants, PLANTS, "plant")
    controller_names = _select(controllers, list(CONTROLLERS), "controller")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [
        (drive_config(config, c, p), s, p, c, direct)
        for s in scenario_names
        for p in plant_names
        for c in controller_names
    ]
    if workers is None:
        workers = max(1, min(os.cpu_count() or 1, 4))
    wall0 = time.perf_counter()
    done: list[tuple[str, str, str, SimResult]] = []
    with Progress("compare", len(tasks), "drives") as progress:
        if workers <= 1 or len(tasks) <= 1:
            for task in tasks:
                done.append(_drive(task))
                progress.update(len(done))
        else:
            pool = ProcessPoolExecutor(
                max_workers=min(workers, len(tasks)), initializer=_ignore_sigint
            )
            try:
                for future in as_completed([pool.submit(_drive, t) for t in tasks]):
                    done.append(future.result())
                    progress.update(len(done))
            except BaseException:  # Ctrl-C: stop the workers mid-drive, not after every drive
                # (the executor has no public way to; at exit it would wait for them)
                for process in list((pool._processes or {}).values()):
                    process.terminate()
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
    wall = time.perf_counter() - wall0
    order = {(t[1], t[2], t[3]): i for i, t in enumerate(tasks)}  # the report in task order
    done.sort(key=lambda d: order[(d[0], d[1], d[2])])
    results = {(s, p, c): r for s, p, c, r in done}

    records = []
    for (s, p, c), r in results.items():
        metrics = {k: to_json(v) for k, v in r.metrics.items() if k != "transitions"}
        records.append({"scenario": s, "plant": p, "controller": c, "metrics": metrics})
    report: dict[str, Any] = {
        "loop": "direct (controller → plant)" if direct else "full (CAN, ECU, gateway)",
        "scenarios": scenario_names,
        "plants": plant_names,
        "controllers": controller_names,
        "wall_time_s": wall,
        "workers": workers,
        "runs": records,
        "best_lateral_max": _best(results, scenario_names, plant_names, controller_names),
        "mpc_not_best": _mpc_not_best(results, scenario_names, plant_names, controller_names),
        "not_finished": _not_finished(results),
    }
    figures: dict[str, str] = {}
    if plots:
        figures = _write_plots(out, results, scenario_names, plant_names, controller_names)
    report["figures"] = figures
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    (out / "report.md").write_text(_markdown(report, results, figures), encoding="utf-8")
    return report


def _not_finished(results: dict[tuple[str, str, str], SimResult]) -> list[dict[str, Any]]:
    """Each drive that did not finish, in report order, with its reason and whether its
    scenario is feasible (an infeasible one is not expected to finish)."""
    out = []
    for (s, p, c), r in results.items():
        if not r.metrics.get("finished"):
            out.append(
                {
                    "scenario": s,
                    "plant": p,
                    "controller": c,
                    "feasible": get_scenario(s).feasible,
                    "reason": str(r.metrics.get("not_finished_reason") or "not finished"),
                }
            )
    return out


def _best(
    results: dict[tuple[str, str, str], SimResult],
    scenarios: list[str],
    plants: list[str],
    controllers: list[str],
) -> dict[str, dict[str, str]]:
    """Scenario → plant → the controller with the smallest max lateral error."""
    best: dict[str, dict[str, str]] = {}
    for s in scenarios:
        best[s] = {}
        for p in plants:
            errors = {c: results[(s, p, c)].metrics["lateral_error_max_m"] for c in controllers}
            best[s][p] = min(errors, key=lambda c: errors[c])
    return best


def _mpc_not_best(
    results: dict[tuple[str, str, str], SimResult],
    scenarios: list[str],
    plants: list[str],
    controllers: list[str],
) -> list[dict[str, Any]]:
    """Each (scenario, plant, MPC variant) whose max lateral error is not below every baseline's.

    Errors within :data:`TIE` of zero are ties, not defeats.
    """
    baselines = [c for c in controllers if c in BASELINE_NAMES]
    out = []
    for s in scenarios:
        for p in plants:
            for c in (c for c in controllers if c in MPC_NAMES):
                mine = results[(s, p, c)].metrics["lateral_error_max_m"]
                better = [
                    b
                    for b in baselines
                    if results[(s, p, b)].metrics["lateral_error_max_m"] <= mine and mine > TIE
                ]
                if better:
                    out.append(
                        {
                            "scenario": s,
                            "plant": p,
                            "controller": c,
                            "lateral_error_max_m": mine,
                            "at_least_as_good": better,
                        }
                    )
    return out


# --- plots ------------------------------------------------------------------------------------


def _write_plots(
    out: Path,
    results: dict[tuple[str, str, str], SimResult],
    scenarios: list[str],
    plants: list[str],
    controllers: list[str],
) -> dict[str, str]:
    figures: dict[str, str] = {}
    for s in scenarios:
        traj = get_scenario(s).trajectory
        for p in plants:
            traces = [_labelled(results[(s, p, c)].trace, c) for c in controllers]
            files = plot_drive(out / "plots" / s / p, traj, traces, title=f"— {s}, {p} plant")
            for kind, path in files.items():
                figures[f"{s}/{p}/{kind}"] = str(path.relative_to(out))
        if s in OBSTACLES:
            plant = "steer-lag" if "steer-lag" in plants else plants[0]
            traces = [_labelled(results[(s, plant, c)].trace, c) for c in controllers]
            path = _layout_plot(out / "plots" / s / "layout.png", s, traces, plant)
            figures[f"{s}/layout"] = str(path.relative_to(out))
        if (
            s in PAPER_SCENARIOS
            and PAPER_PLANT in plants
            and all(c in controllers for c in MPC_NAMES)
        ):
            pair = [
                _labelled(results[(s, PAPER_PLANT, "mpc")].trace, "MPC, kinematic model"),
                _labelled(results[(s, PAPER_PLANT, "mpc-steer")].trace, "MPC, steering-aware"),
            ]
            files = plot_drive(
                out / "paper-fig2-4" / s, traj, pair, title=f"— {s}, full vehicle plant"
            )
            for kind, path in files.items():
                figures[f"paper/{s}/{kind}"] = str(path.relative_to(out))
    return figures


def _labelled(trace: Trace, label: str) -> Trace:
    return dataclasses.replace(trace, label=label)


def _layout_plot(path: Path, scenario: str, traces: list[Trace], plant: str) -> Path:
    """The parking scene seen from above: obstacles, plan, driven paths, the car at its goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon, Rectangle

    traj = get_scenario(scenario).trajectory
    fig, ax = plt.subplots(figsize=(9, 6))
    for box in OBSTACLES[scenario]:
        ax.add_patch(
            Rectangle(
                (box.x_min, box.y_min),
                box.x_max - box.x_min,
                box.y_max - box.y_min,
                color="0.75",
            )
        )
    ax.plot(traj.x, traj.y, "k--", lw=1.2, label="plan (rear axle)")
    for tr in traces:
        ax.plot(tr.x, tr.y, lw=1.3, label=tr.label)
    x, y, h = float(traj.x[-1]), float(traj.y[-1]), float(traj.heading[-1])
    ax.add_patch(Polygon(footprint(x, y, h), fill=False, ec="tab:blue", lw=1.5))
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{scenario}: scene and paths ({plant} plant)")
    ax.legend(loc="best", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- markdown ---------------------------------------------------------------------------------


def _cell(metrics: dict[str, Any], key: str, factor: float, fmt: str) -> str:
    value = metrics.get(key)
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if fmt == "{:d}":
        return fmt.format(int(value))
    return fmt.format(value * factor)


def _markdown(
    report: dict[str, Any], results: dict[tuple[str, str, str], SimResult], figures: dict[str, str]
) -> str:
    lines = [
        "# leafgate controller comparison",
        "",
        f"Loop: {report['loop']}. {len(report['runs'])} drives in {report['wall_time_s']:.1f} s "
        f"({report['workers']} processes). Errors are measured on the true (plant) states against "
        "the reference polyline; steering rate is the actual road-wheel angle's. Controller time "
        "is the wall time of one controller step on this machine. Bold: the smallest max "
        "lateral error on that plant.",
        "",
        "Controllers: `mpc` — the paper's MPC (kinematic model); `mpc-steer` — the same with the "
        "steering actuator (lag τ, dead time) in the prediction model; `pure-pursuit`; "
        "`stanley`.",
        "",
    ]
    header = ["plant", "controller", *(c[1] for c in COLUMNS), "finished"]
    for s in report["scenarios"]:
        sc = get_scenario(s)
        note = "" if sc.feasible else " Infeasible by design: judged on speed and honesty."
        lines += [f"## {s}", "", f"{sc.description}.{note}", ""]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "---|" * len(header))
        for p in report["plants"]:
            best = report["best_lateral_max"][s][p]
            for c in report["controllers"]:
                m = results[(s, p, c)].metrics
                cells = [_cell(m, key, f, fmt) for key, _, f, fmt in COLUMNS]
                if c == best:
                    cells[1] = f"**{cells[1]}**"
                done = "yes" if m.get("finished") else "no"
                if m.get("clearance_min_m", 0.0) < 0.0:  # the body went into an obstacle
                    done += f"; {-m['clearance_min_m']:.2f} m into {m['clearance_min_obstacle']}"
                lines.append("| " + " | ".join([p, c, *cells, done]) + " |")
        lines.append("")
        links = [
            f"[{k.split('/', 1)[1]}]({v})" for k, v in figures.items() if k.startswith(f"{s}/")
        ]
        if links:
            lines += ["Plots: " + ", ".join(links), ""]
    lines += ["## Where the MPC is not the most accurate", ""]
    compared_mpc = [c for c in report["controllers"] if c in MPC_NAMES]
    compared_base = [c for c in report["controllers"] if c in BASELINE_NAMES]
    if not compared_mpc or not compared_base:
        lines.append("Not compared: this run did not drive both an MPC variant and a baseline.")
    elif not report["mpc_not_best"]:
        lines.append(
            "Nowhere: on every scenario and plant "
            + ", ".join(f"`{c}`" for c in compared_mpc)
            + " beat "
            + ", ".join(f"`{c}`" for c in compared_base)
            + "."
        )
    else:
        lines += [
            "Each MPC variant (kinematic or steering-aware model) whose max lateral error is not "
            f"below both baselines' (errors under {TIE * 1e3:.0f} mm count as ties):",
            "",
        ]
    for item in report["mpc_not_best"]:
        lines.append(
            f"- {item['scenario']}, {item['plant']} plant: `{item['controller']}` "
            f"{item['lateral_error_max_m']:.3f} m, matched or beaten by "
            + ", ".join(f"`{b}`" for b in item["at_least_as_good"])
        )
    lines.append("")
    lines += ["## Drives that did not finish", ""]
    if not report["not_finished"]:
        lines.append("None: every drive finished.")
    for feasible, title in (
        (True, "Feasible scenarios (failures)"),
        (False, "Infeasible by design (expected)"),
    ):
        drives = [d for d in report["not_finished"] if d["feasible"] == feasible]
        if drives:
            lines += [f"{title}:", ""]
            lines += [
                f"- {d['scenario']}, `{d['controller']}`, {d['plant']} plant: {d['reason']}"
                for d in drives
            ]
            lines.append("")
    lines.append("")
    paper = [f"[{k}]({v})" for k, v in figures.items() if k.startswith("paper/")]
    if paper:
        lines += [
            "## The paper's Figs. 2–4, with the steering-aware model",
            "",
            "Plain MPC (kinematic prediction model) against the steering-aware MPC on the full "
            f"vehicle ({PAPER_PLANT}) plant: " + ", ".join(paper),
            "",
        ]
    return "\n".join(lines)


# --- command line -----------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``leafgate compare`` options (for the CLI to add to its sub-parser)."""
    parser.add_argument("--config", help="YAML config (default: the embedded defaults)")
    parser.add_argument("--out", required=True, help="output directory for the report")
    parser.add_argument(
        "--scenario", action="append", help="only these scenarios (repeat or comma-separate)"
    )
    parser.add_argument("--plant", action="append", help="only these plants")
    parser.add_argument("--controller", action="append", help="only these controllers")
    parser.add_argument(
        "--direct", action="store_true", help="controller drives the plant (skip CAN and gateway)"
    )
    parser.add_argument(
        "--workers", type=positive_int, help="parallel processes (default: CPU count)"
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.epilog = (
        "Exit status: 0 when every drive on a feasible scenario finished (drives on scenarios "
        "infeasible by design, such as tight-hairpin, are listed but expected not to finish); "
        "1 when a feasible drive did not finish (each one and why on stderr; the report is "
        "written all the same); 2 for a bad config or an unknown name."
    )


def cmd_compare(args: argparse.Namespace) -> int:
    """Run ``leafgate compare`` from parsed arguments (see :func:`add_arguments`).

    :raises ~leafgate.errors.LeafgateError: for a bad config or an unknown name (the CLI
        prints it)
    """
    cfg = load_config(getattr(args, "config", None))
    out = Path(args.out)
    report = run_compare(
        cfg,
        out,
        scenarios=getattr(args, "scenario", None),
        plants=getattr(args, "plant", None),
        controllers=getattr(args, "controller", None),
        direct=bool(getattr(args, "direct", False)),
        workers=getattr(args, "workers", None),
        plots=not getattr(args, "no_plots", False),
    )
    print(f"{'scenario':<20} the most accurate controller (smallest max lateral error) per plant")
    for s, per_plant in report["best_lateral_max"].items():
        print(f"{s:<20} " + "  ".join(f"{p}: {c}" for p, c in per_plant.items()))
    unfinished = report["not_finished"]
    expected = [d for d in unfinished if not d["feasible"]]
    failed = [d for d in unfinished if d["feasible"]]
    runs = len(report["runs"])
    print(
        f"{runs} drives in {report['wall_time_s']:.1f} s: {runs - len(unfinished)} finished, "
        f"{len(expected)} did not finish as expected (infeasible scenarios), "
        f"{len(failed)} feasible drives did not finish; "
        f"wrote {out / 'report.md'} and {out / 'report.json'}"
    )
    if expected:
        print(f"{len(expected)} drives did not finish, as expected (infeasible by design):")
        for line in _unfinished_lines(expected):
            print(line)
    if failed:
        print(
            f"leafgate compare: {len(failed)} of {runs} drives on feasible scenarios did not "
            "finish (exit 1):",
            file=sys.stderr,
        )
        for line in _unfinished_lines(failed):
            print(line, file=sys.stderr)
        return 1
    return 0


def _unfinished_lines(drives: list[dict[str, Any]]) -> list[str]:
    """The drives that did not finish, grouped by scenario: ``controller × plant: reason``."""
    lines: list[str] = []
    scenario = None
    for d in drives:
        if d["scenario"] != scenario:
            scenario = d["scenario"]
            lines.append(f"  {scenario}:")
        lines.append(f"    {d['controller']} × {d['plant']} plant: {d['reason']}")
    return lines


__all__ = [
    "CONTROLLERS",
    "PLANTS",
    "add_arguments",
    "cmd_compare",
    "drive_config",
    "run_compare",
]
