"""``leafgate replay play LOG… -i … -c …``: timed playback onto a CAN bus.

``--ids commands`` or ``--ids reports`` plays the vehicle profile's command or report frames
(the profile from ``--profile``, ``--config`` or a session's recorded configuration).

Frames are sent at their recorded spacing (divided by ``speed``) on absolute deadlines of a
monotonic clock, so the playback does not drift over a long log; ``start`` skips the first
seconds of the log and ``ids`` plays only the listed IDs — e.g. only the gateway's commands
(0x0A0–0x0A2) to drive the simulated ECU or a bench ECU, or only the ECU's reports to feed a
gateway. Without ``ids`` the gateway's own command IDs are left out (``--all-ids`` plays them),
so a playback onto a live bus never commands the car. They are the vehicle profile's: a
session names its own; a CAN log names none, and there is no default (another car's log would
play its commands and leave out only the default car's), so without ``--profile`` or
``--config`` the playback of a CAN log is refused. A session's ``/can`` topic plays as well,
and a rotated log plays as one when its parts are given in order. Parts whose times do not
continue each other — the next part starts more than :data:`MAX_PART_JUMP` s after the
previous one ends, or more than :data:`MAX_PART_BACK` s before — are refused before any frame is
sent, naming the two files: played on, the gap would be waited out (at ``--speed 1``, possibly
for years), and frames from before the log's first one cannot be placed on its timeline.
Frames that are not played are counted by reason (before ``--start``, not in ``--ids``,
out of order: earlier than the log's first frame); an out-of-order frame is a selected frame
left unsent, so the playback then exits with status 1.

Playback is a tool, not the control path: a send error stops it with an error.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import can

from leafgate.can.bus import copy_frame, open_bus
from leafgate.can.profile import PROFILE_NAMES
from leafgate.cliargs import non_negative_number, non_negative_seconds
from leafgate.config.can import BusConfig
from leafgate.errors import BusError, ConfigError, ReplayError
from leafgate.record.logs import FrameSource, group_parts, is_end_marker, is_session
from leafgate.text import plural

__all__ = [
    "MAX_PART_BACK",
    "MAX_PART_JUMP",
    "PlayStats",
    "add_arguments",
    "check_continuity",
    "default_ids",
    "main_play",
    "parse_ids",
    "play_frames",
    "play_from_args",
]


#: s: the largest forward jump from one part's last frame to the next part's first that a
#: playback of several files accepts (a rotated log's parts follow each other within ms).
MAX_PART_JUMP = 60.0
#: s: the largest backward jump accepted there (clock jitter; more is the wrong order or
#: another recording).
MAX_PART_BACK = 1.0


@dataclass(frozen=True)
class PlayStats:
    """What a playback did."""

    sent: int  # frames sent
    skipped: int  # frames not sent: the sum of the reasons below
    duration: float  # s of log time played
    wall_time: float  # s
    max_lateness: float  # s, worst delay of a send behind its deadline
    before_start: int = 0  # frames within --start of the first frame
    not_selected: int = 0  # frames whose ID is not in --ids
    markers: int = 0  # end-of-recording markers (not frames of the drive)
    out_of_order: int = 0  # frames timed before the log's first frame: no place on its timeline

    def to_dict(self) -> dict[str, Any]:
        return vars(self).copy()

    def skipped_text(self, start: float = 0.0) -> str:
        """``"12 skipped: 10 before --start 5 s, 2 not in --ids"`` (just ``"0 skipped"``)."""
        reasons = [
            (self.before_start, f"before --start {start:g} s"),
            (self.not_selected, "not in --ids"),
            (self.markers, "end-of-recording markers"),
            (self.out_of_order, "out of order: timed before the log's first frame"),
        ]
        parts = [f"{n} {why}" for n, why in reasons if n]
        return f"{self.skipped} skipped" + (f": {', '.join(parts)}" if parts else "")


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
    sent = before_start = not_selected = markers = out_of_order = 0
    t0_log: float | None = None  # log time of the first frame
    base_log: float | None = None  # log time that maps to base_wall
    base_wall = clock()
    last_log = 0.0
    max_late = 0.0
    for msg in frames:
        if is_end_marker(msg):  # the recorder's, not a frame of the drive
            markers += 1
            continue
        if t0_log is None:
            t0_log = msg.timestamp
        if ids is not None and msg.arbitration_id not in ids:
            not_selected += 1
            continue
        if msg.timestamp < t0_log:
            out_of_order += 1
            continue
        if msg.timestamp - t0_log < start:
            before_start += 1
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
            bus.send(copy_frame(msg, timestamp=0.0, channel=None, is_error_frame=False, is_rx=True))
        except can.CanError as exc:
            raise BusError(
                f"playback stopped after {plural(sent, 'frame')}: send failed: {exc}"
            ) from None
        sent += 1
    return PlayStats(
        sent=sent,
        skipped=before_start + not_selected + markers + out_of_order,
        duration=0.0 if base_log is None else last_log - base_log,
        wall_time=clock() - base_wall,
        max_lateness=max_late,
        before_start=before_start,
        not_selected=not_selected,
        markers=markers,
        out_of_order=out_of_order,
    )


def _profile_ids(
    log: str | Path, side: str, config: str | Path | None, profile: str | None
) -> frozenset[int]:
    """The IDs of the profile's command or report frames (``--ids commands|reports``)."""
    from leafgate.can.codec import CanCodec
    from leafgate.record.logs import recording_context

    context = recording_context(log, config=config, profile=profile)
    codec = CanCodec(context.config.can.dbw_dbc, context.config.can.car_dbc, context.profile)
    if side == "commands":
        return codec.receive_ids("commands")
    return codec.receive_ids("reports") | codec.receive_ids("car")


