"""Operator replies tell the truth (issue 19): ``accepted`` means the requested state was
reached or is being entered by this request; a request that changes nothing says so."""

from __future__ import annotations

from test_gateway_core import FakeController, Rig

from leafgate.control.base import ControlOutput
from leafgate.messages import GatewayState, OperatorRequest, Pose

S = GatewayState


def _at_goal(ctl: FakeController, pose: Pose, steer: float) -> ControlOutput:
    """A controller whose car already stands on the trajectory's last point."""
    return ControlOutput(steer_angle=0.0, accel=0.0, speed=0.0, finished=True)


def test_engage_at_the_trajectorys_end_is_not_accepted() -> None:
    rig = Rig(FakeController(_at_goal))
    rig.run(0.1)
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and rig.state == S.STANDBY
    # old code: {"accepted": true, "state": "STANDBY", "reason": "engaged"}
    assert not reply.accepted, reply
    assert reply.state == S.STANDBY and reply.reason == "not ENGAGED: trajectory end reached"
    assert reply.to_dict()["accepted"] is False


def test_disengage_in_standby_changes_nothing_and_says_so() -> None:
    rig = Rig()
    rig.run(0.1)
    reply = rig.step(OperatorRequest.DISENGAGE).reply
    assert reply is not None
    assert reply.to_dict() == {
        "accepted": False,
        "state": "STANDBY",
        "reason": "already in STANDBY",
        "changed": False,
    }


def test_reset_in_standby_without_a_fault_changes_nothing() -> None:
    rig = Rig()
    rig.run(0.1)
    result = rig.step(OperatorRequest.RESET)
    assert result.reply is not None and not result.reply.accepted and not result.reply.changed
    assert "nothing to reset" in result.reply.reason


def test_reset_in_standby_clears_a_reported_ecu_fault() -> None:
    rig = Rig()
    rig.ecu.fault = True
    rig.run(0.1)
    reply = rig.step(OperatorRequest.RESET).reply
    assert reply is not None and reply.accepted and reply.changed
    assert reply.reason.startswith("clearing the ECU's faults")


def test_engage_accepted_is_engaged_and_changed() -> None:
    rig = Rig()
    rig.run(0.1)
    reply = rig.step(OperatorRequest.ENGAGE).reply
    assert reply is not None and reply.accepted and reply.changed and reply.state == S.ENGAGED
    again = rig.step(OperatorRequest.ENGAGE).reply
    assert again is not None and not again.accepted and not again.changed
    assert again.reason == "already engaged"
