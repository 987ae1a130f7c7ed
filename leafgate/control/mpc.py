"""The paper's model predictive controller (Ignéczi, Horváth, Pup), as a leafgate Controller.

Each control tick:

1. reference — nearest waypoint (forward search), the vehicle's projection on the path, the
   path-aligned frame there, and ``Np`` reference points placed along the path by the planned
   speed profile (:mod:`leafgate.control.reference`);
2. model — the kinematic bicycle linearised at the current state and last input (eq. 7–12) and
   augmented (eq. 15–19) with all four states as outputs (see :mod:`leafgate.control.model`
   for why the frame is path-aligned and why ``x`` is an output);
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

Faults never raise: non-finite inputs or results give ``converged=False,
status="non-finite"`` and the last applied command; a bad trajectory gives
``status="bad-trajectory"``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from leafgate.config import VehicleConfig
from leafgate.control.config import MpcConfig
from leafgate.control.model import (
    N_INPUTS,
    N_STATES,
    derivative,
    linearise,
    prediction_matrices,
    rk4_step,
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

        self.C = np.eye(N_STATES)  # outputs: along-track, lateral, speed, heading error
        self.ny = self.C.shape[0]
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
        to_end = math.hypot(traj.x[seg.end] - pose.x, traj.y[seg.end] - pose.y)
        if at_rest and to_end <= cfg.goal_tolerance:
            if self._seg + 1 < len(path.segments):
                self._seg += 1  # a cusp: drive the next segment, in the other direction
                seg = path.segments[self._seg]
                self._index = seg.start
                self._u_prev[0] = 0.0
                self._lam = None
            else:
                self._finished = True
        if self._finished:
            return self._finish(seg, t0)

        direction = seg.direction
        a_min, a_max = self._accel_limits(direction)
        u_prev = self._u_prev
        u_prev[0] = min(max(u_prev[0], a_min), a_max)  # limits flip with the direction
        u_prev[1] = min(max(u_prev[1], -self.tan_max), self.tan_max)

        # path-aligned frame at the vehicle's projection
        s0 = path.project(seg, self._index, pose.x, pose.y)
        s_ref = path.horizon_arclength(seg, s0, self.steps)
        pts = path.sample(seg, np.concatenate(([s0], s_ref)))  # (Np+1, 3): x, y, heading
        ox, oy, psi0 = (float(v) for v in pts[0])
        c, s = math.cos(psi0), math.sin(psi0)
        dx, dy = pose.x - ox, pose.y - oy
        state = np.array(
            [c * dx + s * dy, -s * dx + c * dy, pose.speed, _wrap(pose.heading - psi0)]
        )
        if cfg.delay_compensation > 0.0:
            state = rk4_step(state, u_prev, cfg.delay_compensation, self.L)

        rot = np.array([[c, -s], [s, c]])  # local → global; its transpose maps back
        ref = np.empty((self.Np, self.ny))
        ref[:, :2] = (pts[1:, :2] - pts[0, :2]) @ rot
        ref[:, 2] = path.reference_speed(s_ref)
        ref[:, 3] = pts[1:, 2] - psi0

        # 2. model: linearise, augment, predict
        # Near standstill the Jacobian is taken at a planning speed in the segment's direction:
        # at v = 0 steering has no effect on the linear prediction (B ∝ v), and a car at rest
        # off the path would "see" only reversing as a way back to it.
        v_lin = direction * max(direction * float(state[2]), cfg.min_model_speed)
        A, B = linearise(np.array([state[0], state[1], v_lin, state[3]]), u_prev, self.Ts, self.L)
        F, S = prediction_matrices(A, B, self.C, self.Np, self.Nc)
        dx_k = np.linalg.solve(A, self.Ts * derivative(state, u_prev, self.L))
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
        self._u_prev = np.array([a_cmd, tan_cmd])

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
