"""Move blocking: the MPC's moves spread over the prediction horizon (issue 13, switch-back).

With the paper's consecutive moves the last of the 10 is held over the 20 steps left of the
3 s horizon; ahead of a rising curvature that held input is a compromise the car feels at once
(a pre-steer to 3.6° at a drive-off where the path needs ≈ 1°, a counter-steer before a bend).
Spread moves follow the plan over the whole horizon with the same 20 variables.
"""

from __future__ import annotations

import numpy as np
import pytest

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.control.model import (
    KinematicPrediction,
    grouped_by_output,
    linearise_along,
    move_steps,
    prediction_matrices_ltv,
)
from leafgate.control.mpc import MpcController

Ts, L = 0.1, 2.7


def test_spread_moves_start_consecutive_and_reach_the_horizon_end() -> None:
    b = move_steps(30, 10, spread=True)
    assert b[0] == 0 and b[1] == 1 and b[-1] == 29
    assert np.all(np.diff(b) >= 1) and np.all(np.diff(np.diff(b)) >= 0)  # farther apart later
    np.testing.assert_array_equal(move_steps(30, 10, spread=False), np.arange(10))
    np.testing.assert_array_equal(move_steps(5, 5, spread=True), np.arange(5))


def _brute_force(A, B, Nc, b, dx0, dU):  # type: ignore[no-untyped-def]
    """The incremental model stepped one by one: Δx_{k+1} = A_k Δx_k + B_k Δu_k (Δu_k the move
    acting from step k, else 0), y_{k+1} = y_k + Δx_{k+1} (C = I, y₀ = 0)."""
    Np = A.shape[0]
    moves = {int(b[j]): dU[2 * j : 2 * j + 2] for j in range(Nc)}
    dx, y, out = dx0.copy(), np.zeros(4), []
    for k in range(Np):
        dx = A[k] @ dx + B[k] @ moves.get(k, np.zeros(2))
        y = y + dx
        out.append(y.copy())
    return np.array(out)  # (Np, 4)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize(("Np", "Nc"), [(30, 10), (12, 4)])
def test_both_predictions_with_spread_moves_are_the_stepped_model(
    seed: int, Np: int, Nc: int
) -> None:
    rng = np.random.default_rng(seed)
    speed = rng.uniform(-3.0, 3.0, Np)
    heading = rng.uniform(-1.0, 1.0, Np)
    tan_delta = float(rng.uniform(-0.5, 0.5))
    dx0 = rng.normal(size=4)
    dU = rng.normal(size=2 * Nc)
    b = move_steps(Np, Nc, spread=True)
    A, B = linearise_along(speed, heading, np.full(Np, tan_delta), Ts, L)
    expected = _brute_force(A, B, Nc, b, dx0, dU)  # (Np, 4), by step
    F, S = prediction_matrices_ltv(A, B, np.eye(4), Nc, b)
    Y = (F[:, :4] @ dx0 + S @ dU).reshape(Np, 4)
    np.testing.assert_allclose(Y, expected, atol=1e-10)
    ST, free = KinematicPrediction(Np, Nc, Ts, L, b)(speed, heading, tan_delta, dx0)
    np.testing.assert_allclose(ST.T, grouped_by_output(S, Np), atol=1e-12)
    np.testing.assert_allclose(free + dU @ ST, expected.T.ravel(), atol=1e-10)


def test_rate_limits_of_spread_moves_cover_the_steps_between_them() -> None:
    ctrl = MpcController(MpcConfig(), VehicleConfig(), 0.02)
    cfg = ctrl.cfg
    gaps = np.diff(ctrl._moves)
    np.testing.assert_allclose(ctrl.du_max[:2], [cfg.jerk_max * 0.02, cfg.steer_rate_max * 0.02])
    np.testing.assert_allclose(ctrl.du_max[2::2], cfg.jerk_max * Ts * gaps)
    np.testing.assert_allclose(ctrl.du_max[3::2], cfg.steer_rate_max * Ts * gaps)
