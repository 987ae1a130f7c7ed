"""``leafgate decode LOG``: print a recorded CAN log decoded with the leafgate DBCs.

Reads any format python-can's :class:`can.LogReader` reads (``.log`` candump, ``.asc``,
``.blf``, ``.trc``, ``.csv``, ``.mf4`` with asammdf, and the same gzip-compressed) and the
``/can`` topic of a session (``.mcap``), through :class:`leafgate.record.logs.FrameSource`; prints one
line per frame and, at the end, how many frames of each ID were received and how many failed
each check. The frames are read with a vehicle profile (``--profile``, ``--config``, or a
session's recorded configuration), whose checks include the car's own counters and checksums
(0x002, 0x176, 0x284, 0x285 on the AZE0). The E2E checks are those of the gateway (:class:`~leafgate.can.codec.CanCodec`),
run with one codec per recorded channel, so a dropped frame in the log shows up as a
``bad_counter`` on the frame after it — unless the recorder lost frames in between (a part
given up after a write failure, frames dropped as its queue overflowed: its markers say so),
when the line says ``counter not judged: the recorder lost frames before it`` and the summary
counts it apart from ``bad_cnt``.

A line reads::

    12.345678  can0  0A0  [8]  DBW_STEER_CMD(STEER_ANGLE_CMD: 0.1 rad, ...)  ok

i.e. timestamp (s), channel, ID, length, then the signals in the style of ``cantools decode
--single-line`` (value-table names for enums), then ``ok`` or the error. An error frame (a
controller's report of a bus error) has ``error`` for its ID and ``error_frame`` for its
status; the summary counts error frames in a row of their own (frames, never ``unknown``: they
are not frames of an unknown ID, and the total's ``unknown`` leaves them out; the first line
says how many), and 29-bit IDs apart from the 11-bit ID of the same number
(:func:`~leafgate.can.codec.frame_key`).

Authenticated frames (profile ``leafgate-dbw-auth``) are verified only with the key
(``--key-file``, or the ``--config``'s ``can.auth_key_file``): a bad MAC or a stale freshness
value is the frame's error. Without the key they are decoded and marked ``ok (MAC not
verified)``, and the summary says that no MAC was checked.

Several files: the parts of a rotated log (``can-…_000.blf``, ``can-…_001.blf`` …) are
decoded in order as one log (one summary; a part missing from the numbering is named in it),
other files each alone. The summary's first line says when the recording is incomplete: a
session cut before its footer "(truncated session)" (of several parts, the part named:
:meth:`~leafgate.record.logs.ChainedSource.truncation`), a log or session without the
recorder's end-of-recording marker "no end-of-recording marker", frames the recorder dropped.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TextIO

import can

from leafgate.can.codec import (
    ERROR_FRAME_KEY,
    CanCodec,
    Decoded,
    FrameStats,
    stats_label,
)
from leafgate.can.profile import Profile
from leafgate.record.logs import ChainedSource, LogParts, group_parts, unread_next_part
from leafgate.text import plural

__all__ = ["authentication_summary", "decode_log", "format_frame", "format_summary"]


def _value_text(value: object, unit: str | None) -> str:
    text = f"{value:.6g}" if isinstance(value, float) else str(value)
    return f"{text} {unit}" if unit else text


def format_frame(
    codec: CanCodec, msg: can.Message, decoded: Decoded, status: str | None = None
) -> str:
    """One log line for a frame and its decode result (see the module docstring); ``status``
    in place of the result's ``ok`` or error."""
    channel = "-" if msg.channel is None else str(msg.channel)
    width = 8 if msg.is_extended_id else 3
    data = bytes(msg.data)
    label = "error" if msg.is_error_frame else f"{msg.arbitration_id:0{width}X}"
    head = f"{msg.timestamp:.6f}  {channel}  {label}  [{len(data)}]"
    message = (
        None
        if decoded.error in ("unknown_id", "wrong_length")
        else codec.message(msg.arbitration_id)
    )
    body = None
    if message is not None:
        try:
            signals = message.decode(data, decode_choices=True, scaling=True)
        except Exception:  # shown raw below; the codec already classified the frame
            signals = None
        if isinstance(signals, dict):
            parts = []
            for sig in message.signals:
                if sig.name in signals:
                    parts.append(f"{sig.name}: {_value_text(signals[sig.name], sig.unit)}")
            body = f"{message.name}({', '.join(parts)})"
    if msg.is_error_frame:  # a controller's report of a bus error: no ID, no message
        return f"{head}  {data.hex(' ').upper()}".rstrip() + f"  {status or 'error_frame'}"
    if body is None:
        name = decoded.name or "unknown"
        body = f"{name} {data.hex(' ').upper()}".rstrip()
    return f"{head}  {body}  {status or decoded.error or 'ok'}"


