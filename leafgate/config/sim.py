"""Simulator section of the configuration (``sim:``): plant and simulated ECU."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from leafgate.config import positive


@dataclass(frozen=True)
class PlantConfig:
    kind: Literal["kinematic", "steer-lag", "dynamic"] = "kinematic"
    input_delay: float = 0.02  # s, pure delay on both inputs (the paper's Simulink delay element)
    steer_tau: float = 0.3  # s, first-order steering lag
    steer_dead_time: float = 0.1  # s
    steer_rate_max: float = 0.6  # rad/s, road-wheel angle rate limit of the actuator
    accel_tau: float = 0.2  # s, first-order lag on acceleration
    # m, the plant's wheelbase minus vehicle.wheelbase: a model error the controller does not know
    wheelbase_error: float = 0.0
    # Dynamic plant only: below blend_speed_low the lateral motion is the kinematic bicycle's,
    # above blend_speed_high the linear-tyre model's, linearly blended between (well-posed at rest).
    blend_speed_low: float = 0.5  # m/s
    blend_speed_high: float = 1.0  # m/s
    # Disturbances (all plants), for offset-free tracking tests
    steer_bias_deg: float = 0.0  # deg, road-wheel misalignment: the wheels point this much
    # further left than the reported (and commanded) angle
    drag_accel: float = 0.0  # m/s², ≤ 0: a constant deceleration opposing the motion (−0.3 is
    # a car rolling on a slight incline or soft ground); it also resists drive-off at rest

    @property
    def steer_bias(self) -> float:
        """Road-wheel misalignment, rad (SI inside; degrees only in the config)."""
        return math.radians(self.steer_bias_deg)

    def __post_init__(self) -> None:
        positive(self, "steer_tau", "steer_rate_max", "accel_tau", "blend_speed_high")
        if not (math.isfinite(self.steer_bias_deg) and abs(self.steer_bias_deg) <= 10.0):
            raise ValueError(
                f"steer_bias_deg must lie in [-10, 10] degrees, got {self.steer_bias_deg!r}"
            )
        if not (math.isfinite(self.drag_accel) and -5.0 <= self.drag_accel <= 0.0):
            raise ValueError(
                "drag_accel opposes the motion: give it as a number in [-5, 0] m/s² "
                f"(e.g. -0.3), got {self.drag_accel!r}"
            )
        for name in ("input_delay", "steer_dead_time", "blend_speed_low"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be zero or positive, got {getattr(self, name)!r}")
        if self.blend_speed_low >= self.blend_speed_high:
            raise ValueError("blend_speed_low must be below blend_speed_high")


@dataclass(frozen=True)
class EcuConfig:
    """The simulated drive-by-wire ECU (docs/can-protocol.md, "ECU semantics")."""

    cmd_timeout: float = 0.1  # s without a valid command → CMD_TIMEOUT
    timeout_decel: float = 3.0  # m/s², braking to a stop after a timeout
    override_torque: float = 2.5  # N·m on the steering wheel
    override_time: float = 0.1  # s the torque must last
    override_brake_pedal: float = 5.0  # % of pedal travel counted as "brake pedal pressed"
    driver_decel: float = 2.0  # m/s², the simulated driver's braking when not engaged
    standstill_speed: float = 0.05  # m/s, below this a gear change is allowed
    default_steer_rate: float = 0.5  # rad/s, road-wheel rate limit when the command sends 0
    speed_kp: float = 1.2  # 1/s, the vehicle's speed controller (speed mode)
    speed_ki: float = 0.3  # 1/s²
    speed_max_accel: float = 1.5  # m/s², speed-mode acceleration limit
    speed_max_decel: float = 3.0  # m/s², speed-mode braking limit
    tick_rate_hz: float = 1000.0  # Hz, real-time step rate of `leafgate sim-ecu`
    # Counter race: more than race_drops command frames dropped for their alive counter within
    # race_window s means a second sender on the command IDs (two interleaved sequences, or a
    # replay that wins the race) → FAULT and brake to rest at timeout_decel.
    race_drops: int = 3
    race_window: float = 0.5  # s

    def __post_init__(self) -> None:
        positive(
            self,
            "cmd_timeout",
            "timeout_decel",
            "override_torque",
            "override_time",
            "override_brake_pedal",
            "driver_decel",
            "standstill_speed",
            "default_steer_rate",
            "speed_kp",
            "speed_max_accel",
            "speed_max_decel",
            "tick_rate_hz",
            "race_window",
        )
        if not (isinstance(self.race_drops, int) and self.race_drops >= 1):
            raise ValueError(f"race_drops must be a whole number ≥ 1, got {self.race_drops!r}")
        if not self.speed_ki >= 0.0:
            raise ValueError(f"speed_ki must be zero or positive, got {self.speed_ki!r}")


@dataclass(frozen=True)
class LocalizationConfig:
    """The simulated localization that ``leafgate sim-ecu`` publishes over Zenoh."""

    rate_hz: float = 50.0  # Hz, Odometry publication rate
    position_noise: float = 0.0  # m, standard deviation of the x and y noise
    heading_noise: float = 0.0  # rad, standard deviation of the heading noise
    latency: float = 0.0  # s, age of the pose when it is published
    seed: int = 1  # noise generator seed, so a run can be repeated

    def __post_init__(self) -> None:
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate_hz must be a positive number, got {self.rate_hz!r}")
        for name in ("position_noise", "heading_noise", "latency"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class SimConfig:
    scenario: str = "s-curve"
    plant: PlantConfig = field(default_factory=PlantConfig)
    ecu: EcuConfig = field(default_factory=EcuConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    # The plant starts this far off the route's first waypoint (batch runs draw these within the
    # gateway's engage envelope): m to the left of its heading, and rad.
    start_lateral_offset: float = 0.0
    start_heading_offset: float = 0.0
