"""Report-age FAULTs of the whole stack while two busy loops hog both cores (issue 17, finding 7).

Runs ``--runs`` s-curve maneuvers, each as separate processes (simulated ECU, daemon, planner:
the fault suite's harness), with docs/watchdogs.md's report thresholds (3 periods: 30 ms for
DBW_STEER_RPT) and two ``while True: pass`` processes beside the stack, and counts the runs that
ended in a report-age FAULT. Before the report ages came from the frames' receive timestamps, 11
of 71 such runs faulted. Prints one JSON object; exit status 0 only if no run had a report-age
FAULT. Also reports the runs that ended in a report-error FAULT (counter skips after a
receive stall are lost frames since, not errors), and every ENABLE=1 command frame judged
against the safety limits at the plant's true state (the harness's judgement), and the
machine's load averages before and after (other work shares the machine).

    python tools/report_age_soak.py --runs 20
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "faults"))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # harness imports tests.conftest

import can

try:  # the fault harness runs the tests' helpers: pytest, from the test extra
    from harness import FaultRun, cpu_hogs, transitions
except ModuleNotFoundError as exc:
    if __name__ != "__main__" or (exc.name or "leafgate").startswith(("leafgate", "tests")):
        raise
    print(
        f"report_age_soak.py: needs {exc.name}, from the test extra: pip install -e '.[test]'",
        file=sys.stderr,
    )
    raise SystemExit(2) from None

from leafgate.can import e2e
from leafgate.can.codec import CanCodec
from leafgate.messages import GatewayState

REPORT_FRAMES = {
    "steer_report": "DBW_STEER_RPT",
    "long_report": "DBW_LONG_RPT",
    "system_report": "DBW_SYSTEM_RPT",
}
AGE_FAULT = re.compile(r"(\w+_report) age ([0-9.]+) s > ([0-9.]+) s")


def sent_late(frames: list[tuple[float, can.Message]], reason: str, at: float) -> bool | None:
    """Whether the bus itself shows the report-age FAULT: in the second before ``at``
    (perf_counter), the ECU sent no frame of the report for longer than the limit, by the
    sniffer's kernel receive timestamps, its alive counter advancing by one across that gap (so
    the sniffer lost nothing there). True: the simulated ECU's process was starved and the
    report really was late (a true FAULT); False: every gap on the bus was within the limit,
    the gateway judged a report stale that had come in time; None: not a report-age FAULT, or
    the sniffer lost frames in a gap over the limit.
    """
    match = AGE_FAULT.search(reason)
    if match is None:
        return None
    frame_id = CanCodec(profile="leafgate-dbw").frame_id(REPORT_FRAMES[match.group(1)])
    limit = float(match.group(3))
    mine = [(t, m) for t, m in frames if m.arbitration_id == frame_id and m.timestamp > 0]
    if len(mine) < 2:
        return None
    offset = min(t - m.timestamp for t, m in mine)  # kernel epoch → perf_counter (least lag)
    ordered = sorted((m for _, m in mine), key=lambda m: m.timestamp)
    near = [m for m in ordered if at - 1.0 <= m.timestamp + offset <= at + 1.0]
    verdict: bool | None = False
    for a, b in itertools.pairwise(near):
        if a.timestamp + offset > at or b.timestamp - a.timestamp <= limit:
            continue  # after the FAULT, or within the limit
        if (b.data[e2e.COUNTER_BYTE] - a.data[e2e.COUNTER_BYTE]) & 0x0F == 1:
            return True  # nothing sent for longer than the limit: the ECU was late
        verdict = None  # the sniffer lost frames in this gap: cannot tell
    return verdict


def one_run(directory: Path) -> dict[str, Any]:
    """One maneuver to its end (or a fault); what ended it."""
    run = FaultRun(directory, "report age under CPU load", report_design_thresholds=True)
    with run:
        run.start()
        run.engage()
        engaged = run.wait_engaged(timeout=20)
        sniffer = run.sniffer
        assert sniffer is not None
        # The ECU reports ENABLED before the next DBW_SYSTEM_CMD (every 100 ms) says ENGAGED: the
        # car, still at rest then, would look done (the runs ended before they drove).
        run.wait_for(
            "ENGAGED on DBW_SYSTEM_CMD",
            lambda: sniffer.gateway_state is not GatewayState.STANDBY,
            5,
        )
        with cpu_hogs(2):
            run.wait_at_rest({GatewayState.STANDBY, GatewayState.FAULT}, timeout=60, hold=1.0)
        status = run.status()
        run.shutdown()
        changes = [t for t in transitions(run.recording_files()[1]) if t["time"] >= engaged]
        outcome = run.outcome(None, status=status)  # the commands judged on the true state
        frames = sniffer.snapshot()
    faults = [t["reason"] for t in changes if t["to"] == "FAULT"]
    ecu_late = [sent_late(frames, t["reason"], t["time"]) for t in changes if t["to"] == "FAULT"]
    return {
        "ended": changes[-1]["to"] if changes else None,
        "reason": changes[-1]["reason"] if changes else None,
        "driven_s": round(changes[-1]["time"] - engaged, 2) if changes else None,
        "faults": faults,
        "report_age_fault": any("report age" in r for r in faults),
        # per FAULT: the ECU really sent late (the bus shows the gap), or not (None: no verdict)
        "ecu_sent_late": ecu_late,
        "report_error_fault": any("report frame errors" in r for r in faults),
        # counter skips the receiver took as frames lost in a receive stall (not errors)
        "can_stall_skips": status.get("can_stall_skips"),
        "commands_checked": outcome.extra.get("commands_checked"),
        "commands_outside_limits": outcome.extra.get("commands_outside_limits"),
        "startup_resets": run.startup_resets,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20, help="maneuvers (default 20)")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    results = []
    started = time.monotonic()
    load_before = os.getloadavg()  # other work on the machine, besides the two busy loops
    with tempfile.TemporaryDirectory(prefix="leafgate-age-") as tmp:
        for k in range(args.runs):
            directory = Path(tmp) / f"run{k:02d}"
            directory.mkdir()
            try:
                results.append(one_run(directory))
            except AssertionError as exc:  # the harness's "timed out waiting for …"
                results.append({"error": str(exc).splitlines()[0]})
    age_faults = sum(1 for r in results if r.get("report_age_fault"))
    verdicts = [v for r in results for v in r.get("ecu_sent_late", ())]
    print(
        json.dumps(
            {
                "runs": len(results),
                "report_age_faults": age_faults,
                "other_faults": sum(
                    1 for r in results if r.get("faults") and not r.get("report_age_fault")
                ),
                "runs_not_completed": sum(1 for r in results if "error" in r),
                "report_error_faults": sum(1 for r in results if r.get("report_error_fault")),
                # report-age FAULTs whose gap the bus itself shows (the simulated ECU's process
                # was starved and sent late: a true FAULT), and those it does not (the gateway
                # judged a report stale that had arrived in time: a false one)
                "report_age_faults_ecu_late": verdicts.count(True),
                "report_age_faults_not_late_on_bus": verdicts.count(False),
                "commands_checked": sum(r.get("commands_checked") or 0 for r in results),
                "commands_outside_limits": sum(
                    r.get("commands_outside_limits") or 0 for r in results
                ),
                "cpus": os.cpu_count(),
                "loadavg_1_5_15_before": [round(x, 2) for x in load_before],
                "loadavg_1_5_15_after": [round(x, 2) for x in os.getloadavg()],
                "wall_s": round(time.monotonic() - started, 1),
                "results": results,
            },
            indent=1,
        )
    )
    return 0 if age_faults == 0 and not any("error" in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
