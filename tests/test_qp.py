"""Hildreth's procedure and the OSQP backend on the MPC's QP form."""

from __future__ import annotations

import copy
import functools
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.control.qp import DaqpBackend, OsqpBackend, hildreth, qphild


def _random_qp(seed: int, n: int = 8, m: int = 12) -> tuple[np.ndarray, ...]:
    """A strictly convex QP with a feasible set containing x = 0 (γ > 0)."""
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(n, n))
    E = G @ G.T + 0.5 * np.eye(n)
    f = rng.normal(size=n) * 10.0
    M = rng.normal(size=(m, n))
    gamma = rng.uniform(0.05, 1.0, size=m)
    return E, f, M, gamma


def _box_qp(seed: int, Nc: int = 6) -> tuple[np.ndarray, ...]:
    """The MPC's structure: amplitude (cumulative) and rate bounds on two inputs."""
    rng = np.random.default_rng(seed)
    n = 2 * Nc
    G = rng.normal(size=(3 * n, n))
    E = 2.0 * (G.T @ G + 0.1 * np.eye(n))
    f = rng.normal(size=n) * 20.0
    cum = np.kron(np.tril(np.ones((Nc, Nc))), np.eye(2))
    eye = np.eye(n)
    M = np.vstack((cum, -cum, eye, -eye))
    u_prev = rng.uniform(-0.5, 0.5, size=2)
    amp = np.array([1.0, 1.0])
    rate = rng.uniform(0.02, 0.3, size=2)
    gamma = np.concatenate(
        (np.tile(amp - u_prev, Nc), np.tile(amp + u_prev, Nc), np.tile(rate, 2 * Nc))
    )
    return E, f, M, gamma


def test_unconstrained_optimum_when_no_constraint_is_active() -> None:
    E, f, M, _ = _random_qp(3)
    gamma = np.full(M.shape[0], 1e6)  # far away
    x_star = -np.linalg.solve(E, f)
    h = hildreth(E, f, M, gamma)
    assert h.converged and h.iterations == 0
    np.testing.assert_allclose(h.x, x_star, atol=1e-12)
    o = OsqpBackend(E, M).solve(E, f, gamma)
    assert o.converged
    np.testing.assert_allclose(o.x, x_star, atol=1e-5)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("kind", ["random", "box"])
def test_hildreth_and_osqp_agree_on_the_first_move(seed: int, kind: str) -> None:
    E, f, M, gamma = _random_qp(seed) if kind == "random" else _box_qp(seed)
    h = hildreth(E, f, M, gamma, max_iter=2000)
    o = OsqpBackend(E, M).solve(E, f, gamma)
    assert o.converged
    if h.converged:
        np.testing.assert_allclose(h.x[:2], o.x[:2], atol=1e-4)
        assert np.all(M @ h.x <= gamma + 1e-6)
    np.testing.assert_array_less(-1e-12, h.lam)  # multipliers are never negative


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.floats(1.0, 1.8))
def test_relaxed_hildreth_reaches_the_same_solution(seed: int, omega: float) -> None:
    E, f, M, gamma = _box_qp(seed)
    plain = hildreth(E, f, M, gamma, max_iter=5000, tol=1e-16)
    relaxed = hildreth(E, f, M, gamma, max_iter=5000, tol=1e-16, relaxation=omega)
    if plain.converged and relaxed.converged:
        np.testing.assert_allclose(relaxed.x, plain.x, atol=1e-5)


def test_warm_start_reaches_the_solution_in_fewer_sweeps() -> None:
    E, f, M, gamma = _box_qp(5)
    cold = hildreth(E, f, M, gamma, max_iter=5000, tol=1e-14)
    assert cold.converged and cold.iterations > 1
    warm = hildreth(E, f, M, gamma, max_iter=5000, tol=1e-14, lam0=cold.lam)
    assert warm.converged and warm.iterations < cold.iterations
    np.testing.assert_allclose(warm.x, cold.x, atol=1e-6)


def test_sweep_cap_is_reported_as_not_converged() -> None:
    E, f, M, gamma = _box_qp(7)
    capped = hildreth(E, f, M, gamma, max_iter=1)
    full = hildreth(E, f, M, gamma, max_iter=5000)
    assert full.iterations > 1  # the cap really cuts the sweeps short
    assert not capped.converged and capped.iterations == 1


