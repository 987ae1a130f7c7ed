"""A recorder whose writer falls behind drops frames: the tools say the recorder lost them, and
never blame the bus (a silence, gaps, E2E counter errors) for the hole.

One s-curve drive is recorded once per module into a BLF log and a session while both writers
are stalled from 8.0 s to 8.5 s of simulated time with room for ``ROOM`` items in their queues:
every item after that is dropped until the stall ends. The simulation runs on one thread and
each writer has caught up before the stall begins and after it ends, so which items are
dropped does not depend on timing.
"""

from __future__ import annotations

import io
import itertools
import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from leafgate.gateway.core import GatewayInputs, StepResult
from leafgate.record.logs import ChainedSource, drop_marker, is_recorder_marker
from leafgate.record.recorder import CanLogRecorder, Recording, SessionRecorder
from leafgate.record.session import (
    TOPIC_LOST,
    TOPIC_TICK,
    LostItems,
    SessionReader,
    TickContinuity,
)
from leafgate.replay.check import check_log, main_check
from leafgate.replay.decode import AFTER_RECORDER_LOSS, decode_log
from leafgate.replay.plot import main_plot
from leafgate.replay.rerun import main_rerun, rerun_session
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario
from tests.conftest import wait_for

EPOCH = 1.8e9  # s: simulated time 0 in Unix time
STALL_FROM, STALL_UNTIL = 8.0, 8.5  # s of simulated time the writers are stalled
ROOM = 100  # items each queue takes during the stall
INPUT_KEY = "/localization/kinematic_state"


class _Stalled:
    """One recorder's writer, stalled on its first item from the stall's start on."""

    def __init__(self, recorder: CanLogRecorder | SessionRecorder) -> None:
        self.bg = recorder._bg
        self.puts = 0
        self.stalling = False
        self.entered = threading.Event()
        self.gate = threading.Event()
        put, write = self.bg.put, self.bg._write

        def counted_put(item: Any) -> None:
            self.puts += 1
            put(item)

        def gated_write(item: Any) -> int:
            if self.stalling:
                self.entered.set()
                self.gate.wait(30.0)
            return write(item)

        self.bg.put = counted_put  # type: ignore[method-assign]
        self.bg._write = gated_write

    def caught_up(self) -> bool:
        """Every item handed in is written or dropped (the writer holds none)."""
        return self.bg.written + self.bg.dropped == self.puts


class _StalledRecording(Recording):
    def __init__(self, recorders: list[Any]) -> None:
        super().__init__(recorders)
        self.writers = [_Stalled(r) for r in recorders]
        self.phase = "before"

    def on_tick(self, now: float, inputs: GatewayInputs, result: StepResult, frames: Any) -> None:
        # a Zenoh input per tick, as the daemon's localization sample would be
        super().on_zenoh_input(INPUT_KEY, b'{"x": 0.0}', now)
        if self.phase == "before" and now >= STALL_FROM:
            assert wait_for(lambda: all(w.caught_up() for w in self.writers))
            for w in self.writers:
                w.bg._queue.maxsize = ROOM
                w.stalling = True
            super().on_tick(now, inputs, result, frames)
            assert wait_for(lambda: all(w.entered.is_set() for w in self.writers))
            self.phase = "stalled"
            return
        if self.phase == "stalled" and now >= STALL_UNTIL:
            for w in self.writers:
                w.stalling = False
                w.gate.set()
            assert wait_for(lambda: all(w.caught_up() for w in self.writers))
            for w in self.writers:
                w.bg._queue.maxsize = 20_000
            self.phase = "after"
        super().on_tick(now, inputs, result, frames)


@dataclass(frozen=True)
class Overflow:
    log: Path
    session: Path
    diagnostics: dict[str, dict[str, Any]]


