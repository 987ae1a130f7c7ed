"""Gateway section of the configuration (``gateway:``): loop rate, watchdogs, safety gate."""

from __future__ import annotations

from dataclasses import dataclass

from leafgate.config import positive


@dataclass(frozen=True)
class GatewayConfig:
    rate_hz: float = 50.0  # Hz, control loop rate (DBW_STEER_CMD period 20 ms)

    def __post_init__(self) -> None:
        positive(self, "rate_hz")

    @property
    def period(self) -> float:
        """Control tick period, s."""
        return 1.0 / self.rate_hz
