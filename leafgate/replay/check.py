"""``leafgate replay check LOG``: the offline safety check of a recorded drive.

The frames are read with a vehicle profile (``--profile``, ``--config``, or a session's
recorded configuration; there is no default), which gives the command IDs, the signals, the
periods and the E2E schemes. For every frame of the log (any python-can format, or a
session's ``/can`` topic):

1. decode it, running the gateway's E2E checks (checksums, counters, length, including the
   car's own on CAR-CAN) with one codec per recorded channel;
2. collect per-ID period statistics: a *median* interval more than 10 % off the profile's
   period is a finding with both values (event frames, such as 0x421's after a gear change,
   make the mean misleading). A stretch in which the whole bus fell silent (longer than
   ``gap_periods`` of the fastest period) is one finding, with its start, length and the IDs
   overdue. Per ID, a *gap* is an interval longer than ``gap_periods`` periods, or one over 1.5
   periods that ends in a skipped counter (frames were lost); gaps the bus silence explains are
   part of it, the others are reported (overlapping ones together), and the counter skip
   after a gap is part of the gap, as is the counter skip after a frame with a bad checksum:
   one corrupted or lost stretch, one finding;
3. re-check every command frame sent enabled against the safety gate's limits
   (:func:`leafgate.gateway.safety.check`: angle, angle rate by speed, lateral acceleration,
   acceleration, jerk, speed, gear at standstill), measured state from the latest valid long
   report before the frame, previous command from the frame before it. After a violating
   frame the check continues from the value the gate would have allowed. A value beyond the
   angle or acceleration envelope is reported as that even when a rate bound is nearer; across
   a short gap the rate bounds allow the time that passed. What cannot be checked is counted
   as *not checkable*, never as a violation: frames before the vehicle state is known (no long
   report with a known gear yet), and the rates of the first command of a log or after a gap
   (the previous command is not in the log), which are checked against the envelope only.

4. judge every ECU report as the gateway does (:mod:`leafgate.gateway.plausibility`, the same
   functions): a report out of the physical range, or disagreeing with the CAR-CAN wheel speeds
   or steering-wheel angle recorded within ``MAX_SKEW`` of it, is a ``report`` finding (one per
   stretch of disagreement), and an out-of-range speed is never used as the measured state.

5. look for the recorder's end-of-recording marker (the last frame of a properly closed log
   or session): without it the recording stopped early (a crash, a full disk, a write error),
   and an ``incomplete`` finding says after which frame and at what time it stops.

6. authenticated command frames (profile ``leafgate-dbw-auth``) are verified only with the key
   (``--key-file``, or the ``--config``'s ``can.auth_key_file``): a bad MAC or a stale or
   repeated freshness value (judged against the recorded timestamps) is an ``e2e`` finding.
   Without the key the frames are decoded and checked as above, and the report says "MAC not
   verified": it never claims a MAC it did not check.

An empty log, a log with no frame on the profile's command IDs (another vehicle's, one made
with another profile, or one without the gateway), a log without an engaged command frame
(cut before the engage, or a drive never engaged), a log whose command frames could none be
checked and a log in which no command's rates could be checked are findings, never "OK":
"OK" says what was checked, so nothing checked is not OK. Timestamps that go backwards
are warned about.

The parts of one recording given together — a rotated log's (``can-…_000.blf``,
``can-…_001.blf`` …), a session's and the sessions resuming it (``session-….2.mcap``) — are
checked as one log, frames chained (:func:`~leafgate.record.logs.group_parts`); a part missing
from the numbering is an ``incomplete`` finding. A part before the last without its
end-of-recording marker was given up by the recorder after a write failure: the stretch until
the next part is one ``incomplete`` finding, lost by the recorder, with its length; the bus
silence, the IDs' gaps and the skipped alive counters across it are the recorder's, not
reported as the bus's. So are the frames the recorder dropped inside a file as its queue
overflowed, which it marks there (:func:`~leafgate.record.logs.drop_marker`): one
``incomplete`` finding says how many; no counter skipped across them is judged, and of a
silence or an ID's gap only what lies outside them. Several logs give one report each and a last line with the verdict over
all of them.

Tolerances are 1.5 quantisation steps of the command signals (read from the DBC, through the
profile's unit and scale): the gate bounds the float command, the frame carries it rounded.

Exit status: 0 when there is no finding, 1 otherwise.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final, TextIO

import can
import numpy as np

from leafgate.can.codec import (
    ERROR_FRAME_KEY,
    CanCodec,
    FrameStats,
    frame_key,
    stats_label,
)
from leafgate.can.profile import Profile
from leafgate.can.secoc import tool_key
from leafgate.config import VehicleConfig
from leafgate.errors import ReplayError
from leafgate.gateway.plausibility import MAX_SKEW, cross_check, report_range_error
from leafgate.gateway.safety import Measured, SafetyLimits, Violation, apply_limits, check
from leafgate.messages import (
    Gear,
    LongCommand,
    LongReport,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    WheelSpeeds,
)
from leafgate.record.logs import (
    ChainedSource,
    FrameSource,
    LogParts,
    RecorderDrop,
    RecorderLoss,
    group_parts,
    is_end_marker,
    is_session,
    part_number,
    recording_context,
    unread_next_part,
)
from leafgate.replay.decode import authentication_summary
from leafgate.replay.report import write_report
from leafgate.settings import LeafgateConfig
from leafgate.text import plural

__all__ = [
    "MAX_GAP_PERIODS",
    "MIN_GAP_PERIODS",
    "CheckReport",
    "Finding",
    "IdStats",
    "add_gap_periods",
    "check_frames",
    "check_log",
    "gap_periods_arg",
    "gap_periods_error",
    "main_check",
]

STEER_KINDS: Final = frozenset({"angle", "angle_rate", "lateral_accel", "non_finite"})
LONG_KINDS: Final = frozenset({"accel", "jerk", "speed", "gear", "non_finite"})
DEFAULT_GAP_PERIODS: Final = 3.0  # nominal periods; the watchdog's report timeout, too
# ``gap_periods`` must be over MIN (an interval of one period is no gap) and at most MAX (a
# second of silence on a 10 ms frame: far past any timeout; more would switch off the silence
# and gap findings, and the rate checks across a gap, without saying so)
MIN_GAP_PERIODS: Final = 1.0
MAX_GAP_PERIODS: Final = 100.0
_TOLERANCE_STEPS: Final = 1.5  # quantisation steps of slack on every re-checked bound
_LOST_FRAME_PERIODS: Final = 1.5  # an interval this long that ends in a counter skip lost frames
_PROGRESS_EVERY: Final = 0.2  # s of wall time between progress bar updates


@dataclass(frozen=True)
class Finding:
    """One problem in the log."""

    time: float  # s, timestamp of the frame (of the gap's start)
    kind: str  # "limit", "e2e" or "gap"
    frame_id: int | None
    name: str  # DBC message name, or the IDs of a gap
    detail: str  # violation kind / E2E error / gap description
    value: float = math.nan  # offending value (rad, m/s², m/s, gear) or gap length (s)
    bound: float = math.nan  # the limit it exceeds

    def to_dict(self) -> dict[str, Any]:
        return {
            "time": _num(self.time),
            "kind": self.kind,
            "id": None if self.frame_id is None else _json_id(self.frame_id),
            "name": self.name,
            "detail": self.detail,
            "value": _num(self.value),
            "bound": _num(self.bound),
        }


@dataclass(frozen=True)
class IdStats:
    """Frames and timing of one CAN ID."""

    frame_id: int
    name: str | None
    frames: int
    nominal_period: float | None  # s, the profile's period, else the median interval
    mean_period: float  # s (NaN with fewer than two frames)
    min_period: float
    max_period: float
    p99_period: float
    gaps: int
    e2e: FrameStats  # decode outcomes (bad CRC, counter, length …)
    profile_period: float | None = None  # s, the period the profile gives the frame
    median_period: float = math.nan  # s
    intervals: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": _json_id(self.frame_id),
            "name": self.name,
            "frames": self.frames,
            "nominal_period_s": _num(self.nominal_period),
            "median_period_s": _num(self.median_period),
            "mean_period_s": _num(self.mean_period),
            "min_period_s": _num(self.min_period),
            "max_period_s": _num(self.max_period),
            "p99_period_s": _num(self.p99_period),
            "gaps": self.gaps,
            "bad_crc": self.e2e.bad_crc,
            "bad_counter": self.e2e.bad_counter,
            "wrong_length": self.e2e.wrong_length,
            "decode_error": self.e2e.decode_error,
        }


@dataclass
class CheckReport:
    """The result of checking one log."""

    path: str
    profile: str = ""  # the vehicle profile the frames were read with
    frames: int = 0
    start: float = math.nan  # s, first timestamp
    end: float = math.nan  # s, last timestamp
    engaged_frames: int = 0  # command frames with ENABLE=1 re-checked against the limits
    command_frames: int = 0  # frames on the profile's command IDs
    # engaged command frames that could not be (fully) checked, by why: the vehicle state is
    # not known yet (state_unknown); the previous command is not in the log, on the first
    # command frame or after a gap (rates_unknown: checked against the envelope only)
    not_checkable: dict[str, int] = field(default_factory=dict)
    backwards: int = 0  # frames whose timestamp is before an earlier frame's
    worst_backwards: float = 0.0  # s
    ids: list[IdStats] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    truncated: bool = False  # a session file that ended before its footer (a part of one)
    truncation: str = ""  # which parts were cut short, in words (ChainedSource.truncation)
    recorder_dropped: int = 0  # frames the recorder marked as dropped (its queue overflowed)
    unknown_frames: int = 0  # frames of an ID the profile does not describe
    error_frames: int = 0  # error frames (a controller's report of a bus error: no ID)
    elapsed: float = 0.0  # s of wall time spent checking
    authentication: str = ""  # what was checked of the MACs ("" for a profile without any)

    @property
    def ok(self) -> bool:
        return not self.findings

    def count(self, kind: str) -> int:
        return sum(1 for f in self.findings if f.kind == kind)

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "profile": self.profile,
            "ok": self.ok,
            "frames": self.frames,
            "duration_s": _num(self.end - self.start),
            "command_frames": self.command_frames,
            "engaged_command_frames": self.engaged_frames,
            "not_checkable": dict(self.not_checkable),
            "violations": self.count("limit"),
            "e2e_errors": self.count("e2e"),
            "gaps": self.count("gap"),
            "bus_silences": self.count("silence"),
            "period_findings": self.count("period"),
            "coverage_findings": self.count("coverage"),
            "backwards_timestamps": self.backwards,
            "worst_backwards_s": self.worst_backwards,
            "truncated": self.truncated,
            "truncation": self.truncation or None,
            "recorder_dropped_frames": self.recorder_dropped,
            "unknown_id_frames": self.unknown_frames,
            "error_frames": self.error_frames,
            "authentication": self.authentication or None,
            "ids": [s.to_dict() for s in self.ids],
            "findings": [f.to_dict() for f in self.findings],
            "elapsed_s": self.elapsed,
        }

    def format(self) -> list[str]:
        """The summary table, the findings, and one verdict line."""
        apart = [
            text
            for n, text in (
                (self.unknown_frames, f"{self.unknown_frames} of an unknown ID"),
                (self.error_frames, plural(self.error_frames, "error frame")),
            )
            if n
        ]
        span = (
            f"{plural(self.frames, 'frame')}"
            + (f" ({', '.join(apart)})" if apart else "")
            + f", {self.end - self.start:.3f} s"
            if self.frames
            else "no frames"
        )
        # the ID column as wide as its widest label: a 29-bit ID has 8 digits
        w = max([5, *(len(stats_label(s.frame_id)) for s in self.ids)])
        lines = [
            f"{self.path}: {span}, profile {self.profile}"
            + (f" ({self.truncation})" if self.truncation else ""),
            f"{'ID':>{w}}  {'name':<20} {'frames':>8} {'period':>8} {'median':>8} {'max':>8} "
            f"{'gaps':>5} {'crc':>5} {'cnt':>5} {'len':>5}",
        ]
        if self.backwards:
            lines.insert(
                1,
                f"warning: the log goes backwards in time at {plural(self.backwards, 'frame')} "
                f"(by up to {self.worst_backwards * 1e3:.1f} ms)",
            )
        for s in self.ids:
            lines.append(
                f"{stats_label(s.frame_id):>{w}}  {(s.name or '?'):<20} {s.frames:>8} {_ms(s.nominal_period):>8} "
                f"{_ms(s.median_period):>8} {_ms(s.max_period):>8} {s.gaps:>5} "
                f"{s.e2e.bad_crc:>5} {s.e2e.bad_counter:>5} {s.e2e.wrong_length:>5}"
            )
        lines.append("(periods in ms)")
        for f in self.findings:
            where = "" if f.frame_id is None else f"{stats_label(f.frame_id)} "
            extra = ""
            if f.kind == "limit":
                extra = f": {f.value:.6g} beyond {f.bound:.6g}"
            when = f"{f.time:.6f}" if math.isfinite(f.time) else "-"  # of the whole log
            lines.append(f"{when}  {f.kind:<7} {where}{f.name}  {f.detail}{extra}")
        not_checkable = ", ".join(
            f"{v} {k.replace('_', ' ')}" for k, v in self.not_checkable.items() if v
        )
        lines.append(
            f"{'OK' if self.ok else 'FAILED'}: "
            f"{plural(self.engaged_frames, 'engaged command frame')} checked (not checkable: "
            f"{not_checkable or 'none'}), {plural(self.count('limit'), 'limit violation')}, "
            f"{plural(self.count('e2e'), 'E2E error')}, {plural(self.count('gap'), 'gap')}, "
            f"{plural(self.count('silence'), 'bus silence')}, "
            f"{plural(self.count('period'), 'period finding')}"
            + (
                f", {plural(self.count('coverage'), 'coverage finding')}"
                if self.count("coverage")
                else ""
            )
            + "".join(
                f", {plural(n, kind + ' finding')}" for kind, n in self._other_findings().items()
            )
            + (f"; {self.authentication}" if self.authentication else "")
        )
        return lines

    def _other_findings(self) -> dict[str, int]:
        """Findings of the kinds the verdict has no fixed count for (``incomplete``, ``report``):
        a FAILED verdict names every kind that failed it."""
        counts: dict[str, int] = {}
        for f in self.findings:
            if f.kind not in _VERDICT_KINDS:
                counts[f.kind] = counts.get(f.kind, 0) + 1
        return counts


#: the finding kinds the verdict line always counts
_VERDICT_KINDS = frozenset({"limit", "e2e", "gap", "silence", "period", "coverage"})


def _num(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _json_id(key: int) -> str:
    """A frame key (:func:`~leafgate.can.codec.frame_key`) in the JSON report: ``0x0A0``,
    ``0x12345678`` for a 29-bit ID, ``error`` for error frames."""
    label = stats_label(key)
    return label if label == "error" else f"0x{label}"


def _ms(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value * 1e3:.1f}"


class _Progress:
    """A one-line progress bar on a terminal (nothing when the stream is not one)."""

    def __init__(self, stream: TextIO | None, source: FrameSource | ChainedSource) -> None:
        self.stream = stream if stream is not None and stream.isatty() else None
        self.source = source
        self.t0 = time.monotonic()
        self.next = self.t0 + _PROGRESS_EVERY

    def update(self, frames: int) -> None:
        now = time.monotonic()
        if self.stream is None or now < self.next:
            return
        self.next = now + _PROGRESS_EVERY
        rate = frames / max(now - self.t0, 1e-9)
        fraction = self.source.fraction()
        if fraction is None:
            bar = f"{frames} frames"
        else:
            filled = int(30 * fraction)
            bar = f"[{'#' * filled}{'.' * (30 - filled)}] {100 * fraction:5.1f}%  {frames} frames"
        self.stream.write(f"\r{bar}  {rate:,.0f} frames/s ")
        self.stream.flush()

    def done(self) -> None:
        if self.stream is not None:
            self.stream.write("\r" + " " * 78 + "\r")
            self.stream.flush()


_SI_PER_UNIT: Final = {"": 1.0, "deg": math.pi / 180.0, "deg/s": math.pi / 180.0, "km/h": 1 / 3.6}


def _tolerances(codec: CanCodec) -> tuple[float, float]:
    """(angle, longitudinal) tolerance: 1.5 quantisation steps of the profile's command
    signals that carry ``steer.angle`` and ``long.accel``/``long.speed``, in SI."""
    angle: list[float] = []
    long: list[float] = []
    for spec in codec.profile.frames_of("command"):
        message = codec.message(codec.frame_id(spec.name))
        assert message is not None
        for sig in spec.signals:
            if sig.source is None:
                continue
            fields = {(sig.source, sig.attr), *sig.also}
            step = abs(message.get_signal_by_name(sig.signal).scale / sig.scale)
            step *= _SI_PER_UNIT[sig.unit]
            if ("steer", "angle") in fields:
                angle.append(step)
            if fields & {("long", "accel"), ("long", "speed")}:
                long.append(step)
    return _TOLERANCE_STEPS * max(angle, default=1e-4), _TOLERANCE_STEPS * max(long, default=1e-3)


@dataclass
class _CommandCheck:
    """The re-check of the engaged command frames, one frame at a time."""

    limits: SafetyLimits
    angle_tol: float
    long_tol: float
    gap: float  # s: a command this long after the previous one is checked without rates
    last_steer: SteerCommand = field(default_factory=lambda: SteerCommand(angle=0.0))
    last_long: LongCommand = field(default_factory=LongCommand)
    steer_time: float = -math.inf  # s, timestamps of the last steer / long command frames
    long_time: float = -math.inf
    long_report: LongReport | None = None
    checked: int = 0  # engaged command frames re-checked
    rates_checked: int = 0  # commands whose rates were re-checked (the previous one known)
    not_checkable: dict[str, int] = field(
        default_factory=lambda: {"state_unknown": 0, "rates_unknown": 0}
    )
    findings: list[Finding] = field(default_factory=list)

    def frame(self, t: float, frame_id: int, name: str, values: tuple[object, ...]) -> None:
        """Re-check the commands of one valid frame (a frame may carry steer and long)."""
        engaged = False
        unknown = self.long_report is None or self.long_report.gear == Gear.NONE
        for value in values:
            if isinstance(value, SteerCommand):
                if value.enable and not unknown:
                    value = self._steer(t, frame_id, name, value)
                engaged |= value.enable
                self.last_steer, self.steer_time = value, t
            elif isinstance(value, LongCommand):
                if value.enable and not unknown:
                    value = self._long(t, frame_id, name, value)
                engaged |= value.enable
                self.last_long, self.long_time = value, t
        if engaged and unknown:
            self.not_checkable["state_unknown"] += 1
        elif engaged:
            self.checked += 1

    def _limits(self, elapsed: float) -> SafetyLimits:
        """The limits after ``elapsed`` s; the envelope alone when the rates cannot be checked
        (counted): on the first command of a log, or after a gap, the previous one is missing."""
        if not elapsed <= self.gap:
            self.not_checkable["rates_unknown"] += 1
            return _envelope(self.limits)
        self.rates_checked += 1
        return _over(self.limits, elapsed)

    def _steer(self, t: float, frame_id: int, name: str, value: SteerCommand) -> SteerCommand:
        measured = _measured(self.long_report, self.limits)
        lim = self._limits(t - self.steer_time)
        args = (self.last_long, self.last_steer, self.last_long, measured, lim)
        found = _violations(value, *args, self.angle_tol, STEER_KINDS)
        self._add(t, frame_id, name, found)
        return apply_limits(value, *args).steer if found else value

    def _long(self, t: float, frame_id: int, name: str, value: LongCommand) -> LongCommand:
        measured = _measured(self.long_report, self.limits)
        lim = self._limits(t - self.long_time)
        found = _violations(
            self.last_steer,
            value,
            self.last_steer,
            self.last_long,
            measured,
            lim,
            self.long_tol,
            LONG_KINDS,
        )
        self._add(t, frame_id, name, found)
        if found:  # continue from what the gate would have sent
            return apply_limits(
                self.last_steer, value, self.last_steer, self.last_long, measured, lim
            ).long
        return value

    def _add(self, t: float, frame_id: int, name: str, found: list[Violation]) -> None:
        for v in found:
            self.findings.append(Finding(t, "limit", frame_id, name, v.kind, v.value, v.bound))


_E2eError = tuple[int, float, int, str, str]  # (index of the frame in its ID, t, id, name, error)


class _Scan:
    """One pass over the frames (steps 1, 3 and 4 of the module notes, and what step 2 needs):
    per-ID timestamps, E2E errors, the command re-check and the report judge, frame by frame."""

    def __init__(
        self,
        template: CanCodec,
        commands: _CommandCheck,
        judge: _ReportJudge,
        new_codec: Callable[[], CanCodec],
    ) -> None:
        self.template = template
        self.commands = commands
        self.judge = judge
        self._new_codec = new_codec  # a codec like the template, for a further channel
        self.command_ids = template.receive_ids("commands")
        self.codecs: dict[object, CanCodec] = {}  # one per recorded channel
        self.times: dict[int, list[float]] = {}
        self.e2e: list[_E2eError] = []
        self._invalid_before: set[int] = set()  # IDs whose previous frame was invalid (CRC, length)
        self.frames = 0
        self.command_frames = 0
        self.first = self.last = math.nan
        self.backwards = 0
        self.worst_backwards = 0.0
        self._latest = -math.inf
        self.ended = False  # the last frame read was an end-of-recording marker

    def take(self, msg: can.Message) -> None:
        if is_end_marker(msg):
            self.ended = True
            return
        self.ended = False  # frames after a marker: a later file or session segment
        self.frames += 1
        t = msg.timestamp
        self._clock(t)
        frame_id = frame_key(msg)  # a 29-bit ID and an error frame apart from the 11-bit IDs
        stamps = self.times.get(frame_id)
        if stamps is None:
            stamps = self.times[frame_id] = []
        stamps.append(t)
        decoded = self._codec(msg.channel).decode(msg)
        if frame_id in self.command_ids:
            self.command_frames += 1
        if not decoded.valid:
            self._e2e(len(stamps) - 1, t, frame_id, decoded.name or "?", decoded.error or "?")
            return
        self._invalid_before.discard(frame_id)
        name = decoded.name or ""
        for value in decoded.values:
            if isinstance(value, (SteerReport, LongReport, WheelSpeeds, SteeringWheelAngle)):
                # judged as the gateway judges them: an implausible report is never the state
                plausible = self.judge.take(t, frame_id, name, value)
                if isinstance(value, LongReport) and plausible:
                    self.commands.long_report = value
        if frame_id in self.command_ids:
            self.commands.frame(t, frame_id, name, decoded.values)

    def _clock(self, t: float) -> None:
        """First and last timestamps, and how far the log goes backwards in time."""
        if self.frames == 1:
            self.first = t
        self.last = t
        if t < self._latest:
            self.backwards += 1
            self.worst_backwards = max(self.worst_backwards, self._latest - t)
        else:
            self._latest = t

    def _codec(self, channel: object) -> CanCodec:
        codec = self.codecs.get(channel)
        if codec is None:
            codec = self.codecs[channel] = self.template if not self.codecs else self._new_codec()
        return codec

    def _e2e(self, index: int, t: float, frame_id: int, name: str, error: str) -> None:
        if error == "unknown_id":
            return
        # A frame with a bad CRC or length never reaches the counter check, so the next good
        # frame of its ID sees a skipped counter: one corrupted frame, one finding.
        if not (error == "bad_counter" and frame_id in self._invalid_before):
            self.e2e.append((index, t, frame_id, name, error))
        if error != "bad_counter":
            self._invalid_before.add(frame_id)
        else:
            self._invalid_before.discard(frame_id)

    def stats(self) -> tuple[dict[int, FrameStats], dict[int, str | None]]:
        """Every channel's decode outcomes merged by ID, and the IDs' names."""
        names = {}
        merged: dict[int, FrameStats] = {}
        for codec in self.codecs.values():
            for frame_id, s in codec.stats.items():
                if s.frames:
                    merged[frame_id] = merged.get(frame_id, FrameStats()) + s
                    names[frame_id] = codec.name_of(frame_id)
        return merged, names


def check_frames(
    frames: Iterable[can.Message],
    limits: SafetyLimits,
    profile: Profile | str,
    *,
    path: str = "",
    gap_periods: float = DEFAULT_GAP_PERIODS,
    dbw_dbc: str | None = None,
    car_dbc: str | None = None,
    progress: _Progress | None = None,
    vehicle: VehicleConfig | None = None,
    require_end: bool = False,
    key: bytes | None = None,
) -> CheckReport:
    """Check a sequence of frames (the core of :func:`check_log`; see the module notes).

    :param frames: the frames in recorded order
    :param limits: the safety gate's limits the commands must respect
    :param profile: the vehicle profile the frames follow (command IDs, signals, periods)
    :param gap_periods: an interval longer than this many nominal periods is a gap
    :param require_end: the frames include the recorder's end-of-recording markers (a file read
        with ``FrameSource(markers=True)``): a recording without one is ``incomplete``
    :param key: verifies authenticated frames' MACs, freshness judged against the recorded
        timestamps (None: decoded, "MAC not verified")
    """
    error = gap_periods_error(gap_periods)
    if error is not None:
        raise ReplayError(f"gap_periods: {error}")
    t_start = time.perf_counter()
    template = CanCodec(dbw_dbc, car_dbc, profile, key=key, clock=None)
    angle_tol, long_tol = _tolerances(template)
    command_gap = gap_periods * template.profile.command_period
    commands = _CommandCheck(limits, angle_tol, long_tol, command_gap)
    judge = _ReportJudge(vehicle or VehicleConfig())
    scan = _Scan(
        template,
        commands,
        judge,
        lambda: CanCodec(dbw_dbc, car_dbc, template.profile, key=key, clock=None),
    )
    take = scan.take
    for msg in frames:
        take(msg)
        if progress is not None and not scan.frames & 0x3FF:
            progress.update(scan.frames)
    if progress is not None:
        progress.done()
    merged, names = scan.stats()
    lost = frames.lost_spans() if isinstance(frames, ChainedSource) else []
    ids, findings = _findings(scan, merged, names, gap_periods, require_end, lost)
    return CheckReport(
        path=path,
        profile=template.profile.name,
        frames=scan.frames,
        start=scan.first,
        end=scan.last,
        engaged_frames=commands.checked,
        not_checkable=dict(commands.not_checkable),
        command_frames=scan.command_frames,
        backwards=scan.backwards,
        worst_backwards=scan.worst_backwards,
        ids=ids,
        findings=findings,
        elapsed=time.perf_counter() - t_start,
        authentication=authentication_summary(template, merged),
        unknown_frames=sum(s.unknown_id for s in merged.values()),
        error_frames=merged.get(ERROR_FRAME_KEY, FrameStats()).frames,
    )


def gap_periods_error(value: float) -> str | None:
    """Why ``value`` is no ``gap_periods`` (None: it is one)."""
    if not MIN_GAP_PERIODS < value <= MAX_GAP_PERIODS:  # NaN and infinities too
        return (
            f"must be a number over {MIN_GAP_PERIODS:g} and at most {MAX_GAP_PERIODS:g} "
            f"(periods of silence that make a gap), not {value:g}"
        )
    return None


def add_gap_periods(parser: argparse.ArgumentParser) -> None:
    """``--gap-periods N`` of ``replay check`` and ``batch check`` (one definition, here where
    it is judged): a finite number over 1 and at most 100 (NaN, ``inf`` or ``1e9`` would switch
    the gap and silence findings off)."""
    parser.add_argument(
        "--gap-periods",
        type=gap_periods_arg,
        default=DEFAULT_GAP_PERIODS,
        metavar="N",
        help=f"a gap is this many periods of silence, over {MIN_GAP_PERIODS:g} and at most "
        f"{MAX_GAP_PERIODS:g} (default {DEFAULT_GAP_PERIODS:g})",
    )


def gap_periods_arg(text: str) -> float:
    """``--gap-periods N`` as argparse's ``type``: refused (exit 2) when it is no gap_periods."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    error = gap_periods_error(value)
    if error is not None:
        raise argparse.ArgumentTypeError(error)
    return value


