"""The daemon is SIGKILLed mid-maneuver: the ECU times out and brakes to a stop, and the
recording up to the kill is readable.

Nothing of the daemon runs after SIGKILL — no clean disengage, no file closing. The ECU's command
timeout (docs/can-protocol.md: 100 ms, then −3 m/s² to a stop) is the only reaction. The recorder makes its
files readable every ``flush_period`` (1 s): the BLF's header and last container, and a closed
MCAP chunk; what was sent after the last flush is lost, and reported.
"""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import time
from collections.abc import Callable

from harness import CLI, PROCESS_TEST, ROOT, FaultRun

from leafgate.record.logs import FrameSource
from leafgate.record.recorder import DEFAULT_REORDER_WINDOW
from leafgate.record.session import SessionReader

pytestmark = PROCESS_TEST

SLACK = 0.4  # s, scheduling noise of four processes on two cores
MAX_SPEED = 2.0  # m/s, the s-curve's top speed
CMD_TIMEOUT = 0.1  # s, docs/can-protocol.md, ECU semantics
TIMEOUT_DECEL = 3.0  # m/s², docs/can-protocol.md, ECU semantics
FLUSH_PERIOD = 1.0  # s, recording.flush_period of the run
REORDER_WINDOW = DEFAULT_REORDER_WINDOW  # s, the CAN log writes frames this much later
COMMAND_RATE = 50 + 50 + 10  # command frames per second (steer, long, system)


def replay_check(path: str) -> dict:
    """``leafgate replay check --json``: a report, whatever its findings (exit 0 or 1)."""
    result = subprocess.run(
        [*CLI, "replay", "check", path, "--profile", "leafgate-dbw", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert result.returncode in (0, 1), result.stderr
    return json.loads(result.stdout)


def test_sigkill_mid_maneuver_ecu_stops_and_recording_is_readable(
    make_run: Callable[..., FaultRun],
) -> None:
    run = make_run("daemon SIGKILLed mid-maneuver")
    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("3 s of driving", lambda: run.sniffer_time() >= engaged + 3.0, 15)
        killed = time.perf_counter()
        assert run.stop("gateway", signal.SIGKILL) == -signal.SIGKILL
        sniffer = run.sniffer
        assert sniffer is not None
        run.wait_for(
            "CMD_TIMEOUT from the ECU",
            lambda: sniffer.first_after(sniffer.cmd_timeouts, killed) is not None,
            5,
            alive=("ecu",),
        )
        run.wait_at_rest(None, timeout=15, alive=("ecu",))
        run.shutdown()
    timeout_at = sniffer.first_after(sniffer.cmd_timeouts, killed)

    logs, session = run.recording_files()
    assert logs and session.exists()
    outcome = run.outcome(killed, status=None, ecu_reaction_at=timeout_at)
    outcome.state = "(killed); ECU CMD_TIMEOUT"
    outcome.reason = "ECU command timeout, braking at 3 m/s²"

    # The recording up to the kill reads back: the CAN log …
    source = FrameSource(logs[-1])
    stamps = [msg.timestamp for msg in source]
    frames = len(stamps)
    backwards = sum(1 for a, b in itertools.pairwise(stamps) if b < a)  # the reorder window
    # … the session, cut short before its footer …
    with SessionReader(session) as reader:
        records = sum(1 for _ in reader.records())
        truncated, error = reader.truncated, reader.error
    # … and the offline check reads both to the end.
    checked_log = replay_check(str(logs[-1]))
    checked_session = replay_check(str(session))
    outcome.extra.update(
        {
            "log_frames": frames,
            "log_backwards_timestamps": backwards,
            "session_records": records,
            "session_truncated": truncated,
            "session_error": error,
            "check_findings": [len(checked_log["findings"]), len(checked_session["findings"])],
        }
    )
    outcome.report()

    assert outcome.reaction_s is not None and 0.0 < outcome.reaction_s <= CMD_TIMEOUT + SLACK
    assert outcome.safe_state_s is not None
    assert outcome.safe_state_s <= CMD_TIMEOUT + MAX_SPEED / TIMEOUT_DECEL + 2 * SLACK
    assert frames > 0 and records > 0
    assert backwards == 0  # sent and received frames in time order, even under this load
    assert truncated, "a SIGKILLed recorder cannot have written the MCAP footer"
    # Lost: at most what was sent since the last flush (plus the writer's queue at the kill).
    assert outcome.frames_missing is not None and outcome.frames_missing_session is not None
    # the CAN log also holds back its reorder window
    assert outcome.frames_missing <= (FLUSH_PERIOD + REORDER_WINDOW + SLACK) * COMMAND_RATE
    assert outcome.frames_missing_session <= (FLUSH_PERIOD + SLACK) * COMMAND_RATE
