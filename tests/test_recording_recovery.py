"""A drive recorded across a full disk: the tools see one recording with a hole the recorder
made, not two drives, a silent bus or a controller that changed.

One s-curve drive is recorded once per module into a BLF log and a session while the disk is
full from 8 s to 10 s of simulated time: the recorder gives both files up and goes on in
``can_001.blf`` and ``session.2.mcap`` (``resumes: session.mcap``).
"""

from __future__ import annotations

import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from leafgate.cli import main
from leafgate.errors import ReplayError
from leafgate.gateway.core import GatewayInputs, StepResult
from leafgate.record.logs import FrameSource, LogParts, end_marker, group_parts
from leafgate.record.recorder import CanLogRecorder, Recording, SessionRecorder
from leafgate.record.session import SessionReader
from leafgate.replay.check import check_log, main_check
from leafgate.replay.decode import AFTER_RECORDER_LOSS, decode_log
from leafgate.replay.rerun import main_rerun, rerun_session
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario
from tests.conftest import Disk, wait_for

EPOCH = 1.8e9  # s: simulated time 0 in Unix time
FULL_FROM, FULL_UNTIL = 8.0, 10.0  # s of simulated time the disk is full


@dataclass(frozen=True)
class Outage:
    logs: list[Path]  # can_000.blf, can_001.blf
    sessions: list[Path]  # session.mcap, session.2.mcap
    lost: dict[str, int]  # recorder diagnostics: items the outage lost


class _FullDiskRecording(Recording):
    """Fills the disk at ``FULL_FROM`` until the recorders have failed, frees it at
    ``FULL_UNTIL`` and waits for them to start their new files (the drive itself goes on)."""

    def __init__(self, recorders: list[Any], disk: Disk) -> None:
        super().__init__(recorders)
        self.disk = disk
        self.phase = "before"

    def on_tick(self, now: float, inputs: GatewayInputs, result: StepResult, frames: Any) -> None:
        writers = [r._bg for r in self.recorders]
        if self.phase == "before" and now >= FULL_FROM:
            self.disk.free = 0  # the next periodic flush fails (nothing drained on purpose)
            assert wait_for(lambda: all(w.failed for w in writers))
            self.phase = "full"
        elif self.phase == "full" and now >= FULL_UNTIL:
            self.disk.free = 10**9
            assert wait_for(lambda: not any(w.failed for w in writers))
            self.phase = "after"
        super().on_tick(now, inputs, result, frames)


@pytest.fixture(scope="module")
def outage(tmp_path_factory: pytest.TempPathFactory) -> Outage:
    directory = tmp_path_factory.mktemp("outage")
    monkeypatch = pytest.MonkeyPatch()
    disk = Disk(directory)
    disk.install(monkeypatch)
    config = LeafgateConfig()
    timing = {"flush_period": 0.05, "retry_period": 0.2}
    log = CanLogRecorder(directory / "can.blf", time_offset=EPOCH, **timing)
    session = SessionRecorder(directory / "session.mcap", config, epoch=EPOCH, **timing)
    try:
        with _FullDiskRecording([log, session], disk) as recording:
            run(config, get_scenario("s-curve"), recorder=recording)
        assert recording.phase == "after"
    finally:
        monkeypatch.undo()
    lost = {"can_log": log.diagnostics()["lost"], "session": session.diagnostics()["lost"]}
    return Outage(list(log.files), list(session.files), lost)


def _findings(report_json: dict[str, Any], kind: str) -> list[dict[str, Any]]:
    return [f for f in report_json["findings"] if f["kind"] == kind]


def test_the_recorder_went_on_in_a_next_part_and_a_resumed_session(outage: Outage) -> None:
    assert [p.name for p in outage.logs] == ["can_000.blf", "can_001.blf"]
    assert [p.name for p in outage.sessions] == ["session.mcap", "session.2.mcap"]
    with SessionReader(outage.sessions[1]) as reader:
        assert reader.read_metadata()["leafgate.session"]["resumes"] == "session.mcap"
    assert outage.lost["can_log"] > 0 and outage.lost["session"] > 0