def _findings(
    scan: _Scan,
    merged: dict[int, FrameStats],
    names: dict[int, str | None],
    gap_periods: float,
    require_end: bool,
    lost: Sequence[_Silence] = (),
) -> tuple[list[IdStats], list[Finding]]:
    """The per-ID statistics and every finding of a finished scan, in time order.

    What the recorder lost (``lost``: the stretches between a part it gave up after a write
    failure and the next, and those in which it dropped frames as its queue overflowed;
    :meth:`~leafgate.record.logs.ChainedSource.lost_spans`) is reported as that
    (:func:`_part_findings`), never as the bus's: a counter skipped across such a stretch is
    not judged, and of a silence or an ID's gap only what lies outside it is (the frames the
    recorder dropped were on the bus somewhere inside it).
    """
    skips = {
        (frame_id, index) for index, _, frame_id, _, error in scan.e2e if error == "bad_counter"
    }
    ids, gaps = _timing(scan.times, scan.template, names, merged, gap_periods, skips, lost)
    findings = list(scan.commands.findings)
    gap_firsts = {(frame_id, index) for frame_id, index, _, _ in gaps}
    for index, t, frame_id, name, kind in scan.e2e:
        if kind == "bad_counter" and (frame_id, index) in gap_firsts:
            continue  # the frames lost in a gap, reported as the gap
        if kind == "bad_counter" and index and _meets(scan.times[frame_id][index - 1], t, lost):
            continue  # maybe the frames the recorder lost: not judged
        findings.append(Finding(t, "e2e", frame_id, name, kind))
    silences = _bus_silences(scan.times, ids, gap_periods, lost)
    findings.extend(_silence_findings(silences, gaps))
    findings.extend(_merge_gaps(_unexplained(gaps, silences, ids, gap_periods), names))
    findings.extend(_period_findings(ids, scan.first))
    findings.extend(_coverage_findings(scan, merged))
    findings.extend(scan.judge.findings)
    if require_end and scan.frames and not scan.ended:
        findings.append(
            Finding(
                scan.last,
                "incomplete",
                None,
                "",
                f"no end-of-recording marker: the recording stops after frame {scan.frames} "
                f"at {scan.last:.3f} s",
            )
        )
    findings.sort(key=lambda f: (f.time, f.kind))
    return ids, findings


