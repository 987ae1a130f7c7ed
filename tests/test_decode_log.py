"""decode_log: any python-can log format, one line per frame, E2E status, per-ID summary."""

from __future__ import annotations

import io
from pathlib import Path

import can
import pytest

from leafgate.can.codec import CanCodec
from leafgate.errors import ReplayError
from leafgate.messages import Gear, GearPosition, LongCommand, LongMode, SteerCommand, WheelSpeeds
from leafgate.replay.decode import decode_log


def recording() -> list[can.Message]:
    """Five good steering commands with one lost, a bad CRC, a short frame, others."""
    codec = CanCodec(profile="leafgate-dbw")
    steer = [codec.encode(SteerCommand(0.01 * i, enable=True)) for i in range(6)]
    corrupt = bytearray(codec.encode(SteerCommand(0.3)).data)
    corrupt[2] ^= 0x40
    frames = [
        steer[0],
        steer[1],
        steer[3],  # steer[2] lost → bad counter
        steer[4],
        can.Message(arbitration_id=0x0A0, data=corrupt, is_extended_id=False),  # bad CRC
        can.Message(arbitration_id=0x0A0, data=bytes(6), is_extended_id=False),  # short
        codec.encode(LongCommand(mode=LongMode.SPEED, speed=1.25, gear=Gear.D)),
        codec.encode(WheelSpeeds(1.0, 1.0, "front")),
        codec.encode(GearPosition(Gear.R)),
        can.Message(arbitration_id=0x3AB, data=b"\x01\x02\x03", is_extended_id=False),
    ]
    for i, msg in enumerate(frames):
        msg.timestamp = 1000.0 + 0.01 * i
        msg.channel = 0
    return frames


def write_log(path: Path, frames: list[can.Message]) -> Path:
    with can.Logger(path) as logger:
        for msg in frames:
            logger.on_message_received(msg)
    return path


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".trc", ".csv"])
def test_every_frame_gets_a_line_with_its_e2e_status(tmp_path: Path, suffix: str) -> None:
    path = write_log(tmp_path / f"drive{suffix}", recording())
    out = io.StringIO()
    assert decode_log(path, out, summary=False, profile="leafgate-dbw") == 0
    lines = out.getvalue().splitlines()
    assert len(lines) == 10
    statuses = [line.rsplit("  ", 1)[1] for line in lines]
    assert statuses == [
        "ok",
        "ok",
        "bad_counter",
        "ok",
        "bad_crc",
        "wrong_length",
        "ok",
        "ok",
        "ok",
        "unknown_id",
    ]
    assert "DBW_STEER_CMD(STEER_ANGLE_CMD: 0.03 rad" in lines[2]
    assert "MODE: SPEED" in lines[6] and "SPEED_CMD: 1.25 m/s" in lines[6]
    assert "GEAR_POSITION(GEAR_SHIFTER: R)" in lines[8]
    assert " 3AB " in lines[9] and "01 02 03" in lines[9]


def test_summary_counts_frames_and_faults_per_id(tmp_path: Path) -> None:
    path = write_log(tmp_path / "drive.log", recording())
    out = io.StringIO()
    decode_log(path, out, profile="leafgate-dbw")
    summary = [line for line in out.getvalue().splitlines() if line.startswith("#")]
    rows = {line.split()[1]: line.split()[2:] for line in summary[2:]}
    # columns: name frames bad_crc bad_cnt bad_len unknown decode
    assert rows["0A0"] == ["DBW_STEER_CMD", "6", "1", "1", "1", "0", "0"]
    assert rows["3AB"] == ["?", "1", "0", "0", "0", "1", "0"]
    assert rows["total"] == ["10", "1", "1", "1", "1", "0"]
    assert "drive.log: 10 frames" in summary[0]


def test_frames_of_two_channels_have_separate_counter_state(tmp_path: Path) -> None:
    codec_a, codec_b = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    frames = []
    for i in range(3):  # both channels carry 0x0A0 with their own counters
        for channel, codec in (("can0", codec_a), ("can1", codec_b)):
            msg = codec.encode(SteerCommand(0.0), timestamp=float(i))
            msg.channel = channel
            frames.append(msg)
    path = write_log(tmp_path / "two.log", frames)
    out = io.StringIO()
    decode_log(path, out, summary=False, profile="leafgate-dbw")
    assert all(line.endswith("  ok") for line in out.getvalue().splitlines())