@pytest.fixture(scope="module")
def overflow(tmp_path_factory: pytest.TempPathFactory) -> Overflow:
    directory = tmp_path_factory.mktemp("overflow")
    config = LeafgateConfig()
    log = CanLogRecorder(directory / "can.blf", time_offset=EPOCH)
    session = SessionRecorder(directory / "session.mcap", config, epoch=EPOCH)
    with _StalledRecording([log, session]) as recording:
        run(config, get_scenario("s-curve"), recorder=recording)
    assert recording.phase == "after"
    (path,) = log.files
    return Overflow(
        path, session.path, {"can_log": log.diagnostics(), "session": session.diagnostics()}
    )


def _findings(report: dict[str, Any], kind: str) -> list[dict[str, Any]]:
    return [f for f in report["findings"] if f["kind"] == kind]


@pytest.mark.parametrize("which", ["log", "session"])
def test_the_recorder_marks_the_frames_it_dropped_where_it_dropped_them(
    overflow: Overflow, which: str
) -> None:
    """Old code counted the drops in diagnostics only: the file held a hole and nothing else."""
    diagnostics = overflow.diagnostics["can_log" if which == "log" else "session"]
    assert diagnostics["fault"] == "" and diagnostics["recoveries"] == 0  # nothing failed
    assert diagnostics["overflowed"] > 50, diagnostics
    source = ChainedSource([getattr(overflow, which)])
    frames = list(source)
    assert not any(is_recorder_marker(m) for m in frames)  # never a frame of the drive
    assert source.drops, "no drop marker"
    assert sum(d.frames for d in source.drops) == diagnostics["overflowed"]
    start = min(d.start for d in source.drops) - EPOCH
    end = max(d.end for d in source.drops) - EPOCH
    assert start >= STALL_FROM and end <= STALL_UNTIL + 0.03, (start, end)
    # nothing recorded inside a stretch the marker covers but what was queued before the drops
    inside = [m for m in frames if source.drops[0].start < m.timestamp < source.drops[-1].end]
    assert len(inside) < ROOM


@pytest.mark.parametrize("which", ["log", "session"])
def test_a_hole_the_recorder_made_is_its_loss_not_a_silent_bus_or_e2e_errors(
    overflow: Overflow, which: str
) -> None:
    """Old code: 'the whole bus silent for 4xx ms', gaps of every ID and a bad_counter per ID
    after the hole, and not a word of the recorder. The bus was busy; the recorder dropped the
    frames. The check still FAILS: it did not see those frames."""
    out = io.StringIO()
    code = main_check([getattr(overflow, which)], profile="leafgate-dbw", as_json=True, out=out)
    assert code == 1  # the hole is a finding: the check cannot claim it saw everything
    report = json.loads(out.getvalue())
    for kind in ("silence", "gap", "e2e"):
        assert not _findings(report, kind), _findings(report, kind)
    (dropped,) = _findings(report, "incomplete")
    diagnostics = overflow.diagnostics["can_log" if which == "log" else "session"]
    n = diagnostics["overflowed"]
    assert f"the recorder dropped {n} frames" in dropped["detail"], dropped["detail"]
    assert "queue overflowed" in dropped["detail"] and "not the bus" in dropped["detail"]
    assert report["recorder_dropped_frames"] == n
    assert report["engaged_command_frames"] > 1500  # both sides of the hole were checked
    text = io.StringIO()
    main_check([getattr(overflow, which)], profile="leafgate-dbw", out=text)
    verdict = text.getvalue().strip().splitlines()[-1]
    assert verdict.startswith("FAILED") and "0 bus silences" in verdict, verdict
    assert "1 incomplete finding" in verdict and "0 E2E errors" in verdict, verdict


@pytest.mark.parametrize("which", ["log", "session"])
def test_decode_does_not_call_the_counter_after_the_recorders_loss_a_bus_error(
    overflow: Overflow, which: str
) -> None:
    """Old code: a ``bad_counter`` line for each ID's first frame after the hole, and as many
    in the summary's bad_cnt column."""
    out = io.StringIO()
    decode_log(getattr(overflow, which), out, profile="leafgate-dbw")
    lines = out.getvalue().splitlines()
    frames = [line for line in lines if not line.startswith("#")]
    assert not [line for line in frames if line.endswith("bad_counter")]
    after = [line for line in frames if line.endswith(AFTER_RECORDER_LOSS)]
    assert len(after) >= 3, "the first frame of each counted ID after the hole"
    summary = [line for line in lines if line.startswith("#")]
    total = next(line for line in summary if line.split()[1] == "total").split()
    assert total[4] == "0", total  # bad_cnt
    assert (
        f"the recorder dropped {overflow.diagnostics['can_log' if which == 'log' else 'session']['overflowed']} frames"
        in summary[0]
    )
    assert any(f"{len(after)} counter skips across frames the recorder lost" in s for s in summary)


