"""Kinematic bicycle model about the rear axle, its linearisation and the augmented model.

State ``x = [x, y, v, θ]`` (m, m, m/s, rad), input ``u = [a, tan δ]`` (m/s², –), wheelbase ``L``
(m). Continuous model, paper eq. 1–6::

    ẋ = v cos θ,   ẏ = v sin θ,   v̇ = a,   θ̇ = v tan δ / L

**Linearisation (eq. 7–12).** :func:`linearise` returns the Jacobians of the forward-Euler map
``x⁺ = x + Ts f(x, u)`` at the current state and input. They hold every entry of the paper's
eq. 11–12 plus three the paper's state-dependent-coefficient form leaves out: ``∂x⁺/∂θ =
−Ts v sin θ``, ``∂y⁺/∂θ = Ts v cos θ`` and ``∂θ⁺/∂v = Ts tan δ / L``. The incremental
(augmented) model propagates *changes* of the state, and it is exactly the ``∂y⁺/∂θ`` entry that
lets a change of heading — hence of steering — move the car sideways in the prediction; with the
paper's matrix the predicted lateral offset would not react to steering at all.

**Output frame (how x enters the outputs).** The controller works in a path-aligned frame that
is rebuilt every cycle: origin at the vehicle's projection on the reference path, x-axis along
the reference heading there. The outputs are all four states, ``C = I``: along-track position,
lateral offset, speed and heading error. The paper's ``C = [y, v, θ]`` (eq. 13) is the special
case of a zero along-track weight; leafgate keeps a small along-track weight because the
reference positions come from the planned speed profile (see
:mod:`leafgate.control.reference`), so that term makes the car stop *on* the final waypoint
and at a cusp instead of merely slowing down near it. In this frame the linearisation point
has ``θ ≈ 0``, where the linear model is most accurate, and the lateral offset is the
cross-track error itself — no global ``x``/``y`` ambiguity when the path runs along an axis.

**Augmented model (eq. 15–19).** State ``[Δx̃; ỹ]``, input ``Δu``: the controller predicts
changes from the measured outputs, which gives it integral action on input biases and makes
the cost penalise input *changes* (a steady steering angle in a bend costs nothing).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt

from leafgate.messages import FloatArray

N_STATES = 4  # [x, y, v, θ]
N_INPUTS = 2  # [a, tan δ]


def derivative(state: FloatArray, u: FloatArray, wheelbase: float) -> FloatArray:
    """Continuous-time derivative of the kinematic bicycle (eq. 1–6).

    :param state: ``[x, y, v, θ]`` in m, m, m/s, rad
    :param u: ``[a, tan δ]`` in m/s² and –
    :param wheelbase: L, m
    :returns: ``[ẋ, ẏ, v̇, θ̇]``
    """
    _, _, v, theta = state
    a, tan_delta = u
    return np.array(
        [v * math.cos(theta), v * math.sin(theta), a, v * tan_delta / wheelbase],
        dtype=np.float64,
    )


def rk4_step(state: FloatArray, u: FloatArray, dt: float, wheelbase: float) -> FloatArray:
    """Integrate the nonlinear model over ``dt`` seconds with the input held (classic RK4).

    Accurate to O(dt⁵) per step; used by tests and as the reference plant in tuning loops.
    """
    state = np.asarray(state, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    k1 = derivative(state, u, wheelbase)
    k2 = derivative(state + 0.5 * dt * k1, u, wheelbase)
    k3 = derivative(state + 0.5 * dt * k2, u, wheelbase)
    k4 = derivative(state + dt * k3, u, wheelbase)
    return state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def euler_step(state: FloatArray, u: FloatArray, Ts: float, wheelbase: float) -> FloatArray:
    """The discrete model whose Jacobians :func:`linearise` returns: ``x + Ts f(x, u)``."""
    return np.asarray(state, dtype=np.float64) + Ts * derivative(state, u, wheelbase)


def linearise(
    state: FloatArray, u: FloatArray, Ts: float, wheelbase: float
) -> tuple[FloatArray, FloatArray]:
    """Discrete linearisation at the current state and input (eq. 7–12, full Jacobian).

    :param state: ``[x, y, v, θ]``
    :param u: ``[a, tan δ]`` (the input currently applied)
    :param Ts: model sample time, s
    :param wheelbase: L, m
    :returns: ``(A, B)``, 4×4 and 4×2, with ``x⁺ ≈ A x + B u`` near the operating point
    """
    _, _, v, theta = state
    tan_delta = u[1]
    c, s = math.cos(theta), math.sin(theta)
    A = np.array(
        [
            [1.0, 0.0, Ts * c, -Ts * v * s],
            [0.0, 1.0, Ts * s, Ts * v * c],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, Ts * tan_delta / wheelbase, 1.0],
        ]
    )
    B = np.array(
        [
            [0.0, 0.0],
            [0.0, 0.0],
            [Ts, 0.0],
            [0.0, Ts * v / wheelbase],
        ]
    )
    return A, B


def augment(
    A: FloatArray, B: FloatArray, C: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The augmented incremental model (eq. 15–19).

    With ``n`` states, ``m`` inputs and ``q`` outputs::

        [Δx⁺]   [ A   0 ] [Δx]   [ B  ]
        [ y⁺] = [ CA  I ] [ y] + [ CB ] Δu,      y = [0 I] [Δx; y]

    :returns: ``(Aa, Ba, Ca)`` of shapes (n+q)×(n+q), (n+q)×m, q×(n+q)
    """
    n = A.shape[0]
    q = C.shape[0]
    Aa = np.zeros((n + q, n + q))
    Aa[:n, :n] = A
    Aa[n:, :n] = C @ A
    Aa[n:, n:] = np.eye(q)
    Ba = np.vstack((B, C @ B))
    Ca = np.hstack((np.zeros((q, n)), np.eye(q)))
    return Aa, Ba, Ca