@pytest.mark.parametrize("which", ["logs", "sessions"])
def test_the_new_file_starts_after_the_outage_not_with_frames_from_before_it(
    outage: Outage, which: str
) -> None:
    """Old code wrote the frames held in the reorder window when the file failed at the start
    of the next one: an island of 0.25 s from before the outage, then the outage inside the
    new file, where no check can tell the recorder's loss from the bus's silence."""
    resumed = getattr(outage, which)[1]
    first = next(iter(FrameSource(resumed))).timestamp - EPOCH
    assert first >= FULL_UNTIL - 0.03, first  # within a tick and the window's order


def test_a_recovered_log_is_one_log_with_the_loss_named_not_a_silent_bus(outage: Outage) -> None:
    """Old code: 'the whole bus silent for 2000 ms' (twice: at the part boundary and at the
    outage inside the next part). The bus was not silent; the recorder lost the frames."""
    report = check_log(group_parts(outage.logs)[0], profile="leafgate-dbw").to_dict()
    assert not _findings(report, "silence"), report["findings"]
    assert not _findings(report, "gap") and not _findings(report, "e2e"), report["findings"]
    (lost,) = _findings(report, "incomplete")
    assert "can_000.blf" in lost["detail"] and "can_001.blf" in lost["detail"]
    assert "lost by the recorder" in lost["detail"], lost["detail"]
    assert lost["value"] >= FULL_UNTIL - FULL_FROM  # s, the stretch not recorded
    assert report["engaged_command_frames"] > 1500  # both sides of the hole were checked


def test_a_resumed_session_is_checked_with_the_session_it_resumes(outage: Outage) -> None:
    """Old code: two unrelated logs, the resumption 'OK' apart from a bus silence that was
    the recorder's outage."""
    (parts,) = group_parts(outage.sessions)
    assert parts.paths == tuple(outage.sessions) and parts.missing == ()
    out = io.StringIO()
    assert main_check(outage.sessions, out=out, as_json=True) == 1  # the hole is a finding
    report = json.loads(out.getvalue())
    assert "session.2.mcap" in report["path"] and "logs" not in report
    assert not _findings(report, "silence"), report["findings"]
    (lost,) = _findings(report, "incomplete")
    assert "session.mcap" in lost["detail"] and "resumes" in lost["detail"], lost["detail"]
    assert lost["value"] >= FULL_UNTIL - FULL_FROM


def test_a_resumption_alone_names_the_session_it_resumes_when_that_is_missing(
    outage: Outage, tmp_path: Path
) -> None:
    resumed = tmp_path / "session.2.mcap"
    shutil.copy(outage.sessions[1], resumed)
    (parts,) = group_parts([resumed])
    assert parts == LogParts((resumed,), (tmp_path / "session.mcap",))
    report = check_log(parts).to_dict()
    assert any("session.mcap" in f["detail"] for f in _findings(report, "incomplete"))
    # given alone beside the session it resumes: checked alone on purpose, as a single part
    (alone,) = group_parts([outage.sessions[1]])
    assert alone == LogParts((outage.sessions[1],))


def test_sessions_named_like_resumptions_are_not_grouped_without_resumes(
    outage: Outage, tmp_path: Path
) -> None:
    """``lap.2.mcap`` that resumes nothing is a session of its own, not a part of ``lap.mcap``."""
    for name in ("lap.mcap", "lap.2.mcap", "lap.3.mcap"):
        shutil.copy(outage.sessions[0], tmp_path / name)
    groups = group_parts(sorted(tmp_path.glob("*.mcap")))
    assert [g.paths for g in groups] == [(p,) for p in sorted(tmp_path.glob("*.mcap"))]
    assert all(g.missing == () for g in groups)


def _frame(t: float) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=0x123, data=b"\x01", is_extended_id=False)


