"""Sim metrics of every built-in scenario, to check that a change to the loop changes nothing.

    .venv/bin/python tools/sim_metrics.py --out before.json            # on the old code
    .venv/bin/python tools/sim_metrics.py --out after.json --against before.json

Runs :func:`leafgate.sim.runner.run` (the full simulated loop, ``config/sim.yaml``) for every
scenario in :data:`leafgate.sim.scenarios.SCENARIOS` on the kinematic and steer-lag plants with
every controller of ``leafgate compare`` and the MPC without the gateway
(:func:`~leafgate.sim.runner.run_direct`, the paper's check), plus the s-curve with each injection, each vehicle
profile, localization noise and latency, and a rolling-window plan. Writes each drive's metrics
(without :data:`~leafgate.sim.runner.WALL_CLOCK_METRICS`), a digest of its per-tick series and
its timeline. ``--against`` compares numbers to ``--tolerance`` (1e-9) and prints a JSON summary
naming every drive and key that differs; the exit status is 1 when any does.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import leafgate
from leafgate.errors import LeafgateError
from leafgate.settings import LeafgateConfig, load_config, with_profile
from leafgate.sim.compare import CONTROLLERS, drive_config
from leafgate.sim.runner import (
    INJECTION_KINDS,
    WALL_CLOCK_METRICS,
    Injection,
    RollingWindow,
    run,
    run_direct,
)
from leafgate.sim.scenarios import SCENARIOS, get_scenario

PLANTS = ("kinematic", "steer-lag")
CONFIG = Path(__file__).resolve().parent.parent / "config" / "sim.yaml"


def _drives(base: LeafgateConfig) -> list[tuple[str, LeafgateConfig, str, dict[str, Any]]]:
    """(name, config, scenario, run() keyword arguments) of every drive compared."""
    out = []
    for scenario in SCENARIOS:
        for plant in PLANTS:
            for controller in CONTROLLERS:
                cfg = drive_config(base, controller, plant)
                out.append((f"{scenario}/{plant}/{controller}", cfg, scenario, {}))
            direct = drive_config(base, "mpc", plant)
            out.append((f"{scenario}/{plant}/mpc direct", direct, scenario, {"direct": True}))
    mpc = drive_config(base, "mpc", "kinematic")
    for kind in INJECTION_KINDS:
        injection = Injection(kind, 6.0, 1.0 if kind != "report-dropout" else 0.3)
        out.append((f"s-curve/inject {kind}", mpc, "s-curve", {"injections": (injection,)}))
    for profile in ("leaf-ze1-lkas", "sze-hlc"):
        # drive_config's copy has no explicit keys: the profile may set the MPC mode
        out.append((f"s-curve/profile {profile}", with_profile(mpc, profile), "s-curve", {}))
    loc = dataclasses.replace(
        mpc.sim.localization, position_noise=0.05, heading_noise=0.01, latency=0.04
    )
    noisy = dataclasses.replace(mpc, sim=dataclasses.replace(mpc.sim, localization=loc))
    out.append(("s-curve/noisy localization", noisy, "s-curve", {}))
    for scenario in ("s-curve", "parallel-park"):
        kwargs = {"window": RollingWindow(12.0, 0.5)}
        out.append((f"{scenario}/rolling window", mpc, scenario, kwargs))
    return out


def _digest(result: Any) -> str:
    h = hashlib.sha256()
    for key in sorted(result.series):
        h.update(key.encode())
        h.update(result.series[key].tobytes())
    h.update(json.dumps(result.states).encode())
    return h.hexdigest()[:16]


def _clean(value: Any) -> Any:
    """JSON-safe (NaN/inf as strings, so they survive the round trip and compare equal)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def _differences(old: Any, new: Any, where: str, tol: float) -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new)):
            if key not in old or key not in new:
                out.append(f"{where}.{key}: only {'before' if key in old else 'after'}")
            else:
                out += _differences(old[key], new[key], f"{where}.{key}", tol)
        return out
    if isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            return [f"{where}: {len(old)} items before, {len(new)} after"]
        return [
            d
            for i, (a, b) in enumerate(zip(old, new, strict=True))
            for d in _differences(a, b, f"{where}[{i}]", tol)
        ]
    numbers = (int, float)
    if isinstance(old, numbers) and isinstance(new, numbers) and not isinstance(old, bool):
        if abs(old - new) <= tol:
            return []
    elif old == new:
        return []
    return [f"{where}: {old!r} before, {new!r} after"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="JSON file to write the drives' metrics to")
    parser.add_argument("--against", help="JSON file of an earlier run to compare with")
    parser.add_argument("--tolerance", type=float, default=1e-9)
    parser.add_argument("--only", help="run only drives whose name contains this text")
    args = parser.parse_args()
    base = load_config(str(CONFIG))
    drives: dict[str, Any] = {}
    wall0 = time.perf_counter()
    for name, cfg, scenario, kwargs in _drives(base):
        if args.only and args.only not in name:
            continue
        try:
            if kwargs.get("direct"):
                result = run_direct(cfg, get_scenario(scenario))
            else:
                result = run(cfg, get_scenario(scenario), **kwargs)
        except LeafgateError as exc:
            drives[name] = {"error": str(exc)}
            continue
        metrics = {k: v for k, v in result.metrics.items() if k not in WALL_CLOCK_METRICS}
        drives[name] = _clean(
            {"metrics": metrics, "series": _digest(result), "timeline": list(result.timeline)}
        )
    Path(args.out).write_text(json.dumps(drives, indent=1, sort_keys=True), encoding="utf-8")
    summary: dict[str, Any] = {
        "drives": len(drives),
        "wall_time_s": round(time.perf_counter() - wall0, 1),
        "out": args.out,
        "package": str(Path(leafgate.__file__).parent),  # which code ran
    }
    status = 0
    if args.against:
        before = json.loads(Path(args.against).read_text(encoding="utf-8"))
        names = [n for n in before if n in drives]
        diffs = {n: _differences(before[n], drives[n], n, args.tolerance) for n in names}
        diffs = {n: d for n, d in diffs.items() if d}
        summary.update(
            against=args.against,
            compared=len(names),
            missing=sorted(set(before) ^ set(drives)) if not args.only else [],
            tolerance=args.tolerance,
            differing=diffs,
        )
        status = 1 if diffs or summary["missing"] else 0
    print(json.dumps(summary, indent=1))
    return status


if __name__ == "__main__":
    sys.exit(main())