_PERIOD_TOLERANCE: Final = 0.10  # a median period this far off the profile's is a finding
_PERIOD_MIN_INTERVALS: Final = 10  # fewer intervals say too little about a period


def _period_findings(ids: list[IdStats], first: float) -> list[Finding]:
    """A median interval more than 10 % off the profile's period (the median, as event frames
    such as 0x421's after a gear change make the mean misleading)."""
    out = []
    for s in ids:
        if s.profile_period is None or s.intervals < _PERIOD_MIN_INTERVALS:
            continue
        if abs(s.median_period - s.profile_period) > _PERIOD_TOLERANCE * s.profile_period:
            out.append(
                Finding(
                    first,
                    "period",
                    s.frame_id,
                    s.name or "?",
                    f"median period {s.median_period * 1e3:.1f} ms, the profile's "
                    f"{s.profile_period * 1e3:.1f} ms",
                    s.median_period,
                    s.profile_period,
                )
            )
    return out


def _coverage_findings(scan: _Scan, stats: dict[int, FrameStats]) -> list[Finding]:
    """An empty log, a log whose command frames could not be checked, a log with no frame on
    the profile's command IDs (another vehicle's recording, one made with another profile, or
    one without the gateway): each is a finding, never "OK"."""
    n, first, command_frames = scan.frames, scan.first, scan.command_frames
    commands, command_ids = scan.commands, scan.command_ids
    profile = scan.template.profile.name
    if n == 0:
        return [Finding(math.nan, "coverage", None, "log", "the log has no frames")]

    def about_commands(detail: str) -> list[Finding]:
        return [Finding(first, "coverage", None, "commands", detail)]

    if commands.checked == 0 and sum(commands.not_checkable.values()) > 0:
        why = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in commands.not_checkable.items())
        return about_commands(
            f"{command_frames} frames on the command IDs of profile {profile}, none could "
            f"be checked ({why}: no long report with a known gear before them)"
        )
    # the profile's frames: neither of an unknown ID nor an error frame (the codec's key rule)
    known = sum(s.frames - s.unknown_id for k, s in stats.items() if k != ERROR_FRAME_KEY)
    if command_frames == 0:
        ids = ", ".join(f"{i:03X}" for i in sorted(command_ids))
        detail = (
            f"no frame of profile {profile} (command IDs {ids}): a recording of another "
            "vehicle? give --profile"
            if known == 0
            else f"no frame on the command IDs of profile {profile} ({ids}): the command stream "
            f"was not checked, only {known} other frames of the profile (a recording without "
            "the gateway, or made with another profile? give --profile)"
        )
        return [Finding(first, "coverage", None, "profile", detail)]
    if commands.checked == 0:
        return about_commands(
            f"nothing checked: none of the {command_frames} frames on the command IDs of "
            f"profile {profile} was sent engaged (a log cut before the engage, or a drive "
            "never engaged): no command was checked against the limits"
        )
    if commands.rates_checked == 0:
        return about_commands(
            f"the rates of none of the {commands.checked} engaged command frames could be "
            "checked (each one's previous command is not in the log): only the envelope "
            "was checked"
        )
    return []


