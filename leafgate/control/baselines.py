"""The classic geometric path trackers the paper compares itself with: Pure Pursuit and Stanley.

Both steer with a geometric law and control speed with a PI loop on the planned speed; both
drive reverse segments and cusps like the MPC (:mod:`leafgate.control.mpc`): the trajectory is
split into direction segments (:class:`~leafgate.control.reference.ReferencePath`), each is
driven to its end, the car stops there, turns the wheel at rest for the next segment and asks
for the other gear in :attr:`~leafgate.messages.ControlOutput.gear`.

**Reverse.** The kinematic bicycle about the rear axle reversing with speed ``v < 0`` and road
wheel angle ``δ`` moves exactly like one driving forward with speed ``−v``, heading ``θ + π``
and wheel angle ``−δ`` (``θ̇ = v tan δ / L = (−v) tan(−δ) / L``). Each law is therefore written
once for forward driving, in the *travel frame* (heading ``θ + π`` in reverse), and its wheel
angle is negated in reverse. For Stanley the "front axle" of the travel frame is a virtual point
one wheelbase behind the rear axle when reversing.

- :class:`PurePursuit` (Coulter 1992): aim at the path point one look-ahead distance ahead,
  ``Ld = max(Ld_min, k_v |v|)``, and steer onto the circle through it:
  ``tan δ = L κ = 2 L sin α / Ld``.
- :class:`Stanley` (Hoffmann, Tomlin, Montemerlo, Thrun 2007): at the front axle,
  ``δ = ψₑ + atan(k e / (k_soft + |v|))`` — heading error plus cross-track error. The softening
  speed ``k_soft`` keeps the cross-track gain finite at (and near) standstill.

Both commands pass the same amplitude and rate limits as the MPC's, so the comparison is fair.
Like the MPC, nothing here raises in the control path: bad inputs give ``converged=False``.

>>> from leafgate.config import VehicleConfig
>>> pp = PurePursuit(PurePursuitConfig(), VehicleConfig(), period=0.02)
>>> pp.period
0.02
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from leafgate.config import VehicleConfig
from leafgate.config.control import PurePursuitConfig, StanleyConfig
from leafgate.config.control import TrackerConfig as _TrackerConfig
from leafgate.control.reference import (
    PathRules,
    Progress,
    ReferencePath,
    Segment,
    prepare_plan,
)
from leafgate.geometry import clip_abs as _clip
from leafgate.geometry import wrap_angle as _wrap
from leafgate.messages import ControlOutput, FloatArray, Gear, Pose, Trajectory

__all__ = [
    "PurePursuit",
    "PurePursuitConfig",
    "SpeedPi",
    "Stanley",
    "StanleyConfig",
]


class SpeedPi:
    """PI speed loop on the speed magnitude in the driving direction, with feed-forward.

    Conditional integration (only within ``band`` of the target, and only while the output is
    not saturated) keeps a large speed step from winding the integral up.

    :param kp: 1/s
    :param ki: 1/s²
    :param band: m/s
    """

    def __init__(self, kp: float, ki: float, band: float) -> None:
        self.kp, self.ki, self.band = kp, ki, band
        self.integral = 0.0  # m/s

    def reset(self) -> None:
        self.integral = 0.0

    def step(
        self, dt: float, target: float, speed: float, feedforward: float, lo: float, hi: float
    ) -> float:
        """:param target: wanted speed magnitude, m/s
        :param speed: speed in the driving direction, m/s
        :param feedforward: acceleration the target itself asks for, m/s²
        :param lo: lowest allowed output, m/s² (gear-relative)
        :param hi: highest allowed output, m/s²
        :returns: gear-relative acceleration, m/s²"""
        error = target - speed
        integral = self.integral + error * dt if abs(error) < self.band else self.integral
        accel = feedforward + self.kp * error + self.ki * integral
        clamped = min(max(accel, lo), hi)
        if clamped == accel:
            self.integral = integral
        return clamped


class _Tracker:
    """Segments, cusps, stopping, alignment at rest, speed loop and limits of both baselines.

    Subclasses give the steering law, :meth:`_law`, for forward driving in the travel frame.
    """

    def __init__(self, cfg: _TrackerConfig, vehicle: VehicleConfig, period: float) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        self.cfg = cfg
        self.period = period
        self.L = vehicle.wheelbase  # m
        self._rules = PathRules.of(cfg, vehicle.wheelbase)  # how a plan's reference is built
        self._speed = SpeedPi(cfg.speed_kp, cfg.speed_ki, cfg.speed_integral_band)
        self.reset()

    # --- Controller protocol ---

    def reset(self) -> None:
        """Forget the trajectory, the segment, the last command and the speed integral."""
        self._traj: Trajectory | None = None
        self._path: ReferencePath | None = None
        self._progress: Progress | None = None
        self._bad_trajectory = ""
        self._steer = math.nan  # rad, last commanded angle (NaN: none yet)
        self._accel = 0.0  # m/s², last signed acceleration command
        self._aligned = False
        self._finished = False
        self._speed.reset()

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        """Compute the command for this tick (never raises on bad data)."""
        t0 = time.perf_counter()
        if trajectory is not self._traj:
            self._set_trajectory(trajectory)
        path, prog = self._path, self._progress
        if path is None or prog is None:
            return self._fault(f"bad-trajectory: {self._bad_trajectory}", 1, t0)
        seg = prog.segment
        if not all(
            math.isfinite(v) for v in (pose.x, pose.y, pose.heading, pose.speed, steer_angle)
        ):
            return self._fault("non-finite", seg.direction, t0)
        if math.isnan(self._steer):
            self._steer = _clip(steer_angle, self.cfg.steer_max)

        cfg = self.cfg
        s0 = prog.s if self._finished else prog.update(pose.x, pose.y, pose.heading)
        at_rest = abs(pose.speed) <= cfg.stop_speed
        passed = prog.passed  # progress has reached the end (not a half-plane test)
        if at_rest and not self._finished and prog.ended(pose.x, pose.y, cfg.goal_tolerance):
            if prog.next_segment():  # a cusp: the next segment, in the other direction
                seg = prog.segment
                self._aligned = False
                self._speed.reset()
                s0 = prog.update(pose.x, pose.y, pose.heading)
                passed = False
            else:
                self._finished = True
        direction = seg.direction
        if self._finished:
            return self._output(
                self._steer,
                -direction * cfg.hold_decel,
                0.0,
                direction,
                t0,
                status="finished",
                finished=True,
            )

        # steering: the law in the travel frame, negated in reverse, within the limits
        law = direction * self._law(path, seg, s0, pose)
        if not math.isfinite(law):
            return self._fault("non-finite", direction, t0)
        target = _clip(law, cfg.steer_max)
        step = cfg.steer_rate_max * self.period
        steer = min(max(target, self._steer - step), self._steer + step)

        if at_rest and not self._aligned:
            if s0 - path.s[seg.start] <= cfg.goal_tolerance and (
                abs(steer_angle - target) > cfg.align_tolerance
                or abs(steer - target) > cfg.align_tolerance
            ):
                # turn the wheel at rest, brake held, before driving off
                return self._output(
                    steer,
                    self._ramp(-direction * cfg.hold_decel),
                    0.0,
                    direction,
                    t0,
                    status="aligning",
                )
            self._aligned = True
        elif not at_rest:
            self._aligned = True
        if passed:  # beyond the end: brake to rest, the next segment corrects
            if at_rest:  # the last segment, farther from its end than the goal tolerance
                out = self._output(
                    steer, self._ramp(-direction * cfg.hold_decel), 0.0, direction, t0
                )
                distance = prog.to_end(pose.x, pose.y)
                return replace(
                    out,
                    converged=False,
                    status=f"off-goal: stopped {distance:.2f} m from the end "
                    f"(tolerance {cfg.goal_tolerance:g} m)",
                )
            return self._output(
                steer,
                self._ramp(-direction * cfg.hold_decel),
                0.0,
                direction,
                t0,
                status="stopping",
            )

        stop = path.stops.get(seg)
        if at_rest and stop is not None and s0 >= stop - cfg.goal_tolerance:
            # the plan comes to rest here (a planner's stop line): hold, as the MPC does, and
            # wait for a plan that moves on
            out = self._output(steer, self._ramp(-direction * cfg.hold_decel), 0.0, direction, t0)
            return replace(
                out,
                status=f"stop-point: the plan stands from {stop:.2f} m of "
                f"{prog.route_length:.2f} m on",
            )
        along = direction * pose.speed
        target_speed, feedforward = self._speed_target(path, seg, s0, abs(pose.speed))
        a_rel = self._speed.step(
            self.period, target_speed, along, feedforward, cfg.accel_min, cfg.accel_max
        )
        accel = self._ramp(direction * a_rel)
        return self._output(steer, accel, direction * target_speed, direction, t0)

    def _speed_target(
        self, path: ReferencePath, seg: Segment, s: float, speed: float
    ) -> tuple[float, float]:
        """The target speed magnitude at arc length ``s`` (m/s) and the acceleration following
        it asks for (m/s², the feed-forward of :class:`SpeedPi`).

        The target is the planned speed, at least creeping, under a stopping curve before the
        end, or before the plan's stop point (:attr:`ReferencePath.stops`: old code crept on
        through it at the creep speed). Two things let the car stop *on* the end rather than past it:

        - The feed-forward of a falling planned speed, ``v dv/ds``. On the plan's braking ramp
          a PI loop alone lags by about ``b / kp`` (0.3 m/s at 0.4 m/s²) and, outside its
          integration band, never catches up: the car reached the end still rolling. A rising
          planned speed gets none: arriving late at a higher speed costs nothing, while the
          acceleration asked for on a short parking move's brief rise is still acting, through
          the jerk limit and the actuator's lag, when its braking should begin.
        - The stopping curve ``√(2 b (d − |v| t_r))`` keeps the distance covered during the
          reaction time ``t_r`` (the braking asked for acts only after the actuator's lag and
          the jerk-limited ramp) in reserve, as a braking distance ``v t_r + v²/2b`` does.

        :param speed: the car's speed magnitude, m/s
        """
        cfg = self.cfg
        end = path.stops.get(seg, float(path.s[seg.end]))  # m, where the plan stops the car
        remaining = end - s - speed * cfg.stop_reaction_time  # m
        stop_curve = math.sqrt(2.0 * cfg.stop_decel * max(remaining, 0.0))  # m/s
        planned, slope = path.speed_and_slope(seg, s)
        if stop_curve < max(planned, cfg.creep_speed):
            # on the curve v² = 2 b (d − v t_r): dv/dt = −b v / (v + b t_r), −b without reserve
            reserve = cfg.stop_decel * cfg.stop_reaction_time  # m/s
            decel = cfg.stop_decel * stop_curve / (stop_curve + reserve) if stop_curve else 0.0
            return stop_curve, -decel
        if planned > cfg.creep_speed:
            return planned, min(planned * slope, 0.0)
        return cfg.creep_speed, 0.0

    # --- the law (subclasses) ---

    def _law(self, path: ReferencePath, seg: Segment, s0: float, pose: Pose) -> float:
        """Road-wheel angle for forward driving in the travel frame, rad."""
        raise NotImplementedError

    # --- helpers ---

    def _set_trajectory(self, trajectory: Trajectory) -> None:
        self._traj = trajectory
        self._aligned = False
        self._finished = False
        self._path, self._progress, self._bad_trajectory = prepare_plan(
            trajectory, self._rules, self.cfg.search_window
        )

    def _where(self) -> dict[str, Any]:
        """The progress fields of an output (none before a usable plan)."""
        return {} if self._progress is None else self._progress.fields(self._finished)

    def _ramp(self, accel: float) -> float:
        """Limit the change of the signed acceleration to the jerk limit."""
        step = self.cfg.jerk_max * self.period
        return min(max(accel, self._accel - step), self._accel + step)

    def _output(
        self,
        steer: float,
        accel: float,
        speed: float,
        direction: int,
        t0: float,
        status: str = "ok",
        finished: bool = False,
    ) -> ControlOutput:
        self._steer, self._accel = steer, accel
        return ControlOutput(
            steer_angle=steer,
            accel=accel,
            speed=speed,
            gear=Gear.D if direction > 0 else Gear.R,
            finished=finished,
            status=status,
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )

    def _fault(self, status: str, direction: int, t0: float) -> ControlOutput:
        steer = 0.0 if math.isnan(self._steer) else self._steer
        return ControlOutput(
            steer_angle=steer,
            accel=self._accel,
            speed=0.0,
            gear=Gear.D if direction > 0 else Gear.R,
            converged=False,
            status=status,
            solve_time=time.perf_counter() - t0,
            **self._where(),
        )


def points_on_path(path: ReferencePath, seg: Segment, s: FloatArray) -> FloatArray:
    """``(x, y, heading)`` rows of the segment at the arc lengths ``s``, continued straight past
    its ends.

    Beyond the end (or before the start) the path is extended along the end's travel direction,
    so look-ahead points and front-axle projections stay meaningful at a stop point.
    """
    clamped = np.clip(s, float(path.s[seg.start]), float(path.s[seg.end]))
    pts = path.sample(seg, clamped)  # a new array: written in place below
    extra = (s - clamped) * seg.direction  # m, along the travel direction past an end
    pts[:, 0] += extra * np.cos(pts[:, 2])
    pts[:, 1] += extra * np.sin(pts[:, 2])
    return pts


class PurePursuit(_Tracker):
    """Pure Pursuit about the rear axle with a speed-dependent look-ahead.

    :param cfg: the ``controller.pure_pursuit`` section
    :param vehicle: wheelbase
    :param period: s, time between two calls of :meth:`step`
    """

    cfg: PurePursuitConfig

    def __init__(self, cfg: PurePursuitConfig, vehicle: VehicleConfig, period: float) -> None:
        super().__init__(cfg, vehicle, period)

    def _law(self, path: ReferencePath, seg: Segment, s0: float, pose: Pose) -> float:
        cfg = self.cfg
        lookahead = min(
            max(cfg.lookahead_min, cfg.lookahead_gain * abs(pose.speed)), cfg.lookahead_max
        )
        tx, ty, _ = points_on_path(path, seg, np.array([s0 + lookahead]))[0].tolist()
        travel = pose.heading if seg.direction > 0 else pose.heading + math.pi
        dx, dy = tx - pose.x, ty - pose.y
        distance = math.hypot(dx, dy)
        if distance < 1e-6:
            return 0.0
        alpha = math.atan2(dy, dx) - travel  # bearing of the target in the travel frame
        return math.atan(2.0 * self.L * math.sin(alpha) / distance)  # tan δ = L·2 sin α / Ld


class Stanley(_Tracker):
    """Stanley's front-axle law with a softened cross-track term, on the front axle's path.

    The plan is the rear axle's. Its front-axle path runs one wheelbase ahead of it along the
    heading, ``F(s) = P(s) + L t(s)``: on a bend of radius R it lies outside, by about
    ``L²/2R``. Stanley's law is stated for the point it steers, the front axle, so it follows
    that path, with the road-wheel angle the path's curvature asks for, ``atan(L κ)``, fed
    forward. Old code measured the front axle's error from the rear axle's path, without the
    feed-forward: on an 8 m radius it held the rear axle 0.46 m inside the bend, and it missed
    the parking goals by 0.2 m.

    :param cfg: the ``controller.stanley`` section
    :param vehicle: wheelbase
    :param period: s, time between two calls of :meth:`step`
    """

    cfg: StanleyConfig

    # m, the plan's curvature is its turn from this far behind to this far ahead: the cubic
    # through the waypoints bends unevenly between them, and over ±0.1 m the fed-forward
    # angle made the wheel reverse 5–17 times where the path asks for 1–5 (kinematic plant)
    CURVATURE_STEP = 0.5

    def __init__(self, cfg: StanleyConfig, vehicle: VehicleConfig, period: float) -> None:
        super().__init__(cfg, vehicle, period)
        # the arc lengths of one curvature, relative to its point
        self._around = np.array([-self.CURVATURE_STEP, 0.0, self.CURVATURE_STEP])

    def _law(self, path: ReferencePath, seg: Segment, s0: float, pose: Pose) -> float:
        cfg = self.cfg
        L = self.L
        travel = pose.heading if seg.direction > 0 else pose.heading + math.pi
        # the travel frame's front axle: one wheelbase ahead in the direction of travel
        fx = pose.x + L * math.cos(travel)
        fy = pose.y + L * math.sin(travel)
        # the rear-axle arc length s whose front-axle point F(s) it projects on, by Newton
        # steps along F'(s) = t + L κ n from the rear axle's own progress
        s = s0
        for _ in range(3):
            qx, qy, tangent, kappa = self._front_path(path, seg, s)
            dx = math.cos(tangent) - L * kappa * math.sin(tangent)
            dy = math.sin(tangent) + L * kappa * math.cos(tangent)
            s += ((fx - qx) * dx + (fy - qy) * dy) / (dx * dx + dy * dy)
        qx, qy, tangent, kappa = self._front_path(path, seg, s)
        along = tangent + math.atan(L * kappa)  # rad, the direction F runs in
        # cross-track error: the front axle's offset to the left of its path, travel frame
        error = -(fx - qx) * math.sin(along) + (fy - qy) * math.cos(along)
        heading_error = _wrap(tangent - travel)
        feed_forward = math.atan(L * kappa)  # rad, the angle the bend asks for
        return (
            heading_error
            + math.atan2(cfg.gain * -error, cfg.softening + abs(pose.speed))
            + feed_forward
        )

    def _front_path(
        self, path: ReferencePath, seg: Segment, s: float
    ) -> tuple[float, float, float, float]:
        """The front-axle path at rear arc length ``s``: ``(x, y)`` of ``F(s)``, the rear
        path's travel direction there (rad) and its curvature in the travel frame (1/m)."""
        h_step = self.CURVATURE_STEP
        behind, here, ahead = points_on_path(path, seg, s + self._around).tolist()
        px, py, h = here
        h_ahead, h_behind = ahead[2], behind[2]
        kappa = _wrap(h_ahead - h_behind) / (2.0 * h_step)
        tangent = h if seg.direction > 0 else h + math.pi
        return px + self.L * math.cos(tangent), py + self.L * math.sin(tangent), tangent, kappa