def test_a_candump_log_of_extended_ids_error_frames_and_oversized_frames(tmp_path: Path) -> None:
    """Reported from outside, with a ``candump -L`` log as the car's bus gives it: the summary
    showed 29-bit ID 12345678 as ``92345678`` (the key's internal flag), an error frame as the
    extended ID ``80000000``, and a classic frame of 10 data bytes decoded as a good one."""
    codec = CanCodec(profile="leafgate-dbw")
    good = bytes(codec.encode(SteerCommand(0.1, enable=True)).data).hex().upper()
    path = tmp_path / "car.log"
    path.write_text(
        "(1600000000.000000) can0 12345678#0011\n"
        f"(1600000000.010000) can0 0A0#{good}0000\n"  # a classic frame cannot carry 10 bytes
        "(1600000000.020000) can0 20000080#0000000000000000\n"  # an error frame
        f"(1600000000.030000) can0 0A0#{good}\n",
        encoding="utf-8",
    )
    out = io.StringIO()
    decode_log(path, out, profile="leafgate-dbw")
    lines = out.getvalue().splitlines()
    assert lines[0].split("  ")[2] == "12345678"
    assert lines[1].endswith("  wrong_length") and "[10]" in lines[1]
    assert lines[2].split("  ")[2] == "error" and lines[2].endswith("  error_frame")
    assert lines[3].endswith("  ok")
    summary = [line for line in lines if line.startswith("#")]
    rows = {line.split()[1]: line.split()[2:] for line in summary[2:]}
    assert rows["12345678"] == ["?", "1", "0", "0", "0", "1", "0"]
    assert rows["0A0"] == ["DBW_STEER_CMD", "2", "0", "0", "1", "0", "0"]
    assert not any(key.startswith(("8", "9")) for key in rows)


def test_error_frames_are_counted_in_their_own_row_and_never_as_unknown_ids(
    tmp_path: Path,
) -> None:
    """Old code counted an error frame as a frame of an unknown ID: ``unknown 1`` in its own
    row and one more in the total's ``unknown``, beside the real unknown IDs."""
    path = tmp_path / "car.log"
    path.write_text(
        "(1600000000.000000) can0 123#0102\n"
        "(1600000000.010000) can0 20000080#0000000000000000\n"  # an error frame
        "(1600000000.020000) can0 20000080#0000000000000000\n"
        "(1600000000.030000) can0 12345678#01\n",
        encoding="utf-8",
    )
    out = io.StringIO()
    decode_log(path, out, profile="leafgate-dbw")
    summary = [line for line in out.getvalue().splitlines() if line.startswith("#")]
    assert summary[0].startswith("# car.log: 4 frames (2 error frames), profile leafgate-dbw")
    rows = {line.split()[1]: line.split()[2:] for line in summary[2:]}
    assert rows["error"] == ["error", "frames", "2", "0", "0", "0", "0", "0"]
    assert rows["total"] == ["4", "0", "0", "0", "2", "0"]  # unknown: 0x123 and 12345678

    from leafgate.replay.check import check_log

    report = check_log(path, profile="leafgate-dbw")
    assert (report.unknown_frames, report.error_frames) == (2, 2)
    assert report.to_dict()["unknown_id_frames"] == 2 and report.to_dict()["error_frames"] == 2
    assert report.format()[0].startswith(
        f"{path}: 4 frames (2 of an unknown ID, 2 error frames), 0.030 s"
    )
    # the coverage finding counts no error frame among the profile's frames
    (coverage,) = [f for f in report.findings if f.kind == "coverage"]
    assert "a recording of another vehicle?" in coverage.detail


def test_a_screen_dump_of_candump_is_refused_naming_the_log_format(tmp_path: Path) -> None:
    path = tmp_path / "screen.log"
    path.write_text("  can0  284   [8]  05 A0 05 A0 00 00 00 00\n", encoding="utf-8")
    with pytest.raises(ReplayError, match=r"screen.log: unreadable: not a candump -L log"):
        decode_log(path, io.StringIO(), profile="leafgate-dbw")


def test_missing_file_is_a_replay_error(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match=r"nothing\.log: no such file"):
        decode_log(tmp_path / "nothing.log", io.StringIO(), profile="leafgate-dbw")