class _ReportJudge:
    """The gateway's report plausibility checks over a log: one finding per stretch."""

    def __init__(self, vehicle: VehicleConfig) -> None:
        self.vehicle = vehicle
        self.latest: dict[type, tuple[float, Any]] = {}  # type → (t, value) of the last good one
        self.findings: list[Finding] = []
        self._range_bad: dict[type, bool] = {}  # the last report of the type was out of range
        self._disagreeing: set[str] = set()  # cross-checks failing now

    def _near(self, kind: type, t: float) -> Any:
        entry = self.latest.get(kind)
        return entry[1] if entry is not None and abs(t - entry[0]) <= MAX_SKEW else None

    def take(self, t: float, frame_id: int, name: str, value: Any) -> bool:
        """Judge one report or CAR-CAN frame; False when the value is out of range."""
        kind = type(value)
        error = (
            report_range_error(value, self.vehicle)
            if isinstance(value, (SteerReport, LongReport))
            else None
        )
        if error is not None and not self._range_bad.get(kind):
            self.findings.append(Finding(t, "report", frame_id, name, error))
        self._range_bad[kind] = error is not None
        if error is not None:
            return False
        self.latest[kind] = (t, value)
        disagreements = cross_check(
            self._near(SteerReport, t),
            self._near(LongReport, t),
            self._near(WheelSpeeds, t),
            self._near(SteeringWheelAngle, t),
            self.vehicle,
        )
        failing = {text.split(" ")[0] + " " + text.split(" ")[2]: text for text in disagreements}
        for key, detail in failing.items():
            if key not in self._disagreeing:
                self.findings.append(Finding(t, "report", frame_id, name, detail))
        self._disagreeing = set(failing)
        return True