def test_a_recovered_non_rotating_log_is_one_log_with_no_part_missing(tmp_path: Path) -> None:
    """Review item: a non-rotating log recovered from a full disk was said to write a ``_001``
    part that checks apart from the base file, with ``_000`` missing. The recorder names every
    log ``_000`` from its start, so the continuation is ``_001`` of the same log."""
    disk = Disk(tmp_path)
    monkeypatch = pytest.MonkeyPatch()
    disk.install(monkeypatch)
    t0 = 1_700_000_000.0
    try:
        rec = CanLogRecorder(tmp_path / "can.log", max_bytes=0, flush_period=0.05, retry_period=0.1)
        for k in range(20):
            rec.on_can_frame(_frame(t0 + 0.01 * k), "rx")
        assert rec.flush()
        disk.free = 0
        rec.on_can_frame(_frame(t0 + 1.0), "rx")
        rec.flush()
        assert rec.fault != ""
        disk.free = 10**9
        assert wait_for(lambda: rec.on_can_frame(_frame(t0 + 5.0), "rx") or rec.fault == "")
        rec.close()
    finally:
        monkeypatch.undo()
    assert [p.name for p in rec.files] == ["can_000.log", "can_001.log"]
    assert group_parts(sorted(tmp_path.glob("can*"))) == [LogParts(tuple(rec.files))]


