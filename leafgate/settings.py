"""The whole configuration of one deployment, composed of the parts' sections."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from leafgate.can.config import CanConfig
from leafgate.can.profile import Profile, SteerRateTable, load_profile
from leafgate.config import VehicleConfig, apply_overrides, from_mapping, load_yaml
from leafgate.control.config import ControllerConfig
from leafgate.errors import ConfigError
from leafgate.gateway.config import GatewayConfig, SafetyConfig
from leafgate.messages import LongMode
from leafgate.replay.config import RecordingConfig
from leafgate.sim.config import SimConfig
from leafgate.transport.config import ZenohConfig


@dataclass(frozen=True)
class LeafgateConfig:
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    gateway: GatewayConfig = field(default_factory=GatewayConfig)
    can: CanConfig = field(default_factory=CanConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)

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
        return apply_profile(LeafgateConfig())
    data = {} if path is None else load_yaml(path)
    source = "defaults" if path is None else str(path)
    if overrides:
        data = {} if data is None else data
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: the configuration is not a mapping")
        source += " with command-line overrides"
        apply_overrides(data, overrides, source)
    return apply_profile(from_mapping(LeafgateConfig, data, source), source)


def with_profile(cfg: LeafgateConfig, profile: str) -> LeafgateConfig:
    """``cfg`` for another vehicle profile (``leafgate sim --profile NAME``).

    :raises ConfigError: the profile is unknown or invalid
    """
    vehicle = dataclasses.replace(cfg.vehicle, profile=profile)
    return apply_profile(dataclasses.replace(cfg, vehicle=vehicle), "--profile")


def apply_profile(cfg: LeafgateConfig, where: str = "config") -> LeafgateConfig:
    """Fit the gateway to what the vehicle profile says about the car; the rest is unchanged.

    - the loop ticks at least as fast as the fastest command frame (``leaf-ze1-lkas``: 100 Hz);
    - the report watchdogs use the profile's report periods; a vehicle without an ECU state
      report has no system-report watchdog;
    - a speed-only interface (``sze-hlc``) gets the MPC's velocity mode;
    - a profile that cannot request a gear refuses trajectories with reverse segments;
    - the vehicle's own steering-angle rate tables bound the safety gate's, where stricter.

    :raises ConfigError: the profile cannot be loaded, or lacks a steering or speed report
    """
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
    return dataclasses.replace(cfg, gateway=gateway, controller=controller)


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
