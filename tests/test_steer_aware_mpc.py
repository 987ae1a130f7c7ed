"""The steering-aware MPC: the actuator model, dead-time compensation, and what it fixes.

The paper's MPC predicts with the kinematic bicycle; on a car whose wheel follows the command
with a lag and a dead time it oscillates (the paper's LGSVL result). The steering-aware model
adds the actuator to the prediction and removes the oscillation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from leafgate.config import VehicleConfig, from_mapping
from leafgate.config.control import ControllerConfig, MpcConfig
from leafgate.config.sim import PlantConfig, SimConfig
from leafgate.control.model import (
    KinematicPrediction,
    augment_steer_lag,
    grouped_by_output,
    linearise,
    linearise_along,
    mid_heading,
    move_steps,
    prediction_matrices,
    prediction_matrices_ltv,
    steer_lag_factor,
    steer_lag_first_increment,
    steer_lag_increment,
)
from leafgate.control.mpc import MpcController
from leafgate.errors import ConfigError
from leafgate.messages import Pose, Trajectory
from leafgate.settings import LeafgateConfig
from leafgate.sim.metrics import sign_changes
from leafgate.sim.runner import run, run_direct
from leafgate.sim.scenarios import get_scenario

Ts, L = 0.1, 2.7  # s, m
PERIOD = 0.02  # s


def _config(model: str, plant: str) -> LeafgateConfig:
    return LeafgateConfig(
        controller=ControllerConfig(mpc=MpcConfig(model=model)),  # type: ignore[arg-type]
        sim=SimConfig(plant=PlantConfig(kind=plant)),  # type: ignore[arg-type]
    )


def _curve_sign_changes(traj: Trajectory) -> int:
    """Reversals of the steering the path itself needs (road-wheel angle of its curvature)."""
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(traj.x), np.diff(traj.y)))))
    angle = np.arctan(L * np.gradient(np.unwrap(traj.heading), s))
    return sign_changes(np.diff(angle), deadband=1e-4)


def test_ltv_prediction_equals_the_step_by_step_recursion() -> None:
    rng = np.random.default_rng(3)
    Np, Nc = 12, 4
    A, B = linearise_along(
        np.linspace(1.5, 0.0, Np), np.linspace(0.0, 0.4, Np), np.full(Np, 0.2), Ts, L
    )
    A, B = augment_steer_lag(A, B, steer_lag_factor(Ts, 0.3), Ts, np.linspace(1.5, 0.0, Np), L)
    C = np.eye(4, 5)
    F, S = prediction_matrices_ltv(A, B, C, Nc)
    dx, y = rng.normal(size=5), rng.normal(size=4)
    dU = rng.normal(size=2 * Nc)
    expected = []
    state_dx, out = dx.copy(), y.copy()
    for k in range(Np):
        du = dU[2 * k : 2 * k + 2] if k < Nc else np.zeros(2)
        state_dx = A[k] @ state_dx + B[k] @ du
        out = out + C @ state_dx
        expected.append(out.copy())
    np.testing.assert_allclose(
        F @ np.concatenate((dx, y)) + S @ dU, np.concatenate(expected), atol=1e-12
    )


def _lag_prediction_by_recursion(
    A: np.ndarray, B: np.ndarray, moves: np.ndarray, dx: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """S (rows by step) and the free response of the lag model, step by step: each move's
    column propagated by the Jacobians from the step it acts at, no inverse of a product."""
    Np, Nc = A.shape[0], len(moves)
    S = np.zeros((Np * 4, 2 * Nc))
    for j, b in enumerate(moves):
        col, acc = B[b].copy(), np.zeros((5, 2))
        for m in range(b + 1, Np + 1):
            if m > b + 1:
                col = A[m - 1] @ col
            acc += col
            S[4 * (m - 1) : 4 * m, 2 * j : 2 * j + 2] = acc[:4]
    free, state, acc_x = [], dx.copy(), np.zeros(5)
    for k in range(Np):
        state = A[k] @ state  # Pₖ₊₁ Δx₀
        acc_x += state
        free.append(acc_x[:4].copy())
    return S, np.concatenate(free)


@pytest.mark.parametrize("tau", [0.3, 0.1, 0.05])
@pytest.mark.parametrize("sizes", [(30, 10, True), (30, 10, False), (7, 3, True), (1, 1, False)])
def test_closed_form_lag_prediction_equals_the_recursion(
    tau: float, sizes: tuple[int, int, bool]
) -> None:
    """KinematicPrediction with the steering lag gives the lag model's S and free response,
    to rounding, also for a fast actuator: β⁻ᵐ (e⁶⁰ at τ = 0.05 s over 30 steps) never enters.
    The general LTV prediction inverts prefix products and loses digits there."""
    Np, Nc, spread = sizes
    moves = move_steps(Np, Nc, spread)
    alpha = steer_lag_factor(Ts, tau)
    rng = np.random.default_rng(round(100 * tau) + Np)
    speed, heading = rng.uniform(-3.0, 3.0, Np), rng.uniform(-1.0, 1.0, Np)
    tan_actual = 0.2
    A, B = linearise_along(speed, heading, np.full(Np, tan_actual), Ts, L)
    A, B = augment_steer_lag(A, B, alpha, Ts, speed, L)
    dx = rng.normal(size=5)
    S, free = _lag_prediction_by_recursion(A, B, moves, dx)
    predict = KinematicPrediction(Np, Nc, Ts, L, moves, steer_alpha=alpha)
    ST, free_closed = predict(speed, heading, tan_actual, tuple(dx))
    scale = max(1.0, float(np.abs(S).max()))
    np.testing.assert_allclose(ST.T, grouped_by_output(S, Np), atol=1e-13 * scale)
    expected_free = grouped_by_output(free[:, None], Np).ravel()
    np.testing.assert_allclose(free_closed, expected_free, atol=1e-12)


def test_lag_prediction_results_survive_the_next_call() -> None:
    """The lag's work buffers are reused between calls; the returned arrays are not them."""
    Np, Nc = 30, 10
    alpha = steer_lag_factor(Ts, 0.3)
    rng = np.random.default_rng(8)
    predict = KinematicPrediction(Np, Nc, Ts, L, move_steps(Np, Nc, True), steer_alpha=alpha)
    args = (rng.uniform(0.0, 3.0, Np), rng.uniform(-1.0, 1.0, Np), 0.2, tuple(rng.normal(size=5)))
    ST, free = predict(*args)
    ST_copy, free_copy = ST.copy(), free.copy()
    predict(rng.uniform(-3.0, 0.0, Np), rng.uniform(-1.0, 1.0, Np), -0.4, rng.normal(size=5))
    np.testing.assert_array_equal(ST, ST_copy)
    np.testing.assert_array_equal(free, free_copy)
    fresh = KinematicPrediction(Np, Nc, Ts, L, move_steps(Np, Nc, True), steer_alpha=alpha)
    fresh_ST, fresh_free = fresh(*args)
    np.testing.assert_array_equal(ST, fresh_ST)
    np.testing.assert_array_equal(free, fresh_free)


