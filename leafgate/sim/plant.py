"""Simulated vehicles: the plants the controller drives in simulation.

All plants integrate the rear-axle kinematic (or dynamic) bicycle accurately with fixed RK4
sub-steps, not one Euler step per control period. The longitudinal input is *gear-relative*, as on
the wire (DBW_LONG_CMD): a positive acceleration speeds the car up in the direction of the engaged
gear (D forward, R backward); a negative one brakes towards rest and never reverses the motion.
In P, N or no gear the car brakes (P) or rolls (N) to rest.

- :class:`KinematicPlant` — the paper's Simulink check: the kinematic bicycle with an optional
  pure input delay on both inputs.
- :class:`SteerLagPlant` — adds the steering actuator (dead time, first-order lag τ, rate limit)
  and a first-order lag on acceleration, the dynamics the paper's MPC does not model.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

from leafgate.config import VehicleConfig
from leafgate.config.sim import PlantConfig
from leafgate.messages import Gear, Pose

MAX_SUBSTEP = 0.002  # s, RK4 sub-step (error far below the metrics' resolution)
STANDSTILL_SPEED = 0.01  # m/s, below this a braked car is at rest
ROLLING_DECEL = 0.3  # m/s², rolling resistance in neutral
INTEGRATE_BAND = 0.2  # m/s, speed error below which the speed controller integrates


def gear_direction(gear: Gear) -> int:
    """+1 for D, −1 for R, 0 for any gear that does not drive."""
    return 1 if gear == Gear.D else -1 if gear == Gear.R else 0


def signed_accel(gear: Gear, accel_cmd: float, speed: float) -> float:
    """Turn a gear-relative acceleration command into d(signed speed)/dt.

    Braking (negative command) opposes the motion, whatever the gear; driving (positive) pushes in
    the gear's direction. The caller clamps the speed at zero when braking crosses it.
    """
    direction = gear_direction(gear)
    if gear == Gear.P:
        return -math.copysign(6.0, speed) if abs(speed) > 0.0 else 0.0  # m/s², park pawl + brake
    if direction == 0:
        decel = max(-accel_cmd, ROLLING_DECEL)
        return -math.copysign(decel, speed) if abs(speed) > 0.0 else 0.0
    if accel_cmd >= 0.0:
        return direction * accel_cmd
    return -math.copysign(-accel_cmd, speed) if abs(speed) > 0.0 else 0.0


def speed_step(gear: Gear, a_rel: float, v0: float, h: float) -> tuple[float, float, float]:
    """One sub-step of the longitudinal motion: ``(a, v1, h_move)``.

    ``a`` is d(signed speed)/dt, ``v1`` the speed after ``h``, and ``h_move`` how long the car
    actually moves: braking stops it exactly at rest within the sub-step and never reverses it.
    """
    a = signed_accel(gear, a_rel, v0)
    v1 = v0 + a * h
    braking_through_zero = (
        v0 != 0.0 and v1 * v0 < 0.0 and (a_rel <= 0.0 or gear_direction(gear) * v0 < 0)
    )
    if braking_through_zero or (v0 == 0.0 and a == 0.0):
        return a, 0.0, (-v0 / a if a != 0.0 else 0.0)  # integrate up to the stop only
    return a, v1, h


def _bicycle_rhs(x: float, y: float, theta: float, v: float, tan_delta: float, wheelbase: float):
    """Kinematic bicycle about the rear axle (paper eq. 1–6), without the speed equation."""
    return v * math.cos(theta), v * math.sin(theta), v * tan_delta / wheelbase


def rk4_pose(
    x: float,
    y: float,
    theta: float,
    v0: float,
    a: float,
    tan_delta: float,
    wheelbase: float,
    h: float,
) -> tuple[float, float, float]:
    """Advance (x, y, θ) over h with speed v0 + a·t and constant steering, by one RK4 step."""
    k1 = _bicycle_rhs(x, y, theta, v0, tan_delta, wheelbase)
    vm = v0 + 0.5 * h * a
    k2 = _bicycle_rhs(
        x + 0.5 * h * k1[0], y + 0.5 * h * k1[1], theta + 0.5 * h * k1[2], vm, tan_delta, wheelbase
    )
    k3 = _bicycle_rhs(
        x + 0.5 * h * k2[0], y + 0.5 * h * k2[1], theta + 0.5 * h * k2[2], vm, tan_delta, wheelbase
    )
    k4 = _bicycle_rhs(
        x + h * k3[0], y + h * k3[1], theta + h * k3[2], v0 + h * a, tan_delta, wheelbase
    )
    return (
        x + h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
        y + h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]),
        theta + h / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]),
    )


class _Delay:
    """A pure time delay on a scalar signal, sampled at the plant's sub-steps."""

    def __init__(self, delay: float, initial: float) -> None:
        self.delay = max(0.0, delay)
        self._queue: deque[tuple[float, float]] = deque()
        self._output = initial

    def push(self, t: float, value: float) -> None:
        if self.delay <= 0.0:
            self._output = value
        else:
            self._queue.append((t + self.delay, value))

    def output(self, t: float) -> float:
        while self._queue and self._queue[0][0] <= t + 1e-12:
            self._output = self._queue.popleft()[1]
        return self._output


