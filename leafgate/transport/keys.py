"""Zenoh key expressions of the gateway, after the configured prefix (DESIGN, "Zenoh interface").

Laid out so that zenoh-bridge-ros2dds with namespace ``leaf`` maps them to the usual ROS 2 /
Autoware topics (``leaf/localization/kinematic_state`` ⇄ ``/leaf/localization/kinematic_state``).
"""

from __future__ import annotations

KINEMATIC_STATE = "localization/kinematic_state"  # in: nav_msgs/msg/Odometry
TRAJECTORY = "planning/trajectory"  # in: autoware_planning_msgs/msg/Trajectory
ENGAGE = "gateway/engage"  # queryable: "engage" / "disengage" / "reset" → JSON reply
STEERING_STATUS = "vehicle/status/steering_status"  # out: SteeringReport
VELOCITY_STATUS = "vehicle/status/velocity_status"  # out: VelocityReport
GEAR_STATUS = "vehicle/status/gear_status"  # out: GearReport
CONTROL_MODE = "vehicle/status/control_mode"  # out: ControlModeReport
CONTROL_CMD = "control/command/control_cmd"  # out: autoware_control_msgs/msg/Control
DIAGNOSTICS = "gateway/diagnostics"  # out: JSON object, 10 Hz
ALIVE = "gateway/alive"  # liveliness token while the gateway runs
