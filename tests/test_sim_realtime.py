"""``leafgate sim --realtime``: the daemon's own runtime against the simulated ECU, in process."""

from __future__ import annotations

import numpy as np
import pytest

from leafgate.settings import LeafgateConfig
from leafgate.sim.realtime import run_realtime
from leafgate.sim.scenarios import _forward

pytestmark = pytest.mark.slow


def test_realtime_run_drives_a_short_straight_to_the_end() -> None:
    scenario = _forward("short", "8 m straight at 2 m/s", lambda u: (u, np.zeros_like(u)), 8.0, 2.0)
    outcome = run_realtime(LeafgateConfig(), scenario)
    metrics = outcome["metrics"]
    assert metrics["final_state"] == "STANDBY"
    assert metrics["lateral_error_max_m"] < 0.05
    assert metrics["final_position_error_m"] < 0.2
    assert metrics["localization_published"] > 50  # the pose went through Zenoh
    events = " ".join(e for _, e in outcome["timeline"])
    assert "ENGAGED" in events
