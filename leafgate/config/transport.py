"""Zenoh section of the configuration (``zenoh:``).

The session is built from this section: ``mode`` (``peer`` by default; the shipped configs set
``router``), explicit ``listen``/``connect`` endpoints, multicast scouting off. For TLS and
access control name a Zenoh JSON5 file in ``config_file`` (a relative path is taken from the
config file's directory); the file is then the base configuration and only non-empty ``listen``/``connect`` lists and the
``extra`` entries of this section are applied on top of it (``mode`` and
``multicast_scouting`` are the file's).

Example (YAML)::

    zenoh:
      prefix: leaf
      listen: ["tcp/127.0.0.1:7450"]
      connect: []
      encoding: cdr

ROS 2 (``ros``): ``bridge`` (default) speaks plain Zenoh for ``zenoh-bridge-ros2dds -n
/<prefix>`` (keys ``<prefix>/<ROS name>``, bridge announcement tokens); ``rmw_zenoh`` makes
leafgate an rmw_zenoh node (see :mod:`leafgate.transport.ros2`) that connects to
``rmw_zenohd`` at ``tcp/127.0.0.1:7447`` unless ``connect`` says otherwise::

    zenoh:
      ros: rmw_zenoh
      ros_distro: jazzy
      domain_id: 0
      node_name: leafgate
      node_namespace: /
      topics:                     # Autoware's names by default; relative ones are resolved
        trajectory: /planning/scenario_planning/trajectory   # under node_namespace
        command_echo: /leafgate/control_cmd                  # off ("") by default

TLS with access control (``config/zenoh/secure.json5``) is one file for every process: the
gateway uses it as written, and each tool points it at the gateway and at its own certificate
with ``extra`` (the file's header shows the lines), e.g. for the operator::

    zenoh:
      config_file: zenoh/secure.json5    # next to config/leafgate.yaml
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

RMW_ZENOHD = "tcp/127.0.0.1:7447"  # where rmw_zenoh nodes find their router by default

# The ROS names leafgate uses, by role: Autoware's vehicle interface defaults.
DEFAULT_TOPICS: dict[str, str] = {
    "kinematic_state": "/localization/kinematic_state",  # in: nav_msgs/msg/Odometry
    "trajectory": "/planning/scenario_planning/trajectory",  # in: Trajectory
    "steering_status": "/vehicle/status/steering_status",
    "velocity_status": "/vehicle/status/velocity_status",
    "gear_status": "/vehicle/status/gear_status",
    "control_mode": "/vehicle/status/control_mode",
    "turn_indicators_status": "/vehicle/status/turn_indicators_status",
    "hazard_lights_status": "/vehicle/status/hazard_lights_status",
    "control_mode_request": "/control/control_mode_request",  # service: ControlModeCommand
    # What was sent to the ECU, as autoware_control_msgs/msg/Control. Off by default: Autoware's
    # own /control/command/control_cmd belongs to its vehicle_cmd_gate.
    "command_echo": "",
}


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
    ros: Literal["bridge", "rmw_zenoh"] = "bridge"  # how ROS 2 sees leafgate
    ros_distro: Literal["humble", "jazzy", "kilted"] = "jazzy"  # for rmw_zenoh's type hashes
    domain_id: int = 0  # ROS_DOMAIN_ID (rmw_zenoh)
    node_name: str = "leafgate"
    node_namespace: str = "/"
    # ROS names by role (keys of DEFAULT_TOPICS); unnamed roles keep Autoware's default.
    topics: dict[str, str] = field(default_factory=dict)
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
        unknown = set(self.topics) - set(DEFAULT_TOPICS)
        if unknown:
            raise ValueError(
                f"topics: unknown role(s) {', '.join(sorted(unknown))} "
                f"(known: {', '.join(DEFAULT_TOPICS)})"
            )
        if self.ros == "rmw_zenoh" and self.encoding != "cdr":
            raise ValueError("ros: rmw_zenoh carries CDR only (set encoding: cdr)")
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"domain_id {self.domain_id} is not a ROS domain (0 to 232)")
        if not self.node_namespace.startswith("/") or "//" in self.node_namespace:
            raise ValueError(f"node_namespace {self.node_namespace!r} must start with '/'")
        if not self.node_name or not all(c.isalnum() or c == "_" for c in self.node_name):
            raise ValueError(f"node_name {self.node_name!r}: letters, digits and '_' only")
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

    @property
    def ros_namespace(self) -> str:
        """The namespace to give zenoh-bridge-ros2dds (``-n /leaf``) in bridge mode."""
        return f"/{self.prefix}"

    def topic(self, role: str) -> str:
        """The fully qualified ROS name for ``role`` ("" when the role is switched off).

        :raises ValueError: for an unknown role
        """
        if role not in DEFAULT_TOPICS:
            raise ValueError(f"unknown topic role {role!r}")
        name = self.topics.get(role, DEFAULT_TOPICS[role])
        if not name:
            return ""
        if name.startswith("/"):
            return name
        return f"{self.node_namespace.rstrip('/')}/{name}"
