"""The paper's model predictive controller (Ignéczi, Horváth, Pup), as a leafgate Controller.

Each control tick:

1. reference — nearest waypoint (forward search), the vehicle's projection on the path, the
   path-aligned frame there, and ``Np`` reference points placed along the path by the planned
   speed profile (:mod:`leafgate.control.reference`);
2. model — the kinematic bicycle (optionally with the steering actuator) linearised (eq. 7–12)
   at the current state for the first step and along the plan for the later ones, and augmented
   (eq. 15–19) with the four kinematic states as outputs (see :mod:`leafgate.control.model` for
   why the frame is path-aligned and why ``x`` is an output);
3. prediction ``Y = F x + S ΔU`` (eq. 22–26) and the QP ``½ΔUᵀEΔU + ΔUᵀf, MΔU ≤ γ``
   (eq. 28–31) with output weights ``Q`` and input-change weights ``R̄``; ``M`` holds the
   input limits of eq. 30 and rows that keep the predicted speed from going against the gear;
4. solve — the unconstrained optimum (eq. 29) when no constraint is violated, else DAQP (the
   default), Hildreth or OSQP — and apply the first move, clipped to the hard limits whatever
   the solver returned.

**Cost per tick.** The step runs every 20 ms, so it is written for few numpy calls: both
models' ``S`` and free response come in closed form (:class:`~leafgate.control.
model.KinematicPrediction`: the kinematic ``A − I`` is nilpotent, the steering lag adds a
triangular block), the prediction's rows are grouped by output
(contiguous rows; ``E`` and ``f`` do not depend on the row order), ``E`` is factored once
(Cholesky) for the unconstrained optimum and Hildreth, and the reference comes from one query
(:meth:`~leafgate.control.reference.ReferencePath.horizon`). ``tools/bench_mpc.py`` measures it.

**Two clocks.** The controller runs every ``period`` (0.02 s) but predicts with a model sampled
every ``sample_time`` Ts (0.1 s), so the preview is long without a large QP. Rate limits are per
second and are applied on the time that really passes: the first move — the change from the
command sent last tick to the one sent now — is bounded by ``rate × period``, and the later
moves of the plan, one model step apart, by ``rate × Ts``. So the command stream never changes
faster than the configured rate, and the plan beyond the first tick stays physically
consistent. Steering-rate limits act on ``tan δ``; since ``d tan δ = (1 + tan² δ) dδ`` a bound
on ``tan δ`` is a (slightly conservative) bound on ``δ``.

**Increments.** The augmented state needs ``Δx̃ₖ = x̃ₖ − x̃ₖ₋₁`` one model step apart, which
does not exist at a 50 Hz tick. leafgate uses the increment the model itself gives over the
next step with the current input, ``A Δx̃ₖ = Ts f(x̃ₖ, uₖ₋₁)``, so the first predicted output is
exactly one model step from the measured state. No history, no clock.

**Steps taken at their middle.** The paper's model steps by forward Euler: each step moves the
car along the heading it has at the step's start (eq. 11). On a bend that lags half a step's
turn, and the MPC, matching its prediction to the plan, held the car inside the arc: 2.7 cm RMS
and 5.4 cm at most on a 5.3 m radius at 2.3 m/s on the kinematic plant. leafgate takes the
heading of each step half way through it — in the first increment (the car's heading plus half
the turn ``Ts v tan δ / L``) and at the operating points along the plan (the mean of two
consecutive reference headings) — which follows an arc to second order: 1.0 cm RMS and 3.6 cm
on that bend. The Jacobians keep the paper's form at those headings; the midpoint map's own
extra terms (of order ``Ts²``, in ``∂x⁺/∂v`` and ``∂x⁺/∂ tan δ``) are left out.

**Spread moves** (``moves: spread``, the default; ``consecutive`` is the paper's). The ``Nc``
moves act at model steps spread over the prediction horizon (move blocking,
:func:`~leafgate.control.model.move_steps`: 0, 1, 3, 5, 8, 11, 15, 19, 24, 29 for 10 moves over
30 steps), not at its first ``Nc`` steps with the last input held over the rest. Ahead of a
rising curvature that held input is a compromise the car feels at once: a counter-steer before
a bend, a pre-steer at a drive-off (3.6° commanded at 0.1 m/s after the ``switch-back``'s cusp
where the path needed ≈ 1°). The rate limit of a later move covers the model steps since the
one before; the QP keeps its 20 variables.

**Time-varying linearisation.** The Jacobians of each model step are taken at that step's
operating point on the plan — the planned speed and the reference heading (at the step's
middle, above) — not once at the
current state (:func:`~leafgate.control.model.prediction_matrices_ltv`). Before a cusp or the goal
the planned speed falls to zero and so does the effect of steering; a single linearisation at
the current speed would believe the car keeps turning after it has stopped, steer too little
in the last metres of a parking move and then creep past the stop point to fix the heading.

**Steering-aware model** (``model: kinematic_steer_lag``). The state gains the actual
``t = tan δ`` with the actuator's first-order lag ``τ`` (:func:`~leafgate.control.model.
augment_steer_lag`): the car turns with the wheel it has, not the one it asked for. The
actuator's dead time is compensated by predicting the state forward over the commands already
sent and not yet acting (a queue of the last ``steer_dead_time / period`` steering commands),
starting from the measured road-wheel angle; the QP then plans from that predicted state, the
instant the command computed now starts to act.

**Near zero speed.** At the start of a segment, at rest, the wheel is first turned towards
the angle the path's curvature needs there, at the steering-rate limit with the brake held
(status ``aligning``) — steering has no effect on a standing car, and driving off with the wheel
on the wrong lock (after a cusp) would leave the path at once. It turns no farther than the
MPC's own drive-off angle, and not at all when the MPC steers the other way
(:meth:`MpcController._align_target`): else the MPC would turn it back before the car moves.
Once the car has passed a segment's end point it brakes to rest (status ``stopping``) and never
creeps on to correct the heading; the next segment (or the finish) starts from where it stopped.
While finished or aligning the wheel holds or ramps monotonically: no chatter at standstill. A
brake hold left at rest when the MPC takes over (a cusp reached off the next segment's start,
where there is no aligning) is released first, at the jerk limit with the wheel held (status
``releasing``): a car at rest does not roll back under its brake, so the hold is no
acceleration to plan with.
At rest the first model step is linearised at the plan's speed of the next one, not at 0: the
incremental model carries a steering move only through the step it is made in (its effect is
∝ v), so at v = 0 the first move would do nothing in the prediction and the MPC would put off
turning the wheel, and driving off, tick after tick.

**Never against the gear.** The QP's linear model would let the predicted speed change sign:
a brake hold at rest (after a cusp the hold is ``−direction · hold_decel``) or any braking
would carry the car backward in D. The car does not roll back under its brake, so the QP has
one more row per predicted speed: ``direction · v_k ≥ min(0, v_fast,k) − 10⁻⁵ m/s``, where
``v_fast,k`` is the speed reached by raising the acceleration along the gear as fast as the
jerk and amplitude limits allow. That input sequence satisfies every other constraint, so the
QP is always feasible; while a hold is left (``v_fast,k < 0``) the rows force it to be released
at the jerk limit, and after that the plan may stop but never reverse. The speed rows of the
prediction depend on the acceleration moves alone (``v_k = v_free,k + Σ_{j<k} Ts (k − j) Δa_j``,
both models), so ``M`` is constant per direction and only ``γ`` changes per tick. A car the MPC
keeps at rest with no hold left for ``_BLOCKED_TIME`` (its plan would roll back, or stays at
rest: e.g. a cusp reached 0.8 m and 30° off a 1 m forward move) gets ``converged=False`` and
status ``blocked: …`` naming the offset, so the gateway stops with the cause.

**Speed bound.** Whatever the QP asks, the car never goes faster than the plan's speed at its
own place on the path plus ``speed_margin``, nor faster than ``max_speed`` (the maneuver limit).
Where the plan slows down, the bound is the plan's speed where the car will be one governor time
constant later, so that the car is slowed in time. In acceleration mode the command is governed
so that the jerk-limited ramp-down ends at the bound (status ``speed-limited``), in velocity mode
the target is clamped. A path the car cannot follow (a hairpin tighter than its turning circle,
the car far off it) is driven at the plan's speed at the car's place, never sprinted through.

**Offset-free.** A constant steering misalignment and a constant drag are estimated from the
measured increments (:mod:`leafgate.control.disturbance`) and the model predicts with them.

Faults never raise: non-finite inputs or results give ``converged=False,
status="non-finite"`` and the last applied command; a bad trajectory gives
``status="bad-trajectory"``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import replace
from typing import Any

import numpy as np
from scipy import optimize
from scipy.linalg import lapack

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.control.disturbance import DisturbanceEstimator
from leafgate.control.model import (
    N_INPUTS,
    N_STATES,
    KinematicPrediction,
    kinematic_first_increment,
    mid_heading,
    move_steps,
    rk4_step,
    steer_lag_factor,
    steer_lag_first_increment,
)
from leafgate.control.qp import DaqpBackend, OsqpBackend, QpResult, hildreth
from leafgate.control.reference import (
    PathRules,
    Progress,
    ReferencePath,
    Segment,
    prepare_plan,
)
from leafgate.geometry import clip as _clamp
from leafgate.geometry import clip_abs as _clip
from leafgate.geometry import wrap_angle as _wrap
from leafgate.messages import ControlOutput, FloatArray, Gear, Pose, Trajectory

_GOVERN_TIME = 0.5  # s, time constant with which a car above the speed bound is slowed
_BLOCKED_TIME = 1.0  # s, the MPC keeping the car at rest this long (no hold left) stops it
_DRIVE_ACCEL = 0.01  # m/s², at rest a command along the gear above this drives off (below
# −this, a brake hold is still being released)
_SPEED_SLACK = 1e-5  # m/s, the speed rows' bound lies this far below the unavoidable speed, so
# that rounding never makes the QP infeasible when that bound forces the fastest release
_ALIGN_SOLVES = 16  # QPs solved at most to find the drive-off angle (once per segment start)
_ALIGN_TOLERANCE = 1e-4  # tan δ, of the drive-off angle (and a first move that small is none)
_EPS_CLIP = 1e-6  # a first move farther than this outside a limit counts as a clip (solver
# tolerances leave smaller excursions, which are clipped but not counted)


_REACH_LAG = 0.5  # m/s: a plan this much faster than the car at its place is placed no
# farther than the car can get (a plan that asks for its speed from rest: :meth:`_reference`)


class _NoMove(Exception):
    """A QP solved for the drive-off angle gave no first move (not converged, not finite)."""


class MpcController:
    """The MPC of the paper, called once per control tick.

    :param cfg: the ``controller.mpc`` section
    :param vehicle: wheelbase and the vehicle's own limits
    :param period: s, time between two calls of :meth:`step`
    """

    def __init__(self, cfg: MpcConfig, vehicle: VehicleConfig, period: float) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        self.cfg = cfg
        self.vehicle = vehicle
        self.period = period
        self.Ts = cfg.sample_time
        self.Np = cfg.prediction_horizon
        self.Nc = cfg.control_horizon
        self.L = vehicle.wheelbase
        self._rules = PathRules.of(cfg, vehicle.wheelbase)  # how a plan's reference is built
        Np, Nc, m = self.Np, self.Nc, N_INPUTS

        self.steer_model = cfg.model == "kinematic_steer_lag"
        # outputs: along-track, lateral, speed, heading error (not the actual tan δ)
        self.ny = N_STATES
        self._alpha = steer_lag_factor(self.Ts, cfg.steer_tau)  # per model step
        self._alpha_tick = steer_lag_factor(period, cfg.steer_tau)  # per control tick
        self._dead_ticks = round(cfg.steer_dead_time / period) if self.steer_model else 0
        q = np.array([cfg.weight_along, cfg.weight_lateral, cfg.weight_speed, cfg.weight_heading])
        self.q_bar = np.tile(q, Np)  # diagonal of Q̄, (Np·ny), stacked by step as in the paper
        self.r_bar = np.tile([cfg.weight_accel_change, cfg.weight_steer_change], Nc)
        self._q_out = np.repeat(q, Np)  # the same weights with the rows grouped by output
        self._q2 = 2.0 * self._q_out
        self._R2 = np.diag(2.0 * self.r_bar)
        self._moves = move_steps(Np, Nc, cfg.moves == "spread")  # the step each move acts from
        # S and the free response in closed form, for either model (steer_alpha: the lag's α)
        self._predict = KinematicPrediction(
            Np, Nc, self.Ts, self.L, self._moves, self._alpha if self.steer_model else None
        )
        self._to_path = np.zeros((N_STATES, 3))  # global → path frame, rotation set per tick
        self._to_path[3, 2] = 1.0  # heading error = reference heading − heading at s0
        self.steps: FloatArray = self.Ts * np.arange(
            1, Np + 1, dtype=np.float64
        )  # s, times of the predicted outputs
        # m, how far the drive limit alone carries the car from rest by each step: a plan
        # faster than the car can get is placed no farther than it gets (:meth:`_reference`)
        self._accel_reach = 0.5 * cfg.accel_max * self.steps**2
        self._speed_lead_index = min(max(round(cfg.speed_lead_time / self.Ts) - 1, 0), Np - 1)

        # constraints on ΔU = [Δa₀, Δt₀, Δa₁, Δt₁, …] (t = tan δ), eq. 30:
        #   u_prev + Σ_{i≤j} Δu_i ≤ u_max,  −(…) ≤ −u_min,  Δu_j ≤ du_max,  −Δu_j ≤ −du_min
        cum = np.kron(np.tril(np.ones((Nc, Nc))), np.eye(m))
        eye = np.eye(Nc * m)
        box = np.vstack((cum, -cum, eye, -eye))
        # and the predicted speeds never against the gear beyond what cannot be avoided
        # (module notes): direction · v_k ≥ v_low,k, k = 1 … Np. The speed rows of the prediction
        # are the same for both models and every tick, v_k = v_free,k + Σ_{j<k} Ts (k − j) Δa_j,
        # so each direction has one constant M (rows −direction · S_v); only γ varies.
        lag = np.arange(1, Np + 1)[:, None] - self._moves[None, :]
        self._speed_rows: FloatArray = np.where(lag > 0, self.Ts * lag, 0.0)  # (Np, Nc)
        speed_S = np.zeros((Np, Nc * m))
        speed_S[:, 0::2] = self._speed_rows
        self._M_dir = {d: np.vstack((box, -d * speed_S)) for d in (1, -1)}
        self.M = self._M_dir[1]  # the constraint matrix of the current direction
        self.tan_max = math.tan(cfg.steer_max)
        self._n_u = Nc * m  # QP variables
        rate = np.array([cfg.jerk_max, cfg.steer_rate_max])  # per second
        gaps = np.diff(self._moves)[:, None]  # model steps between two moves
        self.du_max: FloatArray = np.concatenate((rate * period, (gaps * rate * self.Ts).ravel()))
        self._du_first = (float(rate[0] * period), float(rate[1] * period))
        # the acceleration along the gear raised as fast as the jerk limits allow, move by move
        # (above the last command), and what input j adds to the speed at step k: Ts for each
        # model step it is held before k (the last move is held to the horizon's end)
        self._ramp: FloatArray = self._du_first[0] + rate[0] * self.Ts * self._moves
        acting = np.searchsorted(self._moves, np.arange(Np), side="right") - 1  # move per step
        held = acting[:, None] == np.arange(Nc)[None, :]  # (Np, Nc)
        self._held: FloatArray = self.Ts * np.cumsum(held, axis=0)
        # γ = [u_hi − u_prev (Nc times); u_prev − u_lo (Nc times); du_max; du_max; speed rows].
        # Per driving direction (the signed accel limits flip): u_lo, u_hi, a template of γ
        # holding its constant rows, and the acceleration limits (a_min, a_max) as floats
        self._limits: dict[int, tuple[FloatArray, FloatArray, FloatArray, tuple[float, float]]] = {}
        for direction in (1, -1):
            a_min, a_max = self._accel_limits(direction)
            u_lo = np.array([a_min, -self.tan_max])
            u_hi = np.array([a_max, self.tan_max])
            template = np.concatenate(
                (np.zeros(2 * Nc * m), self.du_max, self.du_max, np.zeros(Np))
            )
            self._limits[direction] = (u_lo, u_hi, template, (a_min, a_max))

        # the multipliers of a feasible unconstrained optimum: all zero, one read-only array
        self._no_multipliers = np.zeros(self.M.shape[0])
        self._no_multipliers.setflags(write=False)
        self._disturbance = DisturbanceEstimator(
            period, self.L, cfg.disturbance_tau_steer, cfg.disturbance_tau_accel
        )
        self._osqp: OsqpBackend | None = None
        self._osqp_M = self.M  # the constraint matrix OSQP holds (same pattern both ways)
        # DAQP holds M: one backend per direction, built only when it is the solver
        self._daqp_dir = (
            {d: DaqpBackend(M) for d, M in self._M_dir.items()} if cfg.solver == "daqp" else {}
        )
        self._daqp = self._daqp_dir.get(1)
        if cfg.solver == "osqp":
            E0 = np.eye(Nc * m)
            self._osqp = OsqpBackend(E0, self.M, eps=cfg.osqp_tolerance)
        self.reset()

    # --- Controller protocol ---

    def reset(self) -> None:
        """Forget the trajectory, the segment, the last inputs and the warm starts."""
        self._traj: Trajectory | None = None
        self._path: ReferencePath | None = None
        self._progress: Progress | None = None
        self._bad_trajectory = ""  # why the plan cannot be driven (shown in the status)
        self._u_prev: FloatArray | None = None  # [a, tan δ] applied last tick
        self._lam: FloatArray | None = None
        self._finished = False
        self._aligned = False  # the wheel has been turned for the current segment's start
        self._align_tan: float | None = None  # tan δ the wheel is being aligned to (at rest)
        self._tick = 0  # calls of step since the reset
        self._standing = 0  # consecutive MPC ticks that kept the car at rest (see _blocked)
        self._standing_tick = -1  # the tick that last counted
        self._s_pose = 0.0  # m, arc length of the pose's projection this tick (the progress's)
        # tan δ commands sent and not yet acting on the wheel (steering-aware model), oldest first
        self._in_flight: deque[float] = deque(maxlen=max(self._dead_ticks, 1))
        if self._osqp is not None:
            self._osqp.reset()
        for backend in self._daqp_dir.values():
            backend.reset()
        self._disturbance.reset()

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        """Compute the command for this tick (never raises on bad data: see module notes)."""
        return self._step(pose, steer_angle, trajectory, time.perf_counter())

    # --- internals ---

    def _accel_limits(self, direction: int) -> tuple[float, float]:
        """Signed acceleration limits: braking in reverse is a positive d(v)/dt."""
        if direction > 0:
            return self.cfg.accel_min, self.cfg.accel_max
        return -self.cfg.accel_max, -self.cfg.accel_min

    def _hold(self, status: str, direction: int, t0: float) -> ControlOutput:
        """The last applied command (or straight ahead, at rest) marked as not converged."""
        u = self._u_prev if self._u_prev is not None else np.zeros(N_INPUTS)
        return ControlOutput(
            steer_angle=math.atan(float(u[1])),
            accel=float(u[0]),
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            converged=False,
            status=status,
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )

    def _set_trajectory(self, trajectory: Trajectory) -> None:
        """A new plan; one that continues the last (a rolling window) keeps the progress."""
        self._traj = trajectory
        self._finished = False
        self._lam = None
        self._align_tan = None  # the new plan's drive-off angle, found when it is needed
        self._path, self._progress, self._bad_trajectory = prepare_plan(
            trajectory, self._rules, self.cfg.search_window, self._progress
        )

    def _where(self) -> dict[str, Any]:
        """The progress fields of an output (none before a usable plan)."""
        return {} if self._progress is None else self._progress.fields(self._finished)

    def _step(
        self, pose: Pose, steer_angle: float, trajectory: Trajectory, t0: float
    ) -> ControlOutput:
        """One control tick: the checks, then the paper's steps 1–4 (module notes)."""
        self._tick += 1
        if trajectory is not self._traj:
            self._set_trajectory(trajectory)
        path, prog = self._path, self._progress
        if path is None or prog is None:
            return self._hold(f"bad-trajectory: {self._bad_trajectory}", 1, t0)
        isfinite = math.isfinite  # a chain of calls: no generator on the hot path
        if not (
            isfinite(pose.x)
            and isfinite(pose.y)
            and isfinite(pose.speed)
            and isfinite(pose.heading)
            and isfinite(steer_angle)
        ):
            return self._hold("non-finite", prog.segment.direction, t0)
        u_prev = self._observe(pose, steer_angle)  # the last applied input, kept in place

        # 1. reference: progress along the segment and its bookkeeping (cusp, finish), then
        #    the path-aligned frame and the horizon's reference points
        done, passed = self._track_segment(pose, t0)
        if done is not None:
            return done
        seg = prog.segment
        direction = seg.direction
        a_prev, t_prev = self._limit_previous(direction)
        if passed:
            return self._brake_to_rest(direction, t0)
        dist = self._disturbance
        bias = dist.bias  # tan δ: the car turns as with tan δ + bias
        drag = direction * dist.accel  # signed d(v)/dt added to the command
        start = self._start_state(pose, steer_angle, direction, bias, drag)
        if start[0] == pose.x and start[1] == pose.y:  # no dead time to predict over
            s0 = self._s_pose  # this tick's projection of the pose, found by the progress
        else:
            s0 = path.project(seg, prog.index, start[0], start[1])
        aligning = self._align_at_start(seg, s0, pose.speed, start, steer_angle, t0, bias, drag)
        if aligning is not None:
            return aligning
        if abs(pose.speed) <= self.cfg.stop_speed and direction * a_prev < -_DRIVE_ACCEL:
            # at rest a brake hold is no acceleration (the car does not roll back under its
            # brake): released before the MPC plans, which then starts from a = 0
            return self._release(direction, t0)
        # the model acts with the effective inputs: the commands plus the disturbances
        a_eff, t_eff = a_prev + drag, t_prev + bias
        pts, ref, kin = self._reference(seg, s0, start, a_eff, t_eff)

        # 2. model: Jacobians along the plan (step 0 at the current state), augment, predict
        ST, free = self._prediction(kin, start[4] + bias, a_eff, t_eff, ref)

        # 3. QP (eq. 31 with Q): E = 2(SᵀQS + R̄), f = −2 SᵀQ (Rs − F x)
        y0 = np.array(kin)[:, None]
        ref -= y0
        err = ref.ravel() - free  # Rs − F x
        E, f = self._qp_terms(ST, err)
        gamma = self._constraint_bounds(direction, u_prev, a_prev, kin[2], free)
        # f is finite only if S and the errors are (a non-finite entry of S reaches every f
        # it touches, even times a zero weight or error), and then so is E. (np.add.reduce is
        # what f.sum() calls, without its Python wrapper; np.float64 is a float.)
        if not isfinite(np.add.reduce(f)):
            return self._hold("non-finite", direction, t0)

        # 4. solve and apply the first move within the hard limits and the speed bound
        result = self._solve(E, f, gamma)
        dU = result.x
        if not isfinite(np.add.reduce(dU)):
            self._lam = None
            return self._hold("non-finite", direction, t0)
        v_cap = self._speed_bound(seg, s0, kin[2])
        return self._apply_first_move(
            result, ST, err, free, y0, pts, v_cap, kin[2], a_prev, t_prev, direction, t0
        )

    def _observe(self, pose: Pose, steer_angle: float) -> FloatArray:
        """The measured increments of this tick → the steering-bias and drag estimates.

        :returns: the last applied input ``[a, tan δ]`` (the wheel's angle before the first tick)
        """
        u_prev = self._u_prev
        if u_prev is None:
            u_prev = self._u_prev = np.array(
                [0.0, math.tan(_clip(steer_angle, self.cfg.steer_max))]
            )
        self._disturbance.update(
            pose.heading,
            pose.speed,
            math.tan(_clip(steer_angle, self.cfg.steer_max)),
            float(u_prev[0]),
        )
        return u_prev

    def _track_segment(self, pose: Pose, t0: float) -> tuple[ControlOutput | None, bool]:
        """Step 1, bookkeeping: advance the progress; at rest at a segment's end move on to the
        next segment (a cusp) or finish; at rest at the plan's stop point hold the car there.

        :returns: the command when this tick ends here (finished, at the stop point, or
            stopped past the end off the goal), else None; and whether the progress has
            passed the segment's end
        """
        cfg, prog = self.cfg, self._progress
        assert prog is not None and self._u_prev is not None
        seg = prog.segment
        if not self._finished:
            self._s_pose = prog.update(pose.x, pose.y, pose.heading)
        at_rest = abs(pose.speed) <= cfg.stop_speed
        passed = prog.passed  # progress has reached the end (not a half-plane test)
        if at_rest and not self._finished and prog.ended(pose.x, pose.y, cfg.goal_tolerance):
            if prog.next_segment():  # a cusp: drive the next segment, in the other direction
                seg = prog.segment
                self._s_pose = prog.update(pose.x, pose.y, pose.heading)
                # The brake holds the car through the gear change: in the new direction that
                # hold has the other sign of d(v)/dt. Starting from it keeps every later move
                # (and the drive-off) inside the jerk bound.
                self._u_prev[0] = -seg.direction * cfg.hold_decel
                self._lam = None
                self._aligned = False
                self._align_tan = None
                passed = False
            else:
                self._finished = True
        if self._finished:
            return self._finish(seg, t0), passed
        stop = prog.path.stops.get(seg)
        if at_rest and stop is not None and prog.s >= stop - cfg.goal_tolerance:
            # the plan comes to rest here (a planner's stop line): hold, and wait for a plan
            # that moves on
            return replace(
                self._brake_to_rest(seg.direction, t0),
                status=f"stop-point: the plan stands from {stop:.2f} m of "
                f"{prog.route_length:.2f} m on",
            ), passed
        if at_rest and passed:  # stopped past the end, farther than the goal tolerance
            distance = prog.to_end(pose.x, pose.y)
            return replace(
                self._brake_to_rest(seg.direction, t0),
                converged=False,
                status=f"off-goal: stopped {distance:.2f} m from the end "
                f"(tolerance {cfg.goal_tolerance:g} m)",
            ), passed
        return None, passed

    def _limit_previous(self, direction: int) -> tuple[float, float]:
        """The last applied input ``(a, tan δ)`` within this direction's limits (they flip)."""
        u_prev = self._u_prev
        assert u_prev is not None
        _, _, _, (a_min, a_max) = self._limits[direction]
        a_prev, t_prev = u_prev.tolist()
        a_prev = min(max(a_prev, a_min), a_max)  # limits flip with the direction
        t_prev = min(max(t_prev, -self.tan_max), self.tan_max)
        u_prev[0], u_prev[1] = a_prev, t_prev
        return a_prev, t_prev

    def _start_state(
        self, pose: Pose, steer_angle: float, direction: int, bias: float, drag: float
    ) -> tuple[float, float, float, float, float]:
        """``(x, y, v, θ, tan δ)`` when the command computed now starts to act (dead time);
        the kinematic model has no actuator state: the measured pose (no call, no tan)."""
        if self.steer_model:
            return self._predict_dead_time(pose, steer_angle, direction, bias, drag)
        return pose.x, pose.y, pose.speed, pose.heading, math.nan

    def _align_at_start(
        self,
        seg: Segment,
        s0: float,
        speed: float,
        start: tuple[float, float, float, float, float],
        steer_angle: float,
        t0: float,
        bias: float,
        drag: float,
    ) -> ControlOutput | None:
        """At rest (the measured ``speed``) at the segment's start, the aligning (or releasing)
        command; else None. ``start`` is :meth:`_start_state`'s."""
        at_rest = abs(speed) <= self.cfg.stop_speed
        if at_rest and not self._aligned:
            assert self._path is not None
            if s0 - self._path.s[seg.start] <= self.cfg.goal_tolerance:
                if self._align_tan is None:
                    self._align_tan = self._align_target(seg, s0, start, steer_angle, bias, drag)
                out = self._align(self._align_tan, steer_angle, seg.direction, t0)
                if out is not None:
                    return out
            self._aligned = True
        elif not at_rest:
            self._aligned = True  # moving: the segment's start is behind us
        return None

    def _reference(
        self,
        seg: Segment,
        s0: float,
        start: tuple[float, float, float, float, float],
        a_eff: float,
        t_eff: float,
    ) -> tuple[FloatArray, FloatArray, list[float]]:
        """Step 1, reference: the horizon's points (rows x, y, heading; ``Np + 1`` points from
        the projection ``s0``), the reference outputs ``Rs`` in the path-aligned frame at
        ``s0`` (4, Np; row 2 the signed planned speed), and the state ``[along, lateral, v,
        heading error]`` in that frame.

        The prediction's rows are grouped by output (all Np along-track positions, then lateral
        offsets, speeds, heading errors): contiguous rows make every numpy call here cheap, and
        E and f do not depend on the order of the rows.
        """
        assert self._path is not None
        gx, gy, gv, gth, _ = start
        # The plan's time places the points; never farther than the car can get from its speed
        # at the drive limit. A plan that asks for 2 m/s from rest on a bend put them where
        # the car could not be yet, and the MPC steered to reach their lateral offset: 21° at
        # the drive-off where the bend needs 7.7°.
        reach = None
        along = max(seg.direction * gv, 0.0)  # the car's speed along the gear
        if abs(self._path.speed_at(seg, s0)) - along > _REACH_LAG:  # the plan runs ahead
            reach = self.steps * along
            reach += self._accel_reach
        pts, ref_speed = self._path.horizon(seg, s0, self.steps, reach)
        ox, oy, psi0 = pts[:, 0].tolist()
        c, s = math.cos(psi0), math.sin(psi0)
        dx, dy = gx - ox, gy - oy
        kin = [c * dx + s * dy, -s * dx + c * dy, gv, _wrap(gth - psi0)]
        if self.cfg.delay_compensation > 0.0 and not self.steer_model:
            u_eff = np.array([a_eff, t_eff])
            kin = rk4_step(np.array(kin), u_eff, self.cfg.delay_compensation, self.L).tolist()
        to_path = self._to_path  # global → path frame; row 2 (speed) stays zero
        to_path[0, 0] = to_path[1, 1] = c
        to_path[0, 1] = s
        to_path[1, 0] = -s
        ref = to_path @ (pts[:, 1:] - pts[:, :1])  # (4, Np) in the path frame
        ref[2] = ref_speed
        return pts, ref, kin

    def _prediction(
        self,
        kin: list[float],
        tan_actual: float,
        a_eff: float,
        t_eff: float,
        ref: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """Step 2: ``Sᵀ`` and the free response ``F x − y₀`` (rows by output), the model
        linearised at the current state for the first step and along the plan for the later
        ones (speed and heading of each step's operating point)."""
        v0, th0 = kin[2], kin[3]
        op = np.empty((2, self.Np))  # speed and heading of each step's operating point
        op[0, 1:] = ref[2, :-1]
        v_op, heading_op = op[0], op[1]  # indexing: cheaper than unpacking the array
        v_op[0] = v0 if abs(v0) > self.cfg.stop_speed else op[0, 1]
        # each step's heading half way through it (module notes): the plan's between the
        # reference points k and k + 1, the car's own for the first step
        np.add(ref[3, :-1], ref[3, 1:], out=heading_op[1:])
        heading_op[1:] *= 0.5
        # A Δx̃ₖ = Ts f(x̃ₖ, uₖ₋₁) at the step's middle, the next step's increment (module notes)
        Ts, L = self.Ts, self.L
        if not self.steer_model:
            th_mid = heading_op[0] = mid_heading((kin[0], kin[1], v0, th0, t_eff), Ts, L)
            increment = (
                Ts * (v0 * math.cos(th_mid)),
                Ts * (v0 * math.sin(th_mid)),
                Ts * a_eff,
                Ts * (v0 * t_eff / L),
            )
            dx_k = kinematic_first_increment(increment, v0, th_mid, t_eff, Ts, L)
            return self._predict(v_op, heading_op, t_eff, dx_k)
        # steering-aware: the car turns with the actual wheel, linearised there; the lag acts
        # on tan δ + bias alike (the actual and the commanded angle shifted by the bias)
        state = (kin[0], kin[1], v0, th0, tan_actual)
        dx = steer_lag_first_increment(state, (a_eff, t_eff), float(v_op[0]), Ts, L, self._alpha)
        heading_op[0] = mid_heading(state, Ts, L)
        return self._predict(v_op, heading_op, tan_actual, dx)

    def _constraint_bounds(
        self, direction: int, u_prev: FloatArray, a_prev: float, v0: float, free: FloatArray
    ) -> FloatArray:
        """``γ`` of this tick (and ``M`` of the direction made current): the input limits, and
        the bounds of the speed rows, ``direction · v_k ≥ min(0, v_fast,k) − ε``.

        ``v_fast,k`` is the speed (along the gear) at step k with the acceleration raised as fast
        as the jerk and amplitude limits allow from the command sent last tick. So the QP may
        not plan a roll-back against the gear (its linear model would let a brake hold, or a
        stop, carry the car backward), except the part that raising the acceleration at once
        cannot avoid: that input sequence meets every other constraint, the QP stays feasible.
        """
        if self.M is not self._M_dir[direction]:
            self.M = self._M_dir[direction]
            if self._daqp is not None:
                self._daqp = self._daqp_dir[direction]
        u_lo, u_hi, template, _ = self._limits[direction]
        Np = self.Np
        v_free = free[2 * Np : 3 * Np] + v0  # no move: the free response's speeds
        v_free *= direction
        w_prev = direction * a_prev
        raised = np.minimum(self._ramp, self.cfg.accel_max - w_prev)  # the drive limit
        low = self._held @ raised  # the speeds the fastest rise adds, along the gear
        low += v_free
        np.minimum(low, 0.0, out=low)
        low -= _SPEED_SLACK
        gamma = template.copy()  # the rate rows; the others written in place (views)
        n_u = self._n_u
        np.subtract(u_hi, u_prev, out=gamma[:n_u].reshape(-1, N_INPUTS))  # each Σ Δu ≤ these
        np.subtract(u_prev, u_lo, out=gamma[n_u : 2 * n_u].reshape(-1, N_INPUTS))
        np.subtract(v_free, low, out=gamma[4 * n_u :])
        return gamma

    def _speed_bound(self, seg: Segment, s0: float, speed: float) -> float:
        """The speed bound, m/s: the plan's speed at the car's place ``s0`` plus the margin, and
        the plan's speed where the car will be in ``_GOVERN_TIME`` at ``speed`` when that is lower
        (the governor slows the car with that time constant: looking ahead by it, the car is
        slowed in time where the plan slows down); never above the maneuver limit.
        """
        path = self._path
        assert path is not None
        here = abs(path.speed_at(seg, s0))
        ahead = abs(path.speed_at(seg, s0 + abs(speed) * _GOVERN_TIME))
        return min(min(here, ahead) + self.cfg.speed_margin, self.cfg.max_speed)

    def _qp_terms(self, ST: FloatArray, err: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Step 3: ``E = 2(SᵀQS + R̄)`` and ``f = −2 SᵀQ (Rs − F x)``."""
        SQ = ST * self._q2  # 2 SᵀQ
        E = SQ @ ST.T
        E += self._R2
        f = SQ @ err
        np.negative(f, out=f)
        return E, f

    def _apply_first_move(
        self,
        result: QpResult,
        ST: FloatArray,
        err: FloatArray,
        free: FloatArray,
        y0: FloatArray,
        pts: FloatArray,
        v_cap: float,
        v0: float,
        a_prev: float,
        t_prev: float,
        direction: int,
        t0: float,
    ) -> ControlOutput:
        """Step 4: the first move within the amplitude and per-tick rate limits whatever the
        solver said, governed to the speed bound ``v_cap`` (m/s); applied, and reported with its
        prediction."""
        _, _, _, (a_min, a_max) = self._limits[direction]
        dU = result.x
        d_a, d_t = dU[:2].tolist()
        a_new = a_prev + d_a
        tan_new = t_prev + d_t
        a_cmd = _clamp(
            a_new,
            max(a_min, a_prev - self._du_first[0]),
            min(a_max, a_prev + self._du_first[0]),
        )
        tan_cmd = _clamp(
            tan_new,
            max(-self.tan_max, t_prev - self._du_first[1]),
            min(self.tan_max, t_prev + self._du_first[1]),
        )
        clips = int(abs(a_cmd - a_new) > _EPS_CLIP) + int(abs(tan_cmd - tan_new) > _EPS_CLIP)
        a_free = a_cmd
        a_cmd = self._govern(a_cmd, a_prev, direction * v0, v_cap, direction)
        limited = a_cmd != a_free
        self._apply(a_cmd, tan_cmd)

        SdU = dU @ ST
        e = err - SdU  # Rs − Y
        cost = float(e @ (self._q_out * e)) + float(dU @ (self.r_bar * dU))
        SdU += free  # Y − y₀, rows by output (in place: SdU is not used again)
        Y = SdU.reshape(self.ny, self.Np)
        Y += y0
        predicted_xy = Y[:2].T @ self._to_path[:2, :2]  # back to the global frame
        predicted_xy += pts[:2, 0]
        # velocity mode: the planned speed one speed-loop time constant ahead, so that the
        # vehicle's proportional speed controller reproduces the planned acceleration
        lead = self._speed_lead_index
        speed_cmd = float(Y[2, lead]) + (a_cmd - a_new) * self.Ts * (lead + 1)
        if direction * speed_cmd < 0.0:
            speed_cmd = 0.0  # never ask the speed controller to drive the other way
        if direction * speed_cmd > v_cap:
            speed_cmd = direction * v_cap
            limited = True
        blocked = self._blocked(result, y0, v0, a_prev, a_cmd, speed_cmd, direction)
        converged = result.converged and not blocked
        if not result.converged:
            status = "not-converged"
        elif blocked:
            status = blocked
        elif clips:
            status = "clipped"
        elif limited:
            status = "speed-limited"
        else:
            status = "ok"
        return ControlOutput(
            steer_angle=math.atan(tan_cmd),
            accel=a_cmd,
            speed=speed_cmd,
            gear=Gear.D if direction > 0 else Gear.R,
            converged=converged,
            iterations=result.iterations,
            clips=clips,
            cost=cost,
            finished=False,
            predicted_xy=predicted_xy,
            status=status,
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )

    def _blocked(
        self,
        result: QpResult,
        y0: FloatArray,
        v0: float,
        a_prev: float,
        a_cmd: float,
        speed_cmd: float,
        direction: int,
    ) -> str:
        """Why the MPC does not drive the car off, once it has kept it at rest for
        ``_BLOCKED_TIME`` with no brake hold left to release; else ``""``.

        From far off the plan (a cusp reached 0.8 m and 30° off it) the QP's optimum may be to
        roll back against the gear; the speed rows forbid that, and the plan then stays at rest
        tick after tick. Said so, the gateway stops with the cause instead of a bare no-progress.
        """
        if self.cfg.mode == "velocity":
            drives = direction * speed_cmd > self.cfg.stop_speed
        else:
            drives = direction * a_cmd > _DRIVE_ACCEL
        standing = (
            abs(v0) <= self.cfg.stop_speed
            and not drives
            and direction * a_prev >= -_DRIVE_ACCEL  # else a brake hold is being released
        )
        if not standing:
            self._standing = 0
            return ""
        self._standing = self._standing + 1 if self._standing_tick == self._tick - 1 else 1
        self._standing_tick = self._tick
        waited = self._standing * self.period
        if waited < _BLOCKED_TIME - 1e-9:
            return ""
        rows = self.M.shape[0] - self.Np  # the speed rows come last
        why = (
            "its plan would roll back against the gear"
            if (result.lam[rows:] > 0.0).any()
            else "its plan stays at rest"
        )
        lateral, heading = float(y0[1, 0]), float(y0[3, 0])
        return (
            f"blocked: at rest {abs(lateral):.2f} m and {math.degrees(abs(heading)):.0f}° off "
            f"the path for {waited:.1f} s, the MPC does not drive off ({why})"
        )

    def _apply(self, accel: float, tan_delta: float) -> None:
        """Remember the command sent this tick (and queue it while it is in the dead time)."""
        u = self._u_prev
        if u is None:
            self._u_prev = np.array([accel, tan_delta])
        else:  # in place: no new array per tick (nothing keeps a reference across ticks)
            u[0] = accel
            u[1] = tan_delta
        if self._dead_ticks:
            self._in_flight.append(tan_delta)

    def _predict_dead_time(
        self, pose: Pose, steer_angle: float, direction: int, bias: float, drag: float
    ) -> tuple[float, float, float, float, float]:
        """``(x, y, v, θ, tan δ)`` once the commands in flight have acted (steering-aware model).

        Starts from the measured pose and road-wheel angle and steps the lagged bicycle one
        control period per queued command; with the kinematic model (or no dead time) it is the
        measured state. ``bias`` (tan δ) and ``drag`` (m/s²) are the estimated disturbances.
        """
        t = math.tan(_clip(steer_angle, self.cfg.steer_max))
        x, y, v, th = pose.x, pose.y, pose.speed, pose.heading
        if not self.steer_model or not self._in_flight:
            return x, y, v, th, t
        assert self._u_prev is not None
        h = self.period
        a = float(self._u_prev[0]) + drag
        for t_cmd in self._in_flight:
            v_next = v + a * h
            if v_next * v < 0.0 or direction * v_next < 0.0:
                v_next = 0.0  # braking stops the car, it does not reverse it
            v_mid = 0.5 * (v + v_next)
            th_mid = th + 0.5 * h * v_mid * (t + bias) / self.L
            x += h * v_mid * math.cos(th_mid)
            y += h * v_mid * math.sin(th_mid)
            th += h * v_mid * (t + bias) / self.L
            t += self._alpha_tick * (t_cmd - t)
            v = v_next
        return x, y, v, th, t

    def _align_target(
        self,
        seg: Segment,
        s0: float,
        start: tuple[float, float, float, float, float],
        steer_angle: float,
        bias: float,
        drag: float,
    ) -> float:
        """The tan δ to turn the wheel to at rest at a segment's start, before driving off:
        towards the path's curvature there, but never past the MPC's own drive-off angle
        (:meth:`_drive_off_tan`) nor away from it — the median of the three.

        Aligned to the path's curvature alone, a car standing off the path (a cusp ends where
        the last move left it) had its wheel turned one way at rest and the MPC turned it back
        as it drove off (0.22 rad at parallel-park's second cusp with the car's config). Where
        the path's curvature lies between the wheel and the MPC's angle, this is the old
        alignment, and the MPC goes on turning the same way.
        """
        path = self._path
        assert path is not None
        ds = 0.25  # m, arc length over which the start curvature is measured
        psi = path.sample(seg, np.array([s0, s0 + ds]))[:, 2]
        span = max(min(s0 + ds, float(path.s[seg.end])) - s0, 1e-6)
        # θ̇ = v tan δ / L: in reverse the heading turns the other way for the same wheel
        # (the wheel that gives it, with the estimated misalignment taken off)
        curvature = seg.direction * self.L * float(psi[1] - psi[0]) / span
        t_path = _clip(curvature - bias, self.tan_max)
        wheel = math.tan(_clip(steer_angle, self.cfg.steer_max))
        drive_off = self._drive_off_tan(seg, s0, start, bias, drag, t_path)
        return sorted((wheel, t_path, drive_off))[1]

    def _drive_off_tan(
        self,
        seg: Segment,
        s0: float,
        start: tuple[float, float, float, float, float],
        bias: float,
        drag: float,
        t_path: float,
    ) -> float:
        """The tan δ from which the MPC's first move, at rest at ``s0``, leaves the wheel where
        it is.

        The first steering move of the QP — every constraint, the brake released (``a = 0``),
        the wheel and the last command at ``t`` — is ≥ 0 at ``t = −tan δ_max`` and ≤ 0 at
        ``+tan δ_max`` (the amplitude limits). From the path's curvature ``t_path``, Brent's
        method finds its zero on the side the move there points to; a move that still points
        outwards at the limit makes the limit the answer. Bounded (``_ALIGN_SOLVES``); a QP that
        does not converge, or a non-finite move, leaves ``t_path``.
        """
        direction = seg.direction
        x, y, v, th, _ = start
        lam = self._lam  # Hildreth's warm start: the solves here are not this tick's

        def first_move(t: float) -> float:
            """The QP's first steering move from the wheel at ``t``."""
            a_eff, t_eff = drag, t + bias
            _, ref, kin = self._reference(seg, s0, (x, y, v, th, t), a_eff, t_eff)
            ST, free = self._prediction(kin, t_eff, a_eff, t_eff, ref)
            ref -= np.array(kin)[:, None]
            err = ref.ravel() - free
            E, f = self._qp_terms(ST, err)
            u_prev = np.array([0.0, t])
            gamma = self._constraint_bounds(direction, u_prev, 0.0, kin[2], free)
            result = self._solve(E, f, gamma)
            move = float(result.x[1])
            if not (result.converged and math.isfinite(move)):
                raise _NoMove
            return move

        try:
            h = first_move(t_path)
            if abs(h) <= _ALIGN_TOLERANCE:
                return t_path
            # a sign change on [t_path, limit] (the move at the limit points back inside)
            limit = math.copysign(self.tan_max, h)
            h_limit = first_move(limit)
            if h * h_limit > 0.0 or abs(h_limit) <= _ALIGN_TOLERANCE:
                return limit  # the MPC turns the wheel to the limit and holds it there
            lo, hi = (t_path, limit) if h > 0.0 else (limit, t_path)
            root, info = optimize.brentq(
                first_move,
                lo,
                hi,
                xtol=_ALIGN_TOLERANCE,
                maxiter=_ALIGN_SOLVES,
                full_output=True,
                disp=False,
            )
        except (_NoMove, ValueError):  # no answer, or no sign change (not expected: see above)
            return t_path
        finally:
            self._lam = lam
        return float(root) if info.converged and math.isfinite(root) else t_path

    def _align(
        self, tan_target: float, steer_angle: float, direction: int, t0: float
    ) -> ControlOutput | None:
        """At rest at a segment's start: turn the wheel to ``tan_target``, brake held.

        :returns: the command of this tick, or None once the wheel is there (drive off)
        """
        assert self._u_prev is not None
        target = math.atan(tan_target)
        tol = self.cfg.align_tolerance
        if abs(steer_angle - target) <= tol and abs(self._u_prev[1] - tan_target) <= tol:
            if abs(self._u_prev[0]) <= 1e-9:
                return None  # wheel there, brake released: the MPC drives off from a = 0
            return self._release(direction, t0)
        step = self._du_first[1]
        tan_cmd = _clamp(tan_target, self._u_prev[1] - step, self._u_prev[1] + step)
        accel = self._ramp_to_hold(direction)
        return self._at_rest(accel, tan_cmd, direction, "aligning", t0)

    def _release(self, direction: int, t0: float) -> ControlOutput:
        """At rest: release the brake hold at the jerk limit with the wheel held still, so the
        command stream stays inside the jerk bound and the MPC starts from what was sent."""
        assert self._u_prev is not None
        step_a = self._du_first[0]
        accel = _clamp(0.0, self._u_prev[0] - step_a, self._u_prev[0] + step_a)
        return self._at_rest(accel, float(self._u_prev[1]), direction, "releasing", t0)

    def _at_rest(
        self, accel: float, tan_cmd: float, direction: int, status: str, t0: float
    ) -> ControlOutput:
        """A command given at rest without the MPC (aligning, releasing), applied."""
        self._apply(accel, tan_cmd)
        return ControlOutput(
            steer_angle=math.atan(tan_cmd),
            accel=accel,
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            status=status,
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )

    def _brake_to_rest(self, direction: int, t0: float) -> ControlOutput:
        """Beyond the segment's end: brake (at the jerk limit) to rest with the wheel held."""
        assert self._u_prev is not None
        accel = self._ramp_to_hold(direction)
        self._apply(accel, float(self._u_prev[1]))
        return ControlOutput(
            steer_angle=math.atan(float(self._u_prev[1])),
            accel=accel,
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            status="stopping",
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )

    def _solve(self, E: FloatArray, f: FloatArray, gamma: FloatArray) -> QpResult:
        """Eq. 29 when it satisfies every constraint, else the configured QP backend (DAQP,
        OSQP or Hildreth).

        ``E`` is factored once (Cholesky); the factor gives the unconstrained optimum and is
        reused by Hildreth for ``E⁻¹Mᵀ`` on its working set.
        """
        chol, x_unc, info = lapack.dposv(E, -f)  # float64 arrays, as E and f are
        if info != 0:  # E not positive definite: cannot happen with R̄ > 0 and finite data
            chol = None
            x_unc = np.linalg.solve(E, -f)
        if (self.M @ x_unc <= gamma).all():
            self._lam = None
            return QpResult(x_unc, True, 0, self._no_multipliers)
        if self._daqp is not None:
            return self._daqp.solve(E, f, gamma)
        if self._osqp is not None:
            if self._osqp_M is self.M:
                return self._osqp.solve(E, f, gamma)
            self._osqp_M = self.M  # the direction changed: the speed rows flip their sign
            return self._osqp.solve(E, f, gamma, M=self.M)
        result = hildreth(
            E,
            f,
            self.M,
            gamma,
            max_iter=self.cfg.max_iterations,
            tol=self.cfg.hildreth_tolerance,
            lam0=self._lam,
            relaxation=self.cfg.hildreth_relaxation,
            chol=chol,
            x_unc=x_unc,
        )
        self._lam = result.lam  # a good start next tick even when the cap was hit
        return result

    def _govern(
        self, accel: float, a_prev: float, speed: float, v_cap: float, direction: int
    ) -> float:
        """The acceleration command within the speed bound ``v_cap`` (m/s, > 0).

        ``speed`` is in the driving direction. Below the bound the acceleration in the driving
        direction is at most ``√(j (v_cap − v))`` — half the jerk ``j`` that the limit allows
        for taking it back to zero before the bound is reached, so the delay of a tick or two
        does not carry the car over it; above it, the car slows at ``(v − v_cap) / 0.5 s``.
        The jerk bound of this tick still holds (the command never drops faster than it).
        """
        jerk = self.cfg.jerk_max
        excess = speed - v_cap
        bound = math.sqrt(jerk * -excess) if excess < 0.0 else -excess / _GOVERN_TIME
        a_dir = direction * accel
        if a_dir <= bound:
            return accel
        floor = direction * a_prev - self._du_first[0]  # the jerk limit of this tick
        return direction * max(bound, floor)

    def _ramp_to_hold(self, direction: int) -> float:
        """The brake-hold acceleration of this tick, reached at the jerk limit.

        The holds (aligning at rest, braking past a segment's end, finished) go through the
        same jerk bound as the MPC's own moves, and are recorded as the last applied input, so
        the next solve starts from what was really sent.
        """
        assert self._u_prev is not None
        step = self._du_first[0]
        want = -direction * self.cfg.hold_decel
        return _clamp(want, self._u_prev[0] - step, self._u_prev[0] + step)

    def _finish(self, seg: Segment, t0: float) -> ControlOutput:
        """At rest on the final waypoint: hold the brake, keep the wheel where it is."""
        assert self._u_prev is not None
        accel = self._ramp_to_hold(seg.direction)
        self._u_prev[0] = accel
        return ControlOutput(
            steer_angle=math.atan(float(self._u_prev[1])),
            accel=accel,
            speed=0.0,
            gear=Gear.D if seg.direction > 0 else Gear.R,
            finished=True,
            status="finished",
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )
