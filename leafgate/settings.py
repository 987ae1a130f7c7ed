"""The whole configuration of one deployment, composed of the parts' sections."""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from leafgate.can.profile import PROFILE_NAMES, Profile, SteerRateTable, load_profile
from leafgate.config import _UNIT_SUFFIXES, VehicleConfig, apply_overrides, from_mapping, load_yaml
from leafgate.config.can import CanConfig
from leafgate.config.control import ControllerConfig
from leafgate.config.gateway import GatewayConfig, SafetyConfig
from leafgate.config.recording import RecordingConfig
from leafgate.config.sim import SimConfig
from leafgate.config.transport import ZenohConfig
from leafgate.errors import ConfigError
from leafgate.messages import LongMode


@dataclass(frozen=True)
class LeafgateConfig:
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    gateway: GatewayConfig = field(default_factory=GatewayConfig)
    can: CanConfig = field(default_factory=CanConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    # Not read from a file: the dotted keys the user set explicitly and where (a file name or
    # "command line"), which a profile may not overrule; and what the profile changed, one
    # line each (``check-config`` prints them, the daemon logs them).
    explicit: Mapping[str, str] = field(default_factory=dict, init=False, compare=False, repr=False)
    adjustments: tuple[str, ...] = field(default=(), init=False, compare=False, repr=False)
    # Not read from a file either: where the config came from, for error lines naming it
    # (the file name, "defaults", "… with command-line overrides").
    source: str = field(default="config", init=False, compare=False, repr=False)

    @property
    def profile(self) -> Profile:
        """The vehicle profile (``vehicle.profile``), loaded once per process."""
        return load_profile(self.vehicle.profile, self.vehicle)

    @property
    def long_mode(self) -> LongMode:
        """The longitudinal command the ECU receives: the MPC's mode (paper §II.B)."""
        return LongMode.SPEED if self.controller.mpc.mode == "velocity" else LongMode.ACCELERATION


def load_config(
    path: str | Path | None, overrides: Mapping[str, Any] | None = None
) -> LeafgateConfig:
    """Load a deployment config; ``None`` gives the embedded defaults.

    :param overrides: dotted keys set on top of the file (``leafgate sim --set KEY=VALUE``,
        :func:`~leafgate.config.parse_overrides`), checked like the file's own keys

    The vehicle profile is applied (:func:`apply_profile`).

    :raises ConfigError: naming the file and the key of the first problem
    """
    if path is None and not overrides:
        return _with_source(apply_profile(LeafgateConfig(), "defaults"), "defaults")
    data = {} if path is None else load_yaml(path)
    source = "defaults" if path is None else str(path)
    bench_where = source
    if overrides and "bench" in overrides:
        # `--set bench=N` picks the bench like the file's own `bench:` key (ports derived)
        if not isinstance(data, dict) and data is not None:
            raise ConfigError(f"{source}: the configuration is not a mapping")
        overrides = dict(overrides)
        data = {**(data or {}), "bench": overrides.pop("bench")}
        bench_where = "--set"
    data = apply_bench(data, bench_where, use_env=bench_where != "--set")
    explicit = dict.fromkeys(explicit_keys(data), source)
    file_source = source
    if overrides:
        data = {} if data is None else data
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: the configuration is not a mapping")
        source += " with command-line overrides"
        apply_overrides(data, overrides, source)
        explicit.update(dict.fromkeys(explicit_keys(_nested(overrides)), "command line"))
    cfg = from_mapping(LeafgateConfig, data, source)
    if path is not None:
        # A relative file path named in the config file is found next to it, as the file's
        # author means (not in the daemon's working directory: under systemd that is "/").
        base = Path(path).parent

        def beside(key: str, value: str | None) -> str | None:
            """``value`` found next to the config file, when the file named it."""
            if value is None or explicit.get(key) != file_source:
                return value
            return str(base / Path(value).expanduser())

        can, vehicle, zenoh = cfg.can, cfg.vehicle, cfg.zenoh
        can = dataclasses.replace(
            can,
            auth_key_file=beside("can.auth_key_file", can.auth_key_file),
            dbw_dbc=beside("can.dbw_dbc", can.dbw_dbc),
            car_dbc=beside("can.car_dbc", can.car_dbc),
        )
        if (
            vehicle.profile not in PROFILE_NAMES
            and Path(vehicle.profile).suffix in (".yaml", ".yml")  # a file, not a name
        ):
            vehicle = dataclasses.replace(
                vehicle, profile=beside("vehicle.profile", vehicle.profile) or vehicle.profile
            )
        zenoh = dataclasses.replace(
            zenoh, config_file=beside("zenoh.config_file", zenoh.config_file)
        )
        cfg = dataclasses.replace(cfg, can=can, vehicle=vehicle, zenoh=zenoh)
    return _with_source(apply_profile(cfg, source, explicit), source)


def _with_source(cfg: LeafgateConfig, source: str) -> LeafgateConfig:
    object.__setattr__(cfg, "source", source)  # frozen: set once, here
    return cfg


def _nested(overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted overrides as the nested mapping a file would hold (for :func:`explicit_keys`)."""
    out: dict[str, Any] = {}
    for dotted, value in overrides.items():
        node = out
        *parents, key = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                break
        else:
            node[key] = value
    return out


def explicit_keys(data: Any, prefix: str = "") -> list[str]:
    """The dotted keys a parsed config file sets (unit suffixes removed: ``rate_hz`` stays,
    ``max_steer_angle_deg`` is ``max_steer_angle``)."""
    if not isinstance(data, Mapping):
        return []
    keys = []
    for raw, value in data.items():
        key = str(raw)
        for suffix in _UNIT_SUFFIXES:
            if key.endswith(suffix):
                key = key[: -len(suffix)]
                break
        dotted = f"{prefix}{key}"
        keys.append(dotted)
        keys.extend(explicit_keys(value, dotted + "."))
    return keys


#: environment variable that picks the bench of a config with a ``bench:`` key
BENCH_ENV = "LEAFGATE_BENCH"
BENCH_CAN_PORT = 43113  # udp_multicast port of bench 0; bench N uses this + N
BENCH_ZENOH_PORT = 17447  # Zenoh TCP port (loopback) of bench 0; bench N uses this + N
MAX_BENCH = 999


def bench_ports(bench: int) -> tuple[int, int]:
    """(udp_multicast port, Zenoh port) of bench ``bench``."""
    return BENCH_CAN_PORT + bench, BENCH_ZENOH_PORT + bench


def apply_bench(data: Any, where: str, *, use_env: bool = True) -> Any:
    """Derive a simulation bench's ports from its number, so two benches on a host stay apart.

    A config with ``bench: N`` (``LEAFGATE_BENCH=N`` or ``leafgate --bench N`` overrides N)
    gets ``can.dbw.kwargs.port`` = 43113 + N and ``zenoh.listen`` = ``tcp/127.0.0.1:`` 17447 + N,
    unless the file sets them itself (test harnesses pick free ports that way). A config
    without ``bench:`` is left as written (the car's config names its own buses and endpoints).

    :param use_env: let ``LEAFGATE_BENCH`` override the number (not for ``--set bench=N``,
        the more specific choice)
    :raises ConfigError: a bench that is not a number in 0–999
    """
    if not isinstance(data, dict) or "bench" not in data:
        return data
    data = dict(data)
    value: Any = data.pop("bench")
    source = f"{where}: bench"
    override = os.environ.get(BENCH_ENV, "").strip()
    if override and use_env:
        value, source = override, f"{BENCH_ENV}={override!r}"
    try:
        bench = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: {value!r} is not a bench number (0–{MAX_BENCH})") from None
    if isinstance(value, bool) or not 0 <= bench <= MAX_BENCH:
        raise ConfigError(f"{source}: {value!r} is not a bench number (0–{MAX_BENCH})")
    can_port, zenoh_port = bench_ports(bench)
    can, zenoh = data.get("can") or {}, data.get("zenoh") or {}
    dbw = can.get("dbw") or {} if isinstance(can, dict) else None
    kwargs = dbw.get("kwargs") or {} if isinstance(dbw, dict) else None
    if not (isinstance(kwargs, dict) and isinstance(zenoh, dict)):
        return data  # a section that is no mapping: the loader names it
    can, dbw, kwargs, zenoh = dict(can), dict(dbw), dict(kwargs), dict(zenoh)  # type: ignore[arg-type]
    kwargs.setdefault("port", can_port)  # a port the file gives itself wins
    dbw["kwargs"] = kwargs
    can["dbw"] = dbw
    zenoh.setdefault("listen", [f"tcp/127.0.0.1:{zenoh_port}"])
    data["can"], data["zenoh"] = can, zenoh
    return data


def with_profile(cfg: LeafgateConfig, profile: str) -> LeafgateConfig:
    """``cfg`` for another vehicle profile (``leafgate sim --profile NAME``).

    :raises ConfigError: the profile is unknown or invalid
    """
    vehicle = dataclasses.replace(cfg.vehicle, profile=profile)
    explicit = {k: v for k, v in cfg.explicit.items() if k != "vehicle.profile"}
    out = apply_profile(dataclasses.replace(cfg, vehicle=vehicle), "--profile", explicit)
    return _with_source(out, cfg.source)


def apply_profile(
    cfg: LeafgateConfig, where: str = "config", explicit: Mapping[str, str] | None = None
) -> LeafgateConfig:
    """Fit the gateway to what the vehicle profile says about the car; the rest is unchanged.

    - the loop ticks at least as fast as the fastest command frame (``leaf-ze1-lkas``: 100 Hz);
    - the report watchdogs use the profile's report periods; a vehicle without an ECU state
      report has no system-report watchdog;
    - a speed-only interface (``sze-hlc``) gets the MPC's velocity mode;
    - a profile that cannot request a gear refuses trajectories with reverse segments;
    - the vehicle's own steering-angle rate tables bound the safety gate's, where stricter.

    Every change is listed in the result's ``adjustments``. A change to a value the user set
    explicitly (``explicit``: dotted key → where it was set; by default the config's own) is
    an error instead, naming the file, the key and the profile; only the safety gate's rate
    tables may be tightened by the vehicle's, as a stricter limit honours the user's.

    :raises ConfigError: the profile cannot be loaded, lacks a steering or speed report, or
        contradicts an explicit value
    """
    explicit = dict(cfg.explicit if explicit is None else explicit)
    try:
        profile = load_profile(cfg.vehicle.profile, cfg.vehicle)
    except ConfigError as exc:
        raise ConfigError(f"{where}: vehicle.profile: {exc}") from None
    steer_period = profile.report_period("steer")
    long_period = profile.report_period("long")
    if steer_period is None or long_period is None:
        raise ConfigError(
            f"{profile.where}: a profile needs report frames refreshing steer and long "
            "(the measured steering angle and speed)"
        )
    gw = cfg.gateway
    watchdog = dataclasses.replace(
        gw.watchdog,
        steer_report_period=steer_period,
        long_report_period=long_period,
        system_report_period=profile.report_period("system"),
    )
    caps = profile.capabilities
    engage = dataclasses.replace(gw.engage, allow_reverse=gw.engage.allow_reverse and caps.gear)
    safety = gw.safety
    if profile.steer_rate is not None:
        safety = _bounded_rates(safety, profile.steer_rate)
    gateway = dataclasses.replace(
        gw,
        rate_hz=max(gw.rate_hz, 1.0 / profile.command_period),
        watchdog=watchdog,
        engage=engage,
        safety=safety,
    )
    controller = cfg.controller
    if caps.longitudinal and "acceleration" not in caps.long_modes:
        controller = dataclasses.replace(
            controller, mpc=dataclasses.replace(controller.mpc, mode="velocity")
        )
    out = dataclasses.replace(cfg, gateway=gateway, controller=controller)
    adjustments = _adjustments(cfg, out, profile, explicit)
    object.__setattr__(out, "explicit", explicit)  # frozen: set once, here
    object.__setattr__(out, "adjustments", adjustments)
    return out


def _get(cfg: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _adjustments(
    before: LeafgateConfig, after: LeafgateConfig, profile: Profile, explicit: Mapping[str, str]
) -> tuple[str, ...]:
    """What :func:`apply_profile` changed, one line each; raise on a change of an explicit
    value."""
    name = profile.name
    caps = profile.capabilities
    why = {
        "controller.mpc.mode": "speed-only interface",
        "gateway.rate_hz": f"its fastest command frame is sent every "
        f"{profile.command_period * 1e3:g} ms",
        "gateway.engage.allow_reverse": "it cannot request a gear",
        "gateway.watchdog.steer_report_period": "its report frames' period",
        "gateway.watchdog.long_report_period": "its report frames' period",
        "gateway.watchdog.system_report_period": "its report frames' period"
        if caps.ecu_status
        else "no ECU state report",
    }
    lines = []
    for key, reason in why.items():
        old, new = _get(before, key), _get(after, key)
        if old == new:
            continue
        if key in explicit:
            text = (
                f"{old} is not available with profile {name} ({reason})"
                if key == "controller.mpc.mode"
                else f"{old} contradicts profile {name} ({reason}: it needs {new})"
            )
            raise ConfigError(f"{explicit[key]}: {key}: {text}")
        lines.append(f"{key}: {old} -> {new} (profile {name}: {reason})")
    if before.gateway.safety != after.gateway.safety:
        lines.append(
            f"gateway.safety rate tables lowered to the vehicle's own steering-angle rate "
            f"limits where stricter (profile {name}: {profile.where})"
        )
    return tuple(lines)


def _bounded_rates(safety: SafetyConfig, table: SteerRateTable) -> SafetyConfig:
    """The safety gate's rate tables, lowered to the vehicle's where those are stricter.

    Both are piecewise linear in speed (held flat beyond their ends); their minimum is too,
    with breakpoints at both tables' breakpoints and where the two cross.
    """
    own = np.asarray(safety.rate_speeds, dtype=float)
    car = np.asarray(table.speeds, dtype=float)
    speeds = np.union1d(own, car)

    def lower(mine: tuple[float, ...], theirs: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
        def f(v: np.ndarray) -> np.ndarray:
            return np.minimum(np.interp(v, own, mine), np.interp(v, car, theirs))

        points = list(speeds)
        for a, b in itertools.pairwise(speeds):
            da = np.interp(a, own, mine) - np.interp(a, car, theirs)
            db = np.interp(b, own, mine) - np.interp(b, car, theirs)
            if da * db < 0.0:  # the tables cross inside this segment
                points.append(a + (b - a) * da / (da - db))
        grid = np.unique(np.asarray(points))
        return grid, f(grid)

    up_speeds, up = lower(safety.rate_up, table.windup)
    down_speeds, down = lower(safety.rate_down, table.unwind)
    grid = np.union1d(up_speeds, down_speeds)
    up_all = np.interp(grid, up_speeds, up)
    down_all = np.interp(grid, down_speeds, down)
    return dataclasses.replace(
        safety,
        rate_speeds=tuple(float(v) for v in grid),
        rate_up=tuple(float(v) for v in up_all),
        rate_down=tuple(float(v) for v in down_all),
    )
