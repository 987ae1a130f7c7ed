"""Offset-free tracking: constant input disturbances estimated from measured increments.

The MPC's model is exact only for a perfect car. Two constant disturbances leave a steady
error that no weight can remove:

- a steering misalignment ``b`` — the car turns as if the road wheels were at ``tan δ + b``
  (a bent track rod, a miscalibrated angle sensor): a steady lateral offset on a straight;
- a longitudinal disturbance ``d`` — drag, a slight incline: ``dv/dt = a + d``; the car stops
  short of the goal.

Both are estimated from what the car really did between two control ticks (the *measured*
increments), and the MPC then predicts with ``tan δ + b`` and ``a + d`` (input disturbances:
the classic offset-free formulation; constant, so the QP's moves are unchanged):

- ``b̂ ← b̂ + (Δt/τ_b)·(L θ̇ / v − tan δ − b̂)`` with ``θ̇`` the heading change over the tick and
  ``δ`` the measured road-wheel angle (the wheel the car has, so the steering lag is no bias),
  while ``|v|`` is above ``min_speed``;
- ``d̂ ← d̂ + (Δt/τ_d)·(Δv/Δt − a − d̂)`` with ``a`` the acceleration commanded, only once the
  command has been steady for ``τ_d / 4`` (an actuator lag turns a ramp into a transient
  difference that is no disturbance). ``d`` is kept relative to the driving direction (drag
  opposes the motion), so it carries over a cusp with the right sign.

Estimates are clamped (``max_bias``, ``max_accel``): a wrong estimate cannot run away.
"""

from __future__ import annotations

import math
from collections import deque


class DisturbanceEstimator:
    """Estimates ``b`` (steering bias in tan δ) and ``d`` (acceleration, direction-relative).

    :param period: s, control tick
    :param wheelbase: m
    :param tau_steer: s, time constant of the bias filter (0: no bias estimate)
    :param tau_accel: s, time constant of the acceleration filter (0: no estimate)
    :param min_speed: m/s, below this nothing is learnt
    :param max_bias: bound on ``|b|`` (tan δ)
    :param max_accel: m/s², bound on ``|d|``
    """

    STEADY_BAND = 0.05  # m/s², the command counts as steady when it varies less than this

    def __init__(
        self,
        period: float,
        wheelbase: float,
        tau_steer: float,
        tau_accel: float,
        min_speed: float = 0.3,
        max_bias: float = math.tan(math.radians(5.0)),
        max_accel: float = 1.0,
    ) -> None:
        self.period = period
        self.L = wheelbase
        self._k_b = min(period / tau_steer, 1.0) if tau_steer > 0.0 else 0.0
        self._k_d = min(period / tau_accel, 1.0) if tau_accel > 0.0 else 0.0
        self.min_speed = min_speed
        self.max_bias = max_bias
        self.max_accel = max_accel
        steady_ticks = max(round(0.25 * tau_accel / period), 1) if tau_accel > 0.0 else 1
        self._commands: deque[float] = deque(maxlen=steady_ticks)
        self.reset()

    def reset(self) -> None:
        """Forget the estimates and the last measurement."""
        self.bias = 0.0  # tan δ
        self.accel = 0.0  # m/s², in the driving direction (drag is negative)
        self._last: tuple[float, float, float] | None = None  # heading, speed, tan δ
        self._commands.clear()

    def update(self, heading: float, speed: float, tan_delta: float, accel_cmd: float) -> None:
        """One tick's measurement, and the signed acceleration (d(v)/dt) commanded at the
        previous tick — the one that acted since the previous measurement."""
        last = self._last
        self._last = (heading, speed, tan_delta)
        self._commands.append(accel_cmd)
        if last is None:
            return
        h0, v0, t0 = last
        if min(abs(v0), abs(speed)) < self.min_speed or v0 * speed <= 0.0:
            return
        v_mid = 0.5 * (v0 + speed)
        if self._k_b:
            rate = _wrap(heading - h0) / self.period
            raw = self.L * rate / v_mid - 0.5 * (t0 + tan_delta)
            b = self.bias + self._k_b * (raw - self.bias)
            self.bias = min(max(b, -self.max_bias), self.max_bias)
        commands = self._commands
        if (
            self._k_d
            and len(commands) == commands.maxlen
            and max(commands) - min(commands) <= self.STEADY_BAND
        ):
            direction = 1.0 if v_mid > 0.0 else -1.0
            raw_d = direction * ((speed - v0) / self.period - accel_cmd)
            d = self.accel + self._k_d * (raw_d - self.accel)
            self.accel = min(max(d, -self.max_accel), self.max_accel)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
