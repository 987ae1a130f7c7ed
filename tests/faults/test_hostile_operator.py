"""Hostile operator requests (issue 17, findings 1 and 9), against the real daemon.

A flood of ``engage`` queries on ``gateway/engage`` while the car drives, then an operator's
``disengage``. Before: requests were served one at a time from an unbounded queue, so the
disengage came 18.9 s late and a stale queued engage re-engaged the car 0.12 s after it. Now a
stop has its own lane and overtakes what is queued; the queued engages are superseded, and an
engage older than the transport's age bound is dropped, so nothing engages afterwards. The same
run checks the strict parsing: a wildcard ``reset`` and a shouted ``ENGAGE`` are refused.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable

from harness import PROCESS_TEST, FaultRun, transitions

from leafgate.messages import GatewayState
from leafgate.transport import keys

pytestmark = PROCESS_TEST

FLOOD = 1.0  # s of engage queries before the disengage
AFTER = 2.0  # s watched after the disengage for a late engage
ANSWER_LIMIT = 1.0  # s, the operator's disengage must be answered within this (before: timeout)


def test_disengage_overtakes_an_engage_flood_and_nothing_engages_after_it(
    make_run: Callable[..., FaultRun],
) -> None:
    run = make_run("engage flood, then disengage")
    stop = threading.Event()
    sent = [0]
    with run.start():
        run.engage()
        engaged = run.wait_engaged()
        run.wait_for("1 s of driving", lambda: run.sniffer_time() >= engaged + 1.0, 15)
        session = run.zenoh()
        key = run.zcfg.key(keys.ENGAGE)
        pending = []

        def flood() -> None:
            while not stop.is_set():
                pending.append(session.get(key, payload=b"engage", timeout=5.0))
                sent[0] += 1
                stop.wait(0.001)

        thread = threading.Thread(target=flood, daemon=True)
        thread.start()
        stop.wait(FLOOD)
        stop.set()
        thread.join(timeout=2)
        asked = run.sniffer_time()
        reply = run.request("disengage", timeout=3.0)
        answered = run.sniffer_time() - asked
        # wildcard and sloppy words never act
        wildcard = [
            json.loads(r.ok.payload.to_bytes())
            for r in session.get(f"{run.zcfg.prefix}/**", payload=b"reset", timeout=2.0)
            if r.ok is not None
        ]
        shouted = run.request("ENGAGE")
        run.wait_for("the watch period", lambda: run.sniffer_time() >= asked + AFTER, 10)
        status = run.status()
        run.shutdown()

    outcome = run.outcome(asked, status=status, reaction_kinds=("STOPPING", "STANDBY"))
    outcome.extra.update(engage_queries=sent[0], disengage_answered_s=round(answered, 3))
    outcome.report()
    assert reply.get("accepted") is True, reply
    assert answered <= ANSWER_LIMIT
    changes = [t for t in transitions(run.recording_files()[1]) if t["time"] >= asked - 0.05]
    assert changes and changes[0]["to"] in ("STOPPING", "STANDBY"), changes
    assert "ENGAGED" not in [t["to"] for t in changes], changes  # no stale engage ran later
    assert status["state"] in (GatewayState.STOPPING.name, GatewayState.STANDBY.name)
    assert wildcard and all(not r["accepted"] for r in wildcard), wildcard
    assert shouted["accepted"] is False and "unknown request" in shouted["reason"]