def test_unknown_format_is_a_one_line_replay_error(tmp_path: Path) -> None:
    path = tmp_path / "drive.xyz"
    path.write_text("hello\n", encoding="utf-8")
    with pytest.raises(ReplayError, match=r"drive\.xyz: .*unknown log format") as info:
        decode_log(path, io.StringIO(), profile="leafgate-dbw")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("name", "content"),
    [("garbage.blf", b"not a blf file" * 20), ("garbage.log", b"this is no candump line\n")],
)
def test_corrupt_log_is_a_one_line_replay_error(tmp_path: Path, name: str, content: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ReplayError, match=f"{name}: unreadable") as info:
        decode_log(path, io.StringIO(), profile="leafgate-dbw")
    assert "\n" not in str(info.value)


def test_the_readable_suffixes_are_one_list_with_what_each_needs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: ``batch check --help`` listed .mf4 as readable, the default install could not
    read it (a reader error quoting python-can's advice), and the README left it out. The help
    texts and the README now list the one set ``batch check`` takes by default, .mf4 with the
    package it needs; without that package an .mf4 is refused saying so."""
    import importlib.util

    from leafgate import cli
    from leafgate.record.logs import NEEDS_PACKAGE, READABLE_SUFFIXES, readable_suffixes_text

    assert readable_suffixes_text() == ".log .asc .blf .trc .csv .mcap; .mf4 needs asammdf"
    assert set(READABLE_SUFFIXES) >= set(NEEDS_PACKAGE)
    for command in (["batch", "check"], ["decode"], ["replay", "check"]):
        with pytest.raises(SystemExit):
            cli.main([*command, "--help"])
        assert readable_suffixes_text() in " ".join(capsys.readouterr().out.split()), command
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    lists = [line for line in readme.splitlines() if "leafgate decode drive/" in line]
    assert lists and all(s in lists[0] for s in READABLE_SUFFIXES)
    assert ".mf4 needs asammdf" in lists[0]
    if importlib.util.find_spec("asammdf") is not None:
        pytest.skip("asammdf is installed here: an .mf4 is read")
    log = tmp_path / "drive.mf4"
    log.write_bytes(b"MDF     4.10    ")
    assert cli.main(["decode", str(log), "--profile", "leafgate-dbw"]) == 1
    assert capsys.readouterr().err == (
        f"leafgate: error: {log}: unreadable: a .mf4 log needs the asammdf package, which is "
        "not installed (pip install asammdf)\n"
    )


def test_replay_check_keeps_29_bit_ids_and_error_frames_apart_from_11_bit_ids(
    tmp_path: Path,
) -> None:
    """``replay check`` keyed its ID table by the raw ID: an error frame was ID 0, and a 29-bit
    ID shared the row of the 11-bit ID of the same number (whose E2E counts are kept apart by
    the codec). One key rule now, :func:`~leafgate.can.codec.frame_key`, for both tools."""
    from leafgate.replay.check import check_log

    codec = CanCodec(profile="leafgate-dbw")
    good = bytes(codec.encode(SteerCommand(0.1, enable=True)).data).hex().upper()
    path = tmp_path / "car.log"
    path.write_text(
        f"(1600000000.000000) can0 0A0#{good}\n"
        "(1600000000.010000) can0 000000A0#0011\n"  # 29-bit 0xA0, not the steering command
        "(1600000000.020000) can0 20000080#0000000000000000\n",  # an error frame
        encoding="utf-8",
    )
    report = check_log(path, profile="leafgate-dbw")
    rows = {row["id"]: row for row in report.to_dict()["ids"]}
    assert set(rows) == {"0x0A0", "0x000000A0", "error"}
    assert rows["0x0A0"]["frames"] == 1 and rows["0x0A0"]["name"] == "DBW_STEER_CMD"
    assert rows["error"]["name"] == "error frames"
    table = report.format()
    assert any(line.split()[:3] == ["error", "error", "frames"] for line in table)
    assert any(line.split()[:2] == ["000000A0", "?"] for line in table)
    # the ID column is as wide as the 29-bit ID: every row's name starts under the header's
    header = next(line for line in table if line.split()[:2] == ["ID", "name"])
    starts = {line.index(line.split()[1], len(line.split()[0])) for line in table[2:5]}
    assert starts == {header.index("name")}, table
