"""The plan is replaced mid-maneuver by one far from the vehicle.

Decision (gateway/core.py): a new plan is judged as an engage would judge it — outside the
engage envelope (1 m, 30°) the gateway makes a controlled stop (STOPPING, then STANDBY) rather
than chase it. Not FAULT: nothing in the gateway, the ECU or the inputs failed — the plan is
valid, only unreachable from here — so the operator can engage again on a plan that fits,
without a reset. Not "keep the old plan": the planner withdrew it, and what made it re-plan
(an obstacle) is unknown to the gateway.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
from harness import PROCESS_TEST, FaultRun, read_trace, transitions

from leafgate.gateway.state import path_deviation
from leafgate.messages import GatewayState, Pose, Trajectory
from leafgate.sim.scenarios import get_scenario

pytestmark = PROCESS_TEST

SHIFT = 5.0  # m, the new plan lies this far to the left of the old one
SLACK = 0.4  # s, scheduling noise of four processes on two cores
STOP_TIME = 2.0 / 1.5 + 1.5 / 2.0  # s, comfort stop from the s-curve's 2 m/s after its jerk ramp
CHASE_LIMIT = 0.3  # m, how far the car may leave the old path while it stops


def shifted(trajectory: Trajectory, left: float) -> Trajectory:
    """The same plan moved ``left`` metres to the left of its start heading."""
    h = float(trajectory.heading[0])
    return Trajectory(
        x=trajectory.x - left * np.sin(h),
        y=trajectory.y + left * np.cos(h),
        heading=trajectory.heading,
        speed=trajectory.speed,
    )


def test_far_trajectory_replacement_stops_instead_of_chasing(
    make_run: Callable[..., FaultRun],
) -> None:
    from leafgate.transport.client import TrajectoryPublisher

    run = make_run("trajectory replaced 5 m away")
    original = get_scenario(run.scenario).trajectory
    far = shifted(original, SHIFT)
    stop = threading.Event()
    published: list[float] = []

    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("3 s of driving", lambda: run.sniffer_time() >= engaged + 3.0, 15)
        run.stop("planner")  # the planner re-plans: its old plan is gone, the new one replaces it
        publisher = TrajectoryPublisher(run.zenoh(), run.zcfg)

        def planner() -> None:
            while not stop.is_set():
                publisher.publish(far)
                published.append(run.sniffer_time())
                stop.wait(0.5)

        thread = threading.Thread(target=planner, daemon=True)
        thread.start()
        try:
            run.wait_at_rest({GatewayState.STANDBY}, timeout=15)
            status = run.status()
        finally:
            stop.set()
            thread.join(timeout=2)
            publisher.close()
        run.shutdown()

    injected = published[0]
    outcome = run.outcome(injected, status=status)
    rows, _ = read_trace(run.trace)
    after = rows[rows[:, 6] >= injected]
    off_path = max(
        path_deviation(Pose(x=r[1], y=r[2], heading=r[3], speed=r[4]), original)[0] for r in after
    )
    outcome.extra["max_off_old_path_m"] = round(off_path, 3)
    outcome.report()

    assert status["state"] == "STANDBY"
    assert "trajectory replaced: vehicle 5.0" in status["reason"], status["reason"]
    changes = [t for t in transitions(run.recording_files()[1]) if t["time"] >= injected - 0.05]
    assert [t["to"] for t in changes] == ["STOPPING", "STANDBY"], changes
    assert outcome.reaction_s is not None and outcome.reaction_s <= SLACK
    assert outcome.safe_state_s is not None and outcome.safe_state_s <= STOP_TIME + 2 * SLACK
    assert off_path <= CHASE_LIMIT  # it did not turn towards the new plan
    assert outcome.frames_missing == 0