class KinematicPlant:
    """The kinematic bicycle with an optional pure delay on both inputs.

    Steering follows the (delayed) command instantly, within the road-wheel angle limit.
    """

    def __init__(
        self,
        vehicle: VehicleConfig,
        start: Pose,
        input_delay: float = 0.0,
        steer_bias: float = 0.0,
        drag_accel: float = 0.0,
    ) -> None:
        """:param steer_bias: rad, the wheels point this much further left than reported
        :param drag_accel: m/s², ≤ 0, a constant deceleration opposing the motion"""
        self.vehicle = vehicle
        self.steer_bias = steer_bias
        self.drag_accel = drag_accel
        self.t = 0.0  # s, plant time
        self.x, self.y, self.heading, self.speed = start.x, start.y, start.heading, start.speed
        self.steer_angle = 0.0  # rad, actual road-wheel angle
        self.steer_rate = 0.0  # rad/s
        self.accel = 0.0  # m/s², actual d(signed speed)/dt
        self.yaw_rate = 0.0  # rad/s
        self.gear = Gear.D if start.speed >= 0.0 else Gear.R
        self._steer_delay = _Delay(input_delay, 0.0)
        self._accel_delay = _Delay(input_delay, 0.0)

    # -- actuator models (overridden by plants with dynamics) --
    def _steer_update(self, target: float, h: float, rate_limit: float) -> None:
        limit = self.vehicle.max_steer_angle
        new = min(max(target, -limit), limit)
        self.steer_rate = (new - self.steer_angle) / h
        self.steer_angle = new

    def _accel_update(self, target: float, h: float) -> float:
        """Return the gear-relative acceleration acting over the next sub-step."""
        return target

    def set_gear(self, gear: Gear) -> bool:
        """Change gear; refused (False) unless the car is at rest."""
        if gear == self.gear:
            return True
        if abs(self.speed) > STANDSTILL_SPEED:
            return False
        self.gear = gear
        return True

    def step(
        self,
        dt: float,
        steer_cmd: float,
        accel_cmd: float,
        gear: Gear | None = None,
        steer_rate_limit: float = 0.0,
    ) -> None:
        """Advance the plant by ``dt`` seconds with commands held constant.

        :param steer_cmd: road-wheel angle command, rad
        :param accel_cmd: gear-relative acceleration command, m/s²
        :param gear: change to this gear first (only honoured at rest); None keeps the gear
        :param steer_rate_limit: actuator rate limit requested by the command, rad/s (0 = default)
        """
        if gear is not None and gear != Gear.NONE:
            self.set_gear(gear)
        n = max(1, math.ceil(dt / MAX_SUBSTEP - 1e-9))
        h = dt / n
        self._steer_delay.push(self.t, steer_cmd)
        self._accel_delay.push(self.t, accel_cmd)
        for _ in range(n):
            self._steer_update(self._steer_delay.output(self.t), h, steer_rate_limit)
            a_rel = self._accel_update(self._accel_delay.output(self.t), h)
            self._advance(h, a_rel)
            self.t += h

    def _with_drag(self, a_rel: float) -> float:
        """The gear-relative acceleration with the drag added: against the motion, and against
        the drive-off at rest (a drive request weaker than the drag does not move the car)."""
        direction = gear_direction(self.gear)
        if self.drag_accel == 0.0 or direction == 0:
            return a_rel
        return a_rel + (self.drag_accel if direction * self.speed >= 0.0 else -self.drag_accel)

    def _advance(self, h: float, a_rel: float) -> None:
        v0 = self.speed
        a, v1, h_move = speed_step(self.gear, self._with_drag(a_rel), v0, h)
        tan_delta = math.tan(self.steer_angle + self.steer_bias)
        if h_move > 0.0:
            self.x, self.y, self.heading = rk4_pose(
                self.x, self.y, self.heading, v0, a, tan_delta, self.vehicle.wheelbase, h_move
            )
        self.accel = (v1 - v0) / h
        self.speed = v1
        self.yaw_rate = v1 * tan_delta / self.vehicle.wheelbase

    def pose(self) -> Pose:
        """The true rear-axle pose (localization without noise)."""
        return Pose(self.x, self.y, self.heading, self.speed, self.yaw_rate, stamp=self.t)