def test_rerun_of_a_resumed_session_refuses_it_starts_mid_drive(
    outage: Outage, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code re-ran it from a gateway in STANDBY against commands sent ENGAGED: DIVERGED,
    as if the controller had changed."""
    resumed = outage.sessions[1]
    with pytest.raises(ReplayError, match=r"resumes session\.mcap.*mid-drive"):
        rerun_session(resumed)
    assert main(["replay", "rerun", str(resumed)]) == 1
    captured = capsys.readouterr()
    assert "DIVERGED" not in captured.out and "IDENTICAL" not in captured.out
    (line,) = captured.err.strip().splitlines()
    assert line.startswith("leafgate: error: ") and "mid-drive" in line
    # the session it resumes re-runs up to its cut
    out = io.StringIO()
    assert main_rerun(outage.sessions[0], out=out) == 0
    assert "IDENTICAL up to the cut" in out.getvalue()


def test_counters_skipped_across_the_recorders_loss_are_not_bus_errors(
    outage: Outage, tmp_path: Path
) -> None:
    """A loss of one frame per ID, with the next frame early (bus jitter): the interval is
    under 1.5 periods, so no gap explains the skipped alive counters. Old code: one E2E
    ``bad_counter`` per ID, errors of the bus; they are the frames the recorder lost."""
    frames = [m for m in FrameSource(outage.logs[1]) if m.timestamp < EPOCH + 16.0]
    cut = EPOCH + 14.0
    before = [m for m in frames if m.timestamp < cut]
    after = [m for m in frames if m.timestamp >= cut + 0.005]  # the frames at 14.000 s
    for m in after:
        m.timestamp -= 0.006  # the next 6 ms early: a 10 ms frame 14 ms after the last kept
    first = tmp_path / "can_000.blf"
    second = tmp_path / "can_001.blf"
    for path, part, marker in ((first, before, False), (second, after, True)):
        writer = can.BLFWriter(str(path))
        for m in part:
            writer.on_message_received(m)
        if marker:
            writer.on_message_received(end_marker(part[-1].timestamp, part[-1].channel))
        writer.stop()
    report = check_log(group_parts([first, second])[0], profile="leafgate-dbw").to_dict()
    assert not _findings(report, "e2e"), _findings(report, "e2e")
    (lost,) = _findings(report, "incomplete")
    assert "lost by the recorder" in lost["detail"]
    assert report["engaged_command_frames"] > 100


@pytest.mark.slow
def test_batch_check_and_rerun_see_one_recording_per_outage(
    outage: Outage, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`batch check` groups with the same function as `replay check`: two rows (the log's
    parts, the session with its resumption), not four; `batch rerun` says the resumption
    cannot be re-run rather than that it diverged."""
    folder = outage.logs[0].parent
    args = ["batch", "check", str(folder), "--profile", "leafgate-dbw", "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "check")]) == 1
    out = capsys.readouterr().out
    assert f"{outage.sessions[0]} … session.2.mcap (2 parts): FINDINGS: incomplete 1;" in out
    assert f"{outage.logs[0]} … can_001.blf (2 parts): FINDINGS: incomplete 1;" in out
    assert "2 logs, 2 with findings or unreadable" in out and "silence" not in out
    args = ["batch", "rerun", str(folder), "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "rerun")]) == 1
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith(f"{outage.sessions[1]}:"))
    assert "not re-run: it resumes session.mcap" in line and "DIVERGED" not in line, line
    assert f"{outage.sessions[0]}: IDENTICAL up to the cut" in out


def test_play_takes_a_session_and_its_resumption_in_their_order(outage: Outage) -> None:
    """A shell glob sorts ``session.2.mcap`` before ``session.mcap``; play refused the pair as
    going back in time. It plays them in the recording's order."""
    from leafgate.config.can import BusConfig
    from leafgate.replay.play import main_play

    globbed = sorted(outage.sessions, key=lambda p: p.name)
    assert globbed[0].name == "session.2.mcap"
    channel = "recovery-play"
    with can.Bus(interface="virtual", channel=channel) as rx:
        out = io.StringIO()
        code = main_play(
            globbed, bus=BusConfig(interface="virtual", channel=channel), speed=0, out=out
        )
        played = 0
        while rx.recv(timeout=0.0) is not None:
            played += 1
    assert code == 0, out.getvalue()
    assert played > 1000


def test_decode_does_not_call_the_counters_after_a_write_failure_bus_errors(
    outage: Outage,
) -> None:
    """Old code: the first frame of each ID in ``can_001.blf`` was a ``bad_counter`` line and
    counted in bad_cnt: errors of the bus for frames the recorder lost in the outage."""
    out = io.StringIO()
    decode_log(outage.logs, out, profile="leafgate-dbw")
    lines = out.getvalue().splitlines()
    assert not [line for line in lines if line.endswith("bad_counter")]
    after = [line for line in lines if line.endswith(AFTER_RECORDER_LOSS)]
    assert after and all(float(line.split()[0]) - EPOCH >= FULL_UNTIL - 0.03 for line in after)
    total = next(line for line in lines if line.startswith("#") and line.split()[1] == "total")
    assert total.split()[4] == "0", total  # bad_cnt


def _header(paths: list[Path]) -> str:
    out = io.StringIO()
    main_check(paths, out=out)
    return out.getvalue().splitlines()[0]


def test_a_chain_names_the_part_cut_short_and_why(outage: Outage, tmp_path: Path) -> None:
    """Old code: '(truncated session)' for the whole recording whenever any part was, which
    read as a crash of the drive. The session given up at the full disk has no footer (the
    recorder leaves a failed file as it is); that is the loss already reported, named as that.
    A last part cut short (a crash after the recovery) is named as the truncated session."""
    header = _header(outage.sessions)
    assert "(part session.mcap cut where the recorder gave it up)" in header, header
    assert "truncated session" not in header, header
    copies = [tmp_path / p.name for p in outage.sessions]
    for source, copy in zip(outage.sessions, copies, strict=True):
        shutil.copy(source, copy)
    with copies[1].open("r+b") as file:  # a crash: the last part stops before its footer
        file.truncate(copies[1].stat().st_size // 2)
    header = _header(copies)
    assert "the last part, session.2.mcap, is a truncated session" in header, header
    assert "part session.mcap cut where the recorder gave it up" in header, header
    out = io.StringIO()
    decode_log(copies, out, profile="leafgate-dbw")
    (summary,) = [line for line in out.getvalue().splitlines() if "profile leafgate-dbw" in line]
    assert "the last part, session.2.mcap, is a truncated session" in summary, summary
    # a single session cut short is still a 'truncated session'
    assert "(truncated session)" in _header([copies[1]])


def test_a_log_beside_sessions_is_not_checked_without_a_profile_but_their_profile_is_named(
    outage: Outage,
) -> None:
    """The daemon's CAN log names no profile, so ``replay check rec/*`` cannot check it; the
    sessions recorded beside it name theirs, which the message now says (old code: only 'give
    --profile'). It is a hint, not a guess: the log is still not checked."""
    out, err = io.StringIO(), io.StringIO()
    assert main_check([*outage.logs, *outage.sessions], out=out, err=err) == 1
    (line,) = [x for x in out.getvalue().splitlines() if ": not checked: " in x]
    assert "can_000.blf" in line and "names no vehicle profile" in line, line
    assert "the 2 sessions beside it were recorded with profile leafgate-dbw" in line, line
    assert "--profile leafgate-dbw if the log is of the same drive" in line, line
