"""leafgate's own Zenoh key expressions after the prefix (docs/design.md, "The Zenoh interface").

The ROS topics and the engage service are named by role in the configuration
(:data:`~leafgate.config.transport.DEFAULT_TOPICS`, Autoware's names by default) and turned
into keys by :class:`~leafgate.transport.rosnode.RosFace`: in bridge mode the ROS name ``/a/b``
is the key ``<prefix>/a/b``, which ``zenoh-bridge-ros2dds -n /<prefix>`` routes to ``/a/b``.
The keys below are leafgate's own and are the same in every mode.
"""

from __future__ import annotations

ENGAGE = "gateway/engage"  # queryable: "engage" / "disengage" / "reset" → JSON reply
DIAGNOSTICS = "gateway/diagnostics"  # out: JSON object, 10 Hz
ALIVE = "gateway/alive"  # liveliness token while the gateway runs

# Bridge-mode keys of Autoware's default topic names (for tools and tests that build keys).
KINEMATIC_STATE = "localization/kinematic_state"  # in: nav_msgs/msg/Odometry
TRAJECTORY = "planning/scenario_planning/trajectory"  # in: autoware_planning_msgs/msg/Trajectory
STEERING_STATUS = "vehicle/status/steering_status"  # out: SteeringReport
VELOCITY_STATUS = "vehicle/status/velocity_status"  # out: VelocityReport
GEAR_STATUS = "vehicle/status/gear_status"  # out: GearReport
CONTROL_MODE = "vehicle/status/control_mode"  # out: ControlModeReport
TURN_INDICATORS_STATUS = "vehicle/status/turn_indicators_status"  # out: TurnIndicatorsReport
HAZARD_LIGHTS_STATUS = "vehicle/status/hazard_lights_status"  # out: HazardLightsReport
