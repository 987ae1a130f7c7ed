"""The MPC controller: optimum, limits, faults as status, segments and gears, construction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.config import VehicleConfig
from leafgate.config.control import ControllerConfig, MpcConfig
from leafgate.control import make_controller
from leafgate.control.baselines import PurePursuit, Stanley
from leafgate.control.mpc import MpcController
from leafgate.errors import ConfigError
from leafgate.messages import Gear, Pose, Trajectory

PERIOD = 0.02  # s


def _curve(n: int = 60, spacing: float = 0.5, speed: float = 1.5) -> Trajectory:
    """A gentle left arc of radius 15 m with a stop at the end."""
    s = spacing * np.arange(n)
    angle = s / 15.0
    v = np.full(n, speed)
    v[-1] = 0.0
    return Trajectory(x=15 * np.sin(angle), y=15 * (1 - np.cos(angle)), heading=angle, speed=v)


def _controller(**kw: object) -> MpcController:
    return MpcController(MpcConfig(**kw), VehicleConfig(), PERIOD)  # type: ignore[arg-type]


def test_unconstrained_step_is_the_closed_form_optimum() -> None:
    """Eq. 29 with Q: ΔU = (SᵀQS + R̄)⁻¹ SᵀQ (Rs − F x) — through both backends."""
    rng = np.random.default_rng(0)
    for solver in ("daqp", "hildreth", "osqp"):
        ctrl = _controller(solver=solver)
        n = ctrl.Nc * 2
        G = rng.normal(size=(ctrl.Np * 4, n))
        err = rng.normal(size=ctrl.Np * 4) * 1e-3  # small: no limit is reached
        Q = np.diag(ctrl.q_bar)
        E = 2.0 * (G.T @ Q @ G + np.diag(ctrl.r_bar))
        f = -2.0 * G.T @ Q @ err
        gamma = np.concatenate(
            (np.full(2 * n, 1.0), ctrl.du_max, ctrl.du_max, np.full(ctrl.Np, 1.0))
        )  # the input limits, then the speed rows (never against the gear)
        result = ctrl._solve(E, f, gamma)
        closed = np.linalg.solve(G.T @ Q @ G + np.diag(ctrl.r_bar), G.T @ Q @ err)
        assert result.converged and result.iterations == 0
        np.testing.assert_allclose(result.x, closed, atol=1e-10)


@pytest.mark.parametrize("solver", ["hildreth", "osqp"])
def test_step_on_the_path_is_ok_and_predicts_along_it(solver: str) -> None:
    traj = _curve()
    ctrl = _controller(solver=solver)
    pose = Pose(traj.x[10], traj.y[10], traj.heading[10], 1.5)
    out = ctrl.step(pose, math.atan(2.7 / 15.0), traj)
    assert out.status == "ok" and out.converged
    assert out.gear == Gear.D
    assert out.predicted_xy is not None and out.predicted_xy.shape == (ctrl.Np, 2)
    # the predicted positions stay near the arc
    radius = np.hypot(out.predicted_xy[:, 0], out.predicted_xy[:, 1] - 15.0)
    assert np.max(np.abs(radius - 15.0)) < 0.1
    assert out.solve_time > 0.0 and math.isfinite(out.cost)


def test_both_backends_apply_the_same_first_move_when_constrained() -> None:
    traj = _curve()
    pose = Pose(traj.x[10] + 0.3, traj.y[10] - 0.6, traj.heading[10] + 0.2, 1.0)
    outs = []
    for solver in ("hildreth", "osqp"):
        ctrl = _controller(solver=solver, max_iterations=5000)
        outs.append(ctrl.step(pose, 0.0, traj))
    assert all(o.converged for o in outs)
    assert outs[0].steer_angle == pytest.approx(outs[1].steer_angle, abs=1e-4)
    assert outs[0].accel == pytest.approx(outs[1].accel, abs=1e-4)


poses = st.tuples(
    st.integers(0, 50),  # waypoint
    st.floats(-1.5, 1.5),  # lateral offset, m
    st.floats(-0.6, 0.6),  # heading error, rad
    st.floats(-0.5, 3.0),  # speed, m/s
    st.floats(-0.6, 0.6),  # measured steering, rad
)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(poses, min_size=1, max_size=6),
    st.sampled_from(["hildreth", "osqp"]),
    st.sampled_from([1, 38]),
)
def test_applied_input_never_leaves_the_limits(
    sequence: list[tuple], solver: str, max_iterations: int
) -> None:
    """Amplitude and per-tick rate limits hold for every output, even at a 1-sweep cap."""
    traj = _curve()
    cfg = MpcConfig(solver=solver, max_iterations=max_iterations)  # type: ignore[arg-type]
    ctrl = MpcController(cfg, VehicleConfig(), PERIOD)
    prev: tuple[float, float] | None = None
    for i, lateral, dpsi, v, steer in sequence:
        psi = traj.heading[i]
        pose = Pose(
            traj.x[i] - lateral * math.sin(psi), traj.y[i] + lateral * math.cos(psi), psi + dpsi, v
        )
        out = ctrl.step(pose, steer, traj)
        assert abs(out.steer_angle) <= cfg.steer_max + 1e-12
        assert cfg.accel_min - 1e-12 <= out.accel <= cfg.accel_max + 1e-12
        if prev is not None:
            assert abs(math.tan(out.steer_angle) - math.tan(prev[0])) <= (
                cfg.steer_rate_max * PERIOD + 1e-12
            )
            assert abs(out.steer_angle - prev[0]) <= cfg.steer_rate_max * PERIOD + 1e-12
            assert abs(out.accel - prev[1]) <= cfg.jerk_max * PERIOD + 1e-12
        prev = (out.steer_angle, out.accel)


def test_iteration_cap_is_reported_and_clipped() -> None:
    traj = _curve()
    ctrl = _controller(solver="hildreth", max_iterations=1)
    pose = Pose(traj.x[5], traj.y[5] - 1.0, traj.heading[5] + 0.4, 2.0)
    out = ctrl.step(pose, 0.0, traj)
    assert not out.converged and out.status == "not-converged"
    assert out.iterations == 1


@pytest.mark.parametrize(
    ("pose", "steer"),
    [
        (Pose(math.nan, 0.0, 0.0, 1.0), 0.0),
        (Pose(0.0, 0.0, math.inf, 1.0), 0.0),
        (Pose(0.0, 0.0, 0.0, 1.0), math.nan),
    ],
)
def test_non_finite_input_is_a_status_not_an_exception(pose: Pose, steer: float) -> None:
    out = _controller().step(pose, steer, _curve())
    assert not out.converged and out.status == "non-finite"
    assert math.isfinite(out.steer_angle) and math.isfinite(out.accel)


def test_bad_trajectory_is_a_status_not_an_exception() -> None:
    bad = Trajectory(x=[0.0, 0.5, 0.5, 1.0], y=[0.0] * 4, heading=[0.0] * 4, speed=[1.0] * 4)
    out = _controller().step(Pose(0.0, 0.0, 0.0, 0.0), 0.0, bad)
    # the reason the controller found is shown, not only stored (issue 13)
    assert not out.converged
    assert out.status == (
        "bad-trajectory: trajectory: 3 waypoint(s) (1 overlapping removed), at least 4 are needed"
    )


def test_reverse_segment_asks_for_reverse_gear_and_brakes_positive() -> None:
    n = 12
    x = -0.5 * np.arange(n)
    traj = Trajectory(x=x, y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, -1.0))
    ctrl = _controller()
    out = ctrl.step(Pose(-2.0, 0.0, 0.0, -1.0), 0.0, traj)
    assert out.gear == Gear.R
    assert out.speed <= 0.0
    out = ctrl.step(Pose(-2.0, 0.0, 0.0, -1.5), 0.0, traj)  # too fast backwards
    assert out.accel > 0.0  # d(v)/dt > 0 slows a reversing car


def test_cusp_switches_segment_at_rest_and_then_finishes() -> None:
    fwd = 0.5 * np.arange(6)  # 0 … 2.5 m forward, then back to 0
    x = np.concatenate((fwd, fwd[-2::-1]))
    speed = np.concatenate(([0.5] * 5, [0.0], [-0.5] * 4, [0.0]))
    y = np.concatenate((np.zeros(6), 0.05 * np.arange(1, 6)))  # offset: no repeated points
    traj = Trajectory(x=x, y=y, heading=np.zeros(x.size), speed=speed)
    ctrl = _controller()
    out = ctrl.step(Pose(1.0, 0.0, 0.0, 0.5), 0.0, traj)
    assert out.gear == Gear.D and not out.finished
    out = ctrl.step(Pose(2.5, 0.0, 0.0, 0.0), 0.0, traj)  # at rest on the cusp
    assert out.gear == Gear.R and not out.finished
    out = ctrl.step(Pose(x[-1], y[-1], 0.0, 0.0), 0.0, traj)  # at rest on the last point
    assert out.finished and out.speed == 0.0
    assert out.accel > 0.0  # the hold request brakes in reverse: positive d(v)/dt


def test_reset_forgets_the_last_input() -> None:
    traj = _curve()
    ctrl = _controller()
    pose = Pose(traj.x[10], traj.y[10] - 0.5, traj.heading[10], 1.5)
    first = ctrl.step(pose, 0.3, traj)
    for _ in range(5):
        ctrl.step(pose, 0.3, traj)
    ctrl.reset()
    again = ctrl.step(pose, 0.3, traj)
    assert again.steer_angle == pytest.approx(first.steer_angle, abs=1e-9)


def test_make_controller_builds_each_kind() -> None:
    ctrl = make_controller(ControllerConfig(), VehicleConfig(), 0.02)
    assert isinstance(ctrl, MpcController) and ctrl.period == 0.02
    assert isinstance(
        make_controller(ControllerConfig(kind="stanley"), VehicleConfig(), 0.02), Stanley
    )
    pure = make_controller(ControllerConfig(kind="pure-pursuit"), VehicleConfig(), 0.02)
    assert isinstance(pure, PurePursuit)


def test_make_controller_refuses_limits_outside_the_vehicle() -> None:
    cfg = ControllerConfig(mpc=MpcConfig(steer_max=math.radians(35)))
    with pytest.raises(ConfigError, match="steer_max"):
        make_controller(cfg, VehicleConfig(), 0.02)
    cfg = ControllerConfig(mpc=MpcConfig(accel_max=2.9))
    with pytest.raises(ConfigError, match="accel_max"):
        make_controller(cfg, VehicleConfig(max_accel=2.5), 0.02)


def test_default_limits_sit_inside_the_vehicle_and_the_safety_gate() -> None:
    cfg, vehicle = MpcConfig(), VehicleConfig()
    assert cfg.steer_max < vehicle.max_steer_angle
    assert vehicle.min_accel < cfg.accel_min < 0.0 < cfg.accel_max < vehicle.max_accel
    assert cfg.steer_rate_max <= 0.5  # rad/s: below the gate's 0.6 rad/s at low speed


@pytest.mark.parametrize("model", ["kinematic", "kinematic_steer_lag"])
def test_earlier_outputs_are_not_changed_by_later_steps(model: str) -> None:
    """The step reuses work buffers; what it returned before must stay as it was."""
    traj = _curve()
    ctrl = _controller(model=model)
    kept = []
    for k in range(12):
        i = 5 + k
        pose = Pose(traj.x[i] + 0.1, traj.y[i] - 0.2, traj.heading[i] + 0.05, 1.4)
        out = ctrl.step(pose, 0.1 * (-1) ** k, traj)
        assert out.predicted_xy is not None
        kept.append((out, out.predicted_xy.copy(), out.steer_angle, out.accel, out.cost))
    for out, xy, steer, accel, cost in kept:
        np.testing.assert_array_equal(out.predicted_xy, xy)
        assert (out.steer_angle, out.accel, out.cost) == (steer, accel, cost)
