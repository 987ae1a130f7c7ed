"""``leafgate replay play``: python-can's bus options, the gateway's command IDs left out by
default (a playback onto a live bus must not command the car), rotated logs as one."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from leafgate.cli import main

REPORT, COMMAND = 0x0B0, 0x0A0  # DBW_STEER_RPT, DBW_STEER_CMD of the leafgate-dbw profile


def _write(path: Path, start: float, ids: tuple[int, ...], n: int = 10) -> None:
    with can.Logger(path) as writer:
        for i in range(n):
            writer.on_message_received(
                can.Message(
                    timestamp=start + 0.01 * i,
                    arbitration_id=ids[i % len(ids)],
                    data=bytes([i] * 8),
                    is_extended_id=False,
                )
            )


def _received(argv: list[str], channel: str) -> list[can.Message]:
    with can.Bus(interface="virtual", channel=channel) as rx:
        assert main(["replay", "play", *argv, "-i", "virtual", "-c", channel, "--speed", "0"]) == 0
        got = []
        while (msg := rx.recv(timeout=0.0)) is not None:
            got.append(msg)
    return got


def _play(argv: list[str], channel: str) -> list[int]:
    return [msg.arbitration_id for msg in _received(argv, channel)]


def test_command_ids_left_out_by_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path / "drive.log", 100.0, (REPORT, COMMAND))
    got = _play([str(tmp_path / "drive.log"), "--profile", "leafgate-dbw"], "play-cli-1")
    # old code: every frame, the gateway's commands included, went onto the bus
    assert got == [REPORT] * 5
    out = capsys.readouterr().out
    assert "5 of the gateway's command IDs" in out and "--all-ids" in out


def test_all_ids_and_explicit_ids_play_commands(tmp_path: Path) -> None:
    _write(tmp_path / "drive.log", 100.0, (REPORT, COMMAND))
    assert (
        _play([str(tmp_path / "drive.log"), "--all-ids"], "play-cli-2")
        == [
            REPORT,
            COMMAND,
        ]
        * 5
    )
    assert _play([str(tmp_path / "drive.log"), "--ids", "0A0"], "play-cli-3") == [COMMAND] * 5


def test_rotated_parts_play_in_order(tmp_path: Path) -> None:
    _write(tmp_path / "can-1_000.log", 100.0, (REPORT,), n=4)
    _write(tmp_path / "can-1_001.log", 100.04, (REPORT + 1,), n=3)
    parts = sorted(str(p) for p in tmp_path.glob("can-*.log"))  # as the shell expands the glob
    assert (
        _play([*parts, "--profile", "leafgate-dbw"], "play-cli-4")
        == [REPORT] * 4 + [REPORT + 1] * 3
    )


def test_bus_kwargs_reach_the_bus_and_a_bus_is_required(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path / "drive.log", 100.0, (REPORT,))
    log = str(tmp_path / "drive.log")
    assert main(["replay", "play", log]) == 1
    assert "give the bus (-i INTERFACE -c CHANNEL) or --config" in capsys.readouterr().err
    # virtual's preserve_timestamps: the receiver sees the sent frame's own stamp (0: unset)
    plain = _received([log, "--profile", "leafgate-dbw"], "play-cli-5")
    kept = _received(
        [log, "--profile", "leafgate-dbw", "--bus-kwargs", "preserve_timestamps=True"], "play-cli-6"
    )
    assert len(kept) == len(plain) == 10
    assert all(m.timestamp == 0.0 for m in kept) and all(m.timestamp > 0.0 for m in plain)
    assert (
        main(["replay", "play", log, "-i", "virtual", "-c", "x", "--bus-kwargs", "channel=y"]) == 1
    )
    assert "kwargs must not repeat channel" in capsys.readouterr().err


def test_replay_check_takes_a_rotated_logs_parts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path / "can-1_000.log", 100.0, (REPORT,), n=4)
    _write(tmp_path / "can-1_001.log", 100.04, (REPORT,), n=3)
    parts = sorted(str(p) for p in tmp_path.glob("can-*.log"))
    # old code: "unrecognized arguments" (one log only), exit 2
    status = main(["replay", "check", *parts, "--profile", "leafgate-dbw"])
    out = capsys.readouterr().out
    assert status in (0, 1) and "can-1_000.log" in out and "can-1_001.log" in out
    missing = str(tmp_path / "missing.log")
    assert main(["replay", "check", parts[0], missing, "--profile", "leafgate-dbw"]) == 1
    assert "missing.log" in capsys.readouterr().err
