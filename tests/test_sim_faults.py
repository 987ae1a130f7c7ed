"""Fault and driver-action injections in the full simulated loop, as ``leafgate sim --inject``.

Each ends in the state docs/state-machine.md prescribes, with the car at rest, and every command frame the
gateway sent while engaged passes the offline safety check (the same check as
``leafgate replay check``) on a recording of the drive.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from leafgate.record.recorder import open_recording
from leafgate.replay.check import check_log
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import Injection, run
from leafgate.sim.scenarios import get_scenario

pytestmark = pytest.mark.slow

# injection → (final gateway state, the transition that must have happened on the way)
EXPECTED = {
    "localization-dropout@8s": ("FAULT", ("ENGAGED", "STOPPING")),
    "position-jump@7s": ("FAULT", ("ENGAGED", "FAULT")),
    "override@10s": ("STANDBY", ("ENGAGED", "STANDBY")),
    "brake-pedal@10s": ("STANDBY", ("ENGAGED", "STANDBY")),
    "report-dropout@6s": ("FAULT", ("ENGAGED", "FAULT")),
    "corrupt-crc@5s": ("FAULT", ("ENGAGED", "FAULT")),
    "stuck-counter@5s": ("FAULT", ("ENGAGED", "FAULT")),
    "command-dropout@9s": ("FAULT", ("ENGAGED", "FAULT")),
    "foreign-command@5s": ("FAULT", ("ENGAGED", "FAULT")),  # another node on our IDs
    "localization-dropout@8s+0.3": ("STANDBY", ("ENGAGED", "STOPPING")),
}


@pytest.mark.parametrize("text", sorted(EXPECTED))
def test_injection_ends_in_designed_state_at_rest_within_limits(text: str, tmp_path: Path) -> None:
    final_state, transition = EXPECTED[text]
    cfg = LeafgateConfig()
    rec_cfg = dataclasses.replace(
        cfg.recording, enabled=True, directory=str(tmp_path), session=None
    )
    recording = open_recording(rec_cfg, cfg, clock=None, wall_clock=None)
    try:
        result = run(
            cfg, get_scenario("s-curve"), injections=(Injection.parse(text),), recorder=recording
        )
    finally:
        recording.close()
    metrics = result.metrics
    assert metrics["final_state"] == final_state, metrics["transitions"]
    pairs = [(t["from"], t["to"]) for t in metrics["transitions"]]
    assert transition in pairs
    assert abs(result.trace.speed[-1]) < 0.01  # at rest at the end
    (log,) = tmp_path.glob("can-*")
    report = check_log(log, cfg)
    assert report.engaged_frames > 100  # the drive was checked, not an empty log
    assert report.count("limit") == 0, [f.to_dict() for f in report.findings if f.kind == "limit"]


def test_short_localization_dropout_stops_then_standby() -> None:
    """A dropout longer than 100 ms but shorter than 500 ms is a controlled stop, not a fault."""
    result = run(
        LeafgateConfig(),
        get_scenario("s-curve"),
        injections=(Injection.parse("localization-dropout@8s+0.3"),),
    )
    reasons = " ".join(t["reason"] for t in result.metrics["transitions"])
    assert "localization age" in reasons
    assert result.metrics["final_state"] == "STANDBY"


def test_bad_injection_text_names_the_problem() -> None:
    with pytest.raises(Exception, match="unknown kind 'meteor'"):
        Injection.parse("meteor@3s")
    with pytest.raises(Exception, match="expected KIND@TIME"):
        Injection.parse("override-at-ten")
