"""Timed playback of a recorded log onto a bus: spacing, speed factor, start offset, ID filter."""

from __future__ import annotations

import io
from pathlib import Path

import can
import pytest

from leafgate import cli
from leafgate.config.can import BusConfig
from leafgate.errors import ConfigError, ReplayError
from leafgate.record.logs import FrameSource, end_marker
from leafgate.replay.play import main_play, parse_ids, play_frames


def log(path: Path) -> list[can.Message]:
    frames = [
        can.Message(
            timestamp=100.0 + 0.01 * i,
            arbitration_id=0x0A0 + i % 3,
            data=bytes([i] * 8),
            is_extended_id=False,
        )
        for i in range(30)
    ]
    with can.Logger(path) as writer:
        for f in frames:
            writer.on_message_received(f)
    return frames


class FakeClock:
    """A clock that only moves when the player sleeps."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.now += dt


def test_frames_leave_at_their_recorded_spacing_divided_by_speed() -> None:
    frames = [can.Message(timestamp=t, arbitration_id=1) for t in (5.0, 5.1, 5.4)]
    clock = FakeClock()
    with can.Bus(interface="virtual", channel="play-1") as bus:
        stats = play_frames(frames, bus, speed=2.0, clock=clock, sleep=clock.sleep)
    assert stats.sent == 3 and stats.duration == pytest.approx(0.4)
    assert clock.sleeps == pytest.approx([0.05, 0.15])  # (0.1, 0.3 s) / 2


def test_start_offset_and_id_filter_select_frames(tmp_path: Path) -> None:
    frames = log(tmp_path / "drive.log")
    with (
        can.Bus(interface="virtual", channel="play-2") as rx,
        can.Bus(interface="virtual", channel="play-2") as tx,
    ):
        stats = play_frames(
            FrameSource(tmp_path / "drive.log"), tx, speed=0, start=0.1, ids=parse_ids("0A0,0x0A2")
        )
        got = []
        while (msg := rx.recv(timeout=0.0)) is not None:
            got.append(msg)
    expected = [
        f for f in frames if f.timestamp - 100.0 >= 0.1 - 1e-9 and f.arbitration_id != 0x0A1
    ]
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [
        (f.arbitration_id, bytes(f.data)) for f in expected
    ]
    assert stats.sent == len(expected) and stats.skipped == len(frames) - len(expected)


def test_main_play_sends_a_log_onto_a_virtual_bus(tmp_path: Path) -> None:
    frames = log(tmp_path / "drive.log")
    with can.Bus(interface="virtual", channel="play-3") as rx:
        out = io.StringIO()
        assert (
            main_play(
                tmp_path / "drive.log",
                bus=BusConfig(interface="virtual", channel="play-3"),
                speed=0,
                all_ids=True,
                out=out,
            )
            == 0
        )
        got = 0
        while rx.recv(timeout=0.0) is not None:
            got += 1
    assert got == len(frames)
    assert f"{len(frames)} frames sent" in out.getvalue()


def test_bad_ids_and_missing_logs_are_replay_errors(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="not a hexadecimal"):
        parse_ids("0A0,zz")
    with pytest.raises(ReplayError, match="no such file"):
        main_play(tmp_path / "missing.log", bus=BusConfig(interface="virtual", channel="x"))


def other_cars_log(path: Path) -> dict[int, int]:
    """A sze-hlc drive: its commands (0x001, 0x005) and a report, ended by the recorder's marker.

    :return: frames per ID
    """
    ids = (0x001, 0x005, 0x123)
    with can.Logger(path) as writer:
        for i in range(30):
            writer.on_message_received(
                can.Message(timestamp=10.0 + 0.01 * i, arbitration_id=ids[i % 3], data=bytes(8))
            )
        writer.on_message_received(end_marker(10.5))
    return {i: 10 for i in ids}


def received(bus: can.BusABC) -> list[int]:
    got = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        got.append(msg.arbitration_id)
    return got


def test_a_can_log_without_a_profile_is_refused_not_played_as_leafgate_dbw(
    tmp_path: Path,
) -> None:
    """There is no default profile: leafgate-dbw's would leave out 0x0A0–0x0A2 and play the
    other car's commands onto the bus."""
    other_cars_log(tmp_path / "hlc.log")
    with can.Bus(interface="virtual", channel="play-4") as rx:
        with pytest.raises(ConfigError, match=r"hlc\.log: .*--profile"):
            main_play(tmp_path / "hlc.log", bus=BusConfig(interface="virtual", channel="play-4"))
        assert received(rx) == []


def test_the_cli_refuses_a_can_log_without_a_profile_with_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other_cars_log(tmp_path / "hlc.log")
    argv = ["replay", "play", str(tmp_path / "hlc.log"), "-i", "virtual", "-c", "play-5"]
    with can.Bus(interface="virtual", channel="play-5") as rx:
        assert cli.main(argv) == cli.EXIT_USAGE
        assert received(rx) == []
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--profile" in err and "Traceback" not in err


