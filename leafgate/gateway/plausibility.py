"""Are the ECU's reports believable? Range checks and cross-checks against CAR-CAN.

A report with a valid CRC and counter may still be forged (issue 17, finding 4: a second sender
with counter = genuine + 1 made the gateway take 20 m/s for truth at 2 m/s, and a 40° angle
beyond the 31° mechanical limit seeded the safety gate). Two checks, used by the gateway core
on every report and by ``leafgate replay check`` on every recorded one (one implementation):

- :func:`report_range_error`: an angle beyond the mechanical limit (with a small margin for
  sensor noise) or a speed beyond what the car can do makes the report invalid;
- :func:`cross_check`: the DBW reports against the vehicle's own CAR-CAN frames, which the
  gateway decodes anyway — DBW_LONG_RPT's speed against the wheel speeds (0x284/0x285), and
  DBW_STEER_RPT's road-wheel angle against the steering-wheel angle (0x002) over the steering
  ratio. A forger must now forge two buses' frames consistently.
"""

from __future__ import annotations

import math

from leafgate.config import VehicleConfig
from leafgate.messages import LongReport, SteeringWheelAngle, SteerReport, WheelSpeeds

MAX_PHYSICAL_SPEED = 45.0  # m/s, above any Leaf's top speed (144 km/h = 40 m/s)
ANGLE_MARGIN = math.radians(1.0)  # rad beyond the mechanical limit still taken as noise
SPEED_TOLERANCE = 0.5  # m/s, plus SPEED_TOLERANCE_RATIO of the speed
SPEED_TOLERANCE_RATIO = 0.1  # the front axle turns faster by 1/cos δ; wheel slip
ANGLE_TOLERANCE = math.radians(3.0)  # rad of road-wheel angle
MAX_SKEW = 0.1  # s between the two frames compared; older pairs are not compared


def report_range_error(value: SteerReport | LongReport, vehicle: VehicleConfig) -> str | None:
    """Why a decoded report is out of the physically possible range, or None."""
    if isinstance(value, SteerReport):
        limit = vehicle.max_steer_angle + ANGLE_MARGIN
        if not abs(value.angle) <= limit:
            return (
                f"steer report angle {math.degrees(value.angle):.1f}° beyond the mechanical "
                f"limit {math.degrees(vehicle.max_steer_angle):.1f}°"
            )
        return None
    if not abs(value.speed) <= MAX_PHYSICAL_SPEED:
        return f"long report speed {value.speed:.1f} m/s beyond {MAX_PHYSICAL_SPEED:g} m/s"
    return None


def cross_check(
    steer: SteerReport | None,
    long: LongReport | None,
    wheels: WheelSpeeds | None,
    steering_wheel: SteeringWheelAngle | None,
    vehicle: VehicleConfig,
) -> list[str]:
    """Disagreements between the DBW reports and the CAR-CAN frames given (none when absent).

    Pass only frames received within :data:`MAX_SKEW` of the report they are compared with.
    """
    out = []
    if long is not None and wheels is not None:
        wheel_speed = 0.5 * (wheels.left + wheels.right)
        tolerance = SPEED_TOLERANCE + SPEED_TOLERANCE_RATIO * wheel_speed
        if abs(abs(long.speed) - wheel_speed) > tolerance:
            out.append(
                f"long report speed {long.speed:.2f} m/s disagrees with the {wheels.axle} "
                f"wheel speeds {wheel_speed:.2f} m/s"
            )
    if steer is not None and steering_wheel is not None:
        road_wheel = steering_wheel.angle / vehicle.steering_ratio
        if abs(steer.angle - road_wheel) > ANGLE_TOLERANCE:
            out.append(
                f"steer report angle {math.degrees(steer.angle):.1f}° disagrees with the "
                f"steering wheel's {math.degrees(road_wheel):.1f}° (0x002)"
            )
    return out
