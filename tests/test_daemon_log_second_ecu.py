"""A second ECU on the bus is named as such in the fault reason (issue 19, item 7): its
report frames' alive counters interleave with the genuine ones (5, 11, 6, 12, …)."""

from __future__ import annotations

from leafgate.can.codec import CanCodec
from leafgate.can.e2e import CounterChecker
from leafgate.gateway.watchdog import ErrorCounter, Status
from leafgate.messages import SteerReport
from leafgate.settings import load_config

STEER_RPT = 0x0B0


def test_interleaved_counters_are_a_second_sender() -> None:
    c = CounterChecker()
    for a, b in zip(range(5, 10), range(11, 16), strict=True):
        c.check(STEER_RPT, a)
        c.check(STEER_RPT, b)
    assert c.second_senders() == [STEER_RPT]
    c.reset(STEER_RPT)
    assert c.second_senders() == []


def test_lost_repeated_and_skipped_counters_are_not() -> None:
    for sequence in ([5, 6, 8, 9, 11, 12], [5, 5, 5, 5, 5], [1, 3, 5, 7, 9, 11], [0, 8] * 4):
        c = CounterChecker()
        for n in sequence:
            c.check(STEER_RPT, n)
        assert c.second_senders() == [], sequence


def _report(angle: float) -> SteerReport:
    return SteerReport(angle, 0.0, 0.0, False, False, False, False)


def test_two_ecus_fault_reason_names_the_second_sender() -> None:
    cfg = load_config(None)
    ecu_a, ecu_b, gateway = (CanCodec.for_config(cfg) for _ in range(3))
    for _ in range(7):  # B started later: its counter runs 7 ahead
        ecu_b.encode(_report(0.0))
    bad = 0
    for k in range(6):
        for ecu in (ecu_a, ecu_b):
            decoded = gateway.decode(ecu.encode(_report(0.01 * k)))
            bad += not decoded.valid
    cause = gateway.second_senders()
    assert cause.startswith("two interleaved alive-counter sequences on DBW_STEER_RPT (0x0B0)")
    check = ErrorCounter(5).update(0, bad, cause)
    # old code: "report frame errors reached 11 (limit 5)", nothing about a second ECU
    assert check.status is Status.ERRORS
    assert check.detail.endswith(": " + cause) and "second sender on the bus" in check.detail


def test_one_ecu_losing_frames_names_no_second_sender() -> None:
    cfg = load_config(None)
    ecu, gateway = CanCodec.for_config(cfg), CanCodec.for_config(cfg)
    for k in range(20):
        frame = ecu.encode(_report(0.0))
        if k % 3:  # every third frame lost
            gateway.decode(frame)
    assert gateway.second_senders() == ""


def test_gateway_fault_reason_carries_the_cause() -> None:
    from test_gateway_core import Rig

    from leafgate.messages import GatewayState

    rig = Rig()
    rig.run(0.1)
    cause = "two interleaved alive-counter sequences on DBW_STEER_RPT (0x0B0): a second sender"
    result = rig.step(bad_report_frames=6, report_error_cause=cause)
    assert rig.state == GatewayState.FAULT
    assert result.diagnostics.fault == f"report frame errors reached 6 (limit 5): {cause}"
