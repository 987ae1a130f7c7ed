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

**Steps at their middle heading.** The controller evaluates these Jacobians, and the first
increment, at each step's heading half way through it (:func:`mid_heading`; :mod:`leafgate.control.
mpc`, "Steps taken at their middle"): the step then moves the car along an arc's chord, to second
order, where forward Euler moves it along the tangent at the start.

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
    # filled entry by entry into zeros: a dozen small numpy calls instead of stacking sixteen
    # rows (this runs every control tick)
    A = np.zeros((n, N_STATES, N_STATES))
    A[:, _DIAG4, _DIAG4] = 1.0
    A[:, 0, 2] = Ts * c
    A[:, 0, 3] = -(Ts * speed * s)
    A[:, 1, 2] = Ts * s
    A[:, 1, 3] = Ts * speed * c
    A[:, 3, 2] = (Ts / wheelbase) * tan_delta
    B = np.zeros((n, N_STATES, N_INPUTS))
    B[:, 2, 0] = Ts
    B[:, 3, 1] = (Ts / wheelbase) * speed
    return A, B


_DIAG4 = (0, 1, 2, 3)


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


def mid_heading(state: tuple[float, ...] | FloatArray, Ts: float, wheelbase: float) -> float:
    """The heading half way through one model step from ``[x, y, v, θ, t]`` (``t = tan δ``):
    ``θ + ½ Ts v t / L``, along which the step moves the car (the midpoint rule: an arc's chord
    runs at its middle heading; the paper's forward Euler moves along the start heading)."""
    _, _, v, theta, t = state[:5]
    return float(theta) + 0.5 * Ts * (float(v) * float(t) / wheelbase)


def steer_lag_increment(
    state: FloatArray, u: FloatArray, Ts: float, wheelbase: float, alpha: float
) -> FloatArray:
    """One model step's change of ``[x, y, v, θ, t]`` with the input ``u = [a, t_cmd]`` held:
    the position moved along :func:`mid_heading`."""
    _, _, v, _, t = state
    a, t_cmd = u
    mid = mid_heading(state, Ts, wheelbase)
    return np.array(
        [
            Ts * v * math.cos(mid),
            Ts * v * math.sin(mid),
            Ts * a,
            Ts * v * t / wheelbase,
            alpha * (t_cmd - t),
        ]
    )


def move_steps(Np: int, Nc: int, spread: bool) -> npt.NDArray[np.intp]:
    """The model steps at which the ``Nc`` moves act: ``0 … Nc − 1`` (the paper), or spread
    over the prediction horizon (move blocking) — consecutive at first, then farther apart,
    the last one near the horizon's end: ``j + round((Np − Nc)(j / (Nc − 1))²)``.

    With consecutive moves the last input is held over the ``Np − Nc`` steps left; ahead of a
    rising curvature that held input is a compromise the car feels at once (a pre-steer at a
    drive-off, a counter-steer before a bend). Spread moves can follow the path over the whole
    horizon with the same number of variables.
    """
    j = np.arange(Nc)
    if not spread or Nc < 2:
        return j
    return j + np.rint((Np - Nc) * (j / (Nc - 1)) ** 2).astype(np.intp)


def prediction_matrices_ltv(
    A: FloatArray,
    B: FloatArray,
    C: FloatArray,
    Nc: int,
    moves: npt.NDArray[np.intp] | None = None,
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

    With ``moves`` (:func:`move_steps`) move j acts from step ``moves[j]`` on instead of j.

    :param A: (Np, n, n), ``B``: (Np, n, m), ``C``: (q, n)
    :returns: ``F`` of shape (Np·q, n+q) and ``S`` of shape (Np·q, Nc·m)
    """
    Np, n, _ = A.shape
    b = np.arange(Nc) if moves is None else moves
    q = C.shape[0]
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
    G = np.linalg.solve(P[b + 1], B[b]).astype(np.float64, copy=False)  # P_{j+1}⁻¹ B_j
    S = _ltv_input_blocks(CQ, G.transpose(1, 0, 2), b)
    return F.reshape(Np * q, n + q), S


def _ltv_input_blocks(CQ: FloatArray, G: FloatArray, b: npt.NDArray[np.intp]) -> FloatArray:
    """``S`` from ``C Qₖ`` (k = 0…Np) and ``Gⱼ = Pⱼ₊₁⁻¹ Bⱼ``: block (k, j) = C (Qₖ − Qⱼ) Gⱼ, k > j.

    All products ``C Qₖ Gⱼ`` come from one 2-D matrix product; the subtracted ``C Qⱼ Gⱼ`` are
    its diagonal blocks, and the blocks with k ≤ j are zeroed by a mask.

    :param CQ: (Np+1, q, n)
    :param G: (n, Nc, m), the moves side by side
    :param b: (Nc,) the step each move acts from (j without move blocking)
    :returns: (Np·q, Nc·m)
    """
    Np1, q, n = CQ.shape
    _, Nc, m = G.shape
    R = (CQ.reshape(Np1 * q, n) @ G.reshape(n, Nc * m)).reshape(Np1, q, Nc, m)
    j = np.arange(Nc)
    diag = R[b, :, j, :]  # (Nc, q, m): C Q_bⱼ Gⱼ
    S = R[1:] - diag.transpose(1, 0, 2)
    S *= _ltv_mask(Np1 - 1, tuple(b.tolist()))
    return S.reshape((Np1 - 1) * q, Nc * m)


@functools.lru_cache(maxsize=8)
def _ltv_mask(Np: int, b: tuple[int, ...]) -> FloatArray:
    """(Np, 1, Nc, 1): 1 where output k = row + 1 depends on move j (k > bⱼ), else 0."""
    mask = (np.arange(Np)[:, None] >= np.array(b)[None, :]).astype(np.float64)
    mask = mask[:, None, :, None]
    mask.setflags(write=False)
    return mask


# --- the kinematic model in closed form --------------------------------------------------------


class KinematicPrediction:
    """The prediction of :func:`prediction_matrices_ltv` for :func:`linearise_along` (``C = I``)
    in closed form, laid out for the QP.

    For the controller's case: speed and heading vary along the horizon, tan δ is one value for
    all steps. Built once per horizon (constant weights), then called every tick.

    Every Jacobian of the kinematic bicycle is ``Aₗ = I + Nₗ`` with ``Nₗ`` non-zero only at
    (0,2) ``aₗ = Ts cos θₗ``, (1,2) ``cₗ = Ts sin θₗ``, (0,3) ``bₗ = −Ts vₗ sin θₗ``, (1,3)
    ``dₗ = Ts vₗ cos θₗ`` and (3,2) ``e = Ts tan δ / L``. Any product of three such ``N`` is
    zero, so the prefix product is::

        Pₘ = Aₘ₋₁ ⋯ A₀ = I + Σ_{l<m} Nₗ + Σ_{l<m} Nₗ Σ_{p<l} Nₚ,

    whose second sum is ``e Σ_{l<m} l bₗ`` at (0,2) and ``e Σ_{l<m} l dₗ`` at (1,2): weighted
    sums over the steps of ``cos θ``, ``sin θ``, ``v sin θ`` and ``v cos θ``, all taken by one
    product with a constant weight matrix. The inverse the input blocks need is explicit:
    ``Pₘ⁻¹ e₂ = [P₀₃P₃₂ − P₀₂, P₁₃P₃₂ − P₁₂, 1, −P₃₂]``, ``Pₘ⁻¹ e₃ = [−P₀₃, −P₁₃, 0, 1]``.
    Block (k, j) of ``S`` is ``Σ_{m=j+1..k} Pₘ Gⱼ`` with ``Gⱼ = Pⱼ₊₁⁻¹ Bⱼ``, and the free
    response ``F [Δx₀; y₀] − y₀`` is ``Σ_{m≤k} Pₘ Δx₀``: one product of all ``Pₘ`` with the
    ``Gⱼ`` and ``Δx₀``, a mask, and a cumulative sum over m. No products along the horizon, no
    solves.

    **Layout.** Rows of the prediction are grouped by output — all ``Np`` steps of the
    along-track position, then of the lateral offset, speed and heading error (the paper
    stacks them by step; the QP's ``E`` and ``f`` do not depend on the order). ``S`` is
    returned transposed, (moves × outputs), as the QP uses it.

    With ``moves`` (:func:`move_steps`) move j acts from step ``bⱼ = moves[j]`` on: its block
    is ``Σ_{m=bⱼ+1..k} Pₘ Gⱼ`` with ``Gⱼ = P_{bⱼ+1}⁻¹ B_{bⱼ}``.

    **Steering lag** (``steer_alpha`` given: :func:`augment_steer_lag`, state ``[x, y, v, θ,
    t]``, ``t`` the actual tan δ with ``t⁺ = β t + α t_cmd``, ``β = 1 − α``). Each Jacobian is
    block triangular, ``Aₗ = [[Kₗ, gₗ e₃], [0, β]]`` with ``Kₗ`` the kinematic one above (``e``
    at the actual tan δ) and ``gₗ = Ts vₗ / L``, so ``Pₘ = [[K̂ₘ, cₘ], [0, βᵐ]]`` with ``K̂ₘ`` the
    kinematic prefix product and ``cₘ = Σ_{l<m} βˡ gₗ Kₘ₋₁ ⋯ Kₗ₊₁ e₃``. Every ``Kₚ`` maps ``e₃``
    to ``e₃ + bₚ e₀ + dₚ e₁`` and leaves ``e₀``, ``e₁`` alone, hence, with ``Tₘ = Σ_{l<m} βˡ
    gₗ``::

        cₘ = [Σ_{p<m} bₚ Tₚ, Σ_{p<m} dₚ Tₚ, 0, Tₘ]

    — two more weighted sums; they carry ``Δx₀``'s ``t`` entry (the caller gives it,
    :func:`steer_lag_first_increment`). The acceleration column of ``Gⱼ`` is the kinematic one
    (with a zero ``t`` entry). The command reaches only ``t``, ``Bⱼ e₁ = α e₄``, and its block
    is taken without ``Pₘ⁻¹`` (whose ``β⁻ᵐ``, e¹⁰ at τ = 0.3 s, would cancel against ``cₘ``): with
    ``s = bⱼ + 1``, ``Pₘ Pₛ⁻¹ = Aₘ₋₁ ⋯ Aₛ`` and the same argument give, for ``m ≥ s``::

        C Pₘ Gⱼ e₁ = α [Σ_{p<m} bₚ Dⱼ,ₚ, Σ_{p<m} dₚ Dⱼ,ₚ, 0, Dⱼ,ₘ],  Dⱼ,ₘ = Σ_{s≤l<m} βˡ⁻ˢ gₗ

    — one product of the speeds with a constant weight matrix per move, and one more for the
    sums over p.

    :param Np: prediction horizon, steps
    :param Nc: control horizon, moves
    :param Ts: model sample time, s
    :param wheelbase: L, m
    :param moves: (Nc,) the step each move acts from; None: ``0 … Nc − 1`` (the paper)
    :param steer_alpha: α of the steering lag per model step (:func:`steer_lag_factor`); None:
        the plain kinematic model
    """

    def __init__(
        self,
        Np: int,
        Nc: int,
        Ts: float,
        wheelbase: float,
        moves: npt.NDArray[np.intp] | None = None,
        steer_alpha: float | None = None,
    ) -> None:
        self.Np, self.Nc, self.Ts, self.L = Np, Nc, Ts, wheelbase
        self.steer_alpha = steer_alpha
        n = N_STATES if steer_alpha is None else N_STATES_STEER  # inputs of the output rows
        b = np.arange(Nc) if moves is None else np.asarray(moves)
        # the step each move acts from (:func:`move_steps`), as a slice when consecutive
        consecutive = bool(np.array_equal(b, np.arange(Nc)))
        self._b: slice | npt.NDArray[np.intp] = slice(0, Nc) if consecutive else b
        step = np.arange(Np, dtype=np.float64)
        before = (step[:, None] < step[None, :] + 1.0).astype(np.float64)  # l < m, m = 1…Np
        # h @ weights: Σ_{l<m} Ts hₗ and Σ_{l<m} Ts l hₗ (Ts folded in here, once)
        self._weights = np.hstack((Ts * before, Ts * step[:, None] * before))
        self._m = step + 1.0  # m = 1 … Np
        # Pₘ's output rows transposed and flattened per m: [i, o, m] = Pₘ[o, i] (o < 4, i < n);
        # the identity is constant
        self._p_identity = np.zeros((n, N_STATES, Np))
        for o in range(N_STATES):
            self._p_identity[o, o] = 1.0
        # rows: move j's two inputs (row 2j + u), then the free response; columns (o, m).
        # Move j acts on the outputs k ≥ bⱼ + 1 only, i.e. Pₘ with m ≥ bⱼ + 1.
        mask = np.ones((2 * Nc + 1, N_STATES, Np))
        for j in range(Nc):
            mask[2 * j : 2 * j + 2, :, : b[j]] = 0.0
        self._mask = mask.reshape(2 * Nc + 1, N_STATES * Np)
        self._upper = (step[:, None] <= step[None, :]).astype(np.float64)  # Σ_{m≤k}
        # Work buffers reused every call (the results never alias them): the identity entries
        # of P and the constant entries of G are written here once, the rest per call.
        self._P = self._p_identity.copy()
        self._G = np.zeros((2 * Nc + 1, n))
        self._G[0:-1:2, 2] = Ts  # entry 2 of each acceleration column (Ts · 1)
        self._e_col = np.empty((2, 1))  # [−e, e]: the tan δ factor of P₀₂ and P₁₂
        self._sign_col = np.array([[-1.0], [1.0]])  # bₗ = −Ts vₗ sin θₗ, dₗ = +Ts vₗ cos θₗ
        if steer_alpha is not None:
            beta = 1.0 - steer_alpha
            # v @ this = Tₘ = Σ_{l<m} βˡ Ts vₗ / L (m = 1…Np); and Σ_{p<m} Ts wₚ as a product
            self._lag_weights = (Ts / wheelbase) * beta ** step[:, None] * before
            self._ts_before = Ts * before
            self._t_prev = np.zeros(Np)  # Tₚ, p = 0 … Np − 1 (T₀ = 0)
            # v @ this = α Dⱼ,ₘ for every move j and m = 1 … Np (row j·Np + m − 1); α folded in
            s_j = (b + 1.0)[:, None]  # (Nc, 1): s = bⱼ + 1
            lag = step[:, None, None] - s_j[None]  # l − s, (Np, Nc, 1)
            acts = (lag >= 0.0) & (before[:, None, :] > 0.0)  # s ≤ l < m
            weights = np.where(acts, steer_alpha * (Ts / wheelbase) * beta**lag, 0.0)
            self._move_weights = weights.reshape(Np, Nc * Np)
            self._d_prev = np.zeros((Nc, Np))  # α Dⱼ,ₚ, p = 0 … Np − 1 (Dⱼ,₀ = 0)

    def __call__(
        self,
        speed: FloatArray,
        heading: FloatArray,
        tan_delta: float,
        dx0: FloatArray | tuple[float, ...],
    ) -> tuple[FloatArray, FloatArray]:
        """``Sᵀ`` and the free response at the operating points ``(speed[l], heading[l], tan δ)``.

        :param speed: (Np,) m/s, operating speed of each step
        :param heading: (Np,) rad, operating heading of each step
        :param tan_delta: operating tan δ of every step (with the steering lag: the actual one)
        :param dx0: (4,) the augmented state's increment ``Δx₀`` (an array or a tuple); (5,)
            with the steering lag
        :returns: ``Sᵀ`` of shape (Nc·2, 4·Np) and ``F [Δx₀; y₀] − y₀`` of shape (4·Np,), both
            grouped by output (column / entry ``o·Np + k − 1`` is output o at step k)
        """
        Np, Nc, Ts = self.Np, self.Nc, self.Ts
        e = (Ts / self.L) * tan_delta
        h = np.empty((4, Np))
        np.cos(heading, out=h[0])
        np.sin(heading, out=h[1])
        np.multiply(h[1::-1], speed, out=h[2:])  # v sin θ, v cos θ
        sums = h @ self._weights  # (4, 2 Np): Σ_{l<m} Ts hₗ, then Σ_{l<m} Ts l hₗ

        # Pₘ for m = 1 … Np, as [i, o, m] = Pₘ[o, i]. Rows (o = 0, 1) are filled together:
        # one numpy call per pair instead of one per entry (each call costs ~1 µs here).
        P = self._P  # identity entries preset, the others overwritten below
        e_col = self._e_col
        e_col[0, 0] = -e
        e_col[1, 0] = e
        np.multiply(sums[2:, Np:], e_col, out=P[2, :2])
        P[2, :2] += sums[:2, :Np]  # P₀₂ = Σ aₗ + e Σ l bₗ, P₁₂ = Σ cₗ + e Σ l dₗ
        np.multiply(sums[2:, :Np], self._sign_col, out=P[3, :2])  # P₀₃ = Σ bₗ, P₁₃ = Σ dₗ
        np.multiply(self._m, e, out=P[2, 3])  # P₃₂ = e m
        lag = self.steer_alpha is not None
        if lag:  # column 4, cₘ: P₃₄ = Tₘ, then P₀₄ = Σ_{p<m} bₚ Tₚ and P₁₄ = Σ_{p<m} dₚ Tₚ
            np.matmul(speed, self._lag_weights, out=P[4, 3])
            t_prev = self._t_prev
            t_prev[1:] = P[4, 3, :-1]
            t_prev = h[2:] * t_prev  # vₚ sin θₚ Tₚ, vₚ cos θₚ Tₚ
            np.multiply(t_prev @ self._ts_before, self._sign_col, out=P[4, :2])

        # rows 2j, 2j+1: the columns of Gⱼ = Pⱼ₊₁⁻¹ Bⱼ, Bⱼ = [Ts e₂, (Ts vⱼ / L) e₃]; last: Δx₀
        #   acceleration: Ts [P₀₃P₃₂ − P₀₂, P₁₃P₃₂ − P₁₂, 1, −P₃₂]
        #   steering:     −g [P₀₃, P₁₃, 0, −1],  g = Ts vⱼ / L
        b = self._b
        Pb = P[2:4, :, b]  # columns 2 and 3 of P_{bⱼ+1}, in one indexing call
        p3 = Pb[1, :2]  # [P₀₃; P₁₃]
        p32 = Pb[0, 3]
        G = self._G  # column 2 preset (Ts for the acceleration, 0 for the steering)
        a, s = G[0:-1:2], G[1::2]  # the acceleration and the steering columns of each Gⱼ
        col = p3 * p32
        col -= Pb[0, :2]  # [P₀₂; P₁₂]
        col *= Ts
        a[:, :2] = col.T
        np.multiply(p32, -Ts, out=a[:, 3])
        if not lag:  # Bⱼ e₁ = g e₃: −g [P₀₃, P₁₃, 0, −1]; with the lag, PG's rows below
            neg_g = speed[b] * -(Ts / self.L)
            np.multiply(p3, neg_g, out=s[:, :2].T)
            np.negative(neg_g, out=s[:, 3])
        G[-1] = dx0

        # Pₘ Gⱼ for every m and j, kept where m ≥ j + 1, summed over m ≤ k
        PG = G @ P.reshape(P.shape[0], N_STATES * Np)
        PG *= self._mask
        if lag:  # the command's rows: α [Σ_{p<m} bₚ Dⱼ,ₚ, Σ_{p<m} dₚ Dⱼ,ₚ, 0, Dⱼ,ₘ] (class notes)
            steer = PG[1::2].reshape(Nc, N_STATES, Np)
            D = (speed @ self._move_weights).reshape(Nc, Np)
            steer[:, 3] = D
            d_prev = self._d_prev
            d_prev[:, 1:] = D[:, :-1]
            hd = h[2:, None, :] * d_prev  # (2, Nc, Np): vₚ sin θₚ Dⱼ,ₚ, vₚ cos θₚ Dⱼ,ₚ
            xy = (hd.reshape(2 * Nc, Np) @ self._ts_before).reshape(2, Nc, Np)
            np.negative(xy[0], out=steer[:, 0])
            steer[:, 1] = xy[1]
        # the sum over m ≤ k as a product with a triangle of ones: one BLAS call, where a
        # cumulative sum along the short rows costs several times more
        out = (PG.reshape(-1, Np) @ self._upper).reshape(2 * Nc + 1, N_STATES * Np)
        return out[:-1], out[-1]


def grouped_by_output(S: FloatArray, Np: int) -> FloatArray:
    """Rows of a prediction matrix stacked by step (the paper's order) regrouped by output.

    :param S: (Np·q, …) with row ``(k − 1)·q + o``
    :returns: the same rows in the order ``o·Np + k − 1`` (a new array)
    """
    q = S.shape[0] // Np
    return S.reshape(Np, q, -1).transpose(1, 0, 2).reshape(S.shape)


def kinematic_first_increment(
    increment: tuple[float, float, float, float],
    speed: float,
    heading: float,
    tan_delta: float,
    Ts: float,
    wheelbase: float,
) -> tuple[float, float, float, float]:
    """``Δx̃`` with ``A Δx̃ = increment`` for the kinematic Jacobian ``A`` at one operating point.

    ``A = I + N`` with ``N³ = 0``, so ``A⁻¹ = I − N + N²``: a few float operations instead of a
    4×4 solve.
    """
    z0, z1, z2, z3 = increment
    a = Ts * math.cos(heading)
    c = Ts * math.sin(heading)
    b = -(Ts * speed * math.sin(heading))
    d = Ts * speed * math.cos(heading)
    e = (Ts / wheelbase) * tan_delta
    w3 = z3 - e * z2  # θ row: the only entry N feeds back into x and y a second time
    return (z0 - a * z2 - b * w3, z1 - c * z2 - d * w3, z2, w3)


def steer_lag_first_increment(
    state: tuple[float, float, float, float, float],
    u: tuple[float, float],
    speed: float,
    Ts: float,
    wheelbase: float,
    alpha: float,
) -> tuple[float, float, float, float, float]:
    """``Δx̃`` with ``A Δx̃ = z`` for the steering-aware model (:func:`augment_steer_lag`).

    ``z`` is one model step's change of ``state = [x, y, v, θ, t]`` with ``u = [a, t_cmd]``
    held (:func:`steer_lag_increment`); ``A`` is the Jacobian at the operating ``speed``, the
    step's :func:`mid_heading` and the actual ``t``. ``A = [[K, g e₃], [0, β]]`` (``g = Ts v /
    L``, ``β = 1 − α``) is block triangular: ``Δt = z_t / β``, then the kinematic part solves
    ``K Δx = z − g e₃ Δt`` (:func:`kinematic_first_increment`). Float operations only, no 5×5
    solve.
    """
    _, _, v, _, t = state
    a, t_cmd = u
    mid = mid_heading(state, Ts, wheelbase)
    dt = alpha * (t_cmd - t) / (1.0 - alpha)
    z3 = Ts * v * t / wheelbase - (Ts * speed / wheelbase) * dt
    z = (Ts * v * math.cos(mid), Ts * v * math.sin(mid), Ts * a, z3)
    return (*kinematic_first_increment(z, speed, mid, t, Ts, wheelbase), dt)