def default_ids(
    config: str | Path | None,
    *,
    ids: str | None,
    all_ids: bool,
    log: str | Path,
    profile: str | None = None,
) -> tuple[frozenset[int] | None, frozenset[int]]:
    """Which IDs to play: (only these or None for any, never these).

    By default the gateway's own command IDs are left out: played onto a bus where a gateway
    runs, they are a second node commanding the car, and the gateway faults ("command
    conflict"). They are the command IDs of the vehicle profile from ``profile``, ``config`` or
    the session's recorded configuration; there is no default profile, as another car's
    commands would then be played and only the default car's left out. ``ids`` (explicit hex
    IDs) or ``all_ids`` needs no profile and plays them.

    :raises ConfigError: a profile is needed and neither given nor recorded (a CAN log)
    """
    if ids and ids not in ("commands", "reports"):
        return parse_ids(ids), frozenset()
    if all_ids:
        return None, frozenset()
    if config is None and profile is None and not is_session(log):
        # A usage error (exit 2), before any frame is sent: a CAN log names no profile.
        raise ConfigError(
            f"{log}: a CAN log names no vehicle profile, so the gateway's command IDs are "
            f"unknown; give --profile NAME|FILE ({', '.join(PROFILE_NAMES)}) or --config "
            "FILE (or --ids / --all-ids)"
        )
    if ids:  # "commands" or "reports": the profile's frames of one side
        return _profile_ids(log, ids, config, profile), frozenset()
    return None, _profile_ids(log, "commands", config, profile)


def chained(sources: Sequence[FrameSource]) -> Iterator[can.Message]:
    """The frames of several files in the order given (a rotated log's parts).

    Check the parts first with :func:`check_continuity`: this chains whatever it is given.
    """
    for source in sources:
        yield from source


def _time_span(path: Path) -> tuple[float, float] | None:
    """The timestamps of a file's first and last frame (None: no frames)."""
    first: float | None = None
    last = 0.0
    for msg in FrameSource(path):
        if first is None:
            first = msg.timestamp
        last = msg.timestamp
    return None if first is None else (first, last)


def check_continuity(
    paths: Sequence[str | Path],
    max_jump: float = MAX_PART_JUMP,
    max_back: float = MAX_PART_BACK,
) -> None:
    """Refuse files whose times do not continue each other, before anything is played.

    Each part must start at most ``max_jump`` s after the previous one (with frames) ends and
    at most ``max_back`` s before. Reads every part once (one file: nothing to check).

    :raises ReplayError: naming the two files, their times and the jump
    """
    if len(paths) < 2:
        return
    previous: tuple[Path, float] | None = None  # (file, its last frame's time)
    for path in map(Path, paths):
        span = _time_span(path)
        if span is None:
            continue
        first, last = span
        if previous is not None:
            prev_path, prev_last = previous
            jump = first - prev_last
            if jump > max_jump or jump < -max_back:
                direction = "after" if jump > 0 else "before"
                raise ReplayError(
                    f"replay play: {path} starts {abs(jump):.3f} s {direction} {prev_path} ends "
                    f"(at {first:.6f} s, the other's last frame at {prev_last:.6f} s): not parts "
                    f"of one log in order (accepted: up to {max_jump:g} s after, {max_back:g} s "
                    "before); play them one at a time"
                )
        previous = (path, last)


