"""Path- and speed-tracking controllers: the paper's MPC, Pure Pursuit and Stanley.

>>> from leafgate.config import VehicleConfig
>>> from leafgate.config.control import ControllerConfig
>>> ctrl = make_controller(ControllerConfig(), VehicleConfig(), period=0.02)
>>> ctrl.period
0.02
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from leafgate.config import VehicleConfig
from leafgate.config.control import ControllerConfig
from leafgate.control.base import Controller
from leafgate.errors import ConfigError

if TYPE_CHECKING:
    from leafgate.control.reference import PathRules

__all__ = ["Controller", "make_controller", "plan_rules"]


def plan_rules(cfg: ControllerConfig, vehicle: VehicleConfig) -> PathRules:
    """How the configured controller builds a plan's reference (its creep speed, and the
    tightest turn it steers: ``wheelbase / tan(steer_max)``); the daemon builds each plan's
    reference with them as the plan arrives, for the controller to take."""
    from leafgate.control.reference import PathRules

    return PathRules.of(cfg.section, vehicle.wheelbase)


def _check_inside_vehicle(ctrl: ControllerConfig, vehicle: VehicleConfig) -> None:
    """The configured controller's limits must lie inside the vehicle's: the gate is the last
    word."""
    cfg, section = ctrl.section, ctrl.section_name
    if cfg.steer_max > vehicle.max_steer_angle:
        raise ConfigError(
            f"controller.{section}.steer_max ({math.degrees(cfg.steer_max):.1f}°) exceeds "
            f"vehicle.max_steer_angle ({math.degrees(vehicle.max_steer_angle):.1f}°)"
        )
    if cfg.accel_max > vehicle.max_accel:
        raise ConfigError(
            f"controller.{section}.accel_max ({cfg.accel_max} m/s²) exceeds vehicle.max_accel "
            f"({vehicle.max_accel} m/s²)"
        )
    if cfg.accel_min < vehicle.min_accel:
        raise ConfigError(
            f"controller.{section}.accel_min ({cfg.accel_min} m/s²) is below vehicle.min_accel "
            f"({vehicle.min_accel} m/s²)"
        )


def make_controller(cfg: ControllerConfig, vehicle: VehicleConfig, period: float) -> Controller:
    """Build the configured controller.

    :param cfg: the ``controller:`` section
    :param vehicle: the vehicle section (wheelbase, limits)
    :param period: s, the control tick
    :raises ConfigError: for an unknown kind, limits outside the vehicle's, or a bad period
    """
    if not (math.isfinite(period) and period > 0.0):
        raise ConfigError(f"control period must be a positive number of seconds, got {period!r}")
    if cfg.kind == "mpc":
        from leafgate.control.mpc import MpcController  # algorithms load only when built

        _check_inside_vehicle(cfg, vehicle)
        return MpcController(cfg.mpc, vehicle, period)
    from leafgate.control.baselines import PurePursuit, Stanley

    if cfg.kind == "pure-pursuit":
        _check_inside_vehicle(cfg, vehicle)
        return PurePursuit(cfg.pure_pursuit, vehicle, period)
    if cfg.kind == "stanley":
        _check_inside_vehicle(cfg, vehicle)
        return Stanley(cfg.stanley, vehicle, period)
    raise ConfigError(
        f"controller.kind: {cfg.kind!r} is not a controller (use mpc, pure-pursuit or stanley)"
    )