def test_lag_first_increment_inverts_the_jacobian() -> None:
    alpha = steer_lag_factor(Ts, 0.3)
    rng = np.random.default_rng(5)
    for _ in range(20):
        state = rng.uniform(-1.0, 1.0, 5) * np.array([5.0, 5.0, 3.0, 3.0, 0.5])
        u = rng.uniform(-1.0, 1.0, 2) * np.array([2.0, 0.5])
        v_op = rng.uniform(-3.0, 3.0)
        th_op = mid_heading(state, Ts, L)  # the step's heading half way through it
        A, B = linearise_along(np.array([v_op]), np.array([th_op]), state[4:], Ts, L)
        A, _ = augment_steer_lag(A, B, alpha, Ts, np.array([v_op]), L)
        dx = steer_lag_first_increment(tuple(state), tuple(u), v_op, Ts, L, alpha)
        increment = steer_lag_increment(state, u, Ts, L, alpha)
        np.testing.assert_allclose(A[0] @ np.array(dx), increment, atol=1e-14)


def test_ltv_prediction_with_constant_jacobians_is_the_papers() -> None:
    A, B = linearise(np.array([1.0, 2.0, 1.5, 0.3]), np.array([0.2, 0.1]), Ts, L)
    F, S = prediction_matrices(A, B, np.eye(4), 30, 10)
    F2, S2 = prediction_matrices_ltv(
        np.repeat(A[None], 30, 0), np.repeat(B[None], 30, 0), np.eye(4), 10
    )
    np.testing.assert_allclose(F2, F, atol=1e-12)
    np.testing.assert_allclose(S2, S, atol=1e-12)


