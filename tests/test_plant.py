"""Simulated plants: accurate integration, gear-relative longitudinal input, actuator dynamics."""

from __future__ import annotations

import itertools
import math

import pytest

from leafgate.config import VehicleConfig
from leafgate.config.sim import PlantConfig
from leafgate.messages import Gear, Pose
from leafgate.sim.plant import KinematicPlant, SpeedController, SteerLagPlant, make_plant

VEHICLE = VehicleConfig()


def test_constant_steering_drives_the_kinematic_circle() -> None:
    delta, v = 0.2, 2.0  # rad, m/s
    plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, v))
    radius = VEHICLE.wheelbase / math.tan(delta)
    plant.step(0.02, delta, 0.0, Gear.D)  # steering is instant without delay
    for _ in range(round(math.pi * radius / v / 0.02)):  # half a circle
        plant.step(0.02, delta, 0.0, Gear.D)
    # After half a turn the rear axle is two radii to the left of the start.
    assert plant.y == pytest.approx(2 * radius, abs=0.05)
    assert abs(plant.x) < 0.3
    assert math.hypot(plant.x, plant.y - radius) == pytest.approx(radius, abs=1e-3)


def test_braking_stops_at_rest_and_never_reverses() -> None:
    for gear, v0 in ((Gear.D, 2.0), (Gear.R, -2.0)):
        plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, v0))
        plant.gear = gear
        for _ in range(100):
            plant.step(0.02, 0.0, -3.0, gear)
        assert plant.speed == 0.0
        assert (plant.x > 0) == (v0 > 0)
        assert abs(plant.x) == pytest.approx(v0 * v0 / 6.0, abs=1e-6)  # v²/(2a)


def test_reverse_gear_accelerates_backwards() -> None:
    plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, 0.0))
    assert plant.set_gear(Gear.R)
    for _ in range(50):
        plant.step(0.02, 0.0, 1.0, Gear.R)
    assert plant.speed == pytest.approx(-1.0, abs=1e-9)
    assert plant.x < 0


def test_gear_change_refused_while_moving() -> None:
    plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, 1.0))
    assert not plant.set_gear(Gear.R)
    assert plant.gear == Gear.D


def test_input_delay_shifts_the_steering_response() -> None:
    plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, 1.0), input_delay=0.1)
    plant.step(0.08, 0.1, 0.0, Gear.D)
    assert plant.steer_angle == 0.0
    plant.step(0.04, 0.1, 0.0, Gear.D)
    assert plant.steer_angle == pytest.approx(0.1)


def test_steer_lag_plant_lags_and_rate_limits() -> None:
    cfg = PlantConfig(
        kind="steer-lag", input_delay=0.0, steer_dead_time=0.1, steer_tau=0.3, steer_rate_max=0.2
    )
    plant = make_plant(cfg, VEHICLE, Pose(0.0, 0.0, 0.0, 1.0))
    assert isinstance(plant, SteerLagPlant)
    plant.step(0.1, 0.5, 0.0, Gear.D)
    assert plant.steer_angle == pytest.approx(0.0, abs=1e-9)  # dead time
    angles = []
    for _ in range(200):
        plant.step(0.02, 0.5, 0.0, Gear.D)
        angles.append(plant.steer_angle)
    rates = [(b - a) / 0.02 for a, b in itertools.pairwise(angles)]
    assert max(rates) <= 0.2 + 1e-9  # the rate limit binds for a large step
    assert angles[-1] == pytest.approx(0.5, abs=0.02)  # and the lag converges


def test_speed_controller_tracks_target() -> None:
    plant = KinematicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, 0.0))
    ctl = SpeedController()
    for _ in range(500):
        plant.step(0.02, 0.0, ctl.step(0.02, 2.0, plant.speed), Gear.D)
    assert plant.speed == pytest.approx(2.0, abs=0.02)
