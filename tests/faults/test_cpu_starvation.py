"""CPU starvation: two busy-loop processes hog both cores while the maneuver runs, and the
localization publisher stops 3 s into it. The loop reports its lateness, and the watchdogs still
act — the localization watchdog, or the overrun watchdog first when the starved loop falls three
ticks behind (docs/watchdogs.md's thresholds for both here).

Whether the loop overruns under this load depends on the scheduler, so the counters are
asserted to be reported, not to be non-zero; their values go into the results table.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from harness import PROCESS_TEST, FaultRun, cpu_hogs, transitions

from leafgate.messages import GatewayState

pytestmark = PROCESS_TEST

FAULT_AGE = 0.5  # s, docs/watchdogs.md: localization older than this → FAULT
STARVED_SLACK = 1.5  # s, what two busy loops on two cores may add to any reaction
MAX_SPEED = 2.0  # m/s, the s-curve's top speed
LOOP_FIGURES = ("ticks", "overruns", "skipped_ticks", "start_lateness_p99_s", "compute_p99_s")


def test_watchdogs_act_while_two_processes_hog_both_cores(
    make_run: Callable[..., FaultRun],
) -> None:
    run = make_run(
        "CPU starvation (2 busy loops) + localization stops",
        injections=["localization-stop@3"],
        localization_design_thresholds=True,
        overrun_design_threshold=True,
    )
    with run.start():
        run.engage()
        run.wait_engaged()
        hogs_at = time.perf_counter()
        with cpu_hogs(2):
            run.wait_at_rest({GatewayState.FAULT}, timeout=25)
            status = run.status()
        run.shutdown()
    # The fault begins with the hogs; when the first reaction came after the localization stop,
    # that stop is the fault the times are measured from. A reaction before it (the overrun
    # watchdog) is one of the reactions under test, not a run that failed early.
    stopped = run.injection_started("localization-stop")
    reactions = [
        t
        for t in transitions(run.recording_files()[1])
        if t["to"] in ("STOPPING", "FAULT") and t["time"] > hogs_at
    ]
    after_stop = stopped is not None and reactions and reactions[0]["time"] >= stopped - 0.05
    outcome = run.outcome(stopped if after_stop else hogs_at, status=status)
    loop = status.get("loop", {})
    outcome.extra.update({f"loop_{k}": loop.get(k) for k in LOOP_FIGURES})
    outcome.extra["measured_from"] = "localization stop" if after_stop else "hogs start"
    outcome.report()

    for name in LOOP_FIGURES:  # the loop reports its timing
        assert name in loop, name
    assert isinstance(loop["overruns"], int) and isinstance(loop["skipped_ticks"], int)
    assert status["state"] == "FAULT"
    assert "localization" in status["reason"] or "overran" in status["reason"], status["reason"]
    assert reactions, "no STOPPING or FAULT recorded"
    if after_stop:
        assert outcome.reaction_s is not None and outcome.reaction_s <= FAULT_AGE + STARVED_SLACK
    assert outcome.safe_state_s is not None
    assert outcome.frames_missing == 0
