"""A plan that asks for its speed from rest: the MPC does not over-steer at the drive-off.

PythonRobotics' courses give every waypoint the course's speed, the first one included. The
horizon's points were placed by the plan's time, 2 m/s from the first tick, where the car could
not be yet: on a bend the MPC steered to reach their lateral offset, 21.5° at the drive-off on
an R = 20 m arc that needs 7.7°, and 2.5 cm off the path.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from leafgate.messages import Pose, Trajectory
from leafgate.settings import load_config
from leafgate.sim.runner import run
from leafgate.sim.scenarios import Scenario, time_budget

RADIUS = 20.0  # m
SPEED = 2.0  # m/s, from the first waypoint on


def _arc() -> Trajectory:
    s = np.arange(0.0, 30.01, 0.5)
    heading = s / RADIUS
    speed = np.full_like(s, SPEED)
    speed[-1] = 0.0
    return Trajectory(
        x=RADIUS * np.sin(heading), y=RADIUS * (1.0 - np.cos(heading)), heading=heading, speed=speed
    )


@pytest.mark.slow
def test_a_plan_at_speed_from_rest_is_driven_off_without_over_steering() -> None:
    traj = _arc()
    scenario = Scenario("arc", "R 20 m at 2 m/s", traj, Pose(0.0, 0.0, 0.0, 0.0), time_budget(traj))
    result = run(load_config(None, {"sim.plant.kind": "kinematic"}), scenario)
    assert result.metrics["finished"]
    needs = math.degrees(math.atan(load_config(None).vehicle.wheelbase / RADIUS))  # 7.7°
    first_metres = result.series["x"] < 3.0
    steer = np.degrees(result.series["steer_target"][first_metres])
    assert steer.max() < 1.3 * needs, (steer.max(), needs)
    assert result.metrics["lateral_error_max_m"] < 0.02
