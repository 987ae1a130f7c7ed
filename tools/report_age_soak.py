"""Report-age FAULTs of the whole stack while two busy loops hog both cores (issue 17, finding 7).

Runs ``--runs`` s-curve maneuvers, each as separate processes (simulated ECU, daemon, planner:
the fault suite's harness), with docs/watchdogs.md's report thresholds (3 periods: 30 ms for
DBW_STEER_RPT) and two ``while True: pass`` processes beside the stack, and counts the runs that
ended in a report-age FAULT. Before the report ages came from the frames' receive timestamps, 11
of 71 such runs faulted. Prints one JSON object; exit status 0 only if no run had a report-age
FAULT.

    python tools/report_age_soak.py --runs 20
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "faults"))

from harness import FaultRun, cpu_hogs, transitions

from leafgate.messages import GatewayState


def one_run(directory: Path) -> dict[str, Any]:
    """One maneuver to its end (or a fault); what ended it."""
    run = FaultRun(directory, "report age under CPU load", report_design_thresholds=True)
    with run:
        run.start()
        run.engage()
        engaged = run.wait_engaged(timeout=20)
        with cpu_hogs(2):
            run.wait_at_rest({GatewayState.STANDBY, GatewayState.FAULT}, timeout=60, hold=1.0)
        run.shutdown()
        changes = [t for t in transitions(run.recording_files()[1]) if t["time"] >= engaged]
    faults = [t["reason"] for t in changes if t["to"] == "FAULT"]
    return {
        "ended": changes[-1]["to"] if changes else None,
        "faults": faults,
        "report_age_fault": any("report age" in r for r in faults),
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
    with tempfile.TemporaryDirectory(prefix="leafgate-age-") as tmp:
        for k in range(args.runs):
            directory = Path(tmp) / f"run{k:02d}"
            directory.mkdir()
            try:
                results.append(one_run(directory))
            except AssertionError as exc:  # the harness's "timed out waiting for …"
                results.append({"error": str(exc).splitlines()[0]})
    age_faults = sum(1 for r in results if r.get("report_age_fault"))
    print(
        json.dumps(
            {
                "runs": len(results),
                "report_age_faults": age_faults,
                "other_faults": sum(
                    1 for r in results if r.get("faults") and not r.get("report_age_fault")
                ),
                "runs_not_completed": sum(1 for r in results if "error" in r),
                "wall_s": round(time.monotonic() - started, 1),
                "results": results,
            },
            indent=1,
        )
    )
    return 0 if age_faults == 0 and not any("error" in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