class SteerLagPlant(KinematicPlant):
    """Kinematic bicycle with steering dead time, first-order lag and rate limit, and an
    acceleration lag: the steering dynamics the paper blames for its LGSVL oscillation."""

    def __init__(self, vehicle: VehicleConfig, start: Pose, cfg: PlantConfig) -> None:
        super().__init__(vehicle, start, 0.0, steer_bias=cfg.steer_bias, drag_accel=cfg.drag_accel)
        self.cfg = cfg
        self._steer_delay = _Delay(cfg.input_delay + cfg.steer_dead_time, 0.0)
        self._accel_delay = _Delay(cfg.input_delay, 0.0)
        self._accel_state = 0.0  # m/s², gear-relative actual acceleration

    def _steer_update(self, target: float, h: float, rate_limit: float) -> None:
        limit = self.vehicle.max_steer_angle
        target = min(max(target, -limit), limit)
        alpha = 1.0 - math.exp(-h / self.cfg.steer_tau)
        delta = alpha * (target - self.steer_angle)
        max_rate = (
            self.cfg.steer_rate_max
            if rate_limit <= 0.0
            else min(rate_limit, self.cfg.steer_rate_max)
        )
        delta = min(max(delta, -max_rate * h), max_rate * h)
        self.steer_rate = delta / h
        self.steer_angle += delta

    def _accel_update(self, target: float, h: float) -> float:
        alpha = 1.0 - math.exp(-h / self.cfg.accel_tau)
        self._accel_state += alpha * (target - self._accel_state)
        if abs(self.speed) <= STANDSTILL_SPEED and target <= 0.0:
            self._accel_state = target  # brakes hold at rest: no lagged creep
        return self._accel_state