def _violations(
    steer: SteerCommand,
    long: LongCommand,
    last_steer: SteerCommand,
    last_long: LongCommand,
    measured: Measured,
    limits: SafetyLimits,
    tolerance: float,
    kinds: frozenset[str],
) -> list[Violation]:
    """The violations of one command frame, of the given kinds.

    The amplitude limits are checked first: a value beyond the angle or acceleration envelope
    is reported as that, even when a rate limit is the nearer bound; only a value inside the
    envelope is reported for its rate.
    """
    args = (steer, long, last_steer, last_long, measured)
    found = [v for v in check(*args, _envelope(limits), tolerance) if v.kind in kinds]
    return found or [v for v in check(*args, limits, tolerance) if v.kind in kinds]


@functools.lru_cache(maxsize=64)
def _envelope(limits: SafetyLimits) -> SafetyLimits:
    """The limits without their rate bounds (angle rate, jerk)."""
    unlimited = tuple(math.inf for _ in limits.rate_up)
    return replace(limits, rate_up=unlimited, rate_down=unlimited, max_jerk=math.inf)


def _over(limits: SafetyLimits, elapsed: float) -> SafetyLimits:
    """The limits for a command ``elapsed`` s after the previous one.

    The gate allows one period's worth of angle rate and jerk between two sent commands. When
    the log lacks frames (a gap), the change between the frames it has spans several periods,
    and is allowed that many periods' worth.
    """
    if elapsed <= 1.5 * limits.period or not math.isfinite(elapsed):
        return limits
    return replace(limits, period=elapsed)


