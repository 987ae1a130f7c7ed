"""Benchmark of the MPC step (reference + linearisation + matrices + solve) and its QP solvers.

Drives the kinematic plant along the S-curve per backend (DAQP, Hildreth, OSQP) from three
standing starts — on the path (constraints inactive almost throughout), 0.8 m beside it, and
0.9 m / 25° off (steering-rate, steering and jerk limits active for seconds) — and times every
``controller.step``. The QPs of the DAQP run's constrained steps are recorded and re-solved, in
the same run, by DAQP the controller's way (one workspace updated in place, each QP started
from the last one's active set), DAQP set up anew for each QP, Hildreth (the configured sweep
cap), OSQP updated in place (the controller's way) and OSQP set up anew; ratios are to DAQP
the controller's way, and each backend's first moves are
compared with DAQP's (converged counts and the largest difference, as measured). The whole MPC
step with constraints active is compared with the same optimisation written with cvxpy four
ways, on 60 of those steps and their QPs, each row timed between two timings of the same
steps (:func:`_cvxpy_rows`: the model handed over with the states as variables, the condensed
QP handed over, the paper's problem built every step, the paper's problem with parameters),
each row with the speed-up and whether it reaches the 100× goal (``pip install 'leafgate[bench]'``;
skipped, and said so, when cvxpy is missing); and the floor under those speed-ups
(:func:`_floor`: the step's Python parts outside its numeric work, plus the DAQP solve). One
untimed drive comes first, so that the first backend timed does not pay for the process's
warm-up. Prints one JSON document; times in
microseconds.

    .venv/bin/python tools/bench_mpc.py [--repeat 3] [--model kinematic_steer_lag]
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import platform
import time
import warnings
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.config.sim import PlantConfig
from leafgate.control.model import N_STATES, augment_steer_lag, linearise_along
from leafgate.control.mpc import MpcController
from leafgate.control.qp import DaqpBackend, OsqpBackend, QpResult, hildreth
from leafgate.messages import ControlOutput, Gear, Pose
from leafgate.sim.plant import gear_direction, make_plant
from leafgate.sim.scenarios import get_scenario

PERIOD = 0.02  # s, control tick
GOAL_MEDIAN_US = 150.0  # the whole MPC step
GOAL_P99_US = 500.0
GOAL_DAQP_MEDIAN_US = 60.0  # DAQP on a QP with constraints active (issue 13)
GOAL_DAQP_P99_US = 200.0
GOAL_CVXPY_RATIO = 100.0  # the whole MPC step vs the cvxpy formulation of its QP
# starts: on the path, 0.8 m beside it, and 0.9 m / 25° off (the steering saturates for seconds)
STARTS = ((0.0, 0.0), (0.8, 0.0), (0.9, math.radians(25.0)))


class _RecordingPrediction:
    """The controller's prediction, which also keeps the model each call was built from while
    its controller records. A callable object rather than a closure: a deep copy of the
    controller (:func:`_copy`) then records into the copy."""

    def __init__(self, ctrl: _RecordingController, predict: Any) -> None:
        self.ctrl = ctrl
        self.predict = predict

    def __call__(self, speed: np.ndarray, heading: np.ndarray, tan: float, dx0: Any) -> Any:
        ST, free = self.predict(speed, heading, tan, dx0)
        if self.ctrl.record:
            # the model the prediction was built from: operating points and Δx₀ (for the
            # cvxpy row that hands cvxpy the model itself), and the free response
            model = (speed.copy(), heading.copy(), tan, np.array(dx0), free.copy())
            self.ctrl._last_model = model
        return ST, free


class _RecordingController(MpcController):
    """Keeps the QPs that reached a solver (constraints active) for the solver rows, and with
    each the terms the QP was built from (``Sᵀ`` and ``Rs − F x``) for the cvxpy rows; only
    while ``record`` is set (else it only adds two attribute reads a step)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.qps: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.terms: list[tuple[np.ndarray, np.ndarray, tuple]] = []
        self.record = False
        self._last_terms: tuple[np.ndarray, np.ndarray, tuple] | None = None
        self._last_model: tuple = ()
        self._predict = _RecordingPrediction(self, self._predict)  # type: ignore[assignment]

    def _qp_terms(self, ST: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.record:
            self._last_terms = (ST, err, self._last_model)
        return super()._qp_terms(ST, err)

    def _drive_off_tan(self, *args: Any) -> float:
        """Not recorded: the QPs solved at rest for the aligning angle are no tick's QP."""
        record, self.record = self.record, False
        try:
            return super()._drive_off_tan(*args)
        finally:
            self.record = record

    def _solve(self, E: np.ndarray, f: np.ndarray, gamma: np.ndarray) -> QpResult:
        result = super()._solve(E, f, gamma)
        if self.record and result.iterations > 0:
            assert self._last_terms is not None
            # the solver rows re-solve every QP with one M: the S-curve is driven forward only
            assert self.M is self._M_dir[1], "a QP of the reverse direction"
            self.qps.append((E.copy(), f.copy(), gamma.copy()))
            ST, err, model = self._last_terms
            self.terms.append((ST.copy(), err.copy(), model))
        return result


def _drive(
    solver: str,
    offset: float,
    dpsi: float,
    record: bool,
    model: str = "kinematic",
    snapshots: list | None = None,
) -> tuple[list, list, Any]:
    """One closed-loop run; returns (step times of unconstrained steps, of constrained, ctrl).

    The second list holds the steps whose QP reached a solver (some constraint active).

    :param snapshots: when given, each constrained step's inputs are appended to it with a
        deep copy of the controller taken just before the step (sharing the plan and its
        reference path, which a step does not change): ``(copy, pose, steer angle, plan)``.
        Its step times then include no copying but follow it: not for the timed rows.
    """
    scenario = get_scenario("s-curve")
    traj = scenario.trajectory
    cfg = MpcConfig(
        solver=solver,  # type: ignore[arg-type]
        prediction_horizon=30,
        control_horizon=10,
        model=model,  # type: ignore[arg-type]
    )
    vehicle = VehicleConfig()
    ctrl = _RecordingController(cfg, vehicle, PERIOD)
    ctrl.record = record
    s = scenario.start
    start = Pose(
        s.x - offset * math.sin(s.heading),
        s.y + offset * math.cos(s.heading),
        s.heading + dpsi,
        0.0,
    )
    plant = make_plant(PlantConfig(), vehicle, start)
    inactive: list[float] = []
    active: list[float] = []
    for _ in range(round(scenario.duration / PERIOD)):
        pose = plant.pose()
        snapshot = None if snapshots is None else _copy(ctrl, traj)
        t0 = time.perf_counter()
        out = ctrl.step(pose, plant.steer_angle, traj)
        elapsed = time.perf_counter() - t0
        (active if out.iterations > 0 else inactive).append(elapsed)
        if snapshots is not None and out.iterations > 0:
            snapshots.append((snapshot, pose, plant.steer_angle, traj))
        if out.finished:
            break
        direction = gear_direction(plant.gear)
        plant.step(PERIOD, out.steer_angle, direction * out.accel, plant.gear)
    return inactive, active, ctrl


def _copy(ctrl: _RecordingController, traj: Any) -> _RecordingController:
    """A deep copy of the controller that shares the plan and its reference path."""
    memo: dict[int, Any] = {id(traj): traj}
    if ctrl._path is not None:
        memo[id(ctrl._path)] = ctrl._path
    return copy.deepcopy(ctrl, memo)


def _stats(samples: list[float]) -> dict[str, float | int]:
    if not samples:
        return {"n": 0}
    arr = np.asarray(samples) * 1e6
    return {
        "n": int(arr.size),
        "median_us": round(float(np.median(arr)), 1),
        "p99_us": round(float(np.percentile(arr, 99)), 1),
    }


def _time_solver(qps: list, solve: Any, repeats: int = 1) -> list[float]:
    """Per QP the fastest of ``repeats`` solves: with ``repeats`` > 1 a preemption of this
    process by others (a shared machine) is not counted as solver time."""
    times = []
    for E, f, gamma in qps:
        best = math.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            solve(E, f, gamma)
            best = min(best, time.perf_counter() - t0)
        times.append(best)
    return times


def _solver_rows(ctrl: MpcController, qps: list, repeats: int) -> dict[str, Any]:
    """Every backend on the same constrained QPs, in this run; first moves compared to DAQP's."""
    M = ctrl.M
    rows: dict[str, Any] = {}
    daqp_backend = DaqpBackend(M)
    reference = [daqp_backend.solve(E, f, g) for E, f, g in qps]

    def agreement(results: list[QpResult]) -> dict[str, Any]:
        """Converged count and the largest first-move difference to DAQP over the QPs both
        solved (checked here, not assumed)."""
        diffs = [
            float(np.abs(r.x[:2] - ref.x[:2]).max())
            for r, ref in zip(results, reference, strict=True)
            if r.converged and ref.converged
        ]
        return {
            "converged": sum(r.converged for r in results),
            "first_move_max_diff_to_daqp": max(diffs) if diffs else None,
        }

    # the controller's way: one workspace, each QP from the last one's active set (once per
    # QP whatever ``repeats``, as OSQP below: a repeat would start from the QP's own answer)
    daqp_backend.reset()
    rows["daqp"] = _stats(_time_solver(qps, daqp_backend.solve))
    rows["daqp"].update(agreement(reference))

    def daqp_cold(E: np.ndarray, f: np.ndarray, g: np.ndarray) -> QpResult:
        daqp_backend.reset()  # a workspace set up for this QP alone
        return daqp_backend.solve(E, f, g)

    rows["daqp_cold_setup"] = _stats(_time_solver(qps, daqp_cold, repeats))
    rows["daqp_cold_setup"].update(agreement([daqp_cold(E, f, g) for E, f, g in qps]))
    cap = ctrl.cfg.max_iterations

    def hild(E: np.ndarray, f: np.ndarray, g: np.ndarray) -> QpResult:
        return hildreth(E, f, M, g, max_iter=cap, tol=ctrl.cfg.hildreth_tolerance, relaxation=1.5)

    rows["hildreth"] = _stats(_time_solver(qps, hild, repeats))
    rows["hildreth"].update(agreement([hild(E, f, g) for E, f, g in qps]))
    backend = OsqpBackend(qps[0][0], M)
    # once per QP whatever ``repeats``: a repeat would warm-start from the QP's own solution
    rows["osqp_in_place_warm"] = _stats(_time_solver(qps, backend.solve))
    backend.reset()
    rows["osqp_in_place_warm"].update(agreement([backend.solve(E, f, g) for E, f, g in qps]))

    A = sp.csc_matrix(M)
    lower = np.full(M.shape[0], -np.inf)

    def cold(E: np.ndarray, f: np.ndarray, g: np.ndarray) -> None:
        solver = osqp.OSQP()
        solver.setup(
            sp.csc_matrix(np.triu(E)),
            f,
            A,
            lower,
            g,
            verbose=False,
            polishing=True,
            eps_abs=1e-7,
            eps_rel=1e-7,
        )
        solver.solve(raise_error=False)

    rows["osqp_cold_setup"] = _stats(_time_solver(qps, cold, repeats))
    return rows


CVXPY_SAMPLES = 60  # constrained QPs per cvxpy row, spread over the whole run
SAME_QP_CHECKS = 5  # of them solved to 1e-12 in the states row, to check it is the same QP


def _model(ctrl: MpcController, err: np.ndarray, recorded: tuple) -> tuple:
    """The model one QP was built from, as the ``states_as_variables`` row hands it to cvxpy:
    the Jacobians ``Aₖ``, ``Bₖ`` at the step's operating points (the functions of the paper's
    equations, not the controller's closed form), the reference relative to ``y₀`` (4, Np), and
    ``Δx₀``."""
    speed, heading, tan, dx0, free = recorded
    Np, Ts, L = ctrl.Np, ctrl.Ts, ctrl.L
    A, B = linearise_along(speed, heading, np.full(Np, tan), Ts, L)
    if ctrl.steer_model:
        A, B = augment_steer_lag(A, B, ctrl._alpha, Ts, speed, L)
    ref = (err + free).reshape(N_STATES, Np)  # Rs − y₀: err is Rs − F x
    return A, B, ref, dx0


def _cvxpy_rows(steps: list) -> dict[str, Any]:
    """The whole MPC step against its optimisation written with cvxpy, side by side.

    ``steps`` are constrained steps of DAQP drives, each a copy of the controller taken just
    before the step and the step's inputs (:func:`_drive`'s snapshots). ``CVXPY_SAMPLES`` of
    them, spread over the drives, are taken. Each is first stepped once, untimed, on a copy
    that records its QP. Then, row by row, the sampled steps are timed (each on a fresh copy),
    the row solves their QPs, and the steps are timed again: the row's ``speedup`` is its
    median over the slower of the two step medians (``mpc_step_median_us``), so a machine whose
    speed changes during the run does not inflate it. Blocks, not alternation step by step:
    a step timed right after a cvxpy solve read 2.5 times slower in one run (490 against
    200 µs), and 1.6 times after reading 32 MB of other data: the caches then hold the other
    work's data, which no tick of the gateway's loop has to live with. A copy's DAQP workspace
    is set up anew (DAQP's cannot be copied), so these steps solve cold where the controller's
    loop starts from the last tick's active set: they are timed slower than the loop runs, by
    about the difference of the ``daqp_cold_setup`` and ``daqp`` solver rows.

    The four rows (solved by OSQP through cvxpy; the first by Clarabel, see there):

    - ``states_as_variables``: the model handed over, as a cvxpy MPC is usually written (so
      PythonRobotics' ``linear_mpc_control``): the states ``Δxₖ`` and outputs ``yₖ`` are
      variables, each step's dynamics ``Δxₖ₊₁ = Aₖ Δxₖ + Bₖ Δuₖ``, ``yₖ₊₁ = yₖ + C Δxₖ₊₁`` a
      constraint, the cost a sum of per-step quadratic forms; cvxpy condenses nothing, the
      solver gets the sparse problem. Built and solved every step (the Jacobians change), by
      Clarabel at its default tolerances: cvxpy's OSQP stops at its iteration limit on about a
      quarter of these problems, and its time would be that of a failed solve.
      ``Aₖ`` and ``Bₖ`` come from :func:`~leafgate.control.model.linearise_along` (and
      :func:`~leafgate.control.model.augment_steer_lag`) at the controller's operating points,
      taken before the clock starts. That it is the MPC's QP is checked on ``SAME_QP_CHECKS``
      of the QPs, solved to 1e-12 by Clarabel: the largest first-move difference to DAQP is
      reported as ``same_qp_first_move_max_diff``;
    - ``given_hessian``: the condensed QP ``½ΔUᵀEΔU + fᵀΔU, MΔU ≤ γ`` handed over with ``E``
      and ``f`` already formed (the MPC's own work), problem built and solved every step;
    - ``paper_problem``: the problem as the paper states it, ``(Rs − Fx − ΦΔU)ᵀQ(Rs − Fx −
      ΦΔU) + ΔUᵀR̄ΔU`` with ``MΔU ≤ γ``, from ``Φ`` (``Sᵀ`` transposed) and ``Rs − Fx`` (the
      condensing done by the MPC), built and solved every step;
    - ``parametrized``: the paper's problem built once with ``Φ``, ``Rs − Fx`` and ``γ`` as cvxpy
      parameters (DPP), their values set and the problem solved every step.

    The reference and prediction a cvxpy MPC step also needs are not added: each row is a lower
    bound of such a step. Every row's first moves are compared with DAQP's (largest difference,
    as measured: cvxpy's OSQP stops at its default tolerances), and cvxpy's statuses counted.
    """
    try:
        import cvxpy as cp
    except ImportError:
        return {"skipped": "cvxpy not installed (pip install 'leafgate[bench]')"}
    pick = np.linspace(0, len(steps) - 1, min(CVXPY_SAMPLES, len(steps))).round().astype(int)
    picked = [steps[i] for i in pick]
    sample = []  # per picked step, its QP: E, f, γ, Sᵀ, Rs − F x and the model
    for snapshot, pose, steer, traj in picked:
        rec = _copy(snapshot, traj)
        rec.record = True
        rec.step(pose, steer, traj)
        assert len(rec.qps) == 1, "a snapshot's step did not reach the solver again"
        ST, err, recorded = rec.terms[0]
        sample.append((*rec.qps[0], ST, err, _model(rec, err, recorded)))
    ctrl = picked[0][0]
    M = ctrl.M
    reference = [DaqpBackend(M).solve(E, f, g).x[:2] for E, f, g, *_ in sample]

    def mpc_step(i: int) -> float:
        """The whole step of sample ``i``, s, on a fresh copy of the controller before it."""
        snapshot, pose, steer, traj = picked[i]
        c = _copy(snapshot, traj)
        t0 = time.perf_counter()
        c.step(pose, steer, traj)
        return time.perf_counter() - t0

    sqrt_q = np.sqrt(ctrl._q_out)
    sqrt_r = np.sqrt(ctrl.r_bar)
    n = M.shape[1]

    def given_hessian(E: np.ndarray, f: np.ndarray, g: np.ndarray, *_: Any) -> Any:
        x = cp.Variable(n)
        cost = 0.5 * cp.quad_form(x, cp.psd_wrap(E)) + f @ x
        problem = cp.Problem(cp.Minimize(cost), [M @ x <= g])
        problem.solve(solver=cp.OSQP)
        return x.value, problem.status

    Np = ctrl.Np
    q_step = np.diag(ctrl.q_bar[:N_STATES])  # Q of one step's outputs
    move_at = {int(k): j for j, k in enumerate(ctrl._moves)}  # step → the move acting from it

    def states(
        _E: Any, _f: Any, g: np.ndarray, _ST: Any, _err: Any, model: tuple, tight: bool = False
    ) -> Any:
        A, B, ref, dx0 = model
        ns = A.shape[1]
        C = np.eye(N_STATES, ns)
        x = cp.Variable(n)  # ΔU, the moves
        dx = cp.Variable((Np + 1, ns))  # Δx₀ … Δx_Np
        y = cp.Variable((Np + 1, N_STATES))  # outputs, relative to y₀
        constraints = [dx[0] == dx0, y[0] == 0, M @ x <= g]
        cost = cp.sum_squares(cp.multiply(sqrt_r, x))
        for k in range(Np):
            step = A[k] @ dx[k]
            if k in move_at:
                j = move_at[k]
                step = step + B[k] @ x[2 * j : 2 * j + 2]
            constraints += [dx[k + 1] == step, y[k + 1] == y[k] + C @ dx[k + 1]]
            cost += cp.quad_form(ref[:, k] - y[k + 1], q_step)
        problem = cp.Problem(cp.Minimize(cost), constraints)
        if tight:  # the check that this is the MPC's QP: solved to 1e-12
            problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
        else:
            problem.solve(solver=cp.CLARABEL)
        return x.value, problem.status

    def paper(_E: Any, _f: Any, g: np.ndarray, ST: np.ndarray, err: np.ndarray, *_: Any) -> Any:
        x = cp.Variable(n)
        cost = cp.sum_squares(cp.multiply(sqrt_q, err - ST.T @ x))
        cost += cp.sum_squares(cp.multiply(sqrt_r, x))
        problem = cp.Problem(cp.Minimize(cost), [M @ x <= g])
        problem.solve(solver=cp.OSQP)
        return x.value, problem.status

    outputs = sample[0][3].shape[1]  # 4 Np predicted outputs
    phi = cp.Parameter((n, outputs))  # Φᵀ: Sᵀ as the MPC forms it
    rs = cp.Parameter(outputs)
    gamma = cp.Parameter(M.shape[0])
    xp = cp.Variable(n)
    cost = cp.sum_squares(cp.multiply(sqrt_q, rs - phi.T @ xp))
    cost += cp.sum_squares(cp.multiply(sqrt_r, xp))
    problem = cp.Problem(cp.Minimize(cost), [M @ xp <= gamma])

    def parametrized(
        _E: Any, _f: Any, g: np.ndarray, ST: np.ndarray, err: np.ndarray, *_: Any
    ) -> Any:
        phi.value, rs.value, gamma.value = ST, err, g
        problem.solve(solver=cp.OSQP)
        return xp.value, problem.status

    rows: dict[str, Any] = {"n": len(sample)}
    # cvxpy warns of an inaccurate solution on stderr; each row counts its statuses instead
    warnings.filterwarnings("ignore", message="Solution may be inaccurate", category=UserWarning)
    solvers: dict[str, Callable[..., Any]] = {
        "states_as_variables": states,
        "given_hessian": given_hessian,
        "paper_problem": paper,
        "parametrized": parametrized,
    }
    for solve in solvers.values():
        solve(*sample[0])  # the first call compiles (parametrized: once for all)

    def step_median_us() -> float:
        median_us = _stats([mpc_step(i) for i in range(len(sample))])["median_us"]
        return float(median_us)

    for name, solve in solvers.items():
        before_us = step_median_us()
        times, diffs, statuses = [], [], Counter[str]()
        for qp, ref in zip(sample, reference, strict=True):
            t0 = time.perf_counter()
            x, status = solve(*qp)
            times.append(time.perf_counter() - t0)
            statuses[status] += 1
            if x is not None:
                diffs.append(float(np.abs(x[:2] - ref).max()))
        step_us = max(before_us, step_median_us())
        row = _stats(times)
        rows[name] = {
            **row,
            "mpc_step_median_us": step_us,
            "speedup": round(row["median_us"] / step_us, 1),
            "status": dict(statuses),  # cvxpy's word: "optimal", "optimal_inaccurate", …
            "first_move_max_diff_to_daqp": max(diffs) if diffs else None,
        }
    stride = max(1, len(sample) // SAME_QP_CHECKS)  # spread over the run, as the sample is
    tight = [states(E, f, g, ST, err, m, tight=True) for E, f, g, ST, err, m in sample[::stride]]
    rows["states_as_variables"]["same_qp_first_move_max_diff"] = max(
        (float(np.abs(x[:2] - ref).max()) if x is not None else math.inf)
        for (x, _), ref in zip(tight, reference[::stride], strict=True)
    )
    return rows


def _floor(steps: list, daqp_median_us: float, cvx: dict[str, Any]) -> dict[str, Any]:
    """What a step with constraints active would take if its numeric work — reference points,
    prediction, ``E``, ``f``, ``γ``, the unconstrained solve and the first move's prediction —
    cost nothing: the Python around it, timed part by part on the constrained steps (each part
    on a fresh copy of the controller before the step, untimed copy), plus the DAQP solve. The
    cvxpy rows' medians over it are the most a compiled numeric core could reach."""
    pick = np.linspace(0, len(steps) - 1, min(CVXPY_SAMPLES, len(steps))).round().astype(int)
    parts: dict[str, list[float]] = {
        "observe": [],
        "track_segment": [],
        "limit_previous": [],
        "speed_bound": [],
        "control_output": [],
    }
    for i in pick:
        snapshot, pose, steer, traj = steps[i]
        c = _copy(snapshot, traj)
        if traj is not c._traj:  # a first step takes the plan first (not timed)
            c._set_trajectory(traj)
        t0 = time.perf_counter()
        c._observe(pose, steer)
        t1 = time.perf_counter()
        c._track_segment(pose, t1)
        t2 = time.perf_counter()
        direction = c._progress.segment.direction
        c._limit_previous(direction)
        t3 = time.perf_counter()
        c._speed_bound(c._progress.segment, c._s_pose, pose.speed)
        t4 = time.perf_counter()
        ControlOutput(
            steer_angle=0.0,
            accel=0.0,
            speed=0.0,
            gear=Gear.D,
            converged=True,
            status="ok",
            solve_time=0.0,
            **c._where(),
        )
        t5 = time.perf_counter()
        for name, dt in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4), strict=True):
            parts[name].append(dt)
    medians = {name: round(float(np.median(v)) * 1e6, 2) for name, v in parts.items()}
    floor = sum(medians.values()) + daqp_median_us
    return {
        "n": int(pick.size),
        "python_parts_median_us": medians,
        "daqp_qp_median_us": daqp_median_us,
        "floor_us": round(floor, 1),
        "speedup_at_floor": {
            name: round(row["median_us"] / floor, 1)
            for name, row in cvx.items()
            if isinstance(row, dict) and "median_us" in row
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=2, help="runs per case (default 2)")
    parser.add_argument(
        "--model",
        choices=("kinematic", "kinematic_steer_lag"),
        default="kinematic",
        help="prediction model of the controller (default kinematic)",
    )
    parser.add_argument(
        "--solve-repeats",
        type=int,
        default=1,
        help="solver rows: per QP the fastest of this many solves (default 1; 5 keeps a "
        "shared machine's preemptions out of the p99)",
    )
    args = parser.parse_args()

    report: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or "?"},
        "config": {
            "Np": 30,
            "Nc": 10,
            "sample_time_s": 0.1,
            "period_s": PERIOD,
            "model": args.model,
            "solve_repeats": args.solve_repeats,
            "starts": [
                {"offset_m": o, "heading_deg": round(math.degrees(h), 1)} for o, h in STARTS
            ],
        },
        "goal": {
            "daqp_qp_median_us": GOAL_DAQP_MEDIAN_US,
            "daqp_qp_p99_us": GOAL_DAQP_P99_US,
            "step_median_us": GOAL_MEDIAN_US,
            "step_p99_us": GOAL_P99_US,
            "step_speedup_vs_cvxpy": GOAL_CVXPY_RATIO,
        },
        "step": {},
    }
    qps: list = []
    ctrl: _RecordingController | None = None
    # one drive untimed first: the first backend timed must not pay for the process's warm-up
    # (imports done lazily, buffers first touched), which once read as DAQP's steps being slower
    # than Hildreth's where neither solved anything
    _drive("hildreth", *STARTS[2], False, args.model)
    for solver in ("daqp", "hildreth", "osqp"):
        inactive: list[float] = []
        active: list[float] = []
        for _ in range(args.repeat):
            for offset, dpsi in STARTS:
                a, b, c = _drive(solver, offset, dpsi, solver == "daqp", args.model)
                inactive += a
                active += b
                if solver == "daqp":
                    qps += c.qps
                    ctrl = c
        report["step"][solver] = {
            "constraints_inactive": _stats(inactive),
            "constraints_active": _stats(active),
            "all": _stats(inactive + active),
        }
    assert ctrl is not None
    rows = _solver_rows(ctrl, qps, max(args.solve_repeats, 1)) if qps else {}
    report["qp_solve_constrained"] = rows
    ratios: dict[str, float] = {}
    base = rows.get("daqp", {}).get("median_us")
    for name, row in rows.items():
        if base and "median_us" in row and name != "daqp":
            ratios[f"{name}_vs_daqp_median"] = round(row["median_us"] / base, 2)
    report["qp_ratios"] = ratios
    # the whole MPC step (DAQP, the steps with constraints active) against each cvxpy row on
    # the same steps' QPs (_cvxpy_rows): copies of the controller before each constrained
    # step of one drive per start, that drive not timed
    steps: list = []
    for offset, dpsi in STARTS:
        _drive("daqp", offset, dpsi, False, args.model, snapshots=steps)
    cvx = _cvxpy_rows(steps) if steps else {"skipped": "no constrained step"}
    report["cvxpy_formulation_step"] = cvx
    speedup = {
        name: row["speedup"]
        for name, row in cvx.items()
        if isinstance(row, dict) and "speedup" in row
    }
    report["step_speedup_vs_cvxpy"] = speedup
    daqp_row = rows.get("daqp", {})
    if steps and "median_us" in daqp_row:
        report["step_floor"] = _floor(steps, daqp_row["median_us"], cvx)
    report["goal_met"] = {
        "daqp_qp": {
            "median": daqp_row.get("median_us", math.inf) <= GOAL_DAQP_MEDIAN_US,
            "p99": daqp_row.get("p99_us", math.inf) <= GOAL_DAQP_P99_US,
        },
        "step": {
            solver: {
                case: {
                    "median": row.get("median_us", math.inf) <= GOAL_MEDIAN_US,
                    "p99": row.get("p99_us", math.inf) <= GOAL_P99_US,
                }
                for case, row in cases.items()
            }
            for solver, cases in report["step"].items()
        },
        "step_speedup_vs_cvxpy": {
            name: ratio >= GOAL_CVXPY_RATIO for name, ratio in speedup.items()
        },
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