def test_conflicting_constraints_never_converge() -> None:
    """x ≤ −1 and −x ≤ −1 (x ≥ 1): infeasible, Hildreth must say so, not raise."""
    E = np.eye(1)
    f = np.zeros(1)
    M = np.array([[1.0], [-1.0]])
    gamma = np.array([-1.0, -1.0])
    result = hildreth(E, f, M, gamma, max_iter=38)
    assert not result.converged
    assert result.iterations == 38


def test_osqp_is_updated_in_place_and_tracks_new_data() -> None:
    E, f, M, gamma = _box_qp(11)
    backend = OsqpBackend(E, M)
    first = backend.solve(E, f, gamma)
    E2 = E + np.eye(E.shape[0])
    second = backend.solve(E2, -f, gamma * 0.5)
    ref = hildreth(E2, -f, M, gamma * 0.5, max_iter=5000, tol=1e-16)
    assert first.converged and second.converged and ref.converged
    np.testing.assert_allclose(second.x, ref.x, atol=1e-4)


def _saturated_qp(seed: int, Nc: int = 10) -> tuple[np.ndarray, ...]:
    """The MPC's QP far off the path: most rate and some amplitude bounds active together
    (amplitude rows then depend on rate rows, and Hildreth's positive set holds more than n)."""
    E, f, M, gamma = _box_qp(seed, Nc)
    n = 2 * Nc
    rate = np.array([0.02, 0.01])
    u_prev = np.array([0.9, -0.95])
    amp = np.array([1.0, 1.0])
    gamma = np.concatenate(
        (np.tile(amp - u_prev, Nc), np.tile(amp + u_prev, Nc), np.tile(rate, 2 * Nc))
    )
    return E, f * 50.0 + 5.0 * np.sign(np.arange(n) % 2 - 0.5), M, gamma


@pytest.mark.parametrize("seed", range(10))
def test_active_set_certificate_gives_the_exact_optimum(seed: int) -> None:
    """Hildreth's result on a heavily constrained QP is the optimum (OSQP at 1e-11), also
    warm-started from the multipliers of a slightly different QP."""
    E, f, M, gamma = _saturated_qp(seed)
    exact = OsqpBackend(E, M, eps=1e-11, max_iter=200_000).solve(E, f, gamma)
    assert exact.converged
    h = hildreth(E, f, M, gamma, max_iter=2000, tol=1e-10, relaxation=1.5)
    assert h.converged
    np.testing.assert_allclose(h.x, exact.x, atol=1e-7)
    assert np.all(M @ h.x <= gamma + 1e-6)
    warm = hildreth(E, f * 1.01, M, gamma, max_iter=2000, tol=1e-10, relaxation=1.5, lam0=h.lam)
    again = OsqpBackend(E, M, eps=1e-11, max_iter=200_000).solve(E, f * 1.01, gamma)
    assert warm.converged
    np.testing.assert_allclose(warm.x, again.x, atol=1e-7)


@pytest.mark.parametrize("seed", range(6))
def test_hildreth_with_a_cholesky_factor_is_hildreth_with_the_inverse(seed: int) -> None:
    from scipy.linalg import lapack

    E, f, M, gamma = _box_qp(seed)
    chol, info = lapack.dpotrf(E)
    assert info == 0
    by_factor = hildreth(E, f, M, gamma, max_iter=2000, chol=chol)
    by_inverse = hildreth(E, f, M, gamma, max_iter=2000, E_inv=np.linalg.inv(E))
    assert by_factor.converged == by_inverse.converged
    np.testing.assert_allclose(by_factor.x, by_inverse.x, atol=1e-9)


# --- DAQP (issue 13): the default backend ------------------------------------------------------


@functools.cache
def _closed_loop_qps() -> list[tuple[np.ndarray, ...]]:
    """The QPs the MPC really solves with constraints active: a parking move and a slalom from
    standing starts 0.9 m and 25° off the path (the steering saturates for seconds)."""
    import dataclasses
    import math

    from leafgate.config.control import ControllerConfig, MpcConfig
    from leafgate.control.mpc import MpcController
    from leafgate.messages import Pose
    from leafgate.settings import LeafgateConfig
    from leafgate.sim.runner import run_direct
    from leafgate.sim.scenarios import get_scenario

    captured: list[tuple[np.ndarray, ...]] = []

    class Capturing(MpcController):
        def _solve(self, E, f, gamma):  # type: ignore[no-untyped-def]
            result = super()._solve(E, f, gamma)
            if result.iterations > 0:  # the unconstrained optimum was not feasible
                captured.append((E.copy(), f.copy(), self.M, gamma.copy()))
            return result

    cfg = LeafgateConfig(controller=ControllerConfig(mpc=MpcConfig(solver="osqp")))
    import leafgate.control.mpc as mpc_module

    original = mpc_module.MpcController
    mpc_module.MpcController = Capturing  # type: ignore[misc]
    try:
        for name in ("parallel-park", "slalom"):
            s = get_scenario(name)
            h = s.start.heading
            start = Pose(
                s.start.x - 0.9 * math.sin(h), s.start.y + 0.9 * math.cos(h), h + 0.44, 0.0
            )
            run_direct(cfg, dataclasses.replace(s, start=start, duration=12.0))
    finally:
        mpc_module.MpcController = original  # type: ignore[misc]
    return captured


