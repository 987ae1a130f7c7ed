"""The whole configuration of one deployment, composed of the parts' sections."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from leafgate.can.config import CanConfig
from leafgate.config import VehicleConfig, from_mapping, load_yaml
from leafgate.control.config import ControllerConfig
from leafgate.gateway.config import GatewayConfig
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
    def long_mode(self) -> LongMode:
        """The longitudinal command the ECU receives: the MPC's mode (paper §II.B)."""
        return LongMode.SPEED if self.controller.mpc.mode == "velocity" else LongMode.ACCELERATION


def load_config(path: str | Path | None) -> LeafgateConfig:
    """Load a deployment config; ``None`` gives the embedded defaults.

    :raises ConfigError: naming the file and the key of the first problem
    """
    if path is None:
        return LeafgateConfig()
    return from_mapping(LeafgateConfig, load_yaml(path), str(path))
