"""The interface every controller (MPC, Pure Pursuit, Stanley) implements.

Controllers are pure in the sense the gateway needs: no clock, no I/O. They are called once per
control tick; the tick period is fixed at construction.
"""

from __future__ import annotations

from typing import Protocol

from leafgate.messages import ControlOutput, Pose, Trajectory


class Controller(Protocol):
    """A path- and speed-tracking controller called once per control tick."""

    period: float  # s, time between two calls of step()

    def reset(self) -> None:
        """Forget all internal state (last inputs, nearest index, warm starts)."""

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        """Compute the next command.

        :param pose: the vehicle's rear-axle pose and signed speed
        :param steer_angle: the measured road-wheel angle, rad
        :param trajectory: the reference; a new object means a new plan (restart the search)
        """
        ...