@pytest.mark.slow
def test_daqp_hildreth_and_osqp_give_the_same_first_move_on_closed_loop_qps() -> None:
    qps = _closed_loop_qps()
    assert len(qps) > 200
    n_dual_bound = 0
    osqp_converged = 0
    for E, f, M, gamma in qps:
        daqp_result = DaqpBackend(M).solve(E, f, gamma)
        assert daqp_result.converged
        reference = hildreth(E, f, M, gamma, max_iter=100_000, tol=1e-20)
        assert reference.converged
        np.testing.assert_allclose(daqp_result.x[:2], reference.x[:2], rtol=0, atol=1e-6)
        n_dual_bound += int((daqp_result.lam > 0).any())
        osqp_result = OsqpBackend(E, M, eps=1e-8).solve(E, f, gamma)
        if osqp_result.converged:  # a capped OSQP says so (checked below); never a wrong answer
            osqp_converged += 1
            np.testing.assert_allclose(osqp_result.x[:2], daqp_result.x[:2], rtol=0, atol=1e-6)
    assert n_dual_bound == len(qps)  # every one of them saturated a constraint
    assert osqp_converged >= 0.97 * len(qps)


@pytest.mark.slow
def test_daqp_from_the_last_active_set_gives_the_answer_of_a_cold_start() -> None:
    """The controller's backend keeps its workspace: each closed-loop QP starts from the last
    one's active set. Same optimum as a workspace set up for each QP alone, in fewer
    iterations (else nothing was carried over); after a reset it starts cold again."""
    qps = [qp for qp in _closed_loop_qps() if qp[2] is _closed_loop_qps()[0][2]]  # one M
    assert len(qps) > 100
    E0, f0, M, gamma0 = qps[0]
    warm, cold = DaqpBackend(M), DaqpBackend(M)
    warm_iterations = cold_iterations = 0
    for E, f, _, gamma in qps:
        w = warm.solve(E, f, gamma)
        cold.reset()
        c = cold.solve(E, f, gamma)
        assert w.converged and c.converged
        np.testing.assert_allclose(w.x, c.x, rtol=0, atol=1e-9)
        warm_iterations += w.iterations
        cold_iterations += c.iterations
    assert warm_iterations < 0.5 * cold_iterations
    warm.reset()
    cold.reset()
    assert warm.solve(E0, f0, gamma0).iterations == cold.solve(E0, f0, gamma0).iterations


def test_daqp_starts_cold_after_a_solve_that_did_not_end_optimal() -> None:
    """A capped solve leaves no active set worth starting from: the next solve is a cold one
    (same iterations as a fresh backend's), and converges."""
    E, f, M, gamma = _box_qp(3)
    fresh = DaqpBackend(M).solve(E, f, gamma)
    assert fresh.converged and fresh.iterations > 1
    backend = DaqpBackend(M)
    backend.solve(E, f, gamma)  # a workspace with the optimal active set...
    backend._settings["iter_limit"] = 1
    backend.reset()
    assert not backend.solve(E, f, gamma).converged  # ...dropped, then capped from cold
    backend._settings["iter_limit"] = 1000
    again = backend.solve(E, f, gamma)
    assert again.converged and again.iterations == fresh.iterations


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_copied_daqp_backend_solves_on_its_own_workspace(how: str) -> None:
    """DAQP's workspace cannot be copied: a deep copy (the benchmark copies controllers) or a
    pickle sets up its own at its first solve and leaves the original's alone."""
    E, f, M, gamma = _box_qp(5)
    original = DaqpBackend(M)
    first = original.solve(E, f, gamma)
    clone = copy.deepcopy(original) if how == "deepcopy" else pickle.loads(pickle.dumps(original))
    from_clone = clone.solve(E, f, gamma)
    assert from_clone.converged and from_clone.iterations == first.iterations  # cold
    assert original.solve(E, f, gamma).iterations < first.iterations  # still warm
    np.testing.assert_allclose(from_clone.x, first.x, rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(20))
