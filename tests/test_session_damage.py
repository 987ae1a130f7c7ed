"""A damaged session is unreadable at an offset, never truncated, empty or OK.

The audit: two sessions concatenated read as the first one, OK; a byte flipped mid-file read as
a crash's truncation (``stops after frame N``); one flipped in the header read as a log with no
frames and no configuration. Only a file that stops before its footer is a crash's cut.
"""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from leafgate import cli
from leafgate.errors import ReplayError
from leafgate.record.logs import FrameSource
from leafgate.record.recorder import SessionRecorder
from leafgate.record.session import TOPIC_TICK, SessionDamaged, SessionReader
from leafgate.replay.decode import decode_log
from leafgate.settings import LeafgateConfig
from tests.test_recorder import record_ticks

PROFILE = "leafgate-dbw"


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A closed session of 200 ticks in 4 chunks (flushed every 50)."""
    path = tmp_path_factory.mktemp("damage") / "s.mcap"
    with SessionRecorder(path, LeafgateConfig(), compression="none") as rec:
        for k in range(4):
            record_ticks(rec, 50, start=1.0 * k)
            assert rec.flush()
    return path


def _all(path: Path) -> SessionReader:
    with SessionReader(path) as reader:
        for _ in reader.records():
            pass
    return reader


def _flipped(session: Path, tmp_path: Path, offset: int) -> Path:
    data = bytearray(session.read_bytes())
    data[offset] ^= 0xFF
    out = tmp_path / f"flip-{offset}.mcap"
    out.write_bytes(bytes(data))
    return out


def test_the_intact_session_reads_whole(session: Path) -> None:
    reader = _all(session)
    assert not reader.truncated and reader.messages > 400


def test_two_sessions_concatenated_are_unreadable_after_the_first(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doubled = tmp_path / "d.mcap"
    size = session.stat().st_size
    doubled.write_bytes(session.read_bytes() * 2)
    with pytest.raises(SessionDamaged) as caught:
        _all(doubled)
    assert caught.value.offset == size
    assert f"{size} bytes after the session's end at offset {size}: not read" in str(caught.value)
    with pytest.raises(ReplayError, match=r"unreadable after \d+ frames: .*bytes after"):
        list(FrameSource(doubled))
    assert cli.main(["replay", "check", str(doubled), "--profile", PROFILE]) != 0
    assert "bytes after the session's end" in capsys.readouterr().err
    with pytest.raises(ReplayError, match="bytes after the session's end"):
        decode_log(doubled, io.StringIO(), profile=PROFILE)


def test_a_byte_flipped_mid_file_is_damage_at_its_offset_not_a_truncation(
    session: Path, tmp_path: Path
) -> None:
    data = session.read_bytes()
    for offset in range(100, len(data) - 8, len(data) // 23):  # chunks, indexes, summary
        flipped = _flipped(session, tmp_path, offset)
        with pytest.raises(SessionDamaged) as caught:
            _all(flipped)
        assert caught.value.offset <= offset or "before offset" in str(caught.value), offset
        assert "offset" in str(caught.value)
        with pytest.raises(ReplayError, match=r"unreadable after \d+ frames: .* offset \d+"):
            list(FrameSource(flipped))


@pytest.mark.parametrize("offset", [9, 17, 20, 30])
def test_a_byte_flipped_in_the_header_is_damage_not_an_empty_log(
    session: Path, tmp_path: Path, offset: int, capsys: pytest.CaptureFixture[str]
) -> None:
    flipped = _flipped(session, tmp_path, offset)
    with pytest.raises(SessionDamaged, match=r"unreadable after 0 messages: .* offset \d+"):
        _all(flipped)
    with pytest.raises(ReplayError, match="unreadable after 0 messages"):
        SessionReader(flipped).read_metadata()
    with pytest.raises(ReplayError, match="unreadable after 0 frames"):
        list(FrameSource(flipped))
    assert cli.main(["replay", "check", str(flipped)]) != 0
    err = capsys.readouterr().err
    assert "unreadable" in err and "no frames" not in err and "profile" not in err


def test_a_session_cut_short_is_still_a_truncation(session: Path, tmp_path: Path) -> None:
    data = session.read_bytes()
    for cut in (len(data) // 2, len(data) - 1, len(data) - 8):
        short = tmp_path / f"cut-{cut}.mcap"
        short.write_bytes(data[:cut])
        with SessionReader(short) as reader:
            ticks = list(reader.records(frozenset({TOPIC_TICK})))
        assert reader.truncated and reader.error, cut
        assert ticks, cut
