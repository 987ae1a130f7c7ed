"""ECU-side faults across processes: its reports stop, or arrive with a bad CRC or a stuck
alive counter; the driver overrides by steering torque or by the brake pedal.

docs/watchdogs.md: a report older than 3 periods → FAULT (here 20: see REPORT_TIMEOUT); report
CRC/counter errors counted +1 bad / −1 good reaching 5 → FAULT; an ECU OVERRIDE → STANDBY (a new
engage needed).
"""

from __future__ import annotations

import re
from collections.abc import Callable

import pytest
from harness import PROCESS_TEST, REPORT_TIMEOUT_PERIODS, FaultRun, read_trace, transitions

from leafgate.messages import GatewayState

pytestmark = PROCESS_TEST

SLACK = 0.4  # s, scheduling noise of four processes on two cores
MAX_SPEED = 2.0  # m/s, the s-curve's top speed
REPORT_TIMEOUT = REPORT_TIMEOUT_PERIODS * 0.010  # s, of DBW_STEER_RPT (100 Hz): docs/watchdogs.md's
# 3 periods (30 ms) are shorter than a scheduling stall of four processes on two loaded cores,
# which then faults the run before its injection; test_watchdog.py holds the gateway to the 3
ERROR_LIMIT = 5  # bad report frames (docs/watchdogs.md)
REPORT_RATE = 100 + 50 + 10  # DBW report frames per second (steer, long, system)
DRIVER_DECEL = 2.0  # m/s², the simulated driver brakes once the ECU hands back
OVERRIDE_TIME = 0.1  # s, docs/can-protocol.md: torque above 2.5 N·m for 100 ms


def _run(run: FaultRun, kind: str, state: GatewayState) -> tuple[float, dict]:
    with run.start():
        run.engage()
        run.wait_engaged()
        run.wait_for(f"{kind} to start", lambda: run.injection_started(kind) is not None, 15)
        run.wait_at_rest({state}, timeout=15)
        status = run.status()
        run.shutdown()
    injected = run.injection_started(kind)
    assert injected is not None
    return injected, status


def test_ecu_reports_stop_faults(make_run: Callable[..., FaultRun]) -> None:
    # The reports come back after 2.5 s (the car stands by then): the fault stays latched.
    run = make_run("ECU reports stop", injections=["report-dropout@3+2.5"])
    injected, status = _run(run, "report-dropout", GatewayState.FAULT)
    outcome = run.outcome(injected, status=status)
    outcome.report()

    assert status["state"] == "FAULT"
    assert "report age" in status["reason"], status["reason"]
    assert outcome.reaction_s is not None and outcome.reaction_s <= REPORT_TIMEOUT + SLACK
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= REPORT_TIMEOUT + MAX_SPEED / DRIVER_DECEL + 2 * SLACK
    assert outcome.frames_missing == 0


@pytest.mark.parametrize(
    ("kind", "fault"),
    [("corrupt-crc", "ECU reports with bad CRC"), ("stuck-counter", "ECU reports stuck counter")],
)
def test_corrupted_ecu_reports_fault(
    make_run: Callable[..., FaultRun], kind: str, fault: str
) -> None:
    run = make_run(fault, injections=[f"{kind}@3"])
    injected, status = _run(run, kind, GatewayState.FAULT)
    outcome = run.outcome(injected, status=status)
    outcome.report()

    assert status["state"] == "FAULT"
    # several bad frames may land in one tick: the count reached is at least the limit
    reached = re.search(r"report frame errors reached (\d+) \(limit (\d+)\)", status["reason"])
    assert reached, status["reason"]
    assert int(reached.group(1)) >= ERROR_LIMIT == int(reached.group(2))
    assert outcome.reaction_s is not None
    assert outcome.reaction_s <= ERROR_LIMIT / REPORT_RATE + SLACK
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= MAX_SPEED / DRIVER_DECEL + 2 * SLACK
    assert outcome.frames_missing == 0


@pytest.mark.parametrize(
    ("injection", "fault"),
    [
        ("override-torque@3+1:torque=5", "driver override: steering torque"),
        ("brake-pedal@3+1:pedal_pct=30", "driver override: brake pedal"),
    ],
)
def test_driver_override_hands_back(
    make_run: Callable[..., FaultRun], injection: str, fault: str
) -> None:
    kind = injection.split("@")[0]
    run = make_run(fault, injections=[injection])
    injected, status = _run(run, kind, GatewayState.STANDBY)
    outcome = run.outcome(injected, status=status)
    outcome.report()

    assert status["state"] == "STANDBY"
    assert status["reason"] == "driver override reported by the ECU"
    assert status["ecu_state"] in ("OVERRIDE", "READY")
    changes = [t for t in transitions(run.recording_files()[1]) if t["time"] >= injected - 0.05]
    assert [(t["from"], t["to"]) for t in changes] == [("ENGAGED", "STANDBY")], changes
    assert outcome.reaction_s is not None and outcome.reaction_s <= OVERRIDE_TIME + SLACK
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= OVERRIDE_TIME + MAX_SPEED / DRIVER_DECEL + 2 * SLACK
    _, footer = read_trace(run.trace)
    counters = next(r["counters"] for r in footer if "counters" in r)
    assert counters["overrides"] == 1
    assert outcome.frames_missing == 0