def format_summary(stats: dict[int, FrameStats], names: dict[int, str | None]) -> list[str]:
    """The summary table: one row per ID, then the totals."""
    header = (
        f"{'ID':>8}  {'name':<20} {'frames':>8} {'bad_crc':>8} {'bad_cnt':>8} "
        f"{'bad_len':>8} {'unknown':>8} {'decode':>8}"
    )
    lines = [header]
    total = FrameStats()
    for frame_id in sorted(stats):
        s = stats[frame_id]
        name = names.get(frame_id) or "?"
        label = stats_label(frame_id)
        lines.append(
            f"{label:>8}  {name:<20} {s.frames:>8} {s.bad_crc:>8} {s.bad_counter:>8} "
            f"{s.wrong_length:>8} {s.unknown_id:>8} {s.decode_error:>8}"
        )
        total = total + s
    lines.append(
        f"{'total':>8}  {'':<20} {total.frames:>8} {total.bad_crc:>8} {total.bad_counter:>8} "
        f"{total.wrong_length:>8} {total.unknown_id:>8} {total.decode_error:>8}"
    )
    return lines


def authentication_summary(codec: CanCodec, stats: dict[int, FrameStats]) -> str:
    """One line on the MACs of a log's authenticated frames ("" for a profile without any):
    how many were verified and failed, or that none was verified (no key)."""
    if not codec.authenticated:
        return ""
    if not codec.verifies:
        unverified = sum(s.mac_unverified for s in stats.values())
        return f"MAC not verified: no key (--key-file) for {unverified} authenticated frames"
    ids = {i for i in stats if codec.authenticates(i)}
    frames = sum(stats[i].frames for i in ids)
    bad_mac = sum(stats[i].bad_mac for i in ids)
    stale = sum(stats[i].stale_freshness for i in ids)
    return (
        f"MAC verified with the key on {frames} authenticated frames: {bad_mac} bad MAC, "
        f"{stale} stale freshness"
    )


def decode_log(
    path: str | Path | LogParts | Sequence[str | Path],
    out: TextIO | None = None,
    *,
    profile: Profile | str,
    summary: bool = True,
    dbw_dbc: str | Path | None = None,
    car_dbc: str | Path | None = None,
    err: TextIO | None = None,
    key: bytes | None = None,
) -> int:
    """Decode a CAN log, one line per frame, then a per-ID summary.

    :param path: the log file (its suffix selects the reader), a rotated log's parts, or
        several files (grouped as :func:`~leafgate.record.logs.group_parts` does, each log
        decoded with its own summary)
    :param out: where the lines go (standard output when None)
    :param profile: the vehicle profile the frames follow (no default: a log of one car read
        with another car's profile shows every frame as an unknown ID)
    :param summary: print the per-ID counts at the end
    :param dbw_dbc: another drive-by-wire DBC than the profile's first
    :param car_dbc: another CAR-CAN DBC than the profile's second
    :param err: where a warning about timestamps going backwards goes (standard error)
    :param key: the key verifying authenticated frames (None: decoded, MAC not verified)
    :return: the exit status, 0 (bad frames are reported, not failures)
    :raises ReplayError: the file is missing, of an unknown format or unreadable
    :raises CanCodecError: a given DBC is unreadable or invalid
    """
    out = out if out is not None else sys.stdout
    err = err if err is not None else sys.stderr
    if isinstance(path, LogParts):
        groups = [path]
    else:
        groups = group_parts([path] if isinstance(path, (str, Path)) else list(path))
    for parts in groups:
        _decode_parts(
            parts,
            out,
            err,
            profile=profile,
            summary=summary,
            dbw_dbc=dbw_dbc,
            car_dbc=car_dbc,
            key=key,
        )
    return 0


#: The status of a frame whose counter skipped across frames the recorder lost (``bad_counter``
#: to the codec): not an error of the bus, and not judged either.
AFTER_RECORDER_LOSS = "counter not judged: the recorder lost frames before it"


