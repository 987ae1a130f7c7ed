"""Quadratic programme solvers for the MPC: ``min ½ xᵀE x + xᵀf  s.t.  M x ≤ γ`` (eq. 30–31).

Three backends return the same :class:`QpResult`:

- :class:`DaqpBackend` — DAQP (Arnström, Bemporad, Axehill), an exact dual active-set solver
  written for the small dense QPs of MPC: the default. A ``M`` of the MPC's shape
  ``[C; −C; I; −I; D]`` is passed as two-sided constraints ``lo ≤ C x ≤ hi`` with simple bounds
  ``lo ≤ x ≤ hi`` (a quarter of the first rows) and the rows ``D`` (the MPC's speed rows, if
  any) one-sided; any other ``M`` as ``M x ≤ γ``. One DAQP workspace is kept and updated in
  place (no allocation in DAQP's solve), and each solve starts from the last one's active set.

- :func:`hildreth` — Hildreth's dual coordinate-ascent procedure as in Wang's ``QPhild``: the
  unconstrained optimum is returned when it is feasible; otherwise the dual
  ``min ½ λᵀPλ + λᵀd, λ ≥ 0`` with ``P = M E⁻¹ Mᵀ`` and ``d = γ + M E⁻¹ f`` is solved by
  sweeps over the multipliers. It may stop at the sweep cap with a slightly infeasible primal;
  the caller must clip what it applies.
- :class:`OsqpBackend` — OSQP set up once with a fixed sparsity pattern, then updated in place
  and warm-started every cycle.

None raises on a hard problem: non-convergence (and infeasibility) is reported in
:attr:`QpResult.converged`, never as converged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import daqp
import numpy as np
import numpy.typing as npt
import osqp
import scipy.sparse as sp
from scipy.linalg import lapack

from leafgate.messages import FloatArray


@dataclass(frozen=True, slots=True)
class QpResult:
    """Solution of one QP.

    ``iterations`` counts Hildreth sweeps (0 when the unconstrained optimum was feasible) or
    OSQP ADMM iterations; ``lam`` holds the multipliers of ``M x ≤ γ`` (≥ 0).
    """

    x: FloatArray
    converged: bool
    iterations: int
    lam: FloatArray


def hildreth(
    E: FloatArray,
    f: FloatArray,
    M: FloatArray,
    gamma: FloatArray,
    max_iter: int = 38,
    tol: float = 1e-12,
    lam0: FloatArray | None = None,
    E_inv: FloatArray | None = None,
    relaxation: float = 1.0,
    feas_tol: float = 1e-6,
    chol: FloatArray | None = None,
    x_unc: FloatArray | None = None,
) -> QpResult:
    """Hildreth's quadratic programming procedure (Wang, ``QPhild``).

    **Active-set certificate.** Hildreth's sweeps find the active set long before the
    multipliers on it converge (the tail is linear convergence on a fixed set). So once the
    set of positive multipliers is the same after two consecutive sweeps, the multipliers on
    it are computed exactly — ``P_AA λ_A = −d_A``, a solve of the size of the active set —
    and accepted when they satisfy the KKT conditions (``λ_A ≥ 0``, no constraint violated by
    more than ``feas_tol``). That point is the optimum the sweeps converge to; it is reported
    as converged after the sweeps done so far. A set that fails the check is not tried again
    and the sweeps go on as before.

    :param E: Hessian, symmetric positive definite (n×n)
    :param f: linear term (n)
    :param M: constraint matrix (m×n)
    :param gamma: constraint bounds (m)
    :param max_iter: sweep cap (the paper uses 38)
    :param tol: convergence threshold on ``‖λₖ − λₖ₋₁‖²`` between two sweeps, relative to
        ``max(1, ‖λₖ‖²)`` (Wang uses 1e-7 absolute; the default is tighter so that the first move
        agrees with OSQP to 1e-4)
    :param lam0: multipliers to start from (warm start), e.g. the previous cycle's
    :param E_inv: ``E⁻¹`` if the caller has it already
    :param relaxation: ω of projected successive over-relaxation; 1 is Hildreth's procedure,
        values in (1, 2) often need fewer sweeps
    :param feas_tol: a small λ change only counts as converged when the primal solution also
        violates no constraint by more than this (in the units of ``γ``)
    :param chol: the upper Cholesky factor ``U`` of ``E = UᵀU`` (LAPACK ``potrf``/``posv``,
        ``lower=0``) if the caller has it; used for every solve with ``E``
    :param x_unc: the unconstrained optimum ``−E⁻¹f`` if the caller has it
    :returns: the primal solution, whether the sweeps converged, the number of sweeps and the
        multipliers
    """
    solve_E = _solver_for(E, E_inv, chol)
    if x_unc is None:
        x_unc = -solve_E(f)
    m = M.shape[0]
    excess = M @ x_unc - gamma
    if np.all(excess <= 0.0):
        return QpResult(x_unc, True, 0, np.zeros(m))

    # Working set: sweeps skip the constraints that are satisfied with a zero multiplier — a
    # full sweep would leave them at zero — and take them in as soon as the primal violates
    # them. The fixed point is Hildreth's; the cost follows the few active constraints, not
    # the 4·Nc·m rows of M.
    lam_full = np.zeros(m)
    working = excess > 0.0
    if lam0 is not None and lam0.shape == (m,) and np.all(np.isfinite(lam0)):
        warm = lam0 > 0.0
        working |= warm
        lam_full[warm] = lam0[warm]
    x = x_unc
    sweeps = 0
    converged = False
    tried: set[tuple[int, ...]] = set()  # active sets whose exact solution failed the check
    while sweeps < max_iter:
        idx = np.flatnonzero(working)
        Mw = M[idx]
        EiMt = solve_E(Mw.T)  # n×|W|
        P = Mw @ EiMt
        d = gamma[idx] - Mw @ x_unc  # = γ + M E⁻¹ f on the working set
        # the sweep is sequential by nature: over Python floats it costs far less per element
        # than numpy calls on short vectors; w = P λ is kept up to date incrementally
        P_rows: list[list[float]] = P.tolist()
        k = len(P_rows)
        scale = [relaxation / P_rows[i][i] if P_rows[i][i] > 0.0 else 0.0 for i in range(k)]
        d_list: list[float] = d.tolist()
        lam_w = lam_full[idx]
        lam: list[float] = lam_w.tolist()
        w: list[float] = (P @ lam_w).tolist()
        rows = range(k)
        idx_list: list[int] = idx.tolist()
        previous: tuple[int, ...] | None = None  # positive set after the last sweep
        while sweeps < max_iter:
            sweeps += 1
            change = 0.0
            for i in rows:
                li = lam[i]
                new = li - (d_list[i] + w[i]) * scale[i]  # a zero row has scale 0: λ stays
                if new < 0.0:
                    new = 0.0
                step = new - li
                if step != 0.0:
                    lam[i] = new
                    row = P_rows[i]  # P is symmetric: column i equals row i
                    for j in rows:
                        w[j] += step * row[j]
                    change += step * step
            lam_w = np.asarray(lam)
            x = x_unc - EiMt @ lam_w
            excess = M @ x - gamma
            if np.any((excess > feas_tol) & ~working):
                break  # a new constraint is violated: take it into the working set
            if (change < tol or change < tol * sum(v * v for v in lam)) and np.all(
                excess <= feas_tol
            ):
                converged = True
                break
            positive = [i for i in rows if lam[i] > 0.0]
            active = tuple(idx_list[i] for i in positive)
            if active == previous and active not in tried:
                positive.sort(key=lam.__getitem__, reverse=True)  # the likeliest members first
                exact = _exact_on_active_set(positive, idx, P, d, EiMt, x_unc, M, gamma, feas_tol)
                if exact is None:
                    tried.add(active)
                else:
                    x, lam_w = exact
                    converged = True
                    break
            previous = active
        lam_full[idx] = lam_w
        if converged:
            break
        working |= excess > feas_tol
    return QpResult(x, converged, sweeps, lam_full)


def qphild(
    E: FloatArray,
    f: FloatArray,
    M: FloatArray,
    gamma: FloatArray,
    max_iter: int = 38,
    tol: float = 1e-7,
) -> QpResult:
    """Hildreth's procedure exactly as Wang's textbook ``QPhild`` (the paper's solver).

    The reference the accelerated :func:`hildreth` is tested against: no warm start, no working
    set, no relaxation, no active-set certificate, a full Gauss–Seidel sweep over all ``m``
    multipliers of the dual ``min ½ λᵀHλ + λᵀK, λ ≥ 0`` (``H = M E⁻¹ Mᵀ``,
    ``K = γ + M E⁻¹ f``), stopping when ``‖λₖ − λₖ₋₁‖² < tol`` (Wang: 10e-8) or after
    ``max_iter`` sweeps (the paper: 38). The primal is ``x = −E⁻¹(f + Mᵀλ)``.
    """
    x_unc = np.asarray(-np.linalg.solve(E, f), dtype=np.float64)
    m = M.shape[0]
    if np.all(M @ x_unc <= gamma):
        return QpResult(x_unc, True, 0, np.zeros(m))
    EiMt = np.asarray(np.linalg.solve(E, M.T), dtype=np.float64)
    H = M @ EiMt
    K = gamma - M @ x_unc
    lam = np.zeros(m)
    converged = False
    sweeps = 0
    while sweeps < max_iter:
        sweeps += 1
        previous = lam.copy()
        for i in range(m):
            w = H[i] @ lam - H[i, i] * lam[i] + K[i]
            lam[i] = max(0.0, -w / H[i, i])
        step = lam - previous
        if step @ step < tol:
            converged = True
            break
    return QpResult(x_unc - EiMt @ lam, converged, sweeps, lam)


def _solver_for(
    E: FloatArray, E_inv: FloatArray | None, chol: FloatArray | None
) -> Callable[[FloatArray], FloatArray]:
    """``B ↦ E⁻¹ B`` from what the caller has: ``E⁻¹``, a Cholesky factor, or only ``E``."""
    if E_inv is not None:
        inverse = E_inv
        return lambda B: inverse @ B
    if chol is None:
        chol, info = lapack.dpotrf(E)
        if info != 0:  # not positive definite (or not finite): the general inverse, as always
            inverse = np.linalg.inv(E).astype(np.float64, copy=False)
            return lambda B: inverse @ B
    factor = chol

    def solve(B: FloatArray) -> FloatArray:
        return np.asarray(lapack.dpotrs(factor, B)[0], dtype=np.float64)

    return solve


def _exact_on_active_set(
    members: list[int],
    idx: npt.NDArray[np.intp],
    P: FloatArray,
    d: FloatArray,
    EiMt: FloatArray,
    x_unc: FloatArray,
    M: FloatArray,
    gamma: FloatArray,
    feas_tol: float,
) -> tuple[FloatArray, FloatArray] | None:
    """The QP's optimum found from a guess of its active set, or None.

    With the constraints of a set ``A`` held as equalities, ``λ_A = −P_AA⁻¹ d_A`` and
    ``x = x_unc − E⁻¹M_Aᵀλ_A``; that is the optimum when ``λ_A ≥ 0`` and ``x`` violates no
    constraint by more than ``feas_tol`` (the KKT conditions). Hildreth's positive set often
    still holds constraints whose multipliers are on their slow way to zero (more than the
    ``n`` that can be independent), or lacks one about to enter, so a few active-set
    corrections are made on the way: a constraint that depends on the ones before it (the
    Cholesky factorisation of ``P_AA`` reports which) or has the most negative multiplier
    leaves ``A``; the most violated constraint of the working set enters it.

    :param members: the guess, as positions in the working set ``idx``, likeliest first
    :returns: ``(x, λ on the working set idx)``
    """
    members = members[: EiMt.shape[0]]  # at most n independent constraints
    for _ in range(_CORRECTIONS + 1):
        if not members:
            return None
        local = np.array(members)
        _, lam_a, info = lapack.dposv(P[local][:, local], -d[local])
        if info > 0:  # the leading minor of order info is singular: that member depends on
            del members[info - 1]  # the ones before it
            continue
        worst = int(np.argmin(lam_a))
        if info != 0 or not lam_a[worst] >= 0.0:  # (the comparison also catches NaN)
            del members[worst]
            continue
        x = x_unc - EiMt[:, local] @ lam_a
        excess = M @ x - gamma
        if np.all(excess <= feas_tol):
            lam_w = np.zeros(idx.shape[0])
            lam_w[local] = lam_a
            return x, lam_w
        row = int(np.argmax(excess))
        at = int(np.searchsorted(idx, row))
        if at >= idx.shape[0] or idx[at] != row or at in members:
            return None  # violated outside the working set: the sweeps take it in first
        members.append(at)
    return None


_CORRECTIONS = 6  # active-set corrections tried on one guess (each is one small solve)


def _csc_full(
    pattern: FloatArray, upper: bool
) -> tuple[sp.csc_matrix, npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """CSC matrix keeping every structural non-zero of ``pattern`` (explicit zeros included).

    :returns: the matrix and the (row, col) index arrays of its data in CSC order
    """
    mask = pattern != 0
    if upper:
        mask = np.triu(np.ones_like(mask, dtype=bool))
    cols, rows = np.nonzero(mask.T)  # column-major order = CSC data order
    indptr = np.concatenate(([0], np.cumsum(mask.sum(axis=0))))
    mat = sp.csc_matrix((pattern[rows, cols].astype(np.float64), rows, indptr), shape=pattern.shape)
    return mat, rows, cols


class OsqpBackend:
    """OSQP for the MPC's QP, set up once and updated in place every cycle.

    The Hessian is treated as dense (its full upper triangle is the pattern) and the constraint
    matrix keeps the pattern of the ``M`` given at construction; later ``M`` must have its
    non-zeros inside that pattern. One-sided rows ``M x ≤ γ`` become ``−∞ ≤ M x ≤ γ``.

    :param E: a Hessian of the right size (values are only a starting point)
    :param M: the constraint matrix; its non-zero pattern is fixed from here on
    :param eps: absolute and relative tolerance of OSQP
    :param max_iter: ADMM iteration cap
    """

    def __init__(
        self, E: FloatArray, M: FloatArray, eps: float = 1e-7, max_iter: int = 4000
    ) -> None:
        self.n = E.shape[0]
        self.m = M.shape[0]
        P, self._p_rows, self._p_cols = _csc_full(np.asarray(E, dtype=np.float64), upper=True)
        A, self._a_rows, self._a_cols = _csc_full(np.asarray(M, dtype=np.float64), upper=False)
        self._solver = osqp.OSQP()
        settings: dict[str, Any] = {
            "verbose": False,
            "eps_abs": eps,
            "eps_rel": eps,
            "max_iter": max_iter,
            "polishing": True,  # active-set polish: exact first moves when it succeeds
            "polish_refine_iter": 10,  # OSQP's 3 left polish failing on a flat-cost QP of the
            # spread moves (ADMM's answer: the same cost to 1e-12, the first move 1.04e-6 off)
            "warm_starting": True,
        }
        self._lower = np.full(self.m, -np.inf)
        self._solver.setup(P, np.zeros(self.n), A, self._lower, np.zeros(self.m), **settings)
        self._solved_code = int(osqp.SolverStatus.OSQP_SOLVED)

    def solve(
        self, E: FloatArray, f: FloatArray, gamma: FloatArray, M: FloatArray | None = None
    ) -> QpResult:
        """Update the QP in place (warm start from the last solution) and solve it.

        :param M: a new constraint matrix with the construction pattern, or None to keep it
        """
        kwargs: dict[str, Any] = {
            "Px": np.ascontiguousarray(E[self._p_rows, self._p_cols]),
            "q": np.asarray(f, dtype=np.float64),
            "u": np.asarray(gamma, dtype=np.float64),
        }
        if M is not None:
            kwargs["Ax"] = np.ascontiguousarray(M[self._a_rows, self._a_cols])
        self._solver.update(**kwargs)
        res = self._solver.solve(raise_error=False)
        x = np.asarray(res.x, dtype=np.float64)
        lam = np.maximum(np.asarray(res.y, dtype=np.float64), 0.0)
        converged = int(res.info.status_val) == self._solved_code and bool(np.all(np.isfinite(x)))
        return QpResult(x, converged, int(res.info.iter), lam)

    def reset(self) -> None:
        """Drop the warm start (next solve starts from zero)."""
        self._solver.warm_start(x=np.zeros(self.n), y=np.zeros(self.m))


class DaqpBackend:
    """DAQP for ``min ½ xᵀE x + xᵀf  s.t.  M x ≤ γ`` with a fixed ``M``.

    When ``M`` starts with ``[C; −C; I; −I]`` (the MPC's cumulative input limits and rate
    limits) the QP goes to DAQP as ``γ₃ ≥ x ≥ −γ₄`` (simple bounds) and ``γ₁ ≥ C x ≥ −γ₂``, and
    any rows ``D`` after those (the MPC's speed rows) as the one-sided ``D x ≤ γ₅``; otherwise
    as the one-sided ``M x ≤ γ``. Multipliers are mapped back to the rows of ``M``.

    The workspace (a ``daqp.Model``) is set up at the first solve and updated in place after
    it, so each solve starts from the previous one's active set: on the MPC's QPs one tick's
    active set is mostly the next one's. The answer is the QP's unique optimum either way (``E``
    is positive definite); only the iterations to it differ. :meth:`reset` and a solve that
    did not end optimal drop the workspace, and the next solve starts cold.

    :param M: the constraint matrix
    :param max_iter: active-set iteration cap (DAQP's ``iter_limit``)
    :param primal_tol: DAQP's primal feasibility tolerance
    """

    OPTIMAL = 1  # DAQP exit flag of an optimal solution; soft-optimal, infeasible, cycling,
    # unbounded and the iteration cap are all reported as not converged

    def __init__(self, M: FloatArray, max_iter: int = 1000, primal_tol: float = 1e-9) -> None:
        M = np.asarray(M, dtype=np.float64)
        self.m, self.n = M.shape
        n = self.n
        self._structured = False
        if self.m >= 4 * n:
            C = M[:n]
            eye = np.eye(n)
            self._structured = bool(
                np.array_equal(M[n : 2 * n], -C)
                and np.array_equal(M[2 * n : 3 * n], eye)
                and np.array_equal(M[3 * n : 4 * n], -eye)
            )
        if self._structured:
            self._A = np.ascontiguousarray(np.vstack((M[:n], M[4 * n :])))
            self._lower = np.full(self.m - 2 * n, -1e30)  # bounds, C, then D (one-sided)
            # DAQP's rows from γ (upper: γ₃, γ₁, γ₅; lower: −γ₄, −γ₂), and M's multipliers from
            # [λ⁺; λ⁻] of DAQP's rows (λ⁺ = max(λ, 0), λ⁻ = max(−λ, 0)), as index arrays
            k, j = self.m - 2 * n, np.arange(n)
            self._upper_rows = np.concatenate((2 * n + j, j, np.arange(4 * n, self.m)))
            self._lower_rows = np.concatenate((3 * n + j, n + j))
            self._lam_rows = np.concatenate((n + j, k + n + j, j, k + j, np.arange(2 * n, k)))
        else:
            self._A = np.ascontiguousarray(M)
            self._lower = np.full(self.m, -1e30)
        self._settings: dict[str, Any] = {"iter_limit": max_iter, "primal_tol": primal_tol}
        self._model: daqp.Model | None = None

    def __getstate__(self) -> dict[str, Any]:
        """Copied or pickled without the workspace (DAQP's cannot be): the copy's first solve
        sets up its own, cold."""
        state = self.__dict__.copy()
        state["_model"] = None
        return state

    def reset(self) -> None:
        """Drop the workspace: the next solve starts with no active set."""
        self._model = None

    def solve(self, E: FloatArray, f: FloatArray, gamma: FloatArray) -> QpResult:
        """Solve one QP, from the last solve's active set (see the class notes)."""
        if self._structured:
            upper = gamma.take(self._upper_rows)
            lower = self._lower.copy()
            np.negative(gamma.take(self._lower_rows), out=lower[: 2 * self.n])
        else:
            upper, lower = np.asarray(gamma, dtype=np.float64), self._lower
        model = self._model
        if model is None:
            model = daqp.Model()
            model.settings = self._settings
            model.setup(E, f, self._A, upper, lower)
            self._model = model
        else:
            model.update(H=E, f=f, bupper=upper, blower=lower)
        x, _, flag, info = model.solve()
        x = np.asarray(x, dtype=np.float64)
        lam_d = np.asarray(info["lam"], dtype=np.float64)
        if self._structured:  # DAQP: λ > 0 on an active upper bound, λ < 0 on a lower one
            k = lam_d.shape[0]
            both = np.empty(2 * k)
            np.maximum(lam_d, 0.0, out=both[:k])
            np.negative(lam_d, out=both[k:])
            np.maximum(both[k:], 0.0, out=both[k:])
            lam = both.take(self._lam_rows)
        else:
            lam = np.maximum(lam_d, 0.0)
        converged = int(flag) == self.OPTIMAL and bool(np.isfinite(x).all())
        if not converged:
            self._model = None  # no active set to start the next QP from
        return QpResult(x, converged, int(info["iterations"]), lam)