class SpeedController:
    """The vehicle's own speed controller (velocity mode): target speed → acceleration.

    PI on the speed magnitude in the engaged gear's direction, with anti-windup by clamping; the
    output is gear-relative like every longitudinal command on the wire.
    """

    def __init__(
        self, kp: float = 1.5, ki: float = 0.1, min_accel: float = -3.0, max_accel: float = 1.5
    ) -> None:
        self.kp, self.ki = kp, ki  # 1/s, 1/s²
        self.min_accel, self.max_accel = min_accel, max_accel  # m/s²
        self._integral = 0.0  # m/s

    def reset(self) -> None:
        self._integral = 0.0

    def step(self, dt: float, target_speed: float, speed_along_gear: float) -> float:
        """:param target_speed: wanted speed magnitude, m/s
        :param speed_along_gear: current speed in the gear's direction, m/s
        :returns: gear-relative acceleration, m/s²"""
        error = target_speed - speed_along_gear
        if target_speed <= 0.0 and speed_along_gear <= 0.05:
            self._integral = 0.0
            return self.min_accel * 0.5  # hold the brake at rest
        # Conditional integration (anti-windup): only near the target and while not saturated,
        # so a large speed step does not charge the integral and overshoot.
        integral = self._integral + error * dt if abs(error) < INTEGRATE_BAND else self._integral
        accel = self.kp * error + self.ki * integral
        clamped = min(max(accel, self.min_accel), self.max_accel)
        if clamped == accel:
            self._integral = integral
        return clamped


def make_plant(cfg: PlantConfig, vehicle: VehicleConfig, start: Pose) -> KinematicPlant:
    """Build the plant named by ``cfg.kind`` (with ``cfg.wheelbase_error`` on its wheelbase)."""
    if cfg.wheelbase_error:
        vehicle = dataclasses.replace(vehicle, wheelbase=vehicle.wheelbase + cfg.wheelbase_error)
    if cfg.kind == "kinematic":
        return KinematicPlant(
            vehicle,
            start,
            input_delay=cfg.input_delay,
            steer_bias=cfg.steer_bias,
            drag_accel=cfg.drag_accel,
        )
    if cfg.kind == "steer-lag":
        return SteerLagPlant(vehicle, start, cfg)
    if cfg.kind == "dynamic":
        return DynamicPlant(vehicle, start, cfg)
    raise ValueError(f"plant kind {cfg.kind!r} is not available")


# ---------------------------------------------------------------------------------------------
# Dynamic bicycle plant (kind "dynamic").
# ---------------------------------------------------------------------------------------------