def test_a_frame_lost_beside_the_recorders_loss_but_not_across_it_is_still_the_buses(
    overflow: Overflow, tmp_path: Path
) -> None:
    """The recorder's loss excuses what lies inside it only: a frame missing from the bus four
    seconds later is a gap of its ID (its counter skip part of it), as before."""
    source = ChainedSource([overflow.log])
    frames = list(source)
    lost = next(
        k for k, m in enumerate(frames) if m.timestamp > EPOCH + 12.0 and m.arbitration_id == 0x0A0
    )
    markers = [drop_marker(d.start, d.end, d.frames, 0) for d in source.drops]
    path = tmp_path / "can_000.blf"
    writer = can.BLFWriter(str(path))
    kept = [m for k, m in enumerate(frames) if k != lost]
    for m in sorted(kept + markers, key=lambda m: m.timestamp):
        writer.on_message_received(m)
    writer.stop()
    report = check_log(path, profile="leafgate-dbw").to_dict()
    assert not _findings(report, "silence") and not _findings(report, "e2e")
    (gap,) = _findings(report, "gap")
    assert gap["id"] == "0x0A0" and gap["time"] < frames[lost].timestamp < gap["time"] + 0.03
    assert any("recorder dropped" in f["detail"] for f in _findings(report, "incomplete"))


def test_old_files_without_drop_markers_read_as_before_and_a_marker_parses() -> None:
    marker = drop_marker(10.0, 10.4567, 321, "can0")
    assert is_recorder_marker(marker)
    assert marker.arbitration_id == 0x1FFFFFFF and marker.is_extended_id
    assert bytes(marker.data) == b"LGL" + (321).to_bytes(3, "big") + (457).to_bytes(2, "big")
    frame = can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b"LGX" + bytes(5))
    assert not is_recorder_marker(frame)


def test_a_drop_earlier_than_the_held_marker_gets_its_own_marker(tmp_path: Path) -> None:
    """Frames reach the recorder from several threads, out of order by up to its window. Old
    code added a later-taken drop with an earlier time to the marker held back at 10.05 s,
    which was still written there: the frame dropped at 10.03 s was outside every marker."""
    rec = CanLogRecorder(tmp_path / "can.log")
    stalled = _Stalled(rec)

    def frame(t: float) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=0x123, data=b"\x01", is_extended_id=False)

    def stall(first: float, queued: tuple[float, ...], dropped: float) -> None:
        assert wait_for(stalled.caught_up)
        stalled.gate, stalled.entered = threading.Event(), threading.Event()
        stalled.bg._queue.maxsize = len(queued)
        stalled.stalling = True
        rec.on_can_frame(frame(first), "rx")  # the writer takes it and waits
        assert wait_for(stalled.entered.is_set)
        for t in queued:
            rec.on_can_frame(frame(t), "rx")
        rec.on_can_frame(frame(dropped), "rx")  # the queue is full: dropped
        stalled.stalling = False
        stalled.gate.set()
        assert wait_for(stalled.caught_up)
        stalled.bg._queue.maxsize = 1000

    stall(10.00, (10.01, 10.02), 10.05)
    stall(10.06, (10.07, 10.08), 10.03)  # from another thread, later than its time
    rec.close()
    assert stalled.bg.overflowed == 2
    source = ChainedSource(rec.files)
    list(source)
    for t in (10.03, 10.05):
        assert any(d.start <= t <= d.end for d in source.drops), (t, source.drops)


