"""Operator replies tell the truth (issue 19): ``accepted`` means the requested state was
reached or is being entered by this request; a request that changes nothing says so."""

from __future__ import annotations

import json

import pytest
from test_gateway_core import FakeController, Rig

from leafgate.control.base import ControlOutput
from leafgate.gateway.state import EngageReply
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
        "already": True,
    }


def test_reset_in_standby_without_a_fault_changes_nothing() -> None:
    rig = Rig()
    rig.run(0.1)
    result = rig.step(OperatorRequest.RESET)
    assert result.reply is not None and not result.reply.accepted and not result.reply.changed
    assert result.reply.already and "nothing to reset" in result.reply.reason


def test_a_refused_request_says_it_changed_nothing() -> None:
    """Old code: a reset while ENGAGED was refused with ``changed: true``: ``changed`` told the
    CLI's exit status (1, a refusal; 3, nothing to do) rather than what the request did."""
    rig = Rig()
    rig.run(0.1)
    assert rig.step(OperatorRequest.ENGAGE).reply.accepted  # type: ignore[union-attr]
    reply = rig.step(OperatorRequest.RESET).reply
    assert reply is not None and reply.to_dict() == {
        "accepted": False,
        "state": "ENGAGED",
        "reason": "reset only in STANDBY or FAULT (is ENGAGED)",
        "changed": False,
        "already": False,
    }


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
    assert again is not None and not again.accepted and not again.changed and again.already
    assert again.reason == "already engaged"


def test_the_cli_exits_1_on_a_refusal_and_3_on_nothing_to_do(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The exit status comes from ``accepted`` and ``already``, whatever ``changed`` says."""
    from leafgate import cli
    from leafgate.transport import client

    replies = {
        "reset": EngageReply(False, S.ENGAGED, "reset only in STANDBY or FAULT (is ENGAGED)"),
        "disengage": EngageReply.unchanged(S.STANDBY, "already in STANDBY"),
        "engage": EngageReply.done(S.ENGAGED, "engaged"),
    }
    monkeypatch.setattr(client, "request", lambda _cfg, what, **_: replies[what].to_dict())
    sim = ["--config", "config/sim.yaml"]
    assert cli.main(["reset", *sim]) == 1
    assert cli.main(["disengage", *sim]) == cli.EXIT_UNCHANGED == 3
    assert cli.main(["engage", *sim, "--wait", "0"]) == 0
    printed = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["already"] for r in printed] == [False, True, False]