def main_play(
    logs: str | Path | Sequence[str | Path],
    *,
    bus: BusConfig | None = None,
    speed: float = 1.0,
    start: float = 0.0,
    ids: str | None = None,
    all_ids: bool = False,
    out: TextIO | None = None,
    config: str | Path | None = None,
    profile: str | None = None,
) -> int:
    """``leafgate replay play LOG… [-i I -c C [-b B] [--bus-kwargs K=V …] | --config F]``.

    :param logs: one log, or the parts of one recording (a rotated log's, a session and its
        resumptions) in any order: :func:`group_parts` puts them in theirs
    :param bus: the bus to play onto; None: the config's dbw bus (its bench's port)
    :param config: the deployment config: its bus, and its profile's command IDs to leave out
    :param profile: the vehicle profile whose command IDs are left out (over the config's)
    :param ids: play only these IDs (hex, comma-separated), the gateway's commands included
    :param all_ids: play every frame, the gateway's commands included
    :return: 0 when every selected frame was sent; 1 when some were out of order (timed
        before the log's first frame) and left unsent
    :raises LeafgateError: unreadable log, parts whose times do not continue each other
        (:func:`check_continuity`), no profile for a CAN log (:class:`ConfigError`), unknown
        interface or a send error (the CLI prints it)
    """
    out = out or sys.stdout
    given = [logs] if isinstance(logs, (str, Path)) else list(logs)
    # one recording's parts in their order (a glob sorts session.2.mcap before session.mcap)
    paths: list[str | Path] = [path for group in group_parts(given) for path in group.paths]
    sources = [FrameSource(path) for path in paths]  # a missing file first: the plainer error
    check_continuity(paths)
    if bus is None:
        if config is None:
            raise ReplayError("replay play: give the bus (-i INTERFACE -c CHANNEL) or --config")
        from leafgate.settings import load_config

        bus = load_config(config).can.dbw
    wanted, excluded = default_ids(config, ids=ids, all_ids=all_ids, log=paths[0], profile=profile)
    left_out = 0  # counted here, not as the rest of the file's frames: those hold end markers

    def without_commands(frames: Iterable[can.Message]) -> Iterator[can.Message]:
        nonlocal left_out
        for msg in frames:
            if msg.arbitration_id in excluded:
                left_out += 1
            else:
                yield msg

    frames: Iterable[can.Message] = chained(sources)
    if excluded:
        frames = without_commands(frames)
    opened = open_bus(bus)
    try:
        stats = play_frames(frames, opened, speed=speed, start=start, ids=wanted)
    finally:
        opened.shutdown()
    names = Path(paths[0]).name + (f" and {len(paths) - 1} more" if len(paths) > 1 else "")
    out.write(
        f"{names}: {plural(stats.sent, 'frame')} sent ({stats.skipped_text(start)}"
        + (
            f"; {left_out} of the gateway's command IDs "
            f"{', '.join(f'{i:03X}' for i in sorted(excluded))} left out: --all-ids plays them"
            if excluded
            else ""
        )
        + f"), {stats.duration:.3f} s of log in {stats.wall_time:.3f} s, "
        f"worst lateness {stats.max_lateness * 1e3:.2f} ms\n"
    )
    if stats.out_of_order:
        print(
            f"leafgate replay play: {plural(stats.out_of_order, 'frame')} not sent: timed before the "
            "log's first frame (out of order), so they have no place on its timeline",
            file=sys.stderr,
        )
        return 1
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``replay play`` options: the bus as python-can's tools take it (``-i/-c/-b``,
    ``--bus-kwargs``), or a leafgate config."""
    from can.cli import add_bus_arguments

    parser.add_argument("log", nargs="+", help="log file(s); a rotated log's parts in order")
    add_bus_arguments(parser, group_title="bus (as python-can's can.player)")
    parser.add_argument(
        "--config",
        help="leafgate config: its dbw bus when -i is not given (config/sim.yaml: the bench's "
        "port), and its vehicle profile's command IDs",
    )
    parser.add_argument(
        "--profile",
        metavar="NAME|FILE",
        help="vehicle profile whose command IDs are left out (or played by --ids commands|reports); "
        "a CAN log names none: give it or --config (a session's recorded one is used)",
    )
    parser.add_argument(
        "--speed",
        type=non_negative_number,
        default=1.0,
        help="speed factor (0: as fast as possible)",
    )
    parser.add_argument(
        "--start", type=non_negative_seconds, default=0.0, help="s into the log to start at"
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--ids",
        help="only these IDs, hex, comma-separated (e.g. 0A0,0A1), or 'commands' / 'reports': "
        "the profile's command or report frames; may include the gateway's commands",
    )
    which.add_argument(
        "--all-ids",
        action="store_true",
        help="play the gateway's command IDs too (left out by default: onto a bus where a "
        "gateway runs, they fault it with a command conflict)",
    )


def play_from_args(args: argparse.Namespace) -> int:
    """Run ``replay play`` from the options of :func:`add_arguments`."""
    bus = None
    # python-can's options are absent from the namespace unless given (argparse.SUPPRESS)
    interface, channel = getattr(args, "interface", None), getattr(args, "channel", None)
    if interface is not None or channel is not None:
        if interface is None or channel is None:
            raise ReplayError("replay play: -i INTERFACE and -c CHANNEL go together")
        try:
            bus = BusConfig(
                interface=interface,
                channel=str(channel),
                bitrate=getattr(args, "bitrate", None) or 500_000,
                kwargs=dict(getattr(args, "bus_kwargs", None) or {}),
            )
        except ValueError as exc:
            raise ReplayError(f"replay play: {exc}") from None
    return main_play(
        args.log,
        bus=bus,
        config=args.config,
        speed=args.speed,
        start=args.start,
        ids=args.ids,
        all_ids=args.all_ids,
        profile=args.profile,
    )