def _measured(report: LongReport | None, limits: SafetyLimits) -> Measured:
    """The gate's view of the vehicle; without a report the gate assumes the speed limit."""
    if report is None:
        return Measured(limits.max_speed, Gear.NONE)
    return Measured(report.speed, report.gear)


_Gap = tuple[int, int, float, float]  # (id, index of the frame after the gap, start, end)


def _timing(
    times: dict[int, list[float]],
    codec: CanCodec,
    names: dict[int, str | None],
    e2e: dict[int, FrameStats],
    gap_periods: float,
    skips: set[tuple[int, int]],
    lost: Sequence[_Silence] = (),
) -> tuple[list[IdStats], list[_Gap]]:
    """Per-ID period statistics and the gaps of every ID with a known or measurable period.

    A gap is an interval over ``gap_periods`` nominal periods, or one over 1.5 periods that
    ends in a skipped alive counter (``skips``: (ID, index of the frame)) — frames were lost.
    An interval that meets a stretch the recorder lost (``lost``) is judged by its stretches
    outside it alone (:func:`_outside`), each a gap when over ``gap_periods`` periods.
    """
    stats: list[IdStats] = []
    gaps: list[_Gap] = []
    periods = {codec.frame_id(f.name): f.period for f in codec.profile.frames}
    for frame_id in sorted(times):
        t = np.asarray(times[frame_id], dtype=np.float64)
        dt = np.diff(t)
        message = codec.message(frame_id)
        nominal: float | None = periods.get(frame_id)
        if nominal is None and message is not None and dt.size >= 3:
            nominal = float(np.median(dt))  # known ID without a period: what it does
        id_gaps = 0
        if nominal is not None and nominal > 0.0 and dt.size:
            long_gap = dt > gap_periods * nominal
            slow = dt > _LOST_FRAME_PERIODS * nominal
            longest = gap_periods * nominal
            for i in np.flatnonzero(slow):
                before, after = float(t[i]), float(t[i + 1])
                if _meets(before, after, lost):
                    pieces = [p for p in _outside(before, after, lost) if p[1] - p[0] > longest]
                elif long_gap[i] or (frame_id, int(i) + 1) in skips:
                    pieces = [(before, after)]
                else:
                    pieces = []
                gaps.extend((frame_id, int(i) + 1, a, b) for a, b in pieces)
                id_gaps += len(pieces)
        stats.append(
            IdStats(
                frame_id=frame_id,
                name=names.get(frame_id) or (message.name if message is not None else None),
                frames=int(t.size),
                nominal_period=nominal,
                mean_period=float(dt.mean()) if dt.size else math.nan,
                min_period=float(dt.min()) if dt.size else math.nan,
                max_period=float(dt.max()) if dt.size else math.nan,
                p99_period=float(np.percentile(dt, 99)) if dt.size else math.nan,
                gaps=id_gaps,
                e2e=e2e.get(frame_id, FrameStats()),
                profile_period=periods.get(frame_id),
                median_period=float(np.median(dt)) if dt.size else math.nan,
                intervals=int(dt.size),
            )
        )
    return stats, gaps


