"""Simulator section of the configuration (``sim:``): plant and simulated ECU."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class PlantConfig:
    kind: Literal["kinematic", "steer-lag", "dynamic"] = "kinematic"
    input_delay: float = 0.02  # s, pure delay on both inputs (the paper's Simulink delay element)
    steer_tau: float = 0.3  # s, first-order steering lag
    steer_dead_time: float = 0.1  # s
    steer_rate_max: float = 0.6  # rad/s, road-wheel angle rate limit of the actuator
    accel_tau: float = 0.2  # s, first-order lag on acceleration


@dataclass(frozen=True)
class EcuConfig:
    cmd_timeout: float = 0.1  # s without a valid command → CMD_TIMEOUT
    timeout_decel: float = 3.0  # m/s², braking to a stop after a timeout
    override_torque: float = 2.5  # N·m on the steering wheel
    override_time: float = 0.1  # s the torque must last


@dataclass(frozen=True)
class SimConfig:
    scenario: str = "s-curve"
    plant: PlantConfig = field(default_factory=PlantConfig)
    ecu: EcuConfig = field(default_factory=EcuConfig)
