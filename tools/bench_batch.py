"""Benchmark of ``leafgate batch sim``: the same short cases in a plain loop and on Dask.

Builds a sweep of ``--cases`` seeded cases on a short generated route (a 1.5 m curve:
about 8 s of simulated driving each), then runs them

1. on a local Dask cluster with each worker count of ``--workers`` (default 2, then 1);
2. in a plain loop in this process (the same task function, no Dask): the per-case cost.

Prints JSON: wall times, per-case cost, the engine's per-case overhead and its ratio to the
plain loop (1 worker), speed-up and efficiency (speed-up ÷ workers, against the 1-worker run),
and whether every run gave the same numbers (wall-clock metrics aside) — checked, not assumed.
The machine's load average is included: on a shared machine the figures move with it.

    .venv/bin/python tools/bench_batch.py --cases 1000 > bench-batch.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from leafgate.batch.engine import EngineRun, run_plain, run_tasks
from leafgate.batch.sweep import expand, load_sweep
from leafgate.batch.tasks import sim_case
from leafgate.sim.runner import WALL_CLOCK_METRICS

ROUTE_POINTS = 4  # waypoints 0.5 m apart: a 1.5 m route (about 8 s of simulated driving)


def write_route(path: Path) -> None:
    """A gentle 1.5 m curve from rest to rest (x, y, heading, speed)."""
    rows = ["x,y,heading,speed"]
    last = ROUTE_POINTS - 1
    for i in range(ROUTE_POINTS):
        x = 0.5 * i
        speed = 0.0 if i == last else min(0.3 + 0.2 * i, 0.8, 0.3 + 0.2 * (last - i))
        rows.append(f"{x:.3f},{0.03 * x * x:.5f},{math.atan(0.06 * x):.6f},{speed:.3f}")
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def write_sweep(folder: Path, cases: int) -> Path:
    route = folder / "short.csv"
    write_route(route)
    samples = max(1, cases // 4)
    path = folder / "bench-sweep.yaml"
    path.write_text(
        f"""name: bench
seed: 1
samples: {samples}
routes: [{route.name}]
plants: [kinematic, steer-lag]
controllers: [mpc, stanley]
disturbances:
  sim.localization.position_noise: [0.0, 0.02]
  sim.localization.latency: [0.0, 0.05]
  sim.plant.steer_bias_deg: [-0.3, 0.3]
  sim.plant.wheelbase_error: [-0.05, 0.05]
  sim.start_lateral_offset: [-0.1, 0.1]
""",
        encoding="utf-8",
    )
    return path


def numbers(run: EngineRun) -> dict[str, dict[str, Any]]:
    skip = WALL_CLOCK_METRICS | {"case_wall_s"}
    return {k: {m: v for m, v in row.items() if m not in skip} for k, row in run.rows.items()}


def _done(name: str, run: EngineRun) -> None:
    """Each run's wall time as soon as it is known (stderr), in case a later one is cut short."""
    print(f"  {name}: {run.wall_s:.1f} s, load average {os.getloadavg()}", file=sys.stderr)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=1000, help="cases (a multiple of 4)")
    parser.add_argument("--workers", default="1,2", help="local cluster sizes to run, e.g. 1,2")
    parser.add_argument("--no-plain", action="store_true", help="skip the plain loop")
    args = parser.parse_args()
    workers = [int(w) for w in args.workers.split(",") if w]
    with tempfile.TemporaryDirectory(prefix="leafgate-bench-batch-") as tmp:
        cases = expand(load_sweep(write_sweep(Path(tmp), args.cases)))
        tasks = {c.case_id: (list(c.argv),) for c in cases}
        out: dict[str, Any] = {
            "cases": len(cases),
            "route": "1.5 m curve from a trajectory file",
            "cpu_count": os.cpu_count(),
            "load_average_before": os.getloadavg(),
            "runs": {},
        }
        runs: dict[str, EngineRun] = {}
        for n in sorted(workers, reverse=True):
            print(f"local cluster, {n} workers: {len(cases)} cases …", file=sys.stderr)
            runs[f"dask-{n}"] = run_tasks(sim_case, tasks, workers=n)
            _done(f"dask-{n}", runs[f"dask-{n}"])
        if not args.no_plain:
            print(f"plain loop: {len(cases)} cases …", file=sys.stderr)
            runs["plain"] = run_plain(sim_case, tasks)
            _done("plain", runs["plain"])
        out["load_average_after"] = os.getloadavg()
    for name, run in runs.items():
        failed = sum(1 for r in run.rows.values() if r.get("status") != "ok")
        out["runs"][name] = {
            "workers": run.workers,
            "wall_s": round(run.wall_s, 2),
            "per_case_s": round(run.wall_s / len(cases), 4),
            "failed_cases": failed,
        }
    reference = next(iter(runs.values()))
    out["identical_numbers_in_every_run"] = all(
        numbers(run) == numbers(reference) for run in runs.values()
    )
    plain, one = runs.get("plain"), runs.get("dask-1")
    if plain is not None and one is not None:
        out["overhead_per_case_s"] = round((one.wall_s - plain.wall_s) / len(cases), 4)
        out["overhead_ratio_1_worker_vs_plain"] = round(one.wall_s / plain.wall_s, 3)
    if one is not None:
        for n in workers:
            if n > 1:
                speedup = one.wall_s / runs[f"dask-{n}"].wall_s
                out[f"speedup_{n}_workers"] = round(speedup, 3)
                out[f"efficiency_{n}_workers"] = round(speedup / n, 3)
    if plain is not None:
        case_s = plain.wall_s / len(cases)
        out["per_case_cost_s"] = round(case_s, 4)
        overhead = out.get("overhead_per_case_s", 0.0)
        # 100,000 cases on 64 cores, one worker process each, at this machine's per-case cost
        # plus the measured engine overhead per case:
        ideal = 100_000 * (case_s + max(overhead, 0.0)) / 64
        out["estimate_100k_cases_64_cores_min"] = round(ideal / 60, 1)
        efficiency = out.get("efficiency_2_workers")  # what this machine measured, if it did
        if efficiency:
            out["estimate_100k_cases_64_cores_at_measured_efficiency_min"] = round(
                ideal / efficiency / 60, 1
            )
    print(json.dumps(out, indent=2))
    return 0 if out["identical_numbers_in_every_run"] else 1


if __name__ == "__main__":
    sys.exit(main())
