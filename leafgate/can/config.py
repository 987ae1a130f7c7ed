"""CAN section of the configuration (``can:``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class BusConfig:
    """One python-can bus: the interface by name and its keyword arguments passed through."""

    interface: str = "virtual"
    channel: str = "leafgate"
    bitrate: int = 500_000  # bit/s
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CanConfig:
    """The two channels of the research Leaf; ``car: null`` means CAR-CAN shares the dbw bus."""

    dbw: BusConfig = field(default_factory=BusConfig)
    car: BusConfig | None = None
