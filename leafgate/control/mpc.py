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
   (eq. 28–31) with output weights ``Q`` and input-change weights ``R̄``;
4. solve — the unconstrained optimum (eq. 29) when no constraint is violated, else Hildreth or
   OSQP — and apply the first move, clipped to the hard limits whatever the solver returned.

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
exactly the Euler step from the measured state. No history, no clock.

**Time-varying linearisation.** The Jacobians of each model step are taken at that step's
operating point on the plan — the planned speed and the reference heading — not once at the
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

**Near zero speed.** At the start of a segment, at rest, the wheel is first turned to the
angle the path's curvature needs there, at the steering-rate limit with the brake held
(status ``aligning``) — steering has no effect on a standing car, and driving off with the wheel
on the wrong lock (after a cusp) would leave the path at once. Once the car has passed a
segment's end point it brakes to rest (status ``stopping``) and never creeps on to correct the
heading; the next segment (or the finish) starts from where it stopped. While finished or
aligning the wheel holds or ramps monotonically: no chatter at standstill.

Faults never raise: non-finite inputs or results give ``converged=False,
status="non-finite"`` and the last applied command; a bad trajectory gives
``status="bad-trajectory"``.
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from leafgate.config import VehicleConfig
from leafgate.control.config import MpcConfig
from leafgate.control.model import (
    N_INPUTS,
    N_STATES,
    N_STATES_STEER,
    augment_steer_lag,
    derivative,
    linearise_along,
    prediction_matrices_ltv,
    rk4_step,
    steer_lag_factor,
    steer_lag_increment,
)
from leafgate.control.qp import OsqpBackend, QpResult, hildreth
from leafgate.control.reference import ReferencePath, Segment, nearest_index, validate
from leafgate.errors import TrajectoryError
from leafgate.messages import ControlOutput, FloatArray, Gear, Pose, Trajectory

