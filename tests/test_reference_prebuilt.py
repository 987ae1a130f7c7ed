"""A new plan's reference is built where the plan arrives, not in a control tick (issue 17,
finding 5: a 10⁶-point plan made one tick last 4.36 s; 2000 points still cost 1.8 ms).

The gateway's transport calls ``on_plan`` on Zenoh's thread with every valid plan before the
control thread can see it; the daemon hands it :func:`~leafgate.control.reference.prebuild`, and
the controller's :func:`~leafgate.control.reference.prepare_plan` takes the built path.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import pytest
from test_transport import WAIT, configs, wait_until

from leafgate.config import VehicleConfig
from leafgate.config.control import MpcConfig
from leafgate.control import make_controller, plan_rules, reference
from leafgate.control.mpc import MpcController
from leafgate.control.reference import PathRules, ReferencePath, prebuild, prepare_plan
from leafgate.messages import OperatorRequest, Pose, Trajectory
from leafgate.runtime.node import GatewayTransport
from leafgate.settings import load_config
from leafgate.transport import client
from leafgate.transport.session import open_session

__all__ = ["configs"]  # the (gateway, tool) configs fixture, from test_transport

RULES = PathRules.of(MpcConfig(), VehicleConfig().wheelbase)  # the default MPC's


def plan(n: int = 2000) -> Trajectory:
    s = np.arange(n) * 0.5
    return Trajectory(
        x=s, y=0.5 * np.sin(s / 20.0), heading=np.arctan(0.025 * np.cos(s / 20.0)), speed=np.ones(n)
    )


class NoBuildInTick(ReferencePath):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        raise AssertionError("a reference path was built in a control tick")


def test_the_controller_takes_the_prebuilt_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    traj = plan()
    prebuild(traj, RULES)
    monkeypatch.setattr(reference, "ReferencePath", NoBuildInTick)
    controller = MpcController(MpcConfig(), VehicleConfig(), 0.02)
    out = controller.step(Pose(0.0, 0.0, 0.0, 0.0), 0.0, traj)  # built here before
    assert out.converged and math.isfinite(out.steer_angle)
    assert out.route_length == pytest.approx(
        float(np.hypot(np.diff(traj.x), np.diff(traj.y)).sum())
    )


def test_a_plan_nobody_prebuilt_is_still_built_and_a_bad_one_refused() -> None:
    path, progress, problem = prepare_plan(plan(50), RULES, 20)
    assert path is not None and progress is not None and problem == ""
    bad = Trajectory(x=np.zeros(5), y=np.zeros(5), heading=np.zeros(5), speed=np.ones(5))
    prebuild(bad, RULES)
    assert prepare_plan(bad, RULES, 20)[:2] == (None, None)
    assert prepare_plan(bad, RULES, 20)[2]


@pytest.mark.parametrize(
    "other",
    [
        PathRules(RULES.creep_speed + 0.1, RULES.min_turn_radius),
        PathRules(RULES.creep_speed, RULES.min_turn_radius + 0.5),
    ],
)
def test_other_rules_build_their_own(other: PathRules) -> None:
    traj = plan(50)
    prebuild(traj, RULES)
    mine = prepare_plan(traj, RULES, 20)[0]
    theirs = prepare_plan(traj, other, 20)[0]
    assert mine is not None and theirs is not None and theirs is not mine


@pytest.mark.parametrize("kind", ["mpc", "pure-pursuit", "stanley"])
def test_the_daemon_builds_with_the_rules_of_the_configured_controller(
    kind: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the daemon prebuilds is what the controller would build: else every plan would be
    built again in a control tick (nothing fails, a tick is late)."""
    cfg = load_config(None, {"controller.kind": kind})
    traj = plan()
    prebuild(traj, plan_rules(cfg.controller, cfg.vehicle))
    monkeypatch.setattr(reference, "ReferencePath", NoBuildInTick)
    controller = make_controller(cfg.controller, cfg.vehicle, cfg.gateway.period)
    out = controller.step(Pose(0.0, 0.0, 0.0, 0.0), 0.0, traj)
    assert math.isfinite(out.steer_angle) and out.route_length > 0.0


def test_prebuilt_plans_are_bounded() -> None:
    plans = [plan(20) for _ in range(reference.PREBUILT_PLANS + 3)]
    for p in plans:
        prebuild(p, RULES)
    assert len(reference._prebuilt_plans) == reference.PREBUILT_PLANS


def test_the_transport_builds_a_plan_on_arrival(configs: Any) -> None:
    built_on: list[threading.Thread] = []

    def on_plan(trajectory: Trajectory) -> None:
        built_on.append(threading.current_thread())
        prebuild(trajectory, RULES)

    def refuse(_r: OperatorRequest) -> dict[str, Any]:
        return {"accepted": False}

    with GatewayTransport.open(configs[0], refuse) as gateway, open_session(configs[1]) as tool:
        gateway.on_plan = on_plan
        client.publish_trajectory(configs[1], plan(), session=tool)
        assert wait_until(lambda: gateway.latest_trajectory() is not None, WAIT)
        sample = gateway.latest_trajectory()
    assert sample is not None and sample.valid
    assert built_on and built_on[0] is not threading.main_thread()
    assert reference._prebuilt(sample.value, RULES) is not None  # ready before the slot
