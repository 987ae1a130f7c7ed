"""Controller section of the configuration (``controller:``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from leafgate.config import positive


@dataclass(frozen=True)
class MpcConfig:
    """The paper's MPC (kinematic bicycle, augmented model, Hildreth's QP)."""

    sample_time: float = 0.1  # s, discretisation step of the prediction model
    prediction_horizon: int = 30  # Np
    control_horizon: int = 10  # Nc
    solver: Literal["hildreth", "osqp"] = "hildreth"
    max_iterations: int = 38  # Hildreth sweeps (the paper's cap)
    mode: Literal["acceleration", "velocity"] = "acceleration"
    model: Literal["kinematic", "kinematic_steer_lag"] = "kinematic"

    def __post_init__(self) -> None:
        positive(self, "sample_time", "prediction_horizon", "control_horizon", "max_iterations")
        if self.control_horizon > self.prediction_horizon:
            raise ValueError("control_horizon must not exceed prediction_horizon")


@dataclass(frozen=True)
class ControllerConfig:
    kind: Literal["mpc", "pure-pursuit", "stanley"] = "mpc"
    mpc: MpcConfig = field(default_factory=MpcConfig)
