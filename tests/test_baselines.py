"""Pure Pursuit and Stanley: the laws, reverse driving, standstill, limits and configuration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leafgate.config import VehicleConfig, from_mapping
from leafgate.config.control import ControllerConfig
from leafgate.control import make_controller
from leafgate.control.baselines import PurePursuit, PurePursuitConfig, Stanley, StanleyConfig
from leafgate.errors import ConfigError
from leafgate.messages import Gear, Pose, Trajectory
from leafgate.settings import LeafgateConfig
from leafgate.sim.compare import drive_config
from leafgate.sim.runner import run_direct
from leafgate.sim.scenarios import Scenario, get_scenario

PERIOD = 0.02  # s
L = VehicleConfig().wheelbase  # m


def _line(direction: int, n: int = 41, speed: float = 1.0) -> Trajectory:
    """A straight line along x with the vehicle heading 0, driven forward (+x) or reversing (−x)."""
    x = direction * 0.5 * np.arange(n)
    v = np.full(n, direction * speed)
    v[-1] = 0.0
    return Trajectory(x=x, y=np.zeros(n), heading=np.zeros(n), speed=v)


def _settled(ctrl: PurePursuit | Stanley, pose: Pose, traj: Trajectory, ticks: int = 200) -> float:
    """The steering command once the rate limit has let it reach the law's angle (car at rest)."""
    out = ctrl.step(pose, 0.0, traj)
    for _ in range(ticks):
        out = ctrl.step(pose, out.steer_angle, traj)
    return out.steer_angle


def test_pure_pursuit_steers_onto_the_circle_through_the_lookahead_point() -> None:
    cfg = PurePursuitConfig(lookahead_min=3.0, lookahead_gain=0.0)
    ctrl = PurePursuit(cfg, VehicleConfig(), PERIOD)
    offset = -0.4  # m, right of the line
    angle = _settled(ctrl, Pose(0.0, offset, 0.0, 0.0), _line(+1))
    # target 3 m along the path from the projection: bearing α, distance d
    d = math.hypot(3.0, offset)
    alpha = math.atan2(-offset, 3.0)
    assert angle == pytest.approx(math.atan(2.0 * L * math.sin(alpha) / d), abs=1e-6)
    assert angle > 0.0  # left, back towards the line


def test_stanley_cross_track_term_is_finite_and_softened_at_standstill() -> None:
    cfg = StanleyConfig(gain=1.5, softening=0.5)
    ctrl = Stanley(cfg, VehicleConfig(), PERIOD)
    offset = 0.1  # m, left of the line: steer right
    angle = _settled(ctrl, Pose(0.0, offset, 0.0, 0.0), _line(+1))
    assert angle == pytest.approx(math.atan2(-cfg.gain * offset, cfg.softening), abs=1e-6)
    assert abs(angle) < cfg.steer_max


