"""`replay check` and `decode` never claim what they did not check (the audit of the log tools).

"OK" is a promise: a log cut before the engage, rates that could none be checked, a silence
threshold that switches the checks off, a rotated log with a part missing, or a file that is no
log at all each fail and say why.
"""

from __future__ import annotations

import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from leafgate import cli
from leafgate.record.logs import END_MARKER_ID, LogParts, end_marker, group_parts, is_end_marker
from leafgate.record.recorder import CanLogRecorder, Recording, SessionRecorder
from leafgate.replay.check import check_log, main_check
from leafgate.replay.decode import decode_log
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario

PROFILE = "leafgate-dbw"


@dataclass(frozen=True)
class Drive:
    log: Path  # one .blf
    parts: list[Path]  # the same drive, rotated into parts
    session: Path


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Drive:
    directory = tmp_path_factory.mktemp("drive")
    config = LeafgateConfig()
    epoch = 1.8e9
    whole = CanLogRecorder(directory / "whole" / "can.blf", time_offset=epoch)
    rotated = CanLogRecorder(directory / "rot" / "can.blf", time_offset=epoch, max_bytes=60_000)
    session = SessionRecorder(directory / "session.mcap", config, epoch=epoch)
    with Recording([whole, rotated, session]) as recording:
        run(config, get_scenario("s-curve"), recorder=recording)
    assert recording.fault == ""
    assert len(rotated.files) >= 4
    return Drive(whole.files[0], list(rotated.files), session.path)


def _write_blf(path: Path, frames: list[can.Message]) -> Path:
    writer = can.BLFWriter(str(path))
    for msg in frames:
        writer.on_message_received(msg)
    writer.stop()
    return path


def _cut(drive: Drive, path: Path, seconds: float) -> Path:
    """The first ``seconds`` of the drive, closed properly (with its end marker)."""
    frames = [m for m in can.BLFReader(str(drive.log)) if not is_end_marker(m)]
    t0 = frames[0].timestamp
    kept = [m for m in frames if m.timestamp < t0 + seconds]
    return _write_blf(path, [*kept, end_marker(kept[-1].timestamp, kept[0].channel)])


def _verdict(text: str) -> str:
    return text.strip().splitlines()[-1]


# --- 1: nothing checked is not OK -----------------------------------------------------------------


