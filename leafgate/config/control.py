"""Controller section of the configuration (``controller:``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from leafgate.config import positive

MAX_HORIZON = 500  # model steps (50 s at 0.1 s); beyond, memory and set-up time explode


@dataclass(frozen=True)
class MpcConfig:
    """The paper's MPC (kinematic bicycle, augmented model, a QP solved by DAQP by default).

    Weights are per output / per input change and dimensionless once multiplied by the squared
    unit (a lateral weight of 20 costs 20 per m² of lateral error at each horizon step). Limits
    are the controller's own, chosen *inside* the vehicle's and the safety gate's limits so the
    gate never has to clamp a healthy MPC command.
    """

    sample_time: float = 0.1  # s, discretisation step of the prediction model
    prediction_horizon: int = 30  # Np: 3 s preview at 0.1 s, ≈ 6 m at parking speed
    control_horizon: int = 10  # Nc
    moves: Literal["spread", "consecutive"] = "spread"  # the model steps the Nc moves act at:
    # spread over the prediction horizon (move blocking), or its first Nc steps (the paper, whose
    # held last input is a compromise felt at once ahead of a rising curvature: counter-steers
    # before a bend, a pre-steer at a drive-off)
    solver: Literal["daqp", "hildreth", "osqp"] = "daqp"  # DAQP: exact dual active set, the
    # default; Hildreth: the paper's solver (capped at max_iterations); OSQP: ADMM
    max_iterations: int = 100  # Hildreth sweeps. The paper caps at 38; with the steering
    # saturated (the last arc of a parking move) warm-started sweeps need up to ≈ 75, and the
    # gateway stops the car on any unconverged solve
    mode: Literal["acceleration", "velocity"] = "acceleration"
    model: Literal["kinematic", "kinematic_steer_lag"] = "kinematic"

    # output weights Q (diagonal), path-aligned frame
    weight_along: float = 1.5  # 1/m², along-track position: stops the car on the goal point
    # (0.5 until issue 13: the last centimetres then crept at ≈ 2 s, and the car came to rest
    # ≈ 4 cm short; 1.5 brings it to ≈ 2 cm with the same lateral errors)
    weight_lateral: float = 40.0  # 1/m², cross-track error: the quantity the tests bound
    weight_speed: float = 2.0  # s²/m², speed error
    weight_heading: float = 4.0  # 1/rad², heading error: damps the lateral response
    # input-increment weights R̄ (diagonal), per model step
    weight_accel_change: float = 1.0  # s⁴/m², Δa: longitudinal smoothness
    weight_steer_change: float = 20.0  # 1/Δ(tan δ)²: steering smoothness

    # input limits (hard: the applied first move is clipped to them)
    accel_min: float = -3.0  # m/s², comfort braking; the Leaf can do −6
    accel_max: float = 1.5  # m/s², comfort drive-off; the Leaf can do +3
    jerk_max: float = 2.0  # m/s³, |da/dt|: comfortable for parking manoeuvres
    steer_max: float = math.radians(30.0)  # rad, road-wheel; 1° inside the Leaf's 31°
    steer_rate_max: float = 0.5  # rad/s, road-wheel; below the gate's 0.6 rad/s at low speed

    # solvers
    hildreth_relaxation: float = 1.5  # ω of projected SOR; 1 = Wang's QPhild. 1.5 converges
    # within the 38-sweep cap on the QPs of a standing start where ω = 1 needs hundreds
    hildreth_tolerance: float = 1e-10  # ‖Δλ‖² between sweeps, relative to ‖λ‖² (≥ 1)
    osqp_tolerance: float = 1e-7  # OSQP eps_abs = eps_rel

    # reference and progress
    align_tolerance: float = 0.03  # rad (and tan δ), at rest at a segment's start the wheel is
    # turned to the path's curvature within this before the car drives off (≈ 1.7°: the lateral
    # error it leaves over the first metre is ≈ 1 cm)
    creep_speed: float = 0.3  # m/s, slowest speed assumed when placing the horizon's points
    search_window: int = 20  # waypoints examined by the forward nearest-point search
    goal_tolerance: float = 0.15  # m, a segment's end counts as reached within this distance
    stop_speed: float = 0.02  # m/s, "at rest" below this; under the gateway's standstill speed
    # (0.05 m/s) so that when the MPC reports finished the gateway sees a car at rest too
    hold_decel: float = 1.0  # m/s², braking request that holds the car once finished
    speed_lead_time: float = 0.8  # s, velocity mode: how far ahead the planned speed is sent
    # (≈ the time constant of the vehicle's speed loop, 1/kp with kp ≈ 1.2–1.5 1/s)
    delay_compensation: float = 0.0  # s, predict the pose this far over the last command

    # offset-free tracking (leafgate.control.disturbance): constant input disturbances
    # estimated from the measured increments; 0 switches an estimate off
    disturbance_tau_steer: float = 1.0  # s, filter of the steering misalignment estimate
    disturbance_tau_accel: float = 2.0  # s, filter of the drag / incline estimate

    # speed bounds: the MPC never asks for more than the plan's speed plus a margin, nor for
    # more than the maneuver limit (so the safety gate's speed clamp is never needed)
    speed_margin: float = 0.15  # m/s, above the plan's speed (the bound is approached from below
    # with a little overshoot: 0.15 keeps the car within 0.2 m/s of the plan)
    max_speed: float = 3.0  # m/s, the maneuver limit (the gateway's safety.max_speed)

    # steering actuator (model "kinematic_steer_lag")
    steer_tau: float = 0.3  # s, first-order lag of the road-wheel angle
    steer_dead_time: float = 0.1  # s, pure delay of the steering actuator

    def __post_init__(self) -> None:
        positive(
            self,
            "sample_time",
            "prediction_horizon",
            "control_horizon",
            "max_iterations",
            "weight_speed",
            "weight_accel_change",
            "weight_steer_change",
            "accel_max",
            "jerk_max",
            "steer_max",
            "steer_rate_max",
            "hildreth_tolerance",
            "osqp_tolerance",
            "creep_speed",
            "align_tolerance",
            "search_window",
            "goal_tolerance",
            "stop_speed",
            "speed_lead_time",
            "steer_tau",
        )
        if self.control_horizon > self.prediction_horizon:
            raise ValueError("control_horizon must not exceed prediction_horizon")
        if self.prediction_horizon > MAX_HORIZON:  # the dense matrices grow as Np·Nc
            raise ValueError(
                f"prediction_horizon must be at most {MAX_HORIZON} steps, got "
                f"{self.prediction_horizon}"
            )
        for name in ("weight_along", "weight_lateral", "weight_heading", "hold_decel"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a number ≥ 0, got {value!r}")
        for name in ("disturbance_tau_steer", "disturbance_tau_accel", "speed_margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a number ≥ 0, got {value!r}")
        positive(self, "max_speed")
        for name in ("delay_compensation", "steer_dead_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} must lie in [0, 1] s, got {value!r}")
        if not 0.0 < self.hildreth_relaxation < 2.0:
            raise ValueError("hildreth_relaxation must lie in (0, 2)")
        if not self.accel_min < 0.0:
            raise ValueError("accel_min must be negative")
        if not self.steer_max < math.pi / 2:
            raise ValueError("steer_max must be below 90°")
        if self.model == "kinematic_steer_lag" and self.steer_tau < self.sample_time / 10.0:
            # the prediction divides by the lag's 1 − α = exp(−Ts/τ): e⁻¹⁰ here, 0 in floats
            # for a wheel some 700 times faster than the model step
            raise ValueError(
                f"steer_tau must be at least sample_time / 10 = {self.sample_time / 10.0:g} s "
                f"with model kinematic_steer_lag, got {self.steer_tau!r} (a wheel that much "
                "faster than the model step is the kinematic model)"
            )


@dataclass(frozen=True)
class TrackerConfig:
    """What both baselines share: the speed loop, the limits and the stop/cusp handling.

    Limits default to the MPC's (:class:`MpcConfig`) so every
    controller works inside the same envelope.
    """

    speed_kp: float = 1.2  # 1/s, proportional gain of the PI speed loop
    speed_ki: float = 0.3  # 1/s², integral gain
    speed_integral_band: float = 0.2  # m/s, integrate only within this speed error (anti-windup)
    creep_speed: float = 0.3  # m/s, slowest target speed while the segment's end is ahead
    stop_decel: float = 0.4  # m/s², target speed ≤ √(2 b d) over the distance d to the end
    stop_reaction_time: float = 0.3  # s, braking acts this late (actuator lag, jerk-limited
    # ramp): the stopping curve keeps |v|·t of the distance to the end in reserve
    accel_min: float = -3.0  # m/s², gear-relative braking limit
    accel_max: float = 1.5  # m/s², gear-relative drive limit
    jerk_max: float = 2.0  # m/s³
    hold_decel: float = 1.0  # m/s², braking request at rest (aligning, finished)
    steer_max: float = math.radians(30.0)  # rad, road-wheel
    steer_rate_max: float = 0.5  # rad/s, road-wheel
    goal_tolerance: float = 0.25  # m, a segment's end counts as reached within this distance
    # (wider than the MPC's 0.15 m: Pure Pursuit ends the parallel park up to ≈ 0.15 m off the
    # goal, and a segment ends only by progress *and* within this distance — farther is
    # "off-goal")
    stop_speed: float = 0.02  # m/s, "at rest" below this
    align_tolerance: float = 0.03  # rad, wheel within this of the law's angle before driving off
    search_window: int = 20  # waypoints examined by the forward nearest-point search

    def __post_init__(self) -> None:
        positive(
            self,
            "speed_kp",
            "speed_integral_band",
            "creep_speed",
            "stop_decel",
            "accel_max",
            "jerk_max",
            "steer_max",
            "steer_rate_max",
            "goal_tolerance",
            "stop_speed",
            "align_tolerance",
            "search_window",
        )
        for name in ("speed_ki", "hold_decel", "stop_reaction_time"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a number ≥ 0, got {value!r}")
        if not self.accel_min < 0.0:
            raise ValueError("accel_min must be negative")
        if not self.steer_max < math.pi / 2:
            raise ValueError("steer_max must be below 90°")


@dataclass(frozen=True)
class PurePursuitConfig(TrackerConfig):
    """Pure Pursuit (``controller.pure_pursuit``): speed-dependent look-ahead."""

    lookahead_min: float = 2.0  # m, look-ahead at (and near) standstill
    lookahead_gain: float = 1.0  # s, Ld = max(lookahead_min, gain·|v|): ≈ 1 s of travel
    lookahead_max: float = 8.0  # m

    def __post_init__(self) -> None:
        super().__post_init__()
        positive(self, "lookahead_min", "lookahead_max")
        if not (math.isfinite(self.lookahead_gain) and self.lookahead_gain >= 0.0):
            raise ValueError(f"lookahead_gain must be ≥ 0, got {self.lookahead_gain!r}")
        if self.lookahead_max < self.lookahead_min:
            raise ValueError("lookahead_max must not be below lookahead_min")


@dataclass(frozen=True)
class StanleyConfig(TrackerConfig):
    """Stanley (``controller.stanley``): heading error plus softened cross-track term."""

    gain: float = 1.5  # 1/s, k: cross-track gain (the error decays as ė ≈ −k e at speed)
    softening: float = 0.5  # m/s, k_soft: atan(k e / (k_soft + |v|)) stays finite at rest

    def __post_init__(self) -> None:
        super().__post_init__()
        positive(self, "gain", "softening")


@dataclass(frozen=True)
class ControllerConfig:
    kind: Literal["mpc", "pure-pursuit", "stanley"] = "mpc"
    mpc: MpcConfig = field(default_factory=MpcConfig)
    pure_pursuit: PurePursuitConfig = field(default_factory=PurePursuitConfig)
    stanley: StanleyConfig = field(default_factory=StanleyConfig)

    @property
    def section_name(self) -> str:
        """The key of the configured controller's own section: ``controller.<section_name>``."""
        return self.kind.replace("-", "_")

    @property
    def section(self) -> MpcConfig | PurePursuitConfig | StanleyConfig:
        """The configured controller's own section."""
        section: MpcConfig | PurePursuitConfig | StanleyConfig = getattr(self, self.section_name)
        return section
