"""Bus faults across processes: a rogue node on the gateway's command IDs, and a bus whose
sends fail for 200 ms.

python-can's ``udp_multicast`` delivers a bus's own frames back to it (multicast loopback), so
the gateway sees its own command frames here; it must tell them from a rogue's
(``test_fault_units.py`` covers both bus behaviours in-process).
"""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Callable
from pathlib import Path

from harness import PROCESS_TEST, FaultRun, RogueNode, read_trace, recorded_commands

from leafgate.messages import EcuState, GatewayState, LongCommand, SteerCommand

pytestmark = PROCESS_TEST

HERE = Path(__file__).resolve().parent
SLACK = 0.4  # s, scheduling noise of four processes on two cores
MAX_SPEED = 2.0  # m/s, the s-curve's top speed
PERIOD = 0.02  # s, control tick
CMD_TIMEOUT = 0.1  # s, docs/can-protocol.md: no valid command this long → the ECU brakes at 3 m/s²
TIMEOUT_DECEL = 3.0  # m/s²
ROGUE_TIME = 0.5  # s the rogue node sends
OUTAGE = 0.2  # s of failing sends


def test_rogue_command_frames_fault_the_gateway_and_are_rejected_by_the_ecu(
    make_run: Callable[..., FaultRun],
) -> None:
    run = make_run("rogue node sends DBW command frames")
    sniffer_system = None
    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("2 s of driving", lambda: run.sniffer_time() >= engaged + 2.0, 15)
        dbw = run.cfg["can"]["dbw"]
        rogue = RogueNode(dbw["channel"], dbw["kwargs"]["port"], run.excluded)
        rng = random.Random(8)
        injected = time.perf_counter()
        try:
            # Both kinds a rogue could send, every 10 ms: garbage (bad CRC) and well-formed
            # frames with the rogue's own alive counter, trying to steer and accelerate.
            k = 0
            while time.perf_counter() < injected + ROGUE_TIME:
                if k % 2:
                    rogue.send_garbage(0x0A0 if k % 4 == 1 else 0x0A1, rng)
                else:
                    rogue.send_value(SteerCommand(angle=0.3, enable=True))
                    rogue.send_value(LongCommand(accel=1.0, enable=True))
                k += 1
                time.sleep(0.01)  # the rogue's own send rate, not a wait for a condition
        finally:
            rogue.close()
        run.wait_at_rest({GatewayState.FAULT}, timeout=15)
        status = run.status()
        assert run.sniffer is not None
        sniffer_system = run.sniffer.system
        run.shutdown()

    outcome = run.outcome(injected, status=status, reaction_kinds=("FAULT",))
    _, footer = read_trace(run.trace)
    counters = next(r["counters"] for r in footer if "counters" in r)
    outcome.extra.update(
        {
            "rogue_frames": rogue.sent,
            "ecu_rejected_bad_crc": counters["bad_crc"],
            "ecu_rejected_bad_counter": counters["bad_counter"],
            "gateway_own_echoes": status["command_ids"]["own_echoes"],
        }
    )
    outcome.report()

    assert status["state"] == "FAULT"
    assert "command conflict" in status["reason"], status["reason"]
    assert "DBW_STEER_CMD" in status["reason"] or "DBW_LONG_CMD" in status["reason"]
    assert outcome.reaction_s is not None and outcome.reaction_s <= PERIOD + SLACK
    # The ECU dropped and counted the rogue's frames (and ours that its counter broke).
    assert counters["bad_crc"] > 0 and counters["bad_counter"] > 0
    assert sniffer_system is not None and sniffer_system.rx_error_count > 0
    # Our own frames came back (udp_multicast) and were not taken for foreign ones.
    assert status["command_ids"]["own_echoes"] > 0
    assert status["command_ids"]["foreign_frames"] <= rogue.sent
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= PERIOD + MAX_SPEED / TIMEOUT_DECEL + 2 * SLACK + ROGUE_TIME
    assert outcome.frames_missing == 0


def test_send_errors_for_200_ms_fault_then_reset_recovers(
    make_run: Callable[..., FaultRun], tmp_path: Path
) -> None:
    trigger = tmp_path / "sends-fail"
    run = make_run(
        "bus send errors for 200 ms",
        daemon=[str(HERE / "send_error_daemon.py"), str(trigger), "run"],
    )
    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("2 s of driving", lambda: run.sniffer_time() >= engaged + 2.0, 15)
        trigger.touch()
        injected = time.perf_counter()
        run.wait_for("the outage", lambda: run.sniffer_time() >= injected + OUTAGE, 5)
        trigger.unlink()
        sniffer = run.sniffer
        assert sniffer is not None
        run.wait_at_rest({GatewayState.FAULT}, timeout=15)

        reply: dict = {}

        def reset_accepted() -> bool:
            nonlocal reply
            reply = run.request("reset")
            return bool(reply.get("accepted"))

        reset_at = run.wait_for("reset accepted", reset_accepted, 10)
        run.wait_for(
            "STANDBY on DBW_SYSTEM_CMD", lambda: sniffer.gateway_state == GatewayState.STANDBY, 5
        )

        def steer_frames_since_reset() -> int:
            return sum(
                1 for t, m in sniffer.snapshot() if m.arbitration_id == 0x0A0 and t > reset_at
            )

        run.wait_for("command frames flowing again", lambda: steer_frames_since_reset() >= 25, 5)
        run.wait_for(
            "the ECU READY again",
            lambda: sniffer.system is not None and sniffer.system.state == EcuState.READY,
            5,
        )
        status = run.status()
        cmd_timeout_at = sniffer.first_after(sniffer.cmd_timeouts, injected)
        run.shutdown()

    outcome = run.outcome(injected, status=status, reaction_kinds=("FAULT",))
    steer_times = [t for t, m in sniffer.snapshot() if m.arbitration_id == 0x0A0]
    gap = max(b - a for a, b in itertools.pairwise(steer_times))
    logs, _ = run.recording_files()
    not_sent = sum((recorded_commands(logs) - run.gateway_frames_on_bus()).values())
    outcome.extra.update(
        {
            "bus_gap_s": round(gap, 3),
            "ecu_cmd_timeout_s": None
            if cmd_timeout_at is None
            else round(cmd_timeout_at - injected, 3),
            "recorded_not_sent": not_sent,
            "reset_reply": reply.get("reason"),
        }
    )
    outcome.report()

    assert outcome.reaction_s is not None and outcome.reaction_s <= PERIOD + SLACK
    # The ECU saw no command for longer than its timeout: it reported it and braked.
    assert gap >= OUTAGE - 2 * PERIOD
    assert cmd_timeout_at is not None and 0.0 < cmd_timeout_at - injected <= CMD_TIMEOUT + SLACK
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= CMD_TIMEOUT + MAX_SPEED / TIMEOUT_DECEL + 2 * SLACK
    # Recovered: reset accepted, STANDBY, frames flowing, the ECU ready.
    assert status["state"] == "STANDBY"
    assert status["reason"].startswith("reset after:"), status["reason"]
    assert "could not be encoded or sent" in status["reason"]
    assert status["loop"]["send_errors"] > 0
    # Every frame on the bus is in the log; the frames that failed are there too (as attempted).
    assert outcome.frames_missing == 0
    assert not_sent > 0