_EPS_CLIP = 1e-6  # a first move farther than this outside a limit counts as a clip (solver
# tolerances leave smaller excursions, which are clipped but not counted)


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
        Np, Nc, m = self.Np, self.Nc, N_INPUTS

        self.steer_model = cfg.model == "kinematic_steer_lag"
        n = N_STATES_STEER if self.steer_model else N_STATES
        # outputs: along-track, lateral, speed, heading error (not the actual tan δ)
        self.C = np.eye(N_STATES, n)
        self.ny = self.C.shape[0]
        self._alpha = steer_lag_factor(self.Ts, cfg.steer_tau)  # per model step
        self._alpha_tick = steer_lag_factor(period, cfg.steer_tau)  # per control tick
        self._dead_ticks = round(cfg.steer_dead_time / period) if self.steer_model else 0
        q = np.array([cfg.weight_along, cfg.weight_lateral, cfg.weight_speed, cfg.weight_heading])
        self.q_bar = np.tile(q, Np)  # diagonal of Q̄, (Np·ny)
        self.r_bar = np.tile([cfg.weight_accel_change, cfg.weight_steer_change], Nc)
        self._q2 = 2.0 * self.q_bar
        self._R2 = np.diag(2.0 * self.r_bar)
        self.steps: FloatArray = self.Ts * np.arange(
            1, Np + 1, dtype=np.float64
        )  # s, times of the predicted outputs
        self._speed_lead_index = min(max(round(cfg.speed_lead_time / self.Ts) - 1, 0), Np - 1)

        # constraints on ΔU = [Δa₀, Δt₀, Δa₁, Δt₁, …] (t = tan δ), eq. 30:
        #   u_prev + Σ_{i≤j} Δu_i ≤ u_max,  −(…) ≤ −u_min,  Δu_j ≤ du_max,  −Δu_j ≤ −du_min
        cum = np.kron(np.tril(np.ones((Nc, Nc))), np.eye(m))
        eye = np.eye(Nc * m)
        self.M = np.vstack((cum, -cum, eye, -eye))
        self.tan_max = math.tan(cfg.steer_max)
        rate = np.array([cfg.jerk_max, cfg.steer_rate_max])  # per second
        self.du_max: FloatArray = np.concatenate((rate * period, np.tile(rate * self.Ts, Nc - 1)))
        self._du_first = (float(rate[0] * period), float(rate[1] * period))
        # γ = γ₀ + G u_prev, with γ₀ per driving direction (the signed accel limits flip)
        tile_eye = np.tile(np.eye(m), (Nc, 1))
        self._gamma_u = np.vstack((-tile_eye, tile_eye, np.zeros((2 * Nc * m, m))))
        self._limits: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}
        for direction in (1, -1):
            a_min, a_max = self._accel_limits(direction)
            u_lo = np.array([a_min, -self.tan_max])
            u_hi = np.array([a_max, self.tan_max])
            gamma0 = np.concatenate(
                (np.tile(u_hi, Nc), -np.tile(u_lo, Nc), self.du_max, self.du_max)
            )
            self._limits[direction] = (u_lo, u_hi, gamma0)

        self._osqp: OsqpBackend | None = None
        if cfg.solver == "osqp":
            E0 = np.eye(Nc * m)
            self._osqp = OsqpBackend(E0, self.M, eps=cfg.osqp_tolerance)
        self.reset()

    # --- Controller protocol ---

    def reset(self) -> None:
        """Forget the trajectory, the segment, the last inputs and the warm starts."""
        self._traj: Trajectory | None = None
        self._path: ReferencePath | None = None
        self._bad_trajectory = ""
        self._seg = 0
        self._index = 0
        self._u_prev: FloatArray | None = None  # [a, tan δ] applied last tick
        self._lam: FloatArray | None = None
        self._finished = False
        self._aligned = False  # the wheel has been turned for the current segment's start
        # tan δ commands sent and not yet acting on the wheel (steering-aware model), oldest first
        self._in_flight: deque[float] = deque(maxlen=max(self._dead_ticks, 1))
        if self._osqp is not None:
            self._osqp.reset()

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
            nearest_index=self._index,
            solve_time=time.perf_counter() - t0,
        )

    def _set_trajectory(self, trajectory: Trajectory) -> None:
        self._traj = trajectory
        self._seg = 0
        self._finished = False
        self._lam = None
        try:
            validate(trajectory, "trajectory")
            self._path = ReferencePath(trajectory, self.cfg.creep_speed)
            self._bad_trajectory = ""
        except (TrajectoryError, ValueError) as exc:
            self._path = None
            self._bad_trajectory = str(exc)
        self._index = -1  # a new plan: search the first segment in full

    def _step(
        self, pose: Pose, steer_angle: float, trajectory: Trajectory, t0: float
    ) -> ControlOutput:
        cfg = self.cfg
        if trajectory is not self._traj:
            self._set_trajectory(trajectory)
        path = self._path
        if path is None:
            return self._hold("bad-trajectory", 1, t0)
        seg = path.segments[self._seg]
        state_in = (pose.x, pose.y, pose.speed, pose.heading, steer_angle)
        if not all(math.isfinite(v) for v in state_in):
            return self._hold("non-finite", seg.direction, t0)
        if self._u_prev is None:
            self._u_prev = np.array([0.0, math.tan(_clip(steer_angle, cfg.steer_max))])

        # 1. reference: nearest waypoint and segment bookkeeping
        traj = path.traj
        if self._index < 0:
            self._index = nearest_index(
                traj, pose.x, pose.y, seg.start, window=seg.end - seg.start + 2, stop=seg.end
            )
        else:
            self._index = nearest_index(
                traj, pose.x, pose.y, self._index, window=cfg.search_window, stop=seg.end
            )
        at_rest = abs(pose.speed) <= cfg.stop_speed
        passed = self._passed_end(seg, pose)
        to_end = math.hypot(traj.x[seg.end] - pose.x, traj.y[seg.end] - pose.y)
        if at_rest and (to_end <= cfg.goal_tolerance or passed):
            if self._seg + 1 < len(path.segments):
                self._seg += 1  # a cusp: drive the next segment, in the other direction
                seg = path.segments[self._seg]
                self._index = seg.start
                self._u_prev[0] = 0.0
                self._lam = None
                self._aligned = False
                passed = False
            else:
                self._finished = True
        if self._finished:
            return self._finish(seg, t0)

        direction = seg.direction
        a_min, a_max = self._accel_limits(direction)
        u_prev = self._u_prev
        u_prev[0] = min(max(u_prev[0], a_min), a_max)  # limits flip with the direction
        u_prev[1] = min(max(u_prev[1], -self.tan_max), self.tan_max)
        if passed:
            return self._brake_to_rest(direction, t0)

        # dead time: the state when the command computed now starts to act
        gx, gy, gv, gth, gt = self._predict_dead_time(pose, steer_angle, direction)

        # path-aligned frame at the (predicted) vehicle's projection
        s0 = path.project(seg, self._index, gx, gy)
        if at_rest and not self._aligned:
            if s0 - path.s[seg.start] <= cfg.goal_tolerance:
                out = self._align(seg, s0, steer_angle, direction, t0)
                if out is not None:
                    return out
            self._aligned = True
        elif not at_rest:
            self._aligned = True  # moving: the segment's start is behind us
        s_ref = path.horizon_arclength(seg, s0, self.steps)
        pts = path.sample(seg, np.concatenate(([s0], s_ref)))  # (Np+1, 3): x, y, heading
        ox, oy, psi0 = (float(v) for v in pts[0])
        c, s = math.cos(psi0), math.sin(psi0)
        dx, dy = gx - ox, gy - oy
        kin = [c * dx + s * dy, -s * dx + c * dy, gv, _wrap(gth - psi0)]
        state = np.array([*kin, gt] if self.steer_model else kin)
        if cfg.delay_compensation > 0.0 and not self.steer_model:
            state = rk4_step(state, u_prev, cfg.delay_compensation, self.L)

        rot = np.array([[c, -s], [s, c]])  # local → global; its transpose maps back
        ref = np.empty((self.Np, self.ny))
        ref[:, :2] = (pts[1:, :2] - pts[0, :2]) @ rot
        ref[:, 2] = path.reference_speed(s_ref)
        ref[:, 3] = pts[1:, 2] - psi0

        # 2. model: Jacobians along the plan (step 0 at the current state), augment, predict
        v_op = np.concatenate(([state[2]], ref[:-1, 2]))
        heading_op = np.concatenate(([state[3]], ref[:-1, 3]))
        tan_op = np.full(self.Np, float(state[4]) if self.steer_model else float(u_prev[1]))
        A, B = linearise_along(v_op, heading_op, tan_op, self.Ts, self.L)
        if self.steer_model:
            A, B = augment_steer_lag(A, B, self._alpha, self.Ts, v_op, self.L)
            increment = steer_lag_increment(state, u_prev, self.Ts, self.L, self._alpha)
        else:
            increment = self.Ts * derivative(state, u_prev, self.L)
        F, S = prediction_matrices_ltv(A, B, self.C, self.Nc)
        dx_k = np.linalg.solve(A[0], increment)  # A Δx̃ₖ = the next step's increment
        x_aug = np.concatenate((dx_k, self.C @ state))
        err = ref.ravel() - F @ x_aug  # Rs − F x

        # 3. QP (eq. 31 with Q): E = 2(SᵀQS + R̄), f = −2 SᵀQ (Rs − F x)
        SQ = S.T * self._q2  # 2 SᵀQ
        E = SQ @ S
        E += self._R2
        f = -(SQ @ err)
        u_lo, u_hi, gamma0 = self._limits[direction]
        gamma = gamma0 + self._gamma_u @ u_prev
        if not math.isfinite(float(E.sum()) + float(f.sum())):
            return self._hold("non-finite", direction, t0)

        # 4. solve and apply the first move within the hard limits
        result = self._solve(E, f, gamma)
        dU = result.x
        if not math.isfinite(float(dU.sum())):
            self._lam = None
            return self._hold("non-finite", direction, t0)
        # the first move, within amplitude and per-tick rate limits whatever the solver said
        a_new = float(u_prev[0] + dU[0])
        tan_new = float(u_prev[1] + dU[1])
        a_cmd = _clamp(
            a_new,
            max(float(u_lo[0]), float(u_prev[0]) - self._du_first[0]),
            min(float(u_hi[0]), float(u_prev[0]) + self._du_first[0]),
        )
        tan_cmd = _clamp(
            tan_new,
            max(-self.tan_max, float(u_prev[1]) - self._du_first[1]),
            min(self.tan_max, float(u_prev[1]) + self._du_first[1]),
        )
        clips = int(abs(a_cmd - a_new) > _EPS_CLIP) + int(abs(tan_cmd - tan_new) > _EPS_CLIP)
        self._apply(a_cmd, tan_cmd)

        Y = F @ x_aug + S @ dU
        e = ref.ravel() - Y
        cost = float(e @ (self.q_bar * e) + dU @ (self.r_bar * dU))
        Yr = Y.reshape(self.Np, self.ny)
        predicted_xy = Yr[:, :2] @ rot.T + pts[0, :2]
        # velocity mode: the planned speed one speed-loop time constant ahead, so that the
        # vehicle's proportional speed controller reproduces the planned acceleration
        lead = self._speed_lead_index
        speed_cmd = float(Yr[lead, 2]) + (a_cmd - a_new) * self.Ts * (lead + 1)
        if direction * speed_cmd < 0.0:
            speed_cmd = 0.0  # never ask the speed controller to drive the other way
        if not result.converged:
            status = "not-converged"
        elif clips:
            status = "clipped"
        else:
            status = "ok"
        return ControlOutput(
            steer_angle=math.atan(tan_cmd),
            accel=a_cmd,
            speed=speed_cmd,
            gear=Gear.D if direction > 0 else Gear.R,
            converged=result.converged,
            iterations=result.iterations,
            clips=clips,
            cost=cost,
            finished=False,
            nearest_index=self._index,
            predicted_xy=predicted_xy,
            status=status,
            solve_time=time.perf_counter() - t0,
        )

    def _apply(self, accel: float, tan_delta: float) -> None:
        """Remember the command sent this tick (and queue it while it is in the dead time)."""
        self._u_prev = np.array([accel, tan_delta])
        if self._dead_ticks:
            self._in_flight.append(tan_delta)

    def _passed_end(self, seg: Segment, pose: Pose) -> bool:
        """True when the car is level with or beyond the segment's end in its driving direction."""
        traj = self._traj
        assert traj is not None
        e = seg.end
        along = (pose.x - traj.x[e]) * math.cos(traj.heading[e]) + (pose.y - traj.y[e]) * math.sin(
            traj.heading[e]
        )
        return seg.direction * along >= 0.0

    def _predict_dead_time(
        self, pose: Pose, steer_angle: float, direction: int
    ) -> tuple[float, float, float, float, float]:
        """``(x, y, v, θ, tan δ)`` once the commands in flight have acted (steering-aware model).

        Starts from the measured pose and road-wheel angle and steps the lagged bicycle one
        control period per queued command; with the kinematic model (or no dead time) it is the
        measured state.
        """
        t = math.tan(_clip(steer_angle, self.cfg.steer_max))
        x, y, v, th = pose.x, pose.y, pose.speed, pose.heading
        if not self.steer_model or not self._in_flight:
            return x, y, v, th, t
        assert self._u_prev is not None
        h = self.period
        a = float(self._u_prev[0])
        for t_cmd in self._in_flight:
            v_next = v + a * h
            if v_next * v < 0.0 or direction * v_next < 0.0:
                v_next = 0.0  # braking stops the car, it does not reverse it
            v_mid = 0.5 * (v + v_next)
            th_mid = th + 0.5 * h * v_mid * t / self.L
            x += h * v_mid * math.cos(th_mid)
            y += h * v_mid * math.sin(th_mid)
            th += h * v_mid * t / self.L
            t += self._alpha_tick * (t_cmd - t)
            v = v_next
        return x, y, v, th, t

    def _align(
        self, seg: Segment, s0: float, steer_angle: float, direction: int, t0: float
    ) -> ControlOutput | None:
        """At rest at a segment's start: turn the wheel to the path's curvature, brake held.

        :returns: the command of this tick, or None once the wheel is there (drive off)
        """
        path = self._path
        assert path is not None and self._u_prev is not None
        ds = 0.25  # m, arc length over which the start curvature is measured
        psi = path.sample(seg, np.array([s0, s0 + ds]))[:, 2]
        span = max(min(s0 + ds, float(path.s[seg.end])) - s0, 1e-6)
        # θ̇ = v tan δ / L: in reverse the heading turns the other way for the same wheel
        tan_target = _clip(direction * self.L * float(psi[1] - psi[0]) / span, self.tan_max)
        target = math.atan(tan_target)
        tol = self.cfg.align_tolerance
        if abs(steer_angle - target) <= tol and abs(self._u_prev[1] - tan_target) <= tol:
            return None
        step = self._du_first[1]
        tan_cmd = _clamp(tan_target, self._u_prev[1] - step, self._u_prev[1] + step)
        self._apply(0.0, tan_cmd)
        return ControlOutput(
            steer_angle=math.atan(tan_cmd),
            accel=-direction * self.cfg.hold_decel,
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            nearest_index=self._index,
            status="aligning",
            solve_time=time.perf_counter() - t0,
        )

    def _brake_to_rest(self, direction: int, t0: float) -> ControlOutput:
        """Beyond the segment's end: brake (at the jerk limit) to rest with the wheel held."""
        assert self._u_prev is not None
        want = -direction * self.cfg.hold_decel
        step = self._du_first[0]
        accel = _clamp(want, self._u_prev[0] - step, self._u_prev[0] + step)
        self._apply(accel, float(self._u_prev[1]))
        return ControlOutput(
            steer_angle=math.atan(float(self._u_prev[1])),
            accel=accel,
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            nearest_index=self._index,
            status="stopping",
            solve_time=time.perf_counter() - t0,
        )

    def _solve(self, E: FloatArray, f: FloatArray, gamma: FloatArray) -> QpResult:
        """Eq. 29 when it satisfies every constraint, else the configured QP backend."""
        x_unc = np.linalg.solve(E, -f).astype(np.float64, copy=False)
        if (self.M @ x_unc <= gamma).all():
            self._lam = None
            return QpResult(x_unc, True, 0, np.zeros(self.M.shape[0]))
        if self._osqp is not None:
            return self._osqp.solve(E, f, gamma)
        E_inv = np.linalg.inv(E).astype(np.float64, copy=False)
        result = hildreth(
            E,
            f,
            self.M,
            gamma,
            max_iter=self.cfg.max_iterations,
            tol=self.cfg.hildreth_tolerance,
            lam0=self._lam,
            E_inv=E_inv,
            relaxation=self.cfg.hildreth_relaxation,
        )
        self._lam = result.lam  # a good start next tick even when the cap was hit
        return result

    def _finish(self, seg: Segment, t0: float) -> ControlOutput:
        """At rest on the final waypoint: hold the brake, keep the wheel where it is."""
        assert self._u_prev is not None
        self._u_prev[0] = 0.0
        return ControlOutput(
            steer_angle=math.atan(float(self._u_prev[1])),
            accel=-seg.direction * self.cfg.hold_decel,
            speed=0.0,
            gear=Gear.D if seg.direction > 0 else Gear.R,
            finished=True,
            nearest_index=self._index,
            status="finished",
            solve_time=time.perf_counter() - t0,
        )


def _clamp(value: float, lo: float, hi: float) -> float:
    return lo if value < lo else hi if value > hi else value


def _clip(value: float, limit: float) -> float:
    return min(max(value, -limit), limit)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
