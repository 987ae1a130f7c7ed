"""The soak script's pure helpers (``tools/soak.py``): no processes, no long runs."""

from __future__ import annotations

import importlib.util
import itertools
import math
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from leafgate.messages import Pose
from leafgate.sim.scenarios import get_scenario

ROOT = Path(__file__).resolve().parent.parent


def _load_soak() -> ModuleType:
    sys.path.insert(
        0, str(ROOT / "tools")
    )  # soak imports tools/_common.py, as when run as a script
    spec = importlib.util.spec_from_file_location("soak", ROOT / "tools" / "soak.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["soak"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


soak = _load_soak()

TRAJECTORIES = {name: get_scenario(name).trajectory for name in ("s-curve", "slalom", "straight")}
angles = st.floats(-math.pi, math.pi)
coordinates = st.floats(-5000.0, 5000.0)


@given(x=coordinates, y=coordinates, heading=angles, name=st.sampled_from(["s-curve", "slalom"]))
def test_moved_trajectory_starts_at_the_pose_with_its_heading(
    x: float, y: float, heading: float, name: str
) -> None:
    trajectory = TRAJECTORIES[name]
    moved = soak.start_at(trajectory, Pose(x, y, heading, 0.0))
    assert moved.x[0] == pytest.approx(x, abs=1e-9)
    assert moved.y[0] == pytest.approx(y, abs=1e-9)
    assert math.remainder(moved.heading[0] - heading, math.tau) == pytest.approx(0.0, abs=1e-12)


@given(x=coordinates, y=coordinates, heading=angles)
def test_moved_trajectory_keeps_its_shape_and_speeds(x: float, y: float, heading: float) -> None:
    trajectory = TRAJECTORIES["s-curve"]
    moved = soak.start_at(trajectory, Pose(x, y, heading, 0.0))
    spacing = np.hypot(np.diff(trajectory.x), np.diff(trajectory.y))
    moved_spacing = np.hypot(np.diff(moved.x), np.diff(moved.y))
    np.testing.assert_allclose(moved_spacing, spacing, atol=1e-9)
    np.testing.assert_allclose(np.diff(moved.heading), np.diff(trajectory.heading), atol=1e-12)
    np.testing.assert_array_equal(moved.speed, trajectory.speed)
    # The heading still points along the path (the rotation turned both together).
    tangent = np.arctan2(np.diff(moved.y[:2]), np.diff(moved.x[:2]))[0]
    assert math.remainder(tangent - moved.heading[0], math.tau) == pytest.approx(0.0, abs=1e-3)


def test_moved_trajectory_turned_a_quarter_goes_left() -> None:
    trajectory = TRAJECTORIES["straight"]  # along +x from (0, 0)
    moved = soak.start_at(trajectory, Pose(10.0, 20.0, math.pi / 2, 0.0))
    length = float(trajectory.x[-1] - trajectory.x[0])
    assert moved.x[-1] == pytest.approx(10.0, abs=1e-9)
    assert moved.y[-1] == pytest.approx(20.0 + length, abs=1e-9)


def frames(counters: list[int], period: float = 0.02) -> list[tuple[bytes, float]]:
    return [
        (bytes([0, 0, 0, 0, 0, 0, 0xA0 | (c % 16), 0]), i * period) for i, c in enumerate(counters)
    ]


def test_counter_gaps_count_lost_frames_across_the_wrap() -> None:
    gaps = soak.CounterGaps()
    for data, t in frames([13, 14, 15, 0, 3, 4]):  # 1 and 2 missing after the wrap
        gaps.feed(0x0A0, data, t)
    assert gaps.frames[0x0A0] == 6
    assert gaps.lost[0x0A0] == 2
    assert gaps.repeated[0x0A0] == 0


def test_counter_gaps_count_a_repeated_counter_not_as_loss() -> None:
    gaps = soak.CounterGaps()
    for data, t in frames([5, 6, 6, 7]):
        gaps.feed(0x0A1, data, t)
    assert gaps.lost[0x0A1] == 0
    assert gaps.repeated[0x0A1] == 1


def test_counter_gaps_keep_ids_apart_and_report_silences() -> None:
    gaps = soak.CounterGaps(silence=0.5)
    gaps.feed(0x0A0, frames([1])[0][0], 0.0)
    gaps.feed(0x0A1, frames([9])[0][0], 0.01)
    gaps.feed(0x0A0, frames([2])[0][0], 0.02)
    gaps.feed(0x0A1, frames([10])[0][0], 1.0)  # in sequence, but after a second of silence
    assert gaps.lost == {}
    assert gaps.silences[0x0A1] == 1 and gaps.silences[0x0A0] == 0
    assert gaps.summary([0x0A1, 0x0A0])["0x0A1"] == {
        "frames": 2,
        "lost": 0,
        "repeated": 0,
        "silences": 1,
    }


def test_counter_gaps_ignore_frames_without_a_counter_byte() -> None:
    gaps = soak.CounterGaps()
    gaps.feed(0x002, b"\x01\x02", 0.0)
    assert gaps.frames[0x002] == 0


@given(st.lists(st.integers(0, 15), min_size=2, max_size=200))
def test_counter_gaps_lost_is_the_sum_of_the_steps(counters: list[int]) -> None:
    gaps = soak.CounterGaps()
    for data, t in frames(counters):
        gaps.feed(0x0A0, data, t)
    steps = [(b - a) % 16 for a, b in itertools.pairwise(counters)]
    assert gaps.lost[0x0A0] == sum(s - 1 for s in steps if s)
    assert gaps.repeated[0x0A0] == steps.count(0)


def test_reason_kind_drops_the_measured_value_only() -> None:
    assert soak.reason_kind("FAULT: steer_report age 0.037 s > 0.03 s") == (
        "FAULT: steer_report age … s > 0.03 s"
    )
    assert soak.reason_kind("localization jumped 2.10 m > 1 m in one sample") == (
        "localization jumped … m > 1 m in one sample"
    )
    assert soak.reason_kind("trajectory end reached") == "trajectory end reached"


def test_loop_figures_take_the_worst_window_and_the_latest_totals() -> None:
    windows = [
        {"compute_median_s": 0.001, "compute_p99_s": 0.004, "compute_max_s": 0.010},
        {"compute_median_s": 0.003, "compute_p99_s": 0.002, "compute_max_s": None},
        {"compute_median_s": 0.002, "compute_p99_s": 0.003, "compute_max_s": 0.020},
    ]
    last = {"ticks": 9000, "overruns": 2, "skipped_ticks": 1}
    figures = soak.loop_figures(windows, last)
    assert figures["compute_p50_s"] == pytest.approx(0.002)
    assert figures["compute_p99_s"] == pytest.approx(0.004)
    assert figures["compute_max_s"] == pytest.approx(0.020)
    assert (figures["ticks"], figures["overruns"], figures["deadline_misses"]) == (9000, 2, 1)


def _report(overruns: int, start_mb: float, end_mb: float, maneuvers: list) -> dict:
    memory = {"gateway": soak.MemoryTrack(), "ecu": soak.MemoryTrack()}
    memory["gateway"].add(start_mb - 5.0, after_warmup=False)  # warm-up: not the baseline
    memory["gateway"].add(start_mb, after_warmup=True)
    memory["gateway"].add(end_mb, after_warmup=True)
    gaps = soak.CounterGaps()
    for data, t in frames([0, 1, 4]):
        gaps.feed(0x0A0, data, t)
    return soak.assemble_report(
        duration=60.0,
        maneuvers=maneuvers,
        refusals={"steer_report age 0.04 s > 0.03 s": 1, "steer_report age 0.05 s > 0.03 s": 2},
        loop=soak.loop_figures([], {"ticks": 3000, "overruns": overruns, "skipped_ticks": 0}),
        memory=memory,
        gaps=gaps,
        command_ids=[0x0A0, 0x0A1],
        report_ids=[0x0B0],
        ecu={"rx_error_count_max": 0},
        final={"died": []},
        max_growth_mb=20.0,
    )


def test_report_passes_with_no_overrun_small_growth_and_a_completed_maneuver() -> None:
    done = [soak.Maneuver("s-curve", "completed", "trajectory end reached", 20.0)]
    report = _report(overruns=0, start_mb=100.0, end_mb=110.0, maneuvers=done)
    assert report["passed"], report["goals"]
    assert report["memory"]["gateway"] == {
        "start_mb": 100.0,
        "end_mb": 110.0,
        "max_mb": 110.0,
        "growth_mb": 10.0,
    }
    assert report["frames"]["commands_lost"] == 2
    assert report["maneuvers"]["engage_refusals"] == {"steer_report age … s > 0.03 s": 3}


@pytest.mark.parametrize(
    ("overruns", "end_mb", "outcome", "missed"),
    [
        (1, 110.0, "completed", "zero_overruns"),
        (0, 120.5, "completed", "memory_growth_under_20_mb"),
        (0, 110.0, "aborted", "maneuvers_completed"),
    ],
)
def test_report_fails_on_each_missed_goal(
    overruns: int, end_mb: float, outcome: str, missed: str
) -> None:
    maneuvers = [soak.Maneuver("slalom", outcome, "FAULT: x", 5.0)]
    report = _report(overruns=overruns, start_mb=100.0, end_mb=end_mb, maneuvers=maneuvers)
    assert not report["passed"]
    assert [name for name, ok in report["goals"].items() if not ok] == [missed]


def test_aborts_are_counted_by_reason_kind() -> None:
    maneuvers = [
        soak.Maneuver("s-curve", "aborted", "FAULT: steer_report age 0.037 s > 0.03 s", 3.0),
        soak.Maneuver("slalom", "aborted", "FAULT: steer_report age 0.045 s > 0.03 s", 4.0),
        soak.Maneuver("s-curve", "completed", "trajectory end reached", 20.0),
        soak.Maneuver("straight", "interrupted", "the soak ended", 2.0),
    ]
    report = _report(overruns=0, start_mb=100.0, end_mb=100.0, maneuvers=maneuvers)
    m = report["maneuvers"]
    assert (m["completed"], m["aborted"], m["interrupted"]) == (1, 2, 1)
    assert m["abort_reasons"] == {"FAULT: steer_report age … s > 0.03 s": 2}
    assert m["by_scenario"]["s-curve"] == {"aborted": 1, "completed": 1}


def test_ecu_log_figures_read_the_closing_line() -> None:
    line = (
        "INFO leafgate.sim.realtime: simulated ECU stopped: 87350 ticks, 42000 frames sent, "
        "12797 received, 1453 overruns; 0 command frames rejected"
    )
    assert soak.ecu_log_figures(line) == {"ticks": 87350, "overruns": 1453}
    assert soak.ecu_log_figures("no such line") == {}