# --- ticks and Zenoh inputs: the session marks them, the re-run stops at the gap ------------


def _session_records(path: Path, topic: str) -> list[dict[str, Any]]:
    with SessionReader(path) as reader:
        return [r.json() for r in reader.records(frozenset({topic}))]


def test_the_session_marks_the_ticks_and_inputs_it_dropped_and_numbers_its_ticks(
    overflow: Overflow,
) -> None:
    """Old code marked the frames only: the ticks and inputs dropped in the stall left a hole
    that read as a continuous drive (ticks 10 ms apart, then 400 ms apart, and no word why)."""
    diagnostics = overflow.diagnostics["session"]
    dropped_ticks, dropped_inputs = (
        diagnostics["overflowed_ticks"],
        diagnostics["overflowed_inputs"],
    )
    assert dropped_ticks > 10 and dropped_inputs > 10, diagnostics
    lost = [LostItems.from_record(d) for d in _session_records(overflow.session, TOPIC_LOST)]
    ticks = [x for x in lost if x.what == "tick"]
    inputs = [x for x in lost if x.what == "input"]
    assert sum(x.count for x in ticks) == dropped_ticks
    assert sum(x.count for x in inputs) == dropped_inputs
    assert {k for x in inputs for k in x.topics} == {INPUT_KEY}
    for x in lost:
        assert STALL_FROM <= x.first <= x.last <= STALL_UNTIL + 0.03, x
    # the ticks written are numbered as handed in: one jump, as long as the ticks dropped
    seqs = [d["seq"] for d in _session_records(overflow.session, TOPIC_TICK)]
    jumps = [(a, b) for a, b in itertools.pairwise(seqs) if b != a + 1]
    assert seqs[0] == 0 and len(jumps) == 1, jumps
    assert jumps[0][1] - jumps[0][0] - 1 == dropped_ticks


def test_rerun_ends_at_the_ticks_the_recorder_dropped_and_says_where(overflow: Overflow) -> None:
    """Old code fed the ticks on both sides of the hole to one gateway as if they followed each
    other, and printed IDENTICAL (or a DIVERGED blamed on the code) over 400 ms it never saw."""
    report = rerun_session(overflow.session)
    assert report.gap is not None and not report.identical and not report.diverged
    dropped = overflow.diagnostics["session"]["overflowed_ticks"]
    assert report.gap.missing == report.gap.dropped == dropped
    assert report.gap.before is not None and STALL_FROM <= report.gap.before < report.gap.after
    assert report.ticks > 0 and report.not_rerun > 0
    # every tick before the gap re-run, none after it
    assert report.ticks == report.gap.seq - report.gap.missing
    out = io.StringIO()
    assert main_rerun(overflow.session, out=out) == 1
    lines = out.getvalue().strip().splitlines()
    assert lines[0].endswith(f"; not the {report.not_rerun} ticks after a gap"), lines[0]
    verdict = lines[-1]
    first, last = report.gap.seq - dropped, report.gap.seq - 1
    assert verdict.startswith(
        f"INCOMPLETE: {dropped} ticks missing (#{first}–#{last}) between the ticks at "
        f"{report.gap.before:.3f} s and {report.gap.after:.3f} s: the recorder dropped them"
    ), verdict
    assert f"the {report.ticks} ticks before it reproduced bit for bit" in verdict
    assert "IDENTICAL" not in out.getvalue()
    (note,) = [line for line in lines if line.startswith("note: ")]
    n = overflow.diagnostics["session"]["overflowed_inputs"]
    assert note.startswith(f"note: {n} Zenoh inputs ({INPUT_KEY} {n}) lost between"), note
    as_json = io.StringIO()
    main_rerun(overflow.session, as_json=True, out=as_json)
    data = json.loads(as_json.getvalue())
    assert data["identical"] is False and data["gap"]["missing_ticks"] == dropped
    assert data["ticks_not_rerun"] == report.not_rerun
    assert sum(x["count"] for x in data["lost_inputs"]) == n