@pytest.mark.parametrize("kind", [PurePursuit, Stanley])
def test_reverse_steers_the_mirror_of_forward(kind: type) -> None:
    """Reversing along −x with the car 0.3 m left of the line is forward driving mirrored:
    the wheel angle is the negative of the forward one for the mirrored offset."""
    cfg = PurePursuitConfig() if kind is PurePursuit else StanleyConfig()
    fwd = _settled(kind(cfg, VehicleConfig(), PERIOD), Pose(0.0, -0.3, 0.0, 0.0), _line(+1))
    rev = _settled(kind(cfg, VehicleConfig(), PERIOD), Pose(0.0, 0.3, 0.0, 0.0), _line(-1))
    assert fwd != 0.0
    assert rev == pytest.approx(-fwd, abs=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pure-pursuit", "stanley"])
def test_reverse_line_from_an_offset_converges_in_reverse_gear(kind: str) -> None:
    traj = _line(-1, n=31)
    start = Pose(0.0, 0.3, 0.0, 0.0)
    scenario = Scenario("reverse-line", "reverse 15 m from 0.3 m off", traj, start, 40.0)
    cfg = LeafgateConfig(controller=ControllerConfig(kind=kind))  # type: ignore[arg-type]
    result = run_direct(cfg, scenario)
    assert result.metrics["finished"]
    assert result.trace.speed.max() <= 0.0  # never forward
    assert any("gear R" in event for _, event in result.timeline)
    assert abs(result.trace.y[-1]) < 0.03  # m, back on the line
    assert result.metrics["final_position_error_m"] < 0.15


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pure-pursuit", "stanley"])
def test_parking_commands_stay_within_angle_and_rate_limits(kind: str) -> None:
    cfg = LeafgateConfig(controller=ControllerConfig(kind=kind))  # type: ignore[arg-type]
    result = run_direct(cfg, get_scenario("parallel-park"))
    limits = cfg.controller.pure_pursuit if kind == "pure-pursuit" else cfg.controller.stanley
    cmd = result.trace.steer_target
    assert np.max(np.abs(cmd)) <= limits.steer_max + 1e-12
    assert np.max(np.abs(np.diff(cmd))) <= limits.steer_rate_max * PERIOD + 1e-12
    assert result.metrics["finished"]  # both cusps driven, stopped at the goal


def _braking_line(direction: int, length: float, cruise: float, decel: float) -> Trajectory:
    """A straight line along x driven forward (+x) or reversing (−x) at ``cruise`` m/s, whose
    planned speed falls as √(2 b d) over the last metres to rest on the end, the way the
    scenarios' plans brake (``decel`` = b, m/s²)."""
    s = np.linspace(0.0, length, round(length / 0.5) + 1)  # m, waypoints 0.5 m apart
    v = np.minimum(cruise, np.sqrt(2.0 * decel * (length - s)))
    return Trajectory(
        x=direction * s, y=np.zeros(len(s)), heading=np.zeros(len(s)), speed=direction * v
    )


@pytest.mark.slow
@pytest.mark.parametrize("plant", ["steer-lag", "dynamic"])
@pytest.mark.parametrize("direction", [+1, -1])
@pytest.mark.parametrize("kind", ["pure-pursuit", "stanley"])
def test_baseline_comes_to_rest_on_the_end_despite_the_longitudinal_lag(
    kind: str, direction: int, plant: str
) -> None:
    """On a plant whose acceleration lags the command, the car follows the plan's braking ramp
    and stops on the end: neither past it nor short of it by more than a few centimetres.

    Without the feed-forward of the planned deceleration the PI loop lagged the ramp by about
    0.3 m/s and the car stopped about 0.3 m past the end, outside the goal tolerance: "off-goal".
    """
    length, cruise = 20.0, 2.0  # m, m/s
    traj = _braking_line(direction, length, cruise, decel=0.4)
    scenario = Scenario(
        "braking-line", "20 m at 2 m/s, braking to the end", traj, Pose(0.0, 0.0, 0.0, 0.0), 40.0
    )
    cfg = drive_config(LeafgateConfig(), kind, plant)
    tracker = cfg.controller.pure_pursuit if kind == "pure-pursuit" else cfg.controller.stanley
    result = run_direct(cfg, scenario)
    travelled = direction * result.trace.x  # m, along the direction of travel
    assert travelled.max() - length <= 0.05  # never more than 5 cm past the end
    assert length - travelled[-1] <= 0.05  # nor stopped short of it
    assert result.metrics["finished"], result.metrics.get("not_finished_reason")
    assert result.metrics["final_position_error_m"] < tracker.goal_tolerance
    assert abs(result.trace.speed[-1]) <= tracker.stop_speed


def test_make_controller_builds_both_baselines_from_yaml_sections() -> None:
    data = {
        "kind": "stanley",
        "stanley": {"gain": 2.0, "softening": 1.0},
        "pure_pursuit": {"lookahead_min": 2.5},
    }
    cfg = from_mapping(ControllerConfig, data, "sim.yaml", "controller")
    ctrl = make_controller(cfg, VehicleConfig(), PERIOD)
    assert isinstance(ctrl, Stanley) and ctrl.cfg.gain == 2.0
    ctrl = make_controller(
        cfg.__class__(kind="pure-pursuit", pure_pursuit=cfg.pure_pursuit), VehicleConfig(), PERIOD
    )
    assert isinstance(ctrl, PurePursuit) and ctrl.cfg.lookahead_min == 2.5


@pytest.mark.parametrize("kind", ["mpc", "pure-pursuit", "stanley"])
def test_each_controller_s_limits_must_lie_inside_the_vehicle_s(kind: str) -> None:
    """The check reads the configured controller's own section and names it in the error."""
    section = kind.replace("-", "_")
    vehicle = VehicleConfig()
    wide = {"steer_max_deg": math.degrees(vehicle.max_steer_angle) + 1.0}
    for key, data, name in (
        ("steer_max", wide, "vehicle.max_steer_angle"),
        ("accel_max", {"accel_max": vehicle.max_accel + 0.5}, "vehicle.max_accel"),
        ("accel_min", {"accel_min": vehicle.min_accel - 0.5}, "vehicle.min_accel"),
    ):
        cfg = from_mapping(ControllerConfig, {"kind": kind, section: data}, "x.yaml", "controller")
        with pytest.raises(ConfigError, match=rf"^controller\.{section}\.{key} .*{name}"):
            make_controller(cfg, vehicle, PERIOD)
        # the same numbers in another controller's section are not this one's limits
        other = "stanley" if kind != "stanley" else "mpc"
        cfg = from_mapping(ControllerConfig, {"kind": other, section: data}, "x.yaml", "controller")
        assert make_controller(cfg, vehicle, PERIOD).period == PERIOD


def test_bad_baseline_config_names_the_key() -> None:
    with pytest.raises(ConfigError, match=r"controller\.pure_pursuit.*lookahead_min"):
        from_mapping(
            ControllerConfig, {"pure_pursuit": {"lookahead_min": -1.0}}, "x.yaml", "controller"
        )
    with pytest.raises(ConfigError, match="softening"):
        from_mapping(ControllerConfig, {"stanley": {"softening": 0.0}}, "x.yaml", "controller")
    with pytest.raises(ConfigError, match=r"controller\.stanley\.steer_max"):
        make_controller(
            ControllerConfig(kind="stanley", stanley=StanleyConfig(steer_max=0.6)),
            VehicleConfig(),
            PERIOD,
        )


@pytest.mark.parametrize("kind", [PurePursuit, Stanley])
def test_bad_inputs_are_a_status_not_an_exception(kind: type) -> None:
    cfg = PurePursuitConfig() if kind is PurePursuit else StanleyConfig()
    ctrl = kind(cfg, VehicleConfig(), PERIOD)
    out = ctrl.step(Pose(math.nan, 0.0, 0.0, 0.0), 0.0, _line(+1))
    assert not out.converged and out.status == "non-finite"
    bad = Trajectory(x=[0.0, 0.0, 1.0, 2.0], y=[0.0] * 4, heading=[0.0] * 4, speed=[1.0] * 4)
    out = kind(cfg, VehicleConfig(), PERIOD).step(Pose(0.0, 0.0, 0.0, 0.0), 0.0, bad)
    assert not out.converged
    assert out.status.startswith("bad-trajectory: trajectory: 3 waypoint")


@pytest.mark.parametrize("kind", [PurePursuit, Stanley])
def test_reverse_segment_asks_for_reverse_and_brakes_at_the_end(kind: type) -> None:
    cfg = PurePursuitConfig() if kind is PurePursuit else StanleyConfig()
    ctrl = kind(cfg, VehicleConfig(), PERIOD)
    traj = _line(-1)
    out = ctrl.step(Pose(-5.0, 0.0, 0.0, -1.0), 0.0, traj)
    assert out.gear == Gear.R and out.speed < 0.0
    for x in np.arange(-5.0, float(traj.x[-1]), -0.25):  # drive on: progress, not a jump
        ctrl.step(Pose(float(x), 0.0, 0.0, -1.0), 0.0, traj)
    out = ctrl.step(Pose(float(traj.x[-1]) - 0.05, 0.0, 0.0, -0.3), 0.0, traj)  # past the end
    assert out.status == "stopping" and out.accel > 0.0  # d(v)/dt > 0 brakes a reversing car
    out = ctrl.step(Pose(float(traj.x[-1]), 0.0, 0.0, 0.0), 0.0, traj)
    assert out.finished and out.gear == Gear.R


def _bend(direction: int, radius: float = 8.0) -> Trajectory:
    """5 m straight, then 15 m of a left bend of ``radius`` m (rear axle), waypoints 0.5 m
    apart; driven forward, or in reverse along the same ground (the vehicle facing back)."""
    s = 0.5 * np.arange(41)
    turn = np.maximum(s - 5.0, 0.0) / radius  # rad turned by each waypoint
    x = np.where(s <= 5.0, s, 5.0 + radius * np.sin(turn))
    y = np.where(s <= 5.0, 0.0, radius * (1.0 - np.cos(turn)))
    speed = np.minimum(np.minimum(0.3 + 0.1 * np.arange(41), 1.5), 0.3 * (40 - np.arange(41)))
    heading = turn if direction > 0 else turn + math.pi
    return Trajectory(x=x, y=y, heading=heading, speed=direction * speed)


@pytest.mark.parametrize("direction", [1, -1])
def test_stanley_holds_the_rear_axle_on_a_bend(direction: int) -> None:
    """Old code held the front axle on the rear axle's path: on an 8 m radius the rear axle ran
    L²/2R = 0.46 m inside the bend (and Stanley missed the parking goals by 0.2 m)."""
    traj = _bend(direction)
    start = Pose(float(traj.x[0]), float(traj.y[0]), float(traj.heading[0]), 0.0)
    scenario = Scenario("bend", "an 8 m bend", traj, start, 60.0)
    cfg = drive_config(LeafgateConfig(), "stanley", "kinematic")
    metrics = run_direct(cfg, scenario).metrics
    assert metrics["finished"], metrics.get("not_finished_reason")
    assert metrics["lateral_error_max_m"] < 0.03
    assert metrics["final_position_error_m"] < 0.05