def test_a_log_cut_before_the_engage_is_not_ok(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    short = _cut(drive, tmp_path / "short.blf", 0.4)
    report = check_log(short, profile=PROFILE)
    assert report.command_frames > 0 and report.engaged_frames == 0
    assert not report.ok
    assert any("nothing checked" in f.detail for f in report.findings)
    assert cli.main(["replay", "check", str(short), "--profile", PROFILE]) == 1
    out = capsys.readouterr().out
    assert _verdict(out).startswith("FAILED: 0 engaged command frames checked")
    assert "no command was checked against the limits" in out
    assert cli.main(["replay", "check", str(short), "--profile", PROFILE, "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["ok"] is False


def test_batch_check_row_of_a_log_cut_before_the_engage_is_not_ok(
    drive: Drive, tmp_path: Path
) -> None:
    from leafgate.batch.tasks import check_case

    short = _cut(drive, tmp_path / "short.blf", 0.4)
    row = check_case(str(short), None, 3.0, PROFILE)
    assert row["status"] == "ok" and row["ok"] is False and row["coverage_findings"] == 1


def test_a_log_whose_rates_could_none_be_checked_is_not_ok(drive: Drive, tmp_path: Path) -> None:
    """The drive slowed down 2.5 times: each command's previous one is 2.5 periods back,
    beyond a 2-period gap threshold, so no command's rates are checked (only the envelope)."""
    frames = list(can.BLFReader(str(drive.log)))
    t0 = frames[0].timestamp
    kept = []
    for msg in frames:
        msg.timestamp = t0 + 2.5 * (msg.timestamp - t0)
        kept.append(msg)
    report = check_log(_write_blf(tmp_path / "sparse.blf", kept), profile=PROFILE, gap_periods=2.0)
    assert report.engaged_frames > 0
    assert not report.ok
    assert any("rates of none" in f.detail for f in report.findings)


@pytest.mark.parametrize("value", ["nan", "inf", "1e9", "-inf", "0", "-3", "1", "101", "x"])
def test_gap_periods_must_be_a_finite_number_over_one(
    value: str, drive: Drive, capsys: pytest.CaptureFixture[str]
) -> None:
    for argv in (
        ["replay", "check", str(drive.log), "--profile", PROFILE],
        ["batch", "check", "."],
    ):
        with pytest.raises(SystemExit) as exc:
            cli.build_parser().parse_args([*argv, "--gap-periods", value])
        assert exc.value.code == 2
        assert "--gap-periods" in capsys.readouterr().err
    with pytest.raises(Exception, match="gap_periods"):
        check_log(drive.log, profile=PROFILE, gap_periods=float(value if value != "x" else "nan"))


def test_gap_periods_in_range_is_taken(drive: Drive) -> None:
    args = cli.build_parser().parse_args(["replay", "check", "x.blf", "--gap-periods", "100"])
    assert args.gap_periods == 100.0
    assert check_log(drive.log, profile=PROFILE, gap_periods=5).ok


# --- 2: a rotated log is one log --------------------------------------------------------------------


def test_group_parts_orders_the_parts_and_names_the_missing(tmp_path: Path) -> None:
    names = [tmp_path / f"can-x_{n:03d}.blf" for n in (2, 0, 3)]
    other = tmp_path / "other.blf"
    (group, alone) = group_parts([*names, other])
    assert group.paths == (names[1], names[0], names[2])
    assert [p.name for p in group.missing] == ["can-x_001.blf"]
    assert alone == LogParts((other,))


def test_a_rotated_log_is_checked_as_one(drive: Drive, capsys: pytest.CaptureFixture[str]) -> None:
    whole = check_log(drive.log, profile=PROFILE)
    assert main_check([str(p) for p in drive.parts], profile=PROFILE) == 0
    out = capsys.readouterr().out
    assert out.count("OK: ") == 1  # one log, one report
    verdict = _verdict(out)
    assert verdict.startswith(f"OK: {whole.engaged_frames} engaged command frames checked")
    assert "not checkable: none" in verdict


def test_a_rotated_log_with_a_part_missing_is_not_ok(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for part in drive.parts:
        shutil.copy(part, tmp_path)
    middle = tmp_path / drive.parts[2].name
    middle.unlink()
    given = sorted(tmp_path.glob("*.blf"))
    assert cli.main(["replay", "check", *map(str, given), "--profile", PROFILE]) == 1
    out = capsys.readouterr().out
    assert f"part {middle.name} of the rotated log is missing" in out
    assert _verdict(out).startswith("FAILED")


def test_a_rotated_log_without_its_last_part_is_not_ok(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each part the recorder closes to go on in the next ends with a marker saying so: old
    code closed it with the recording's end marker, so the parts without the last one read as
    a whole recording, OK, with the end of the drive never checked."""
    for part in drive.parts[:-1]:
        shutil.copy(part, tmp_path)
    last = drive.parts[-1].name
    given = sorted(tmp_path.glob("*.blf"))
    assert cli.main(["replay", "check", *map(str, given), "--profile", PROFILE]) == 1
    out = capsys.readouterr().out
    assert f"goes on in part {last}, which is missing: its frames were not checked" in out, out
    assert _verdict(out).startswith("FAILED")
    decoded = io.StringIO()
    decode_log(group_parts(given)[0], out=decoded, profile=PROFILE)
    assert f"the recording goes on in part {last}, missing" in decoded.getvalue()
    # the whole drive, and a part checked on its own with the next one beside it, are fine
    assert main_check([str(p) for p in drive.parts], profile=PROFILE) == 0
    shutil.copy(drive.parts[-1], tmp_path)
    for path in given:
        log = check_log(group_parts([path])[0], profile=PROFILE)
        assert not any("goes on in part" in f.detail for f in log.findings)


def test_several_logs_end_with_one_verdict_over_all(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    short = _cut(drive, tmp_path / "short.blf", 0.4)
    argv = ["replay", "check", str(short), str(drive.log), "--profile", PROFILE]
    assert cli.main(argv) == 1
    out = capsys.readouterr().out
    assert _verdict(out) == f"FAILED: 1 of 2 logs failed the check: {short}"
    assert cli.main([*argv, "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] is False and [r["ok"] for r in doc["logs"]] == [False, True]
    assert (
        cli.main(["replay", "check", str(drive.log), str(drive.session), "--profile", PROFILE]) == 0
    )
    assert _verdict(capsys.readouterr().out) == "OK: all 2 logs checked without a finding"


# --- 3: a file that is no log is refused ----------------------------------------------------------


@pytest.mark.parametrize("suffix", [".asc", ".log", ".csv"])
@pytest.mark.parametrize("content", ["png", "json"])
def test_a_file_that_is_no_log_is_refused_naming_it(
    suffix: str, content: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / f"not-a-log{suffix}"
    if content == "png":
        path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)) * 4)
    else:
        path.write_text(json.dumps({"frames": 3, "ok": True}, indent=2) + "\n")
    for argv in (
        ["replay", "check", str(path), "--profile", PROFILE],
        ["decode", str(path), "--profile", PROFILE],
        ["replay", "play", str(path), "-i", "virtual", "-c", "x", "--all-ids"],
    ):
        assert cli.main(argv) != 0, argv
        captured = capsys.readouterr()
        assert f"{path}: unreadable: not a" in captured.err and " log" in captured.err, argv
        assert "0 frames" not in captured.out


def test_an_empty_or_header_only_text_log_is_still_an_empty_log(tmp_path: Path) -> None:
    empty = tmp_path / "empty.asc"
    empty.write_text("")
    header = tmp_path / "header.asc"
    header.write_text("date Fri Dec 4 10:00:00.000 am 2026\nbase hex  timestamps absolute\n")
    for path in (empty, header):
        report = check_log(path, profile=PROFILE)
        assert not report.ok and report.findings[0].detail == "the log has no frames"


def test_replay_check_of_an_empty_log_says_no_frames_and_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: "empty.log: 0 frames, nan s", and the finding's time printed as nan."""
    empty = tmp_path / "empty.log"
    empty.write_text("")
    assert cli.main(["replay", "check", str(empty), "--profile", PROFILE]) == 1
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"{empty}: no frames, profile {PROFILE}"
    assert "nan" not in out and "-  coverage log  the log has no frames" in out
    assert out.splitlines()[-1].startswith("FAILED: ")


# --- 4: decode takes a rotated log's parts, and says when a recording is incomplete ---------------


def test_decode_takes_a_rotated_logs_parts_as_one(drive: Drive) -> None:
    one, parts = io.StringIO(), io.StringIO()
    decode_log(drive.log, one, profile=PROFILE)
    assert cli.main(["decode", *map(str, drive.parts), "--profile", PROFILE, "--no-summary"]) == 0
    decode_log([str(p) for p in drive.parts], parts, profile=PROFILE)
    frame_lines = [line for line in one.getvalue().splitlines() if not line.startswith("#")]
    assert [ln for ln in parts.getvalue().splitlines() if not ln.startswith("#")] == frame_lines
    summary = [ln for ln in parts.getvalue().splitlines() if ln.startswith("#")]
    assert f"({len(drive.parts)} parts)" in summary[0]
    # the same counts: no counter error at a part boundary
    assert summary[1:] == [ln for ln in one.getvalue().splitlines() if ln.startswith("#")][1:]


def test_decode_says_a_recording_is_incomplete(drive: Drive, tmp_path: Path) -> None:
    frames = [m for m in can.BLFReader(str(drive.log)) if m.arbitration_id != END_MARKER_ID]
    no_marker = _write_blf(tmp_path / "no-marker.blf", frames)
    out = io.StringIO()
    decode_log(no_marker, out, profile=PROFILE)
    header = [ln for ln in out.getvalue().splitlines() if ln.startswith("# no-marker")]
    assert "no end-of-recording marker" in header[0]
    data = drive.session.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    out = io.StringIO()
    decode_log(cut, out, profile=PROFILE)
    header = [ln for ln in out.getvalue().splitlines() if ln.startswith("# cut.mcap")]
    assert "(truncated session)" in header[0] and "no end-of-recording marker" in header[0]
    out = io.StringIO()
    decode_log(drive.log, out, profile=PROFILE)
    header = [ln for ln in out.getvalue().splitlines() if ln.startswith("# can_000")]
    assert "marker" not in header[0] and "truncated" not in header[0]


def test_batch_check_checks_a_rotated_log_as_one(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: every part was a log of its own, so each part after the first began
    mid-drive and the parts were counted as that many logs, none of them whole."""
    logs = tmp_path / "in"
    logs.mkdir()
    for part in drive.parts:
        shutil.copy(part, logs)
    argv = ["batch", "check", str(logs), "--profile", PROFILE, "--workers", "1"]
    assert cli.main([*argv, "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    whole = check_log(drive.log, profile=PROFILE)
    assert f"({len(drive.parts)} parts): OK: {whole.frames} frames" in out, out
    assert "1 log, 0 with findings" in out


def test_batch_check_line_of_a_finding_without_a_name_has_no_empty_field(
    drive: Drive, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log that stops without its end marker: the finding names no frame. Old code printed
    ``first: incomplete: : no end-of-recording marker``."""
    logs = tmp_path / "in"
    logs.mkdir()
    frames = [m for m in can.BLFReader(str(drive.log)) if not is_end_marker(m)]
    _write_blf(logs / "open.blf", frames)
    argv = ["batch", "check", str(logs), "--profile", PROFILE, "--workers", "1"]
    assert cli.main([*argv, "--out", str(tmp_path / "out")]) == 1
    out = capsys.readouterr().out
    assert "first: incomplete: no end-of-recording marker" in out, out


def test_counts_of_one_are_singular(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Old code: '1 frames', '1 coverage findings'."""
    log = tmp_path / "foreign.log"
    log.write_text("(1700000000.000000) vcan0 123#00\n")
    assert main_check(log, profile=PROFILE) == 1
    out = capsys.readouterr().out
    assert f"{log}: 1 frame (1 of an unknown ID), " in out
    verdict = _verdict(out)
    assert "0 engaged command frames checked" in verdict and "1 coverage finding;" not in verdict
    # a foreign log has no end marker: that fails it too, and the verdict says so
    assert verdict.endswith(", 1 coverage finding, 1 incomplete finding"), verdict


@pytest.mark.parametrize("name", ["gone.mcap", "gone.log", "gone.blf"])
def test_a_missing_recording_is_no_such_file_not_a_missing_profile(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """Old code: "the recording names no vehicle profile; give --profile …" for a file that is
    not there (found by an outside look at `leafgate batch check`)."""
    path = tmp_path / name
    assert cli.main(["replay", "check", str(path)]) == 1
    err = capsys.readouterr().err
    assert err == f"leafgate: error: {path}: no such file\n"
