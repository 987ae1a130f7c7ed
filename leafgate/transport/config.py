"""Zenoh section of the configuration (``zenoh:``).

Peer mode with explicit ``listen``/``connect`` endpoints and multicast scouting off is the
default. For router mode, TLS and access control name a Zenoh JSON5 file in ``config_file``;
the file is then the base configuration and only non-empty ``listen``/``connect`` lists and the
``extra`` entries of this section are applied on top of it (``mode`` and
``multicast_scouting`` are the file's).

Example (YAML)::

    zenoh:
      prefix: leaf
      listen: ["tcp/127.0.0.1:7447"]
      connect: []
      encoding: cdr

TLS with access control (``config/zenoh/secure.json5``) is one file for every process: the
gateway uses it as written, and each tool points it at the gateway and at its own certificate
with ``extra`` (the file's header shows the lines), e.g. for the operator::

    zenoh:
      config_file: config/zenoh/secure.json5
      connect: ["tls/127.0.0.1:7447"]
      extra:
        mode: '"client"'
        listen/endpoints: '[]'
        transport/link/tls/connect_certificate: '"/etc/leafgate/tls/operator.pem"'
        transport/link/tls/connect_private_key: '"/etc/leafgate/tls/operator.key"'
        access_control/enabled: 'false'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from leafgate.config import positive

_KEY_SPECIAL = set("*$?#")  # wildcard and selector characters that may not appear in a prefix


@dataclass(frozen=True)
class ZenohConfig:
    """How the gateway and the tools reach each other over Zenoh."""

    prefix: str = "leaf"  # key-expression prefix; zenoh-bridge-ros2dds namespace
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()  # endpoints such as "tcp/127.0.0.1:7447"
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str | None = None  # a Zenoh JSON5 file (router mode, TLS, access control)
    encoding: Literal["cdr", "json"] = "cdr"
    # Raw Zenoh settings: JSON5 path → JSON5 value, e.g. {"transport/shared_memory/enabled":
    # "false"}; applied last.
    extra: dict[str, str] = field(default_factory=dict)
    query_timeout: float = 2.0  # s, how long a tool waits for the gateway's answer
    express: bool = True  # publish without batching: lower latency for the 50 Hz statuses
    # Input bounds (issue 17, finding 5): a larger payload is dropped before it is decoded; a
    # plan with more points is refused (the controller's reference is built from every point;
    # a 10⁶-point plan made one tick last 4.36 s). The scenarios have at most 143 points.
    max_payload_bytes: int = 1_000_000
    max_plan_points: int = 2000
    # s, how far the localization sender's clock may be off ours. A pose whose header stamp is
    # older than that counts as received that much earlier (400 ms-old stamps are stale however
    # promptly they arrive); a stamp further in the future marks the pose invalid.
    max_clock_offset: float = 0.05

    def __post_init__(self) -> None:
        positive(self, "query_timeout", "max_payload_bytes", "max_plan_points", "max_clock_offset")
        prefix = self.prefix
        if (
            not prefix
            or prefix.startswith("/")
            or prefix.endswith("/")
            or "//" in prefix
            or _KEY_SPECIAL & set(prefix)
        ):
            raise ValueError(
                f"prefix {prefix!r} is not a plain key expression "
                "(non-empty, no leading/trailing '/', no '*', '$', '?', '#')"
            )

    def key(self, suffix: str) -> str:
        """The full key expression for ``suffix``, e.g. ``key("gateway/engage")``."""
        return f"{self.prefix}/{suffix}"