def matrix_powers(A: FloatArray, count: int) -> FloatArray:
    """``[A⁰, A¹, …, A^(count−1)]`` stacked as (count, n, n), by repeated doubling.

    Each doubling is one batched matmul, so ``count`` = 31 costs five numpy calls instead of
    thirty.
    """
    n = A.shape[0]
    out = np.empty((count, n, n))
    out[0] = np.eye(n)
    if count == 1:
        return out
    out[1] = A
    have = 2
    while have < count:
        take = min(have, count - have)
        # A^(have + i) = A^i · A^have for i < take
        np.matmul(out[:take], out[have - 1] @ A, out=out[have : have + take])
        have += take
    return out


def prediction_matrices(
    A: FloatArray, B: FloatArray, C: FloatArray, Np: int, Nc: int
) -> tuple[FloatArray, FloatArray]:
    """Prediction ``Y = F x + S ΔU`` of the augmented model over ``Np`` steps, ``Nc`` moves.

    Equal to eq. 22–26 applied to :func:`augment` ``(A, B, C)`` — ``F`` stacks ``Cₐ Aₐⁱ``
    (i = 1…Np), block (i, j) of ``S`` is ``Cₐ Aₐ^(i−j) Bₐ`` for i ≥ j — but computed from the
    plant's own (smaller) matrices through the block structure of the augmented powers::

        Aₐᵏ = [[Aᵏ, 0], [C Σ_{i=1..k} Aⁱ, I]]   ⇒   Cₐ Aₐᵏ = [C Σ_{i=1..k} Aⁱ, I],
                                                    Cₐ Aₐᵏ Bₐ = C Σ_{i=0..k} Aⁱ B

    One stack of powers, one cumulative sum, and index arithmetic for the lower-triangular
    Toeplitz blocks of ``S``; no loop over blocks.

    :returns: ``F`` of shape (Np·q, n+q) and ``S`` of shape (Np·q, Nc·m)
    """
    n = A.shape[0]
    q = C.shape[0]
    cum = np.cumsum(matrix_powers(A, Np + 1), axis=0)  # Σ_{i=0..k} Aⁱ, k = 0 … Np
    F = np.empty((Np, q, n + q))
    F[:, :, :n] = C @ (cum[1:] - np.eye(n))
    F[:, :, n:] = np.eye(q)
    G = C @ cum[:Np] @ B  # (Np, q, m): Cₐ Aₐᵏ Bₐ for k = 0 … Np−1
    S = toeplitz_blocks(G, Nc)
    return F.reshape(Np * q, n + q), S


def toeplitz_blocks(G: FloatArray, Nc: int) -> FloatArray:
    """Block lower-triangular Toeplitz matrix with block (i, j) = ``G[i − j]`` (i ≥ j), else 0.

    :param G: (Np, q, m) stack of blocks
    :returns: (Np·q, Nc·m)
    """
    Np, q, m = G.shape
    padded = np.concatenate((np.zeros((1, q, m)), G))  # index 0 is the zero block
    blocks = padded[_lag_index(Np, Nc)]  # (Np, Nc, q, m)
    return blocks.transpose(0, 2, 1, 3).reshape(Np * q, Nc * m)


@functools.lru_cache(maxsize=8)
def _lag_index(Np: int, Nc: int) -> npt.NDArray[np.intp]:
    """(Np, Nc) index of block (i, j) into ``[0, G₀, G₁, …]``: i − j + 1, 0 above the diagonal."""
    lag = np.arange(Np)[:, None] - np.arange(Nc)[None, :]
    index = np.where(lag >= 0, lag + 1, 0)
    index.setflags(write=False)
    return index
