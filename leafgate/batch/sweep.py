"""Sweep files of ``leafgate batch sim``: routes × plants × controllers × seeded disturbances.

A sweep file is YAML (``config/sweep.yaml`` is the example)::

    name: example            # names the cases' output folders in the command lines
    seed: 2026               # case i has seed `seed + i`: the seed of its draws and its noise
    samples: 2               # seeded cases per route × plant × controller
    routes: [s-curve, slalom, routes/loop.csv]   # built-in scenarios or trajectory files
    plants: [kinematic, steer-lag]               # kinematic, steer-lag, dynamic
    controllers: [mpc, stanley]                  # mpc, mpc-steer, pure-pursuit, stanley
    config: null             # base configuration file (default: the embedded one)
    set:                     # the same dotted keys as `leafgate sim --set`, for every case
      controller.mpc.prediction_horizon: 30
    disturbances:            # dotted key: [low, high], drawn uniformly per case from its seed
      sim.localization.position_noise: [0.0, 0.05]   # m; the noise itself follows --seed
      sim.plant.steer_bias_deg: [-0.5, 0.5]          # deg, actuator bias
      sim.start_lateral_offset: [-0.3, 0.3]          # m, within gateway.engage.max_distance
    thresholds:              # metric: upper bound, or the required true/false
      lateral_error_max_m: 0.5
      finished: true
      exit_status: 0         # the default: `leafgate sim` exits 1 when the drive did not
                             # finish or hit something (1 accepts such cases)
    timeout_s: 300           # a case running longer is recorded as failed
    max_cases: 100000        # the most cases the sweep may expand to (default 100,000)

Each case becomes one ``leafgate sim`` command line: ``--scenario`` (or ``--trajectory``),
``--controller``, ``--plant``, ``--seed`` and one ``--set`` per setting and drawn disturbance.
The batch runs exactly that command line, so the line in the results reproduces the case alone.
Files named in the sweep (routes, config) are relative to the sweep file.
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from leafgate.batch.results import threshold_error
from leafgate.config import load_yaml, parse_overrides
from leafgate.errors import ConfigError
from leafgate.settings import LeafgateConfig, load_config
from leafgate.sim.compare import CONTROLLERS, PLANTS
from leafgate.sim.scenarios import SCENARIOS

__all__ = ["Case", "Sweep", "expand", "load_sweep"]

_KEYS = (
    "name",
    "seed",
    "samples",
    "routes",
    "plants",
    "controllers",
    "config",
    "set",
    "disturbances",
    "thresholds",
    "timeout_s",
    "max_cases",
)
#: The most cases a sweep expands to unless its ``max_cases`` says more: a typo such as
#: ``samples: 1000000000`` is refused when the file is read, not found after minutes of
#: expanding (each case holds its command line: about 1 kB). 100,000 is the size of run the
#: README's cluster estimate is for.
MAX_CASES = 100_000
#: Disturbances that move the start pose: they must stay inside the gateway's engage envelope.
_ENVELOPE = {
    "sim.start_lateral_offset": ("max_distance", "m"),
    "sim.start_heading_offset": ("max_heading_error", "rad"),
}
#: The bound on a case's ``exit_status`` when the sweep gives none: 0, as the case run alone.
DEFAULT_EXIT_STATUS = 0.0
_DRAW_STREAM = 1  # the draws' random stream, apart from the noise's (same seed, other stream)


@dataclass(frozen=True)
class Case:
    """One ``leafgate sim`` run of a sweep."""

    case_id: str
    route: str
    plant: str
    controller: str
    seed: int
    argv: tuple[str, ...]  # the `leafgate sim` arguments (without --out and --no-plots)
    out_name: str  # the --out folder of the printed command line

    @property
    def command(self) -> str:
        """The command line that runs this case alone."""
        return shlex.join(["leafgate", "sim", *self.argv, "--out", self.out_name])


@dataclass(frozen=True)
class Sweep:
    path: str
    name: str = "sweep"
    seed: int = 0
    samples: int = 1
    routes: tuple[str, ...] = ()
    plants: tuple[str, ...] = ("kinematic",)
    controllers: tuple[str, ...] = ("mpc",)
    config: str | None = None  # absolute path of the base configuration
    settings: dict[str, Any] = field(default_factory=dict)
    disturbances: dict[str, tuple[float, float]] = field(default_factory=dict)
    thresholds: dict[str, float | bool] = field(default_factory=dict)
    timeout_s: float | None = None
    max_cases: int = MAX_CASES

    @property
    def size(self) -> int:
        return len(self.routes) * len(self.plants) * len(self.controllers) * self.samples


def _names(path: str, key: str, value: Any, known: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{path}: {key}: expected a non-empty list")
    for item in value:
        if item not in known:
            raise ConfigError(f"{path}: {key}: unknown {item!r} (known: {', '.join(known)})")
    return tuple(value)


def _number(path: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{path}: {key}: expected a finite number, got {value!r}")
    return float(value)


def _value_text(value: Any) -> str:
    """A --set value as YAML text that reads back as the same value."""
    if isinstance(value, float):
        return _float_text(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, str)):
        return str(value)
    import json

    return json.dumps(value)  # lists and mappings: JSON is YAML


def _float_text(value: float) -> str:
    """Six decimals, no exponent (YAML 1.1 reads ``1e-06`` as a string)."""
    text = f"{value:.6f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    return "0.0" if text == "-0.0" else text


def load_sweep(path: str | Path) -> Sweep:
    """Read and check a sweep file.

    :raises ConfigError: one line naming the file and the key
    """
    path = Path(path)
    data = load_yaml(path)
    where = str(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of {', '.join(_KEYS)}")
    for key in data:
        if key not in _KEYS:
            raise ConfigError(f"{where}: {key}: unknown key (known: {', '.join(_KEYS)})")
    base_dir = path.parent
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not name or "/" in name:
        raise ConfigError(f"{where}: name: expected a word (it names output folders)")
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{where}: seed: expected an integer >= 0, got {seed!r}")
    samples = data.get("samples", 1)
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ConfigError(f"{where}: samples: expected an integer >= 1, got {samples!r}")
    routes_raw = data.get("routes")
    if isinstance(routes_raw, str):
        routes_raw = [routes_raw]
    if not isinstance(routes_raw, list) or not routes_raw:
        raise ConfigError(f"{where}: routes: expected a non-empty list of scenarios or files")
    routes: list[str] = []
    for route in routes_raw:
        if not isinstance(route, str) or not route:
            raise ConfigError(f"{where}: routes: expected names or file paths, got {route!r}")
        if route in SCENARIOS:
            routes.append(route)
            continue
        file = base_dir / route
        if Path(route).suffix.lower() not in (".csv", ".yaml", ".yml"):
            raise ConfigError(
                f"{where}: routes: {route!r} is neither a scenario "
                f"({', '.join(SCENARIOS)}) nor a .csv/.yaml trajectory file"
            )
        if not file.is_file():
            raise ConfigError(f"{where}: routes: {route!r}: no such file ({file})")
        routes.append(str(file.resolve()))
    plants = _names(where, "plants", data.get("plants", ["kinematic"]), PLANTS)
    controllers = _names(where, "controllers", data.get("controllers", ["mpc"]), list(CONTROLLERS))
    config = data.get("config")
    if config is not None:
        if not isinstance(config, str) or not (base_dir / config).is_file():
            raise ConfigError(f"{where}: config: no such file {config!r}")
        config = str((base_dir / config).resolve())
    settings = data.get("set") or {}
    if not isinstance(settings, dict):
        raise ConfigError(f"{where}: set: expected a mapping of dotted keys to values")
    settings = {str(k): v for k, v in settings.items()}
    disturbances: dict[str, tuple[float, float]] = {}
    raw = data.get("disturbances") or {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: disturbances: expected a mapping of dotted keys to ranges")
    for key, value in raw.items():
        dotted = f"disturbances.{key}"
        if isinstance(value, list) and len(value) == 2:
            lo, hi = (_number(where, dotted, v) for v in value)
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            lo = hi = _number(where, dotted, value)
        else:
            raise ConfigError(f"{where}: {dotted}: expected [low, high] or a number")
        if lo > hi:
            raise ConfigError(f"{where}: {dotted}: low {lo:g} is above high {hi:g}")
        disturbances[str(key)] = (lo, hi)
    thresholds: dict[str, float | bool] = {}
    raw = data.get("thresholds") or {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: thresholds: expected a mapping of metric names to bounds")
    for key, value in raw.items():
        thresholds[str(key)] = (
            value if isinstance(value, bool) else _number(where, f"thresholds.{key}", value)
        )
    error = threshold_error(thresholds, where)  # a typo is refused before any case runs
    if error is not None:
        raise ConfigError(error)
    # a case's own command line is a verdict: `leafgate sim` exits 1 when the drive did not
    # finish or hit something, and the batch does not call that case within its thresholds
    # unless the file says so (`exit_status: 1`)
    thresholds.setdefault("exit_status", DEFAULT_EXIT_STATUS)
    timeout = data.get("timeout_s")
    if timeout is not None and not _number(where, "timeout_s", timeout) > 0:
        raise ConfigError(f"{where}: timeout_s: expected a positive number of seconds")
    max_cases = data.get("max_cases", MAX_CASES)
    if isinstance(max_cases, bool) or not isinstance(max_cases, int) or max_cases < 1:
        raise ConfigError(f"{where}: max_cases: expected an integer >= 1, got {max_cases!r}")
    sweep = Sweep(
        path=where,
        name=name,
        seed=seed,
        samples=samples,
        routes=tuple(routes),
        plants=plants,
        controllers=controllers,
        config=config,
        settings=settings,
        disturbances=disturbances,
        thresholds=thresholds,
        timeout_s=None if timeout is None else float(timeout),
        max_cases=max_cases,
    )
    if sweep.size > max_cases:  # before any case is made: expanding would take minutes and memory
        raise ConfigError(
            f"{where}: samples: {samples} makes {sweep.size} cases ({len(sweep.routes)} routes × "
            f"{len(sweep.plants)} plants × {len(sweep.controllers)} controllers × {samples} "
            f"samples), above the bound of {max_cases} (max_cases: raise it in the sweep file)"
        )
    _check_keys(sweep)
    return sweep


def _check_keys(sweep: Sweep) -> None:
    """Every setting and disturbance key is a config key taking the values given, checked as
    ``leafgate sim --set`` checks them."""
    sections: list[tuple[str, dict[str, Any]]] = [("set", sweep.settings)]
    for end in (0, 1):
        sections.append(
            ("disturbances", {k: bounds[end] for k, bounds in sweep.disturbances.items()})
        )
    for section, values in sections:
        for key, value in values.items():
            try:
                load_config(sweep.config, parse_overrides([f"{key}={_value_text(value)}"]))
            except ConfigError as exc:
                raise ConfigError(f"{sweep.path}: {section}: {exc}") from None
    settings = parse_overrides(f"{k}={_value_text(v)}" for k, v in sweep.settings.items())
    _check_envelope(sweep, load_config(sweep.config, settings))


def _check_envelope(sweep: Sweep, base: LeafgateConfig) -> None:
    engage = base.gateway.engage
    for key, (limit_name, unit) in _ENVELOPE.items():
        if key not in sweep.disturbances:
            continue
        limit = getattr(engage, limit_name)
        lo, hi = sweep.disturbances[key]
        if max(abs(lo), abs(hi)) >= limit:
            raise ConfigError(
                f"{sweep.path}: disturbances.{key}: [{lo:g}, {hi:g}] {unit} leaves the engage "
                f"envelope (gateway.engage.{limit_name} = {limit:g} {unit})"
            )


def expand(sweep: Sweep) -> list[Case]:
    """The sweep's cases, in a fixed order; case ``i`` has seed ``sweep.seed + i``."""
    cases: list[Case] = []
    width = max(4, len(str(sweep.size - 1)))
    index = 0
    for route in sweep.routes:
        for plant in sweep.plants:
            for controller in sweep.controllers:
                for _ in range(sweep.samples):
                    cases.append(_case(sweep, index, width, route, plant, controller))
                    index += 1
    return cases


def _case(sweep: Sweep, index: int, width: int, route: str, plant: str, controller: str) -> Case:
    seed = sweep.seed + index
    argv: list[str] = []
    if sweep.config is not None:
        argv += ["--config", sweep.config]
    argv += ["--scenario", route] if route in SCENARIOS else ["--trajectory", route]
    # `sim --controller` takes compare's names (mpc-steer: the MPC with the lag model)
    argv += ["--controller", controller, "--plant", plant, "--seed", str(seed)]
    settings = dict(sweep.settings)
    rng = np.random.default_rng([seed, _DRAW_STREAM])
    for key, (lo, hi) in sweep.disturbances.items():
        settings[key] = float(rng.uniform(lo, hi)) if hi > lo else lo
    for key, value in settings.items():
        argv += ["--set", f"{key}={_value_text(value)}"]
    case_id = f"{index:0{width}d}"
    return Case(
        case_id=case_id,
        route=route if route in SCENARIOS else Path(route).name,
        plant=plant,
        controller=controller,
        seed=seed,
        argv=tuple(argv),
        out_name=f"{sweep.name}-{case_id}",
    )
