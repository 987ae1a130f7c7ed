"""Issue 13: the MPC never plans a roll-back against the gear, and a car it will not drive off
is stopped with the cause — not held braked until the no-progress watchdog fires.

Old code (main 205f110): the QP's linear model let the predicted speed go against the gear. At
rest in D after a cusp, with the brake hold still applied (``_u_prev[0] = −hold``), the hold
was modelled as an acceleration that moves the car backward; the MPC planned a roll-back
first, kept the brake on tick after tick with status ``ok``, and the gateway's no-progress
watchdog stopped the car with a reason that hid the cause (``parallel-park`` from the engage
envelope's corners, 6 of 88 runs of ``tools/route_goals.py``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.control.mpc import MpcController
from leafgate.messages import ControlOutput, Pose, Trajectory
from leafgate.sim.plant import KinematicPlant, gear_direction
from tests import routes

PERIOD = 0.02


class _Recording(MpcController):
    """Keeps, per solved tick, the predicted speeds and what the unavoidable bound needs."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.plans: list[tuple[np.ndarray, float, float, int]] = []
        self.ST: np.ndarray | None = None

    def _qp_terms(self, ST: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.ST = ST
        return super()._qp_terms(ST, err)

    def _apply_first_move(self, result: Any, ST: np.ndarray, *args: Any) -> ControlOutput:
        _, free, y0, _, _, v0, a_prev, _, direction, _ = args
        Y = (result.x @ ST + free).reshape(self.ny, self.Np) + y0
        self.plans.append((Y[2].copy(), v0, a_prev, direction))
        return super()._apply_first_move(result, ST, *args)


def _unavoidable(
    cfg: MpcConfig, moves: np.ndarray, v0: float, a_prev: float, direction: int
) -> np.ndarray:
    """Speeds along the gear with the acceleration raised as fast as the limits allow: the
    first move by ``jerk × period``, each later one by ``jerk × Ts`` per model step since the
    one before (``moves``: the step each acts from), up to the drive limit."""
    Ts, Np = cfg.sample_time, cfg.prediction_horizon
    v, w, out = direction * v0, direction * a_prev, []
    for k in range(Np):
        b = int(moves[moves <= k].max())  # the move acting at step k
        a = min(cfg.accel_max, w + cfg.jerk_max * PERIOD + cfg.jerk_max * Ts * b)
        v += Ts * a
        out.append(v)
    return np.array(out)


def _pull_forward() -> Trajectory:
    """The parking manoeuvre's pull-forward move: 1.15 m, turning right (R = 5 m, then easing)."""
    return routes.leg([(0.55, -0.2), (0.6, -0.1)], v_max=0.4)


def _drive_from_hold(
    ctrl: MpcController, traj: Trajectory, start: Pose, ticks: int
) -> tuple[list[ControlOutput], KinematicPlant]:
    """At rest at ``start``, the brake hold applied as a cusp leaves it, then closed loop."""
    plant = KinematicPlant(VehicleConfig(), start)
    ctrl.step(plant.pose(), plant.steer_angle, traj)
    assert ctrl._u_prev is not None
    ctrl._u_prev[0] = -ctrl.cfg.hold_decel  # as _track_segment leaves it at a cusp (in D)
    outs = []
    for _ in range(ticks):
        out = ctrl.step(plant.pose(), plant.steer_angle, traj)
        outs.append(out)
        if not out.converged:
            break
        plant.step(PERIOD, out.steer_angle, gear_direction(plant.gear) * out.accel, plant.gear)
    return outs, plant


def test_predicted_speeds_never_go_against_the_gear_beyond_the_unavoidable() -> None:
    """Old code: from the hold at rest the plan rolled back in D 7 mm/s faster than releasing
    the brake at once would leave it (and kept the brake on: the car stood braked for good)."""
    cfg = MpcConfig()
    ctrl = _Recording(cfg, VehicleConfig(), PERIOD)
    start = Pose(0.2, 0.9, math.radians(30.0), 0.0)
    _drive_from_hold(ctrl, _pull_forward(), start, 150)
    assert len(ctrl.plans) > 50
    for speeds, v0, a_prev, direction in ctrl.plans:
        moves = getattr(ctrl, "_moves", np.arange(cfg.control_horizon))  # (old code: none)
        low = np.minimum(_unavoidable(cfg, moves, v0, a_prev, direction), 0.0)
        assert np.all(direction * speeds >= low - 1e-4), (direction * speeds - low).min()


def test_a_brake_hold_at_rest_is_released_and_never_kept_on() -> None:
    """Old code: the brake stayed on (−0.29 m/s² in D at rest) with status ``ok`` for as long
    as the controller ran. Now a hold at rest is released at the jerk limit before the MPC
    plans (status ``releasing``), and no command the MPC plans keeps a standing car braked."""
    cfg = MpcConfig()
    ctrl = MpcController(cfg, VehicleConfig(), PERIOD)
    start = Pose(0.2, 0.9, math.radians(30.0), 0.0)
    plant = KinematicPlant(VehicleConfig(), start)
    ctrl.step(plant.pose(), plant.steer_angle, _pull_forward())
    assert ctrl._u_prev is not None
    ctrl._u_prev[0] = -cfg.hold_decel  # as _track_segment leaves it at a cusp (in D)
    step = cfg.jerk_max * PERIOD
    held = 0  # consecutive ticks at rest with a brake command that is not being released
    for k in range(300):
        out = ctrl.step(plant.pose(), plant.steer_angle, _pull_forward())
        if k < round(cfg.hold_decel / step):  # released at the jerk limit, the wheel held
            assert out.status == "releasing"
            assert out.accel == pytest.approx(-cfg.hold_decel + (k + 1) * step)
        at_rest = abs(plant.speed) <= cfg.stop_speed
        braked = at_rest and out.accel < -0.01 and out.status != "releasing"
        held = held + 1 if braked else 0
        assert held <= 1, (k, out.status, out.accel)
        if not out.converged:
            break
        plant.step(PERIOD, out.steer_angle, gear_direction(plant.gear) * out.accel, plant.gear)


@pytest.mark.slow
def test_a_cusp_reached_too_far_off_the_next_move_stops_with_the_cause() -> None:
    """``parallel-park`` from the engage envelope's corner (−0.9 m, −25°) reaches its first cusp
    about 1 m and 33° off the 1.15 m pull-forward move. Old code: the brake was kept on and the
    no-progress watchdog stopped the car ("no progress: 0.00 m along the plan in 3.0 s"); now
    the MPC says why it does not drive off."""
    from leafgate.settings import load_config
    from leafgate.sim.runner import run
    from leafgate.sim.scenarios import get_scenario, offset_start

    sc = offset_start(get_scenario("parallel-park"), -0.9, math.radians(-25.0))
    m = run(load_config(None, {"sim.plant.kind": "kinematic"}), sc).metrics
    assert not m["finished"]
    reason = m["not_finished_reason"]
    assert "controller: blocked: at rest" in reason, reason
    assert "roll back against the gear" in reason
    assert m["progress_m"] == pytest.approx(6.8, abs=0.1)  # at the first cusp


def test_a_drivable_start_from_the_hold_drives_off() -> None:
    """The same hold on a start the plan can be driven from: released, then driven forward to
    the end of the move (never blocked)."""
    traj = routes.leg([(6.0, 0.0)], v_max=0.5)
    ctrl = MpcController(MpcConfig(), VehicleConfig(), PERIOD)
    outs, plant = _drive_from_hold(ctrl, traj, Pose(0.3, 0.3, math.radians(10.0), 0.0), 900)
    assert all(o.converged for o in outs)
    assert not any(o.status.startswith("blocked") for o in outs)
    assert outs[-1].finished and plant.x > 5.8


@pytest.mark.parametrize("model", ["kinematic", "kinematic_steer_lag"])
@pytest.mark.parametrize("direction", [1, -1])
def test_speed_rows_of_the_constraints_are_the_prediction_s(model: str, direction: int) -> None:
    """The constant speed rows in ``M`` are the speed rows of the prediction's ``S`` (both models,
    both gears): ``−direction · v_k``'s dependence on the moves."""
    traj = routes.leg([(10.0, 0.1)], v_max=1.0)
    heading = 0.15
    if direction < 0:  # the same path driven backwards: the car faces against its motion
        traj = Trajectory(traj.x, traj.y, traj.heading + math.pi, -traj.speed)
        heading += math.pi
    ctrl = _Recording(MpcConfig(model=model), VehicleConfig(), PERIOD)  # type: ignore[arg-type]
    out = ctrl.step(Pose(2.0, 0.1, heading, direction * 0.7), 0.05, traj)
    assert out.converged and ctrl.ST is not None
    Np = ctrl.Np
    speed_S = ctrl.ST[:, 2 * Np : 3 * Np].T
    np.testing.assert_allclose(ctrl.M[-Np:], -direction * speed_S, atol=1e-12)
