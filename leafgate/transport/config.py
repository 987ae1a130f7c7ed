"""Zenoh section of the configuration (``zenoh:``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class ZenohConfig:
    prefix: str = "leaf"
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str | None = None  # a Zenoh JSON5 file (router mode, TLS, access control)
    encoding: Literal["cdr", "json"] = "cdr"
    extra: dict[str, str] = field(default_factory=dict)
