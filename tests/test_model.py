"""The kinematic bicycle, its linearisation, the augmented model and the prediction matrices."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.control.model import (
    KinematicPrediction,
    augment,
    derivative,
    euler_step,
    grouped_by_output,
    kinematic_first_increment,
    linearise,
    linearise_along,
    matrix_powers,
    prediction_matrices,
    prediction_matrices_ltv,
    rk4_step,
)

L = 2.70  # m, Leaf wheelbase
Ts = 0.1  # s

states = st.tuples(
    st.floats(-50, 50), st.floats(-50, 50), st.floats(-3, 3), st.floats(-math.pi, math.pi)
)
inputs = st.tuples(st.floats(-3, 3), st.floats(-0.6, 0.6))


def _fd_jacobians(x: np.ndarray, u: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Central finite differences of the Euler map x + Ts f(x, u)."""
    A = np.zeros((4, 4))
    B = np.zeros((4, 2))
    for j in range(4):
        e = np.zeros(4)
        e[j] = h
        A[:, j] = (euler_step(x + e, u, Ts, L) - euler_step(x - e, u, Ts, L)) / (2 * h)
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        B[:, j] = (euler_step(x, u + e, Ts, L) - euler_step(x, u - e, Ts, L)) / (2 * h)
    return A, B


@settings(max_examples=60, deadline=None)
@given(states, inputs)
def test_linearisation_matches_finite_differences(x: tuple, u: tuple) -> None:
    xa, ua = np.array(x), np.array(u)
    A, B = linearise(xa, ua, Ts, L)
    A_fd, B_fd = _fd_jacobians(xa, ua)
    np.testing.assert_allclose(A, A_fd, atol=1e-7)
    np.testing.assert_allclose(B, B_fd, atol=1e-7)


def test_linearisation_contains_the_papers_entries() -> None:
    """Eq. 11–12: Ts cos θ, Ts sin θ, Ts on a, Ts v / L on tan δ."""
    x = np.array([1.0, 2.0, 1.5, 0.4])
    A, B = linearise(x, np.array([0.0, 0.0]), Ts, L)
    assert A[0, 2] == pytest.approx(Ts * math.cos(0.4))
    assert A[1, 2] == pytest.approx(Ts * math.sin(0.4))
    assert B[2, 0] == pytest.approx(Ts)
    assert B[3, 1] == pytest.approx(Ts * 1.5 / L)


def test_rk4_follows_the_exact_circle() -> None:
    """Constant speed and steering: a circle of radius L / tan δ about a known centre."""
    v, tan_delta = 2.0, 0.2
    radius = L / tan_delta
    x = np.array([0.0, 0.0, v, 0.0])
    t_end, dt = 5.0, 0.05
    for _ in range(round(t_end / dt)):
        x = rk4_step(x, np.array([0.0, tan_delta]), dt, L)
    angle = v * t_end / radius
    assert x[0] == pytest.approx(radius * math.sin(angle), abs=1e-6)
    assert x[1] == pytest.approx(radius * (1 - math.cos(angle)), abs=1e-6)
    assert x[3] == pytest.approx(angle, abs=1e-9)


def test_derivative_is_the_bicycle() -> None:
    d = derivative(np.array([0.0, 0.0, 2.0, math.pi / 2]), np.array([0.5, 0.1]), L)
    np.testing.assert_allclose(d, [0.0, 2.0, 0.5, 2.0 * 0.1 / L], atol=1e-12)


def test_augmented_step_equals_difference_of_two_plant_steps() -> None:
    """For a linear plant the augmented model (eq. 18) is exact."""
    rng = np.random.default_rng(1)
    A = np.eye(4) + 0.1 * rng.normal(size=(4, 4))
    B = rng.normal(size=(4, 2))
    C = rng.normal(size=(3, 4))
    Aa, Ba, Ca = augment(A, B, C)
    x_prev, u_prev, u_now = rng.normal(size=4), rng.normal(size=2), rng.normal(size=2)
    x_now = A @ x_prev + B @ u_prev
    x_next = A @ x_now + B @ u_now
    aug_now = np.concatenate((x_now - x_prev, C @ x_now))
    aug_next = Aa @ aug_now + Ba @ (u_now - u_prev)
    np.testing.assert_allclose(aug_next[:4], x_next - x_now, atol=1e-12)
    np.testing.assert_allclose(aug_next[4:], C @ x_next, atol=1e-12)
    np.testing.assert_allclose(Ca @ aug_next, C @ x_next, atol=1e-12)


def test_augmented_step_tracks_the_nonlinear_plant_to_second_order() -> None:
    x_prev = np.array([0.0, 0.0, 1.5, 0.1])
    u_prev = np.array([0.2, 0.05])
    x_now = euler_step(x_prev, u_prev, Ts, L)
    u_now = u_prev + np.array([0.01, 0.002])
    x_next = euler_step(x_now, u_now, Ts, L)
    A, B = linearise(x_now, u_prev, Ts, L)
    Aa, Ba, _ = augment(A, B, np.eye(4))
    aug_next = Aa @ np.concatenate((x_now - x_prev, x_now)) + Ba @ (u_now - u_prev)
    np.testing.assert_allclose(aug_next[4:], x_next, atol=1e-4)


