"""Localization that is old by its own stamps (issue 17, finding 3), across processes.

The simulated localization publishes every pose promptly but stamped 0.4 s in the past. Before,
age was judged by receive time only, so these poses were fresh and the car was engaged (the
closed loop then oscillated to ±28°). Now the header stamp counts as well, beyond the configured
clock offset: the engage is refused, naming the localization's age. (The drift and the second
source are caught by the dead-reckoning check: tests/test_watchdog.py.)
"""

from __future__ import annotations

import time
from collections.abc import Callable

import yaml
from harness import PROCESS_TEST, FaultRun

pytestmark = PROCESS_TEST

LATENCY = 0.4  # s, how old every pose's stamp is when it is published


def test_poses_stamped_400_ms_ago_are_refused_at_engage(
    make_run: Callable[..., FaultRun],
) -> None:
    # Not about the reports: on a loaded machine a starved receive thread loses udp_multicast
    # datagrams, and the skipped counters on six report IDs at once can reach the default error
    # limit (seen once in CI). Relaxed here, as the harness relaxes what a test is not about.
    run = make_run(
        "localization stamped 400 ms ago",
        localization_design_thresholds=True,
        watchdog={"max_report_errors": 50},
    )
    cfg = yaml.safe_load(run.config.read_text())
    cfg["sim"]["localization"]["latency"] = LATENCY
    run.config.write_text(yaml.safe_dump(cfg))
    with run.start():
        run.wait_for("a planned trajectory", lambda: run.status().get("state") is not None, 20)
        replies = []
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            replies.append(run.request("engage"))
            time.sleep(0.3)
        status = run.status()
        run.shutdown()
    assert replies and not any(r.get("accepted") for r in replies), replies
    assert all("localization" in r["reason"] for r in replies[-3:]), replies[-3:]
    assert run.sniffer is not None and run.sniffer.engaged_at is None  # the ECU never engaged
    age = (status.get("watchdogs") or {}).get("localization", {}).get("age")
    assert age is not None and age >= LATENCY - 0.05 - 0.01, status.get("watchdogs")