def test_steer_lag_jacobians_match_finite_differences_of_the_increment() -> None:
    """At the step's middle heading, the paper's Jacobians and the midpoint step's own differ by
    exactly the midpoint's extra terms, which the model leaves out: ``∂/∂v`` and ``∂/∂t`` of
    the position through the half turn ``½ Ts v t / L`` (of order ``Ts²``)."""
    alpha = steer_lag_factor(Ts, 0.3)
    x = np.array([0.5, -0.2, 1.2, 0.3, 0.15])
    u = np.array([0.4, -0.1])
    mid = mid_heading(x, Ts, L)
    A4, B4 = linearise_along(np.array([x[2]]), np.array([mid]), np.array([x[4]]), Ts, L)
    A, B = augment_steer_lag(A4, B4, alpha, Ts, np.array([x[2]]), L)
    v, t = x[2], x[4]
    turn = np.array([-math.sin(mid), math.cos(mid)]) * Ts * v  # ∂(x, y)⁺/∂θ_mid
    A[0, :2, 2] += turn * 0.5 * Ts * t / L  # through θ_mid's ½ Ts t / L per unit speed
    A[0, :2, 4] += turn * 0.5 * Ts * v / L  # and its ½ Ts v / L per unit tan δ

    def step(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return x + steer_lag_increment(x, u, Ts, L, alpha)

    eps = 1e-7
    num_A = np.column_stack(
        [(step(x + eps * e, u) - step(x - eps * e, u)) / (2 * eps) for e in np.eye(5)]
    )
    num_B = np.column_stack(
        [(step(x, u + eps * e) - step(x, u - eps * e)) / (2 * eps) for e in np.eye(2)]
    )
    np.testing.assert_allclose(A[0], num_A, atol=1e-7)
    np.testing.assert_allclose(B[0], num_B, atol=1e-7)


def test_model_is_selected_by_config_and_checked() -> None:
    cfg = from_mapping(MpcConfig, {"model": "kinematic_steer_lag", "steer_tau": 0.25}, "s.yaml")
    assert MpcController(cfg, VehicleConfig(), PERIOD).steer_model
    assert not MpcController(MpcConfig(), VehicleConfig(), PERIOD).steer_model
    with pytest.raises(ConfigError, match="model"):
        from_mapping(MpcConfig, {"model": "dynamic"}, "s.yaml")
    # a lag so fast that 1 − α is 0 in floats: refused at load, not a division by zero per tick
    fast = {"model": "kinematic_steer_lag", "steer_tau": 0.0001}
    with pytest.raises(ConfigError, match=r"steer_tau must be at least sample_time / 10 = 0.01 s"):
        from_mapping(MpcConfig, fast, "s.yaml")
    assert from_mapping(MpcConfig, {**fast, "model": "kinematic"}, "s.yaml").steer_tau == 0.0001


def test_dead_time_is_compensated_over_the_commands_in_flight() -> None:
    """A wheel commanded hard left a moment ago is predicted to be turning left now, so the
    controller steers less than one that believes the measured (still straight) wheel."""
    n = 40
    traj = Trajectory(
        x=0.5 * np.arange(n), y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, 2.0)
    )
    pose = Pose(5.0, -0.3, 0.0, 2.0)  # right of the line: steer left
    fast = 5.0  # rad/s: a rate limit that does not bind, so only the prediction differs
    ctrl = MpcController(
        MpcConfig(model="kinematic_steer_lag", steer_rate_max=fast), VehicleConfig(), PERIOD
    )
    fresh = ctrl.step(pose, 0.0, traj).steer_angle
    for _ in range(7):  # commands go out, the measured wheel has not moved yet (dead time)
        last = ctrl.step(pose, 0.0, traj).steer_angle
    no_comp = MpcController(
        MpcConfig(model="kinematic_steer_lag", steer_dead_time=0.0, steer_rate_max=fast),
        VehicleConfig(),
        PERIOD,
    )
    for _ in range(8):
        plain = no_comp.step(pose, 0.0, traj).steer_angle
    assert fresh > 0.0 and last > 0.0
    assert last < plain - 0.003  # rad: it counts on the left turn already on its way


@pytest.mark.slow
def test_plain_mpc_oscillates_on_the_steer_lag_plant_and_the_steering_aware_one_does_not() -> None:
    scenario = get_scenario("slalom")  # 3 m/s: where the lag matters most
    curve = _curve_sign_changes(scenario.trajectory)
    plain = run_direct(_config("kinematic", "steer-lag"), scenario).metrics
    aware = run_direct(_config("kinematic_steer_lag", "steer-lag"), scenario).metrics
    assert plain["steer_rate_sign_changes"] > curve + 3  # it oscillates
    assert aware["steer_rate_sign_changes"] <= curve + 1  # the curve's own, plus the stop
    assert aware["lateral_error_max_m"] < 0.1
    # 6.7 cm against 4.1 cm (with forward-Euler steps it was 25 cm against 5.3 cm)
    assert plain["lateral_error_max_m"] > 1.5 * aware["lateral_error_max_m"]


@pytest.mark.slow
def test_steering_aware_mpc_tracks_the_s_curve_on_the_dynamic_plant_within_10_cm() -> None:
    result = run(_config("kinematic_steer_lag", "dynamic"), get_scenario("s-curve"))
    assert result.metrics["lateral_error_max_m"] <= 0.10
    assert result.metrics["finished"] and result.metrics["solver_not_converged"] == 0


def test_steering_aware_output_stays_within_the_limits_when_far_off() -> None:
    n = 40
    traj = Trajectory(
        x=0.5 * np.arange(n), y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, 2.0)
    )
    cfg = MpcConfig(model="kinematic_steer_lag")
    ctrl = MpcController(cfg, VehicleConfig(), PERIOD)
    prev = None
    for k in range(50):
        out = ctrl.step(Pose(1.0 + 0.04 * k, 2.0, 0.5, 2.0), math.radians(10.0), traj)
        assert abs(out.steer_angle) <= cfg.steer_max + 1e-12
        if prev is not None:
            assert abs(out.steer_angle - prev) <= cfg.steer_rate_max * PERIOD + 1e-12
        prev = out.steer_angle