def test_the_profiles_commands_are_left_out_and_counted_without_the_end_marker(
    tmp_path: Path,
) -> None:
    counts = other_cars_log(tmp_path / "hlc.log")
    out = io.StringIO()
    with can.Bus(interface="virtual", channel="play-6") as rx:
        main_play(
            tmp_path / "hlc.log",
            bus=BusConfig(interface="virtual", channel="play-6"),
            speed=0,
            profile="sze-hlc",
            out=out,
        )
        got = received(rx)
    assert got == [0x123] * counts[0x123]
    assert "10 frames sent (0 skipped; 20 of the gateway's command IDs 001, 005 left out" in (
        out.getvalue()
    )


def test_explicit_ids_or_all_ids_need_no_profile(tmp_path: Path) -> None:
    counts = other_cars_log(tmp_path / "hlc.log")
    with can.Bus(interface="virtual", channel="play-7") as rx:
        bus = BusConfig(interface="virtual", channel="play-7")
        main_play(tmp_path / "hlc.log", bus=bus, speed=0, ids="123", out=io.StringIO())
        assert received(rx) == [0x123] * counts[0x123]
        main_play(tmp_path / "hlc.log", bus=bus, speed=0, all_ids=True, out=io.StringIO())
        assert len(received(rx)) == sum(counts.values())  # the end marker is not played


def timed_log(path: Path, t0: float, n: int = 20) -> None:
    with can.Logger(path) as writer:
        for i in range(n):
            writer.on_message_received(
                can.Message(timestamp=t0 + 0.01 * i, arbitration_id=0x123, data=bytes(8))
            )


@pytest.mark.parametrize("order", ["foreign-first", "fresh-first"])
def test_parts_whose_times_do_not_continue_are_refused_before_anything_is_sent(
    tmp_path: Path, order: str
) -> None:
    """A foreign log from 2023 and a fresh recording: in one order the playback would wait out
    years at --speed 1, in the other skip the second file as if before --start."""
    timed_log(tmp_path / "foreign.log", 1_700_000_000.0)
    timed_log(tmp_path / "fresh.log", 1_790_000_000.0)
    parts = [tmp_path / "foreign.log", tmp_path / "fresh.log"]
    if order == "fresh-first":
        parts.reverse()
    with can.Bus(interface="virtual", channel="play-8") as rx:
        bus = BusConfig(interface="virtual", channel="play-8")
        with pytest.raises(ReplayError) as info:
            main_play(parts, bus=bus, speed=1, all_ids=True, out=io.StringIO())
        assert received(rx) == []
    text = str(info.value)
    assert str(parts[0]) in text and str(parts[1]) in text
    assert ("after" if order == "foreign-first" else "before") in text


def test_parts_that_continue_each_other_play_as_one_log(tmp_path: Path) -> None:
    timed_log(tmp_path / "part1.log", 100.0)
    timed_log(tmp_path / "part2.log", 100.2)  # 10 ms after part 1's last frame
    out = io.StringIO()
    with can.Bus(interface="virtual", channel="play-9") as rx:
        bus = BusConfig(interface="virtual", channel="play-9")
        parts = [tmp_path / "part1.log", tmp_path / "part2.log"]
        assert main_play(parts, bus=bus, speed=0, all_ids=True, out=out) == 0
        assert len(received(rx)) == 40
    assert "40 frames sent (0 skipped)" in out.getvalue()


def test_skipped_frames_are_counted_by_reason() -> None:
    frames = [
        can.Message(timestamp=t, arbitration_id=i)
        for t, i in ((10.0, 1), (10.1, 2), (10.5, 1), (9.0, 1), (10.6, 1))
    ]
    with can.Bus(interface="virtual", channel="play-10") as bus:
        stats = play_frames(frames, bus, speed=0, start=0.2, ids={1})
    assert (stats.sent, stats.skipped) == (2, 3)
    assert (stats.before_start, stats.not_selected, stats.out_of_order) == (1, 1, 1)
    assert stats.skipped_text(0.2) == (
        "3 skipped: 1 before --start 0.2 s, 1 not in --ids, "
        "1 out of order: timed before the log's first frame"
    )


def test_out_of_order_frames_are_said_and_fail_the_playback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "mixed.log").write_text(  # written as is: python-can's writer reorders
        "".join(f"({t:.6f}) vcan0 123#00\n" for t in (100.0, 100.01, 50.0, 100.02))
    )
    out = io.StringIO()
    with can.Bus(interface="virtual", channel="play-11") as rx:
        bus = BusConfig(interface="virtual", channel="play-11")
        status = main_play(tmp_path / "mixed.log", bus=bus, speed=0, all_ids=True, out=out)
        assert len(received(rx)) == 3
    assert status == 1
    assert "1 skipped: 1 out of order" in out.getvalue()
    assert "1 frame not sent: timed before" in capsys.readouterr().err  # not "1 frames"
