"""``leafgate replay play LOG --interface … --channel …``: timed playback onto a CAN bus.

``--ids commands`` or ``--ids reports`` plays the vehicle profile's command or report frames
(the profile from ``--profile``, ``--config`` or a session's recorded configuration).

Frames are sent at their recorded spacing (divided by ``speed``) on absolute deadlines of a
monotonic clock, so the playback does not drift over a long log; ``start`` skips the first
seconds of the log and ``ids`` plays only the listed IDs — e.g. only the gateway's commands
(0x0A0–0x0A2) to drive the simulated ECU or a bench ECU, or only the ECU's reports to feed a
gateway. A session's ``/can`` topic plays as well.

Playback is a tool, not the control path: a send error stops it with an error.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import can

from leafgate.can.bus import open_bus
from leafgate.can.config import BusConfig
from leafgate.errors import BusError, ReplayError
from leafgate.replay.logs import FrameSource, is_end_marker

__all__ = ["PlayStats", "main_play", "parse_ids", "play_frames"]


@dataclass(frozen=True)
class PlayStats:
    """What a playback did."""

    sent: int  # frames sent
    skipped: int  # frames before the start offset or filtered out
    duration: float  # s of log time played
    wall_time: float  # s
    max_lateness: float  # s, worst delay of a send behind its deadline

    def to_dict(self) -> dict[str, Any]:
        return vars(self).copy()


def parse_ids(text: str | None) -> frozenset[int] | None:
    """``"0A0,0A1,0x0A2"`` (hex) → a set of IDs; None or empty → None (all).

    :raises ReplayError: an item is not a hexadecimal ID
    """
    if not text:
        return None
    ids = set()
    for item in text.replace(" ", "").split(","):
        if not item:
            continue
        try:
            ids.add(int(item, 16))
        except ValueError:
            raise ReplayError(f"--ids {text!r}: {item!r} is not a hexadecimal CAN ID") from None
    return frozenset(ids)


def _copy(msg: can.Message) -> can.Message:
    """The frame as sent: data and flags kept, timestamp and channel left to the bus."""
    return can.Message(
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_fd=msg.is_fd,
        bitrate_switch=msg.bitrate_switch,
        dlc=msg.dlc,
        data=msg.data,
    )


def play_frames(
    frames: Iterable[can.Message],
    bus: can.BusABC,
    *,
    speed: float = 1.0,
    start: float = 0.0,
    ids: Collection[int] | None = None,
    clock: Callable[[], float] = time.perf_counter,
    sleep: Callable[[float], None] = time.sleep,
) -> PlayStats:
    """Send recorded frames onto ``bus`` at their recorded spacing.

    :param speed: playback speed factor (2 = twice as fast); 0 sends as fast as possible
    :param start: s of log time to skip from the first frame
    :param ids: play only these IDs (None: all)
    :param clock: monotonic clock, s (injectable for tests)
    :param sleep: how to wait, s
    :raises BusError: a frame could not be sent
    """
    if speed < 0:
        raise ReplayError(f"speed must be 0 (as fast as possible) or positive, got {speed}")
    sent = skipped = 0
    t0_log: float | None = None  # log time of the first frame
    base_log: float | None = None  # log time that maps to base_wall
    base_wall = clock()
    last_log = 0.0
    max_late = 0.0
    for msg in frames:
        if t0_log is None:
            t0_log = msg.timestamp
        if (
            msg.timestamp - t0_log < start
            or (ids is not None and msg.arbitration_id not in ids)
            or is_end_marker(msg)  # the recorder's, not a frame of the drive
        ):
            skipped += 1
            continue
        if base_log is None:
            base_log, base_wall = msg.timestamp, clock()
        last_log = msg.timestamp
        if speed > 0:
            deadline = base_wall + (msg.timestamp - base_log) / speed
            now = clock()
            if now < deadline:
                sleep(deadline - now)
            else:
                max_late = max(max_late, now - deadline)
        try:
            bus.send(_copy(msg))
        except can.CanError as exc:
            raise BusError(f"playback stopped after {sent} frames: send failed: {exc}") from None
        sent += 1
    return PlayStats(
        sent=sent,
        skipped=skipped,
        duration=0.0 if base_log is None else last_log - base_log,
        wall_time=clock() - base_wall,
        max_lateness=max_late,
    )


def _profile_ids(
    log: str | Path, side: str, config: str | Path | None, profile: str | None
) -> frozenset[int]:
    """The IDs of the profile's command or report frames (``--ids commands|reports``)."""
    from leafgate.can.codec import CanCodec
    from leafgate.replay.logs import recording_context

    context = recording_context(log, config=config, profile=profile)
    codec = CanCodec(context.config.can.dbw_dbc, context.config.can.car_dbc, context.profile)
    if side == "commands":
        return codec.receive_ids("commands")
    return codec.receive_ids("reports") | codec.receive_ids("car")


def main_play(
    log: str | Path,
    *,
    interface: str,
    channel: str,
    speed: float = 1.0,
    start: float = 0.0,
    ids: str | None = None,
    bitrate: int = 500_000,
    bus_kwargs: dict[str, Any] | None = None,
    out: TextIO | None = None,
    config: str | Path | None = None,
    profile: str | None = None,
) -> int:
    """``leafgate replay play LOG --interface I --channel C [--speed F] [--start S] [--ids …]``.

    :return: 0 when every selected frame was sent
    :raises LeafgateError: unreadable log, unknown interface or a send error (the CLI prints it)
    """
    out = out or sys.stdout
    if ids in ("commands", "reports"):  # the profile's frames of one side
        wanted: frozenset[int] | None = _profile_ids(log, ids, config, profile)
    else:
        wanted = parse_ids(ids)
    source = FrameSource(log)
    bus = open_bus(
        BusConfig(
            interface=interface, channel=channel, bitrate=bitrate, kwargs=dict(bus_kwargs or {})
        )
    )
    try:
        stats = play_frames(source, bus, speed=speed, start=start, ids=wanted)
    finally:
        bus.shutdown()
    out.write(
        f"{Path(log).name}: {stats.sent} frames sent ({stats.skipped} skipped), "
        f"{stats.duration:.3f} s of log in {stats.wall_time:.3f} s, "
        f"worst lateness {stats.max_lateness * 1e3:.2f} ms\n"
    )
    return 0