_Silence = tuple[float, float]  # (last frame before, first frame after), s


def _bus_silences(
    times: dict[int, list[float]],
    ids: list[IdStats],
    gap_periods: float,
    lost: Sequence[_Silence] = (),
) -> list[_Silence]:
    """Stretches in which no frame at all was on the bus: longer than ``gap_periods`` of the
    fastest known period. Of an interval that meets a stretch the recorder lost (``lost``),
    only its stretches outside it can be (:func:`_outside`): the bus may have been busy in it."""
    periods = [s.nominal_period for s in ids if s.nominal_period]
    if not periods or not times:
        return []
    threshold = gap_periods * min(periods)
    t = np.sort(np.concatenate([np.asarray(v, dtype=np.float64) for v in times.values()]))
    dt = np.diff(t)
    out: list[_Silence] = []
    for i in np.flatnonzero(dt > threshold):
        pieces = _outside(float(t[i]), float(t[i + 1]), lost)
        out.extend(p for p in pieces if p[1] - p[0] > threshold)
    return out


def _meets(before: float, after: float, stretches: Sequence[_Silence]) -> bool:
    """Whether the interval from ``before`` to ``after`` (s) meets one of the stretches: the
    frames missing in it may be among those the stretch lost."""
    return any(before < end and after > start for start, end in stretches)


def _outside(before: float, after: float, stretches: Sequence[_Silence]) -> list[_Silence]:
    """The pieces of the interval from ``before`` to ``after`` (s) outside the stretches (the
    recorder's losses, in time order): where it is known that no frame was there."""
    pieces = []
    for start, end in sorted(stretches):
        if end <= before or start >= after:
            continue
        if start > before:
            pieces.append((before, start))
        before = max(before, end)
    if after > before:
        pieces.append((before, after))
    return pieces


def _overlaps(gap: _Gap, silence: _Silence) -> bool:
    return gap[2] <= silence[0] and gap[3] >= silence[1]


def _silence_findings(silences: list[_Silence], gaps: list[_Gap]) -> list[Finding]:
    """One finding per bus silence, naming its start, length and the IDs whose gap spans it."""
    out = []
    for silence in silences:
        ids = sorted({g[0] for g in gaps if _overlaps(g, silence)})
        label = ", ".join(stats_label(i) for i in ids) or "none overdue"
        length = silence[1] - silence[0]
        out.append(
            Finding(
                silence[0],
                "silence",
                None,
                "bus",
                f"the whole bus silent for {length * 1e3:.0f} ms; IDs overdue: {label}",
                length,
            )
        )
    return out


def _unexplained(
    gaps: list[_Gap], silences: list[_Silence], ids: list[IdStats], gap_periods: float
) -> list[_Gap]:
    """The per-ID gaps a bus silence does not explain: those that, without the silence, would
    still be longer than ``gap_periods`` periods of their ID."""
    nominal = {s.frame_id: s.nominal_period or 0.0 for s in ids}
    out = []
    for gap in gaps:
        silent = sum(s[1] - s[0] for s in silences if _overlaps(gap, s))
        if silent and (gap[3] - gap[2]) - silent <= gap_periods * nominal[gap[0]]:
            continue
        out.append(gap)
    return out


def _merge_gaps(gaps: list[_Gap], names: dict[int, str | None]) -> list[Finding]:
    """One finding per stretch of time in which one or more IDs fell silent."""
    out: list[Finding] = []
    group: list[_Gap] = []
    end = -math.inf

    def emit() -> None:
        if not group:
            return
        start = min(g[2] for g in group)
        stop = max(g[3] for g in group)
        ids = sorted({g[0] for g in group})
        frame_id = ids[0] if len(ids) == 1 else None
        label = ", ".join(stats_label(i) for i in ids)
        name = (names.get(ids[0]) or "?") if len(ids) == 1 else f"{len(ids)} IDs"
        out.append(
            Finding(
                start,
                "gap",
                frame_id,
                name,
                f"{(stop - start) * 1e3:.0f} ms without frames of {label}",
                stop - start,
            )
        )

    for gap in sorted(gaps, key=lambda g: g[2]):
        if gap[2] > end:
            emit()
            group = []
        group.append(gap)
        end = max(end, gap[3])
    emit()
    return out


def check_log(
    path: str | Path | LogParts,
    config: LeafgateConfig | str | Path | None = None,
    *,
    profile: str | None = None,
    gap_periods: float = DEFAULT_GAP_PERIODS,
    progress: TextIO | None = None,
    key_file: str | None = None,
) -> CheckReport:
    """Check a recorded log or session, or one recording's parts as one (see the module notes).

    :param path: a python-can log, a ``.mcap`` session, or one recording's parts
        (:func:`~leafgate.record.logs.group_parts`)
    :param config: the configuration (or its file) whose safety limits and vehicle profile
        apply; a session's recorded configuration when None
    :param profile: the vehicle profile (``--profile NAME|FILE``), over the configuration's
    :param progress: a stream for the progress bar (drawn only when it is a terminal)
    :param key_file: the key verifying authenticated frames; None: the ``config``'s
        ``can.auth_key_file`` when a config is given (a session's recorded one is not used)
    :raises ReplayError: the file is missing, of an unknown format or unreadable, or nothing
        names the vehicle profile (a python-can log without ``config`` or ``profile``)
    :raises ConfigError: the configuration or profile does not load
    """
    parts = path if isinstance(path, LogParts) else LogParts((Path(path),))
    context = recording_context(parts.paths[0], config=config, profile=profile)
    cfg = context.config
    limits = SafetyLimits.from_config(cfg.gateway.safety, cfg.vehicle, cfg.gateway.period)
    source = ChainedSource(parts.paths, markers=True)
    report = check_frames(
        source,
        limits,
        context.profile,
        path=parts.name,
        gap_periods=gap_periods,
        dbw_dbc=cfg.can.dbw_dbc,
        car_dbc=cfg.can.car_dbc,
        progress=_Progress(progress, source),
        vehicle=cfg.vehicle,
        require_end=True,
        key=tool_key(key_file, cfg if config is not None else None),
    )
    report.truncated = source.truncated
    report.truncation = source.truncation()
    report.recorder_dropped = sum(d.frames for d in source.drops)
    extra = _part_findings(parts, source)
    if extra:
        report.findings = sorted(report.findings + extra, key=lambda f: (f.time, f.kind))
    return report


