"""A stop signal while ENGAGED: the controlled stop, whichever signal it is.

SIGHUP comes when the terminal or ssh session that started the daemon as a shell job (README
section 2) closes; its default action killed the daemon mid-maneuver (status 129, no ENABLE=0
frame, no log line, the recording without its end marker). SIGTERM is systemd's stop.
"""

from __future__ import annotations

import signal
from collections.abc import Callable

import pytest
from harness import PROCESS_TEST, FaultRun, transitions

from leafgate.can.codec import CanCodec
from leafgate.messages import SteerCommand
from leafgate.record.logs import FrameSource

pytestmark = PROCESS_TEST


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGTERM], ids=lambda s: s.name)
def test_stop_signal_while_engaged_disengages_and_closes_the_recording(
    make_run: Callable[..., FaultRun], sig: signal.Signals
) -> None:
    run = make_run(f"daemon {sig.name} mid-maneuver")
    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("1 s of driving", lambda: run.sniffer_time() >= engaged + 1.0, 15)
        assert run.stop("gateway", sig) == 0, run.logs_tail()
        sniffer = run.sniffer
        assert sniffer is not None
        frames = sniffer.snapshot()
        run.shutdown()

    codec = CanCodec(profile="leafgate-dbw")
    steer = [
        value
        for _, msg in frames
        if msg.arbitration_id == 0x0A0
        and isinstance(value := codec.decode(msg).value, SteerCommand)
    ]
    assert steer and steer[-1].enable is False, steer[-3:]  # ENABLE=0, not a silent bus

    reason = f"{sig.name} received"
    gateway_log = run.log("gateway")
    assert f"{reason}: disengaging" in gateway_log
    assert f"state ENGAGED → STANDBY: {reason}" in gateway_log, gateway_log[-2000:]

    logs, session = run.recording_files()
    last = [t for t in transitions(session) if t["from"] == "ENGAGED"][-1]
    assert (last["to"], last["reason"]) == ("STANDBY", reason)
    source = FrameSource(logs[-1])
    assert sum(1 for _ in source) > 0
    assert source.ended and not source.continues, "the CAN log has no end-of-recording marker"