def _incomplete_note(parts: LogParts, source: ChainedSource) -> str:
    """What the summary's first line says of an incomplete recording ("" for a complete one)."""
    notes = []
    truncation = source.truncation()
    if truncation:
        notes.append(f" ({truncation})")
    if source.frames and not source.ended:
        notes.append("; no end-of-recording marker: the recording stops early")
    lost = {loss.before for loss in source.losses}
    for loss in source.losses:
        notes.append(
            f"; part {loss.before.name} has no end-of-recording marker: the recorder lost "
            f"{loss.end - loss.start:.3f} s before {loss.after.name}"
        )
    for span_path, _, _, ended in source.spans[:-1]:
        if not ended and span_path not in lost:
            notes.append(f"; part {span_path.name} has no end-of-recording marker")
    drops = source.drops
    if drops:
        notes.append(
            f"; the recorder dropped {plural(sum(d.frames for d in drops), 'frame')} "
            f"({plural(len(drops), 'drop marker')}: its queue overflowed)"
        )
    after = unread_next_part(parts, source.continues)
    if after is not None:
        notes.append(f"; the recording goes on in part {after.name}, missing")
    if parts.missing:
        names = ", ".join(m.name for m in parts.missing)
        notes.append(f"; missing part{'s' if len(parts.missing) > 1 else ''} {names}")
    return "".join(notes)


def _decode_parts(
    parts: LogParts,
    out: TextIO,
    err: TextIO,
    *,
    profile: Profile | str,
    summary: bool,
    dbw_dbc: str | Path | None,
    car_dbc: str | Path | None,
    key: bytes | None,
) -> None:
    """Decode one log (a file, or a rotated log's parts as one): see :func:`decode_log`."""
    path = parts.paths[0] if len(parts.paths) == 1 else Path(parts.name)
    # fails early on a bad DBC; freshness is judged against the recorded timestamps
    template = CanCodec(dbw_dbc, car_dbc, profile, key=key, clock=None)
    codecs: dict[object, CanCodec] = {}  # one per recorded channel: separate counter state

    def codec_for(channel: object) -> CanCodec:
        codec = codecs.get(channel)
        if codec is None:
            codec = codecs[channel] = (
                CanCodec(dbw_dbc, car_dbc, template.profile, key=key, clock=None)
                if codecs
                else template
            )
        return codec

    latest = -math.inf
    backwards = 0
    worst = 0.0
    previous: dict[tuple[object, int], float] = {}  # (channel, ID) → its last frame's time
    not_judged: dict[int, int] = {}  # ID → counter skips across the recorder's losses
    source = ChainedSource(parts.paths)  # the one reader of logs and sessions
    for msg in source:
        codec = codec_for(msg.channel)
        decoded = codec.decode(msg)
        slot = (msg.channel, msg.arbitration_id)
        status = None
        if decoded.error == "bad_counter" and slot in previous:
            before = previous[slot]
            if any(before < end and msg.timestamp > start for start, end in source.lost_spans()):
                status = AFTER_RECORDER_LOSS
                not_judged[msg.arbitration_id] = not_judged.get(msg.arbitration_id, 0) + 1
        previous[slot] = msg.timestamp
        line = format_frame(codec, msg, decoded, status)
        if decoded.valid and not codec.verifies and codec.authenticates(msg.arbitration_id):
            line += " (MAC not verified)"
        if msg.timestamp < latest:
            backwards += 1
            worst = max(worst, latest - msg.timestamp)
            line += "  (timestamp goes backwards)"
        else:
            latest = msg.timestamp
        out.write(line + "\n")
    if backwards:
        err.write(
            f"leafgate: warning: {path}: timestamps go backwards at {plural(backwards, 'frame')} "
            f"(by up to {worst * 1e3:.1f} ms)\n"
        )
    note = _incomplete_note(parts, source)
    if note and not summary:
        err.write(f"leafgate: warning: {parts.name}: incomplete{note}\n")
    if summary:
        merged: dict[int, FrameStats] = {}
        names: dict[int, str | None] = {}
        for codec in codecs.values():
            for frame_id, s in codec.stats.items():
                if s.frames:
                    merged[frame_id] = merged.get(frame_id, FrameStats()) + s
                    names[frame_id] = codec.name_of(frame_id)
        for frame_id, n in not_judged.items():  # not the bus's: counted apart
            merged[frame_id] = replace(
                merged[frame_id], bad_counter=merged[frame_id].bad_counter - n
            )
        # error frames have no ID: counted in their own row (the codec's key), not as unknown
        error_frames = merged.get(ERROR_FRAME_KEY, FrameStats()).frames
        out.write(
            f"# {path.name}: {plural(sum(s.frames for s in merged.values()), 'frame')}"
            + (f" ({plural(error_frames, 'error frame')})" if error_frames else "")
            + f", profile {template.profile.name}{note}\n"
        )
        for line in format_summary(merged, names):
            out.write("# " + line + "\n")
        auth = authentication_summary(template, merged)
        if auth:
            out.write(f"# {auth}\n")
        skipped = sum(not_judged.values())
        if skipped:
            out.write(
                f"# {plural(skipped, 'counter skip')} across frames the recorder lost: not "
                "judged, not counted in bad_cnt\n"
            )