def _part_findings(parts: LogParts, source: ChainedSource) -> list[Finding]:
    """The parts of a recording missing from the numbering, the stretches the recorder lost
    between a part it gave up and the next, and a next part the last one names but that was not
    given (the last part's own missing end marker is the check's own finding)."""
    out = []
    spans = source.spans
    for missing in parts.missing:
        number = part_number(missing)
        before = [s for s in spans if (part_number(s[0]) or 0) < (number or 0)]
        t = before[-1][2] if before else (spans[0][1] if spans else math.nan)
        on_disk = " (on disk, not given)" if missing.is_file() else ""
        out.append(
            Finding(
                t,
                "incomplete",
                None,
                "parts",
                f"part {missing.name} of the {'session' if is_session(missing) else 'rotated log'}"
                f" is missing{on_disk}: its frames were not checked",
            )
        )
    after = unread_next_part(parts, source.continues)
    if after is not None:
        on_disk = " (on disk, not given)" if after.is_file() else ""
        out.append(
            Finding(
                spans[-1][2],
                "incomplete",
                None,
                "parts",
                f"part {spans[-1][0].name} ends where the recording goes on in part "
                f"{after.name}, which is missing{on_disk}: its frames were not checked",
            )
        )
    out.extend(_loss_finding(loss) for loss in source.losses)
    out.extend(_drop_findings(source.drops))
    lost = {loss.before for loss in source.losses}
    for span_path, _, last, ended in spans[:-1]:
        if not ended and span_path not in lost:  # a part without frames
            out.append(
                Finding(
                    last,
                    "incomplete",
                    None,
                    "parts",
                    f"part {span_path.name} has no end-of-recording marker: it stops early",
                )
            )
    return out


def _loss_finding(loss: RecorderLoss) -> Finding:
    """One stretch the recorder lost, said as that: not a silent bus, not bus errors."""
    how = (
        f"{loss.after.name} resumes it"
        if is_session(loss.after)
        else f"the recording goes on in part {loss.after.name}"
    )
    return Finding(
        loss.start,
        "incomplete",
        None,
        "parts",
        f"part {loss.before.name} ends without its end-of-recording marker (the recorder gave "
        f"it up: a write failure) and {how} {loss.end - loss.start:.3f} s later: the frames in "
        "between were lost by the recorder, not checked",
        loss.end - loss.start,
    )


def _drop_findings(drops: Sequence[RecorderDrop]) -> list[Finding]:
    """The frames the recorder dropped as its queue overflowed, said as that: one finding for
    the recording, with how many, in how many stretches and over how long."""
    if not drops:
        return []
    frames = sum(d.frames for d in drops)
    start, end = min(d.start for d in drops), max(d.end for d in drops)
    covered = sum(b - a for a, b in _union((d.start, d.end) for d in drops))
    where = (
        f"from {start:.3f} s over {covered * 1e3:.0f} ms"
        if len(drops) == 1
        else f"in {len(drops)} stretches from {start:.3f} s to {end:.3f} s ({covered:.3f} s in all)"
    )
    return [
        Finding(
            start,
            "incomplete",
            None,
            "recorder",
            f"the recorder dropped {plural(frames, 'frame')} {where}: its queue overflowed (the "
            "writer fell behind), not the bus: those frames were not checked, and no gap, "
            "silence or counter of the bus is judged across them",
            covered,
        )
    ]


def _union(spans: Iterable[_Silence]) -> list[_Silence]:
    """Overlapping stretches joined."""
    out: list[_Silence] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def main_check(
    log: str | Path | Sequence[str | Path],
    *,
    config: str | Path | None = None,
    profile: str | None = None,
    as_json: bool = False,
    gap_periods: float = DEFAULT_GAP_PERIODS,
    out: TextIO | None = None,
    err: TextIO | None = None,
    key_file: str | None = None,
) -> int:
    """``leafgate replay check LOG… [--config FILE] [--profile NAME|FILE] [--json] …``.

    The files are grouped into logs (:func:`~leafgate.record.logs.group_parts`: a rotated
    log's parts are one log); each log gets its report. With several logs, an unreadable one
    is reported and counted as failed, the others still checked, and a last line (or, with
    ``--json``, one object ``{"ok", "logs"}``) gives the verdict over all of them.

    :return: 0 when no log has a finding, 1 otherwise
    :raises LeafgateError: unreadable log (of a single one), configuration or profile
    """
    out = out or sys.stdout
    err = err or sys.stderr
    paths = [log] if isinstance(log, (str, Path)) else list(log)
    groups = group_parts(paths)
    reports: list[CheckReport] = []
    failed: list[str] = []
    unreadable: list[dict[str, Any]] = []
    for parts in groups:
        try:
            report = check_log(
                parts,
                config,
                profile=profile,
                gap_periods=gap_periods,
                progress=err,
                key_file=key_file,
            )
        except ReplayError as exc:
            if len(groups) == 1:
                raise
            err.write(f"leafgate: error: {exc}\n")
            failed.append(parts.name)
            unreadable.append({"path": parts.name, "ok": False, "error": str(exc)})
            if not as_json:
                out.write(f"FAILED: {parts.name}: not checked: {exc}\n")
            continue
        if report.backwards:
            err.write(
                f"leafgate: warning: {report.path}: timestamps go backwards at "
                f"{plural(report.backwards, 'frame')} (by up to "
                f"{report.worst_backwards * 1e3:.1f} ms)\n"
            )
        reports.append(report)
        if not report.ok:
            failed.append(report.path)
        if len(groups) == 1 or not as_json:
            write_report(report, as_json, out)
    if len(groups) > 1:
        if as_json:
            logs = [r.to_dict() for r in reports] + unreadable
            json.dump({"ok": not failed, "logs": logs}, out, indent=2)
            out.write("\n")
        elif failed:
            out.write(
                f"FAILED: {len(failed)} of {plural(len(groups), 'log')} failed the check: "
                f"{', '.join(failed)}\n"
            )
        else:
            out.write(f"OK: all {plural(len(groups), 'log')} checked without a finding\n")
    return 1 if failed else 0
