"""The dynamic bicycle plant (linear tyres, kinematic at low speed)."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.config import VehicleConfig
from leafgate.config.sim import PlantConfig
from leafgate.messages import Gear, Pose
from leafgate.sim.plant import DynamicPlant, SteerLagPlant, make_plant

VEHICLE = VehicleConfig()
PLANT = PlantConfig(kind="dynamic")


def understeer_gradient(v: VehicleConfig) -> float:
    """K in r = u δ / (L + K u²), s²/m (axle cornering stiffnesses)."""
    lr = v.wheelbase - v.cg_to_front
    return (
        v.mass
        * (lr * v.cornering_stiffness_rear - v.cg_to_front * v.cornering_stiffness_front)
        / (v.wheelbase * v.cornering_stiffness_front * v.cornering_stiffness_rear)
    )


def test_make_plant_builds_the_dynamic_plant() -> None:
    assert isinstance(make_plant(PLANT, VEHICLE, Pose(0.0, 0.0, 0.0, 0.0)), DynamicPlant)


@pytest.mark.parametrize("delta", [0.02, -0.05])
def test_steady_state_yaw_rate_matches_understeer_gradient_at_5_mps(delta: float) -> None:
    u = 5.0  # m/s
    plant = make_plant(PLANT, VEHICLE, Pose(0.0, 0.0, 0.0, u))
    for _ in range(300):  # 6 s: steering lag and yaw transient long settled
        plant.step(0.02, delta, 0.0)
    expected = u * delta / (VEHICLE.wheelbase + understeer_gradient(VEHICLE) * u**2)
    kinematic = u * math.tan(delta) / VEHICLE.wheelbase
    assert plant.speed == pytest.approx(u)
    assert plant.yaw_rate == pytest.approx(expected, rel=2e-3)
    assert abs(plant.yaw_rate) < abs(kinematic) * 0.97  # the Leaf understeers: K > 0
    assert plant.pose().yaw_rate == plant.yaw_rate


def test_steady_state_heading_changes_at_the_yaw_rate() -> None:
    plant = make_plant(PLANT, VEHICLE, Pose(0.0, 0.0, 0.0, 5.0))
    for _ in range(300):
        plant.step(0.02, 0.03, 0.0)
    h0 = plant.heading
    plant.step(1.0, 0.03, 0.0)
    assert plant.heading - h0 == pytest.approx(plant.yaw_rate * 1.0, rel=1e-6)


@pytest.mark.parametrize("speed", [0.3, -0.4])
def test_below_blend_speed_matches_the_kinematic_plant(speed: float) -> None:
    start = Pose(1.0, -2.0, 0.3, speed)
    dynamic = DynamicPlant(VEHICLE, start, PLANT)
    kinematic = SteerLagPlant(VEHICLE, start, PLANT)  # same actuator, kinematic bicycle
    for k in range(500):  # 10 s of steering back and forth at constant low speed
        steer = 0.5 * math.sin(0.02 * k)
        dynamic.step(0.02, steer, 0.0)
        kinematic.step(0.02, steer, 0.0)
    a, b = dynamic.pose(), kinematic.pose()
    assert abs(a.x - b.x) < 1e-6 and abs(a.y - b.y) < 1e-6
    assert a.heading == pytest.approx(b.heading, abs=1e-6)
    assert a.yaw_rate == pytest.approx(b.yaw_rate, abs=1e-9)
    assert dynamic.lateral_speed == 0.0


def test_in_the_blend_zone_it_stays_close_to_the_kinematic_plant() -> None:
    start = Pose(0.0, 0.0, 0.0, 0.8)
    dynamic = DynamicPlant(VEHICLE, start, PLANT)
    kinematic = SteerLagPlant(VEHICLE, start, PLANT)
    for _ in range(250):  # 5 s, a quarter of a tight circle
        dynamic.step(0.02, 0.4, 0.0)
        kinematic.step(0.02, 0.4, 0.0)
    gap = math.hypot(dynamic.x - kinematic.x, dynamic.y - kinematic.y)  # m
    assert gap < 0.05


def test_accelerating_through_the_blend_zone_has_no_yaw_rate_jump() -> None:
    plant = DynamicPlant(VEHICLE, Pose(0.0, 0.0, 0.0, 0.0), PLANT)
    plant.step(1.0, 0.3, 0.0)  # steer at rest
    rates = []
    for _ in range(1000):  # 0 → 2 m/s in 2 s
        plant.step(0.002, 0.3, 1.0)
        rates.append(plant.yaw_rate)
    steps = [abs(b - a) for a, b in itertools.pairwise(rates)]
    kinematic_step = 1.0 * math.tan(0.3) / VEHICLE.wheelbase * 0.002  # rad/s per 2 ms
    assert max(steps) < 1.5 * kinematic_step  # no jump where the models hand over


def test_braking_to_rest_stops_exactly_and_stays() -> None:
    plant = make_plant(PLANT, VEHICLE, Pose(0.0, 0.0, 0.0, 3.0))
    for _ in range(200):
        plant.step(0.02, 0.2, -3.0)
    assert plant.speed == 0.0
    assert plant.yaw_rate == 0.0
    x = plant.x
    plant.step(1.0, 0.2, -3.0)
    assert plant.x == x


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-1.0, 1.0),  # rad, beyond the steering limit on purpose
            st.floats(-6.0, 3.0),  # m/s²
            st.sampled_from([Gear.D, Gear.R, Gear.N, Gear.P]),
            st.sampled_from([0.001, 0.01, 0.05]),  # s
        ),
        min_size=1,
        max_size=40,
    ),
    st.floats(-2.0, 2.0),
)
def test_never_produces_nan_from_standstill(
    inputs: list[tuple[float, float, Gear, float]], start_speed: float
) -> None:
    plant = make_plant(PLANT, VEHICLE, Pose(0.0, 0.0, 0.0, start_speed))
    for steer, accel, gear, dt in inputs:
        plant.step(dt, steer, accel, gear)
        pose = plant.pose()
        values = (pose.x, pose.y, pose.heading, pose.speed, pose.yaw_rate, plant.accel)
        assert all(math.isfinite(v) for v in values)
        assert abs(plant.steer_angle) <= VEHICLE.max_steer_angle + 1e-12