def test_daqp_solves_the_mpc_box_qp_exactly(seed: int) -> None:
    E, f, M, gamma = _box_qp(seed)
    result = DaqpBackend(M).solve(E, f, gamma)
    reference = hildreth(E, f, M, gamma, max_iter=100_000, tol=1e-20)
    assert result.converged
    np.testing.assert_allclose(result.x, reference.x, atol=1e-8)
    assert (M @ result.x <= gamma + 1e-8).all()


@pytest.mark.parametrize("seed", range(20))
def test_daqp_multipliers_belong_to_the_rows_of_m(seed: int) -> None:
    """DAQP sees the box rows as bounds and two-sided rows; the multipliers it returns are
    mapped back to M's rows, the extra one-sided rows (the MPC's speed rows) included: the
    KKT conditions of ``M x ≤ γ`` hold with them."""
    E, f, M, gamma = _box_qp(seed)
    rng = np.random.default_rng(100 + seed)
    D = rng.normal(size=(4, M.shape[1]))
    M = np.vstack((M, D))
    gamma = np.concatenate((gamma, rng.uniform(0.0, 0.5, size=4)))
    backend = DaqpBackend(M)
    assert backend._structured
    result = backend.solve(E, f, gamma)
    assert result.converged
    assert (result.lam >= 0.0).all() and (result.lam > 0.0).any()
    np.testing.assert_allclose(E @ result.x + f + M.T @ result.lam, 0.0, atol=1e-8)
    np.testing.assert_allclose(result.lam * (M @ result.x - gamma), 0.0, atol=1e-8)


@pytest.mark.parametrize("seed", range(5))
def test_daqp_on_a_general_constraint_matrix(seed: int) -> None:
    E, f, M, gamma = _random_qp(seed)
    result = DaqpBackend(M).solve(E, f, gamma)
    reference = OsqpBackend(E, M, eps=1e-10, max_iter=100_000).solve(E, f, gamma)
    assert result.converged and reference.converged
    np.testing.assert_allclose(result.x, reference.x, atol=1e-6)


def test_daqp_infeasible_and_capped_are_not_converged() -> None:
    E = np.eye(2)
    f = np.zeros(2)
    M = np.array([[1.0, 0.0], [-1.0, 0.0]])
    gamma = np.array([-1.0, -1.0])  # x₀ ≤ −1 and x₀ ≥ 1
    assert not DaqpBackend(M).solve(E, f, gamma).converged
    E, f, M, gamma = _box_qp(3)
    assert not DaqpBackend(M, max_iter=1).solve(E, f, gamma).converged


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("kind", ["random", "box", "saturated"])
def test_accelerated_hildreth_agrees_with_the_textbook_qphild(seed: int, kind: str) -> None:
    """The working set, the relaxation, the warm start and the active-set certificate change
    how fast the sweeps get there, not where: both reach the same optimum."""
    qp = {"random": _random_qp, "box": _box_qp, "saturated": _saturated_qp}[kind](seed)
    E, f, M, gamma = qp
    textbook = qphild(E, f, M, gamma, max_iter=20_000, tol=1e-20)
    fast = hildreth(E, f, M, gamma, max_iter=5000, relaxation=1.5)
    assert textbook.converged and fast.converged
    np.testing.assert_allclose(fast.x, textbook.x, atol=1e-6)
    if kind != "saturated":  # there, dependent active rows leave the multipliers non-unique
        np.testing.assert_allclose(fast.lam, textbook.lam, atol=1e-5)


def test_textbook_qphild_returns_the_unconstrained_optimum_without_sweeps() -> None:
    E, f, M, _ = _random_qp(4)
    result = qphild(E, f, M, np.full(M.shape[0], 1e6))
    assert result.converged and result.iterations == 0
    np.testing.assert_allclose(result.x, -np.linalg.solve(E, f), atol=1e-12)


def test_textbook_qphild_stops_at_the_papers_38_sweeps() -> None:
    """Wang's cap: a saturated QP is not solved in 38 sweeps, and that is reported."""
    E, f, M, gamma = _saturated_qp(0)
    result = qphild(E, f, M, gamma, tol=1e-20)
    assert result.iterations == 38 and not result.converged