def test_plot_of_the_session_names_the_ticks_it_bridges(overflow: Overflow, tmp_path: Path) -> None:
    out = io.StringIO()
    assert main_plot(overflow.session, out=tmp_path, stdout=out) == 0
    notes = [line for line in out.getvalue().splitlines() if line.startswith("note: ")]
    dropped = overflow.diagnostics["session"]["overflowed_ticks"]
    assert any(
        n.startswith(f"note: {dropped} ticks missing (#") and "the recorder dropped them" in n
        for n in notes
    ), notes
    assert any("Zenoh inputs" in n for n in notes), notes


def test_a_tick_gap_without_a_lost_record_is_still_a_gap_and_old_sessions_say_unchecked(
    overflow: Overflow, tmp_path: Path
) -> None:
    """Ticks numbered 0, 1, 5: three missing, whoever lost them (no lost record says why)."""
    continuity = TickContinuity()
    assert continuity.take_tick({"seq": 0, "now": 1.0}) is None
    assert continuity.take_tick({"seq": 1, "now": 1.01}) is None
    gap = continuity.take_tick({"seq": 5, "now": 1.05})
    assert gap is not None and gap.missing == 3 and gap.dropped == 0
    assert gap.text() == (
        "3 ticks missing (#2–#4) between the ticks at 1.010 s and 1.050 s: the recorder lost them"
    )
    # a lost record logged late, after the tick that ends its gap, still accounts for it
    continuity.take_lost({"what": "tick", "count": 3, "first": 1.02, "last": 1.04})
    assert continuity.gaps[-1].dropped == 3
    assert continuity.gaps[-1].text().endswith("the recorder dropped them (its queue overflowed)")
    late = TickContinuity()
    gap = late.take_tick({"seq": 2, "now": 0.5})
    assert gap is not None and gap.before is None and "before the first tick" in gap.text()
    unnumbered = TickContinuity()
    assert unnumbered.take_tick({"now": 1.0}) is None and unnumbered.numbered is False
    assert unnumbered.take_tick({"now": 9.0}) is None  # a clock jump alone is not judged


@pytest.mark.slow
def test_batch_rerun_says_incomplete_where_the_recorder_dropped_ticks(
    overflow: Overflow, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: ``DIVERGED at 8.500 s``, blaming the code for the hole the recorder made."""
    from leafgate.batch.results import read_table
    from leafgate.cli import main

    session = tmp_path / "in" / overflow.session.name
    session.parent.mkdir()
    session.write_bytes(overflow.session.read_bytes())
    args = ["batch", "rerun", str(session.parent), "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "out")]) == 1
    out = capsys.readouterr().out
    dropped = overflow.diagnostics["session"]["overflowed_ticks"]
    assert f"{session}: INCOMPLETE: {dropped} ticks missing (#" in out, out
    assert "1 session, 1 not reproduced" in out, out
    (row,) = read_table(tmp_path / "out" / "results.parquet")
    assert row["identical"] is False and row["gap"].startswith(f"{dropped} ticks missing")


def test_rerun_verdicts_never_read_alike_over_unchecked_ticks() -> None:
    """A session from before ticks were numbered cannot show a gap: its IDENTICAL says so. A gap
    before the first tick re-runs nothing and says that."""
    from leafgate.record.session import TickGap
    from leafgate.replay.rerun import RerunReport

    old = RerunReport("old.mcap", ticks=3, numbered=False)
    assert old.identical
    assert old.format()[-1].startswith("IDENTICAL: every recorded command reproduced bit for bit")
    assert "not numbered" in old.format()[-1]
    assert RerunReport("new.mcap", ticks=3).format()[-1] == (
        "IDENTICAL: every command reproduced bit for bit"
    )
    start = RerunReport("start.mcap", gap=TickGap(2, 2, None, 0.5), not_rerun=9)
    assert not start.identical
    assert start.format()[-1].startswith(
        "INCOMPLETE: 2 ticks missing (#0–#1) before the first tick, at 0.500 s: the recorder "
        "lost them; no tick before it; the 9 ticks after it not re-run"
    ), start.format()[-1]
