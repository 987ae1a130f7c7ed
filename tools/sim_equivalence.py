"""Does a refactoring change what the simulator drives? Dump and compare per-tick series.

``dump`` drives every built-in scenario (or ``--scenarios``) through the whole gateway
(``leafgate.sim.runner.run``) and directly (``run_direct``), on the kinematic and steer-lag
plants with each plant's default model, and saves every per-tick series of each drive to an
``.npz`` file. ``compare`` reads two such files and prints JSON: how many series were compared,
the largest absolute difference, and the series that differ by more than ``--tolerance``.

Before and after a change (the code under test is whatever ``leafgate`` imports, so point
``PYTHONPATH`` at a checkout of the old commit for the first dump)::

    PYTHONPATH=/tmp/old .venv/bin/python tools/sim_equivalence.py dump /tmp/before.npz
    .venv/bin/python tools/sim_equivalence.py dump /tmp/after.npz
    .venv/bin/python tools/sim_equivalence.py compare /tmp/before.npz /tmp/after.npz

Exit status of ``compare``: 0 when every series agrees within the tolerance, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from leafgate.settings import load_config
from leafgate.sim.runner import default_model, run, run_direct
from leafgate.sim.scenarios import SCENARIOS, get_scenario

PLANTS = ("kinematic", "steer-lag")


def dump(out: str, names: list[str]) -> None:
    data: dict[str, np.ndarray] = {}
    for plant in PLANTS:
        cfg = load_config(
            None, {"sim.plant.kind": plant, "controller.mpc.model": default_model(plant)}
        )
        for name in names:
            for label, drive in (("run", run), ("direct", run_direct)):
                result = drive(cfg, get_scenario(name))
                for key, series in result.series.items():
                    data[f"{plant}/{name}/{label}/{key}"] = np.asarray(series, dtype=np.float64)
    np.savez(out, **data)  # type: ignore[arg-type]
    print(json.dumps({"file": out, "series": len(data)}))


def compare(a: str, b: str, tolerance: float) -> int:
    before, after = np.load(a), np.load(b)
    only = sorted(set(before.files) ^ set(after.files))
    worst, differ = 0.0, []
    for key in sorted(set(before.files) & set(after.files)):
        x, y = before[key], after[key]
        if x.shape != y.shape:
            differ.append({"series": key, "shape": [list(x.shape), list(y.shape)]})
            continue
        d = float(np.max(np.abs(x - y))) if x.size else 0.0
        worst = max(worst, d)
        if d > tolerance:
            differ.append({"series": key, "max_abs_difference": d})
    report = {
        "compared": len(set(before.files) & set(after.files)),
        "only_in_one": only,
        "max_abs_difference": worst,
        "tolerance": tolerance,
        "differ": differ,
    }
    print(json.dumps(report, indent=1))
    return 0 if not differ and not only else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_dump = sub.add_parser("dump", help="drive the scenarios, save their series")
    p_dump.add_argument("out", help="the .npz file to write")
    p_dump.add_argument("--scenarios", help="comma-separated subset (default: all)")
    p_cmp = sub.add_parser("compare", help="compare two dumps")
    p_cmp.add_argument("before")
    p_cmp.add_argument("after")
    p_cmp.add_argument("--tolerance", type=float, default=1e-9)
    args = parser.parse_args()
    if args.command == "dump":
        names = args.scenarios.split(",") if args.scenarios else list(SCENARIOS)
        unknown = [n for n in names if n not in SCENARIOS]
        if unknown:
            print(f"unknown scenario(s): {', '.join(unknown)}", file=sys.stderr)
            return 2
        dump(args.out, names)
        return 0
    return compare(args.before, args.after, args.tolerance)


if __name__ == "__main__":
    sys.exit(main())
