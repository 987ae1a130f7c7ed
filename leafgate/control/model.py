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


# --- time-varying prediction and the steering actuator ----------------------------------------

N_STATES_STEER = 5  # [x, y, v, θ, t]: the kinematic states and the actual t = tan δ


def linearise_along(
    speed: FloatArray, heading: FloatArray, tan_delta: FloatArray, Ts: float, wheelbase: float
) -> tuple[FloatArray, FloatArray]:
    """Jacobians of the Euler map at ``Np`` operating points along the horizon (vectorised).

    The entries are those of :func:`linearise`, evaluated at each step's own speed, heading and
    steering instead of the current ones. Near a stop the planned speed falls towards 0 and so
    does the effect of steering: a model linearised once at the current (or a floor) speed
    believes the car keeps turning after it has stopped, and steers too little before a cusp.

    :param speed: (Np,) m/s, signed operating speed of each step
    :param heading: (Np,) rad, operating heading (in the controller's frame)
    :param tan_delta: (Np,) operating tan δ
    :returns: ``(A, B)`` of shapes (Np, 4, 4) and (Np, 4, 2)
    """
    n = speed.shape[0]
    c, s = np.cos(heading), np.sin(heading)
    zero, one = np.zeros(n), np.ones(n)
    vs, vc = Ts * speed * s, Ts * speed * c
    rows = (
        (one, zero, Ts * c, -vs),
        (zero, one, Ts * s, vc),
        (zero, zero, one, zero),
        (zero, zero, (Ts / wheelbase) * tan_delta, one),
    )
    A = np.stack([entry for row in rows for entry in row], axis=1).reshape(n, N_STATES, N_STATES)
    B = np.stack(
        (zero, zero, zero, zero, np.full(n, Ts), zero, zero, (Ts / wheelbase) * speed), axis=1
    ).reshape(n, N_STATES, N_INPUTS)
    return A, B


def steer_lag_factor(Ts: float, tau: float) -> float:
    """α of the exact zero-order-hold discretisation of ``ṫ = (t_cmd − t)/τ``: ``t⁺ = t + α(t_cmd − t)``."""
    return 1.0 - math.exp(-Ts / tau)


def augment_steer_lag(
    A: FloatArray, B: FloatArray, alpha: float, Ts: float, speed: FloatArray, wheelbase: float
) -> tuple[FloatArray, FloatArray]:
    """Add the steering actuator to stacks of kinematic Jacobians (model ``kinematic_steer_lag``).

    State ``[x, y, v, θ, t]`` with ``t`` the *actual* tan δ, input ``[a, t_cmd]``::

        θ⁺ = θ + Ts v t / L,   t⁺ = t + α (t_cmd − t)

    The kinematic ``∂θ⁺/∂t_cmd`` moves to ``∂θ⁺/∂t`` (the car turns with the wheel it has, not
    the one it asked for), and the command reaches ``t`` only through the lag.

    :param A: (Np, 4, 4) and ``B`` (Np, 4, 2) from :func:`linearise_along`
    :param speed: (Np,) m/s, the operating speeds used for ``A`` and ``B``
    :returns: ``(A5, B5)`` of shapes (Np, 5, 5) and (Np, 5, 2)
    """
    n = A.shape[0]
    A5 = np.zeros((n, N_STATES_STEER, N_STATES_STEER))
    A5[:, :N_STATES, :N_STATES] = A
    A5[:, 3, 4] = Ts * speed / wheelbase
    A5[:, 4, 4] = 1.0 - alpha
    B5 = np.zeros((n, N_STATES_STEER, N_INPUTS))
    B5[:, :N_STATES, 0] = B[:, :, 0]
    B5[:, 4, 1] = alpha
    return A5, B5


def steer_lag_increment(
    state: FloatArray, u: FloatArray, Ts: float, wheelbase: float, alpha: float
) -> FloatArray:
    """One model step's change of ``[x, y, v, θ, t]`` with the input ``u = [a, t_cmd]`` held."""
    _, _, v, theta, t = state
    a, t_cmd = u
    return np.array(
        [
            Ts * v * math.cos(theta),
            Ts * v * math.sin(theta),
            Ts * a,
            Ts * v * t / wheelbase,
            alpha * (t_cmd - t),
        ]
    )


def prediction_matrices_ltv(
    A: FloatArray, B: FloatArray, C: FloatArray, Nc: int
) -> tuple[FloatArray, FloatArray]:
    """``Y = F [Δx₀; y₀] + S ΔU`` of the augmented model with step-dependent ``Aₖ``, ``Bₖ``.

    The incremental model of eq. 15–19 with Jacobians taken at each step's operating point:
    ``Δxₖ₊₁ = Aₖ Δxₖ + Bₖ Δuₖ``, ``yₖ₊₁ = yₖ + C Δxₖ₊₁`` (the Jacobian of a difference of two
    consecutive steps is the one at the later step). With ``Pₘ = Aₘ₋₁ ⋯ A₀`` and
    ``Qₖ = Σ_{m=1..k} Pₘ``::

        yₖ = y₀ + C Qₖ Δx₀ + Σ_{j<min(k,Nc)} C (Qₖ − Qⱼ) Pⱼ₊₁⁻¹ Bⱼ Δuⱼ

    (every ``Aₖ`` of the bicycle has determinant 1, so the inverses exist). With all ``Aₖ``,
    ``Bₖ`` equal this is :func:`prediction_matrices`. One loop of ``Np`` 4×4 products, the rest
    batched.

    :param A: (Np, n, n), ``B``: (Np, n, m), ``C``: (q, n)
    :returns: ``F`` of shape (Np·q, n+q) and ``S`` of shape (Np·q, Nc·m)
    """
    Np, n, _ = A.shape
    q = C.shape[0]
    m = B.shape[2]
    P = np.empty((Np + 1, n, n))
    P[0] = np.eye(n)
    P[1:] = A
    # prefix products P[k] = A[k−1] ⋯ A[0] by a doubling scan: ⌈log₂ Np⌉ batched products
    # instead of Np sequential ones
    d = 1
    while d < Np:
        P[d + 1 :] = P[d + 1 :] @ P[1 : Np + 1 - d]
        d *= 2
    CQ = C @ (np.cumsum(P, axis=0) - np.eye(n))  # C Q[k], Q[k] = Σ_{m=1..k} P[m], Q[0] = 0
    F = np.empty((Np, q, n + q))
    F[:, :, :n] = CQ[1:]
    F[:, :, n:] = np.eye(q)
    G = np.linalg.solve(P[1 : Nc + 1], B[:Nc])  # (Nc, n, m): P_{j+1}⁻¹ B_j
    # block (k, j) = C Q_k G_j − C Q_j G_j, k = 1…Np
    blocks = np.matmul(CQ[1:, None], G[None]) - np.matmul(CQ[:Nc], G)[None]  # (Np, Nc, q, m)
    blocks[~_ltv_mask(Np, Nc)] = 0.0
    S = blocks.transpose(0, 2, 1, 3).reshape(Np * q, Nc * m)
    return F.reshape(Np * q, n + q), S


@functools.lru_cache(maxsize=8)
def _ltv_mask(Np: int, Nc: int) -> npt.NDArray[np.bool_]:
    """(Np, Nc): True where output k = row + 1 depends on move j (k > j)."""
    mask = np.arange(Np)[:, None] >= np.arange(Nc)[None, :]
    mask.setflags(write=False)
    return mask