class DynamicPlant(SteerLagPlant):
    """Dynamic bicycle with linear tyres, blended to the kinematic bicycle at low speed.

    Lateral dynamics about the centre of gravity (mass ``m``, yaw inertia ``Iz``, ``lf``/``lr``
    from the cg to the axles, axle cornering stiffnesses ``Cf``/``Cr`` from
    :class:`~leafgate.config.VehicleConfig`), with ``u`` the body-axis speed, ``vy`` the lateral
    speed of the cg and ``r`` the yaw rate::

        Fyf = -Cf (vy + lf r - u tan δ) / |u|      Fyr = -Cr (vy - lr r) / |u|
        m (vy' + u r) = Fyf cos δ + Fyr            Iz r' = lf Fyf cos δ - lr Fyr

    Dividing by ``|u|`` (not ``u``) keeps the tyre forces opposed to sliding when reversing. At
    speed the steady state gives the understeer-gradient yaw rate ``r = u δ / (L + K u²)``,
    ``K = m (lr Cr - lf Cf) / (L Cf Cr)``. The tyre model is singular at rest, so below
    ``blend_speed_low`` the lateral motion is the kinematic bicycle's (``r = u tan δ / L``, no
    rear-axle side-slip), above ``blend_speed_high`` the dynamic one, linearly blended between;
    after each sub-step the lateral states are pulled to the same blend, so they are consistent
    when the speed rises. The steering actuator (dead time, lag τ, rate limit) and the
    acceleration lag are those of :class:`SteerLagPlant`; the speed along the body axis follows the
    acceleration as in the other plants. :meth:`pose` reports the rear-axle centre.
    """

    def __init__(self, vehicle: VehicleConfig, start: Pose, cfg: PlantConfig) -> None:
        super().__init__(vehicle, start, cfg)
        self.lf = vehicle.cg_to_front  # m
        self.lr = vehicle.wheelbase - vehicle.cg_to_front  # m
        self.lateral_speed = 0.0  # m/s, side-slip speed of the rear-axle centre (body frame)
        self._vy = self.lr * self.yaw_rate  # m/s, lateral speed of the cg, kinematic at start
        # Floor of |u| in the tyre model: only reached where the kinematic blend weight is zero.
        self._u_floor = max(cfg.blend_speed_low, 0.1)  # m/s

    def _dynamic_weight(self, u: float) -> float:
        """Weight of the dynamic model: 0 below blend_speed_low, 1 above blend_speed_high."""
        lo, hi = self.cfg.blend_speed_low, self.cfg.blend_speed_high
        return min(max((abs(u) - lo) / (hi - lo), 0.0), 1.0)

    def _rhs(
        self, state: tuple[float, ...], a: float, tan_d: float, cos_d: float
    ) -> tuple[float, ...]:
        """Time derivative of (x, y, ψ, u, vy, r) with constant acceleration and steering."""
        _, _, psi, u, vy, r = state
        v = self.vehicle
        w = self._dynamic_weight(u)
        r_kin = u * tan_d / v.wheelbase
        u_abs = max(abs(u), self._u_floor)
        f_front = -v.cornering_stiffness_front * (vy + self.lf * r - u * tan_d) / u_abs  # N
        f_rear = -v.cornering_stiffness_rear * (vy - self.lr * r) / u_abs  # N
        dvy = (f_front * cos_d + f_rear) / v.mass - u * r
        dr = (self.lf * f_front * cos_d - self.lr * f_rear) / v.yaw_inertia
        r_b = w * r + (1.0 - w) * r_kin
        slip_rear = w * (vy - self.lr * r)  # m/s, rear-axle side-slip; zero when kinematic
        return (
            u * math.cos(psi) - slip_rear * math.sin(psi),
            u * math.sin(psi) + slip_rear * math.cos(psi),
            r_b,
            a,
            dvy,
            dr,
        )

    def _rk4(
        self, state: tuple[float, ...], a: float, tan_d: float, cos_d: float, h: float
    ) -> tuple[float, ...]:
        k1 = self._rhs(state, a, tan_d, cos_d)
        k2 = self._rhs(
            tuple(s + 0.5 * h * k for s, k in zip(state, k1, strict=True)), a, tan_d, cos_d
        )
        k3 = self._rhs(
            tuple(s + 0.5 * h * k for s, k in zip(state, k2, strict=True)), a, tan_d, cos_d
        )
        k4 = self._rhs(tuple(s + h * k for s, k in zip(state, k3, strict=True)), a, tan_d, cos_d)
        return tuple(
            s + h / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
            for s, d1, d2, d3, d4 in zip(state, k1, k2, k3, k4, strict=True)
        )

    def _advance(self, h: float, a_rel: float) -> None:
        v0 = self.speed
        a, v1, h_move = speed_step(self.gear, self._with_drag(a_rel), v0, h)
        tan_d = math.tan(self.steer_angle + self.steer_bias)
        cos_d = math.cos(self.steer_angle + self.steer_bias)
        r, vy = self.yaw_rate, self._vy
        if h_move > 0.0:
            state = (self.x, self.y, self.heading, v0, vy, r)
            self.x, self.y, self.heading, _, vy, r = self._rk4(state, a, tan_d, cos_d, h_move)
        # Pull the lateral states to the blend at the new speed (exactly kinematic at rest).
        w = self._dynamic_weight(v1)
        r_kin = v1 * tan_d / self.vehicle.wheelbase
        r = w * r + (1.0 - w) * r_kin
        vy = w * vy + (1.0 - w) * self.lr * r_kin
        if not (math.isfinite(r) and math.isfinite(vy)):  # cannot happen with finite inputs
            r, vy = r_kin, self.lr * r_kin
        self.yaw_rate, self._vy = r, vy
        self.lateral_speed = vy - self.lr * r
        self.accel = (v1 - v0) / h
        self.speed = v1