def test_matrix_powers_by_doubling() -> None:
    A = np.array([[1.0, 0.1], [-0.2, 0.9]])
    powers = matrix_powers(A, 13)
    for k in range(13):
        np.testing.assert_allclose(powers[k], np.linalg.matrix_power(A, k), atol=1e-12)


@pytest.mark.parametrize(
    ("Np", "Nc", "rows"), [(30, 10, [0, 1, 2, 3]), (7, 3, [1, 2, 3]), (5, 5, [1])]
)
def test_prediction_matrices_equal_block_by_block_construction(
    Np: int, Nc: int, rows: list[int]
) -> None:
    A, B = linearise(np.array([1.0, 2.0, 1.5, 0.3]), np.array([0.2, 0.1]), Ts, L)
    C = np.eye(4)[rows]
    F, S = prediction_matrices(A, B, C, Np, Nc)
    Aa, Ba, Ca = augment(A, B, C)
    q, m = C.shape[0], 2
    F_ref = np.vstack([Ca @ np.linalg.matrix_power(Aa, i) for i in range(1, Np + 1)])
    S_ref = np.zeros((Np * q, Nc * m))
    for i in range(Np):
        for j in range(min(i + 1, Nc)):
            S_ref[i * q : (i + 1) * q, j * m : (j + 1) * m] = (
                Ca @ np.linalg.matrix_power(Aa, i - j) @ Ba
            )
    np.testing.assert_allclose(F, F_ref, atol=1e-10)
    np.testing.assert_allclose(S, S_ref, atol=1e-10)


# --- the closed-form kinematic prediction ------------------------------------------------------

horizons = st.sampled_from([(30, 10), (7, 3), (5, 5), (1, 1), (12, 1)])


@settings(max_examples=40, deadline=None)
@given(horizons, st.integers(0, 10_000), st.floats(-0.6, 0.6))
def test_closed_form_kinematic_prediction_equals_the_general_one(
    sizes: tuple[int, int], seed: int, tan_delta: float
) -> None:
    """S and the free response of KinematicPrediction are those of prediction_matrices_ltv."""
    Np, Nc = sizes
    rng = np.random.default_rng(seed)
    speed = rng.uniform(-3.0, 3.0, Np)
    heading = rng.uniform(-1.0, 1.0, Np)
    dx0 = rng.normal(size=4)
    A, B = linearise_along(speed, heading, np.full(Np, tan_delta), Ts, L)
    F, S = prediction_matrices_ltv(A, B, np.eye(4), Nc)
    ST, free = KinematicPrediction(Np, Nc, Ts, L)(speed, heading, tan_delta, dx0)
    np.testing.assert_allclose(ST.T, grouped_by_output(S, Np), atol=1e-12)
    expected_free = grouped_by_output((F[:, :4] @ dx0)[:, None], Np).ravel()
    np.testing.assert_allclose(free, expected_free, atol=1e-11)


def test_kinematic_prediction_results_survive_the_next_call() -> None:
    """Work buffers are reused between calls; the returned arrays must not be among them."""
    Np, Nc = 30, 10
    rng = np.random.default_rng(3)
    predict = KinematicPrediction(Np, Nc, Ts, L)
    args = (rng.uniform(0.0, 3.0, Np), rng.uniform(-1.0, 1.0, Np), 0.2, (0.1, -0.2, 0.05, 0.01))
    ST, free = predict(*args)
    ST_copy, free_copy = ST.copy(), free.copy()
    predict(rng.uniform(-3.0, 0.0, Np), rng.uniform(-1.0, 1.0, Np), -0.4, rng.normal(size=4))
    np.testing.assert_array_equal(ST, ST_copy)
    np.testing.assert_array_equal(free, free_copy)
    fresh_ST, fresh_free = KinematicPrediction(Np, Nc, Ts, L)(*args)
    np.testing.assert_array_equal(ST, fresh_ST)
    np.testing.assert_array_equal(free, fresh_free)


def test_outputs_grouped_by_output_are_a_row_permutation() -> None:
    S = np.arange(24.0).reshape(6, 4)  # Np = 3 steps of q = 2 outputs
    grouped = grouped_by_output(S, 3)
    np.testing.assert_array_equal(grouped, S[[0, 2, 4, 1, 3, 5]])


@settings(max_examples=40, deadline=None)
@given(states, inputs)
def test_first_increment_inverts_the_jacobian(x: tuple, u: tuple) -> None:
    state, inp = np.array(x), np.array(u)
    A, _ = linearise(state, inp, Ts, L)
    z = Ts * derivative(state, inp, L)
    dx = kinematic_first_increment(tuple(z), x[2], x[3], u[1], Ts, L)
    np.testing.assert_allclose(dx, np.linalg.solve(A, z), atol=1e-12)
