"""``leafgate replay check LOG``: the offline safety check of a recorded drive.

For every frame of the log (any python-can format, or a session's ``/can`` topic):

1. decode it with the leafgate DBCs, running the gateway's E2E checks (CRC, alive counter,
   length) with one codec per recorded channel;
2. collect per-ID period statistics and find *gaps*: an interval longer than ``gap_periods``
   nominal periods (the DBC's ``GenMsgCycleTime``, else the ID's median interval), or one over
   1.5 periods that ends in a skipped alive counter (frames were lost). Gaps of several IDs that
   overlap in time are one finding (the bus or the logger stalled), and the counter skip after
   a gap is part of it, as is the counter skip after a frame with a bad CRC: one corrupted or
   lost stretch, one finding;
3. re-check every command frame sent with ENABLE=1 against the safety gate's limits
   (:func:`leafgate.gateway.safety.check`: angle, angle rate by speed, lateral acceleration,
   acceleration, jerk, speed, gear at standstill), measured state from the latest valid
   DBW_LONG_RPT before the frame, previous command from the frame before it. After a violating
   frame the check continues from the value the gate would have allowed, so one bad frame is one
   finding, not a cascade of rate violations. A value beyond the angle or acceleration envelope
   is reported as that even when a rate bound is nearer; across a gap the rate bounds allow
   the time that passed.

4. judge every ECU report as the gateway does (:mod:`leafgate.gateway.plausibility`, the same
   functions): a report out of the physical range, or disagreeing with the CAR-CAN wheel speeds
   or steering-wheel angle recorded within ``MAX_SKEW`` of it, is a ``report`` finding (one per
   stretch of disagreement), and an out-of-range speed is never used as the measured state.

5. look for the recorder's end-of-recording marker (the last frame of a properly closed log
   or session): without it the recording stopped early (a crash, a full disk, a write error),
   and an ``incomplete`` finding says after which frame and at what time it stops.

Tolerances are 1.5 quantisation steps of the command signal (read from the DBC): the gate
bounds the float command, the frame carries it rounded.

Exit status: 0 when there is no finding, 1 otherwise (a limit violation, an E2E error or a gap).
"""

from __future__ import annotations

import functools
import json
import math
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final, TextIO

import can
import numpy as np

from leafgate.can.codec import CanCodec, FrameStats
from leafgate.config import VehicleConfig
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
from leafgate.replay.logs import FrameSource, is_end_marker, is_session
from leafgate.replay.session import SessionReader
from leafgate.settings import LeafgateConfig, load_config

__all__ = ["CheckReport", "Finding", "IdStats", "check_frames", "check_log", "main_check"]

STEER_KINDS: Final = frozenset({"angle", "angle_rate", "lateral_accel", "non_finite"})
LONG_KINDS: Final = frozenset({"accel", "jerk", "speed", "gear", "non_finite"})
DEFAULT_GAP_PERIODS: Final = 3.0  # nominal periods; the watchdog's report timeout, too
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
            "time": self.time,
            "kind": self.kind,
            "id": None if self.frame_id is None else f"0x{self.frame_id:03X}",
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
    nominal_period: float | None  # s, DBC cycle time, else the median interval
    mean_period: float  # s (NaN with fewer than two frames)
    min_period: float
    max_period: float
    p99_period: float
    gaps: int
    e2e: FrameStats  # decode outcomes (bad CRC, counter, length …)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": f"0x{self.frame_id:03X}",
            "name": self.name,
            "frames": self.frames,
            "nominal_period_s": _num(self.nominal_period),
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
    frames: int = 0
    start: float = math.nan  # s, first timestamp
    end: float = math.nan  # s, last timestamp
    engaged_frames: int = 0  # command frames with ENABLE=1 re-checked against the limits
    ids: list[IdStats] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    truncated: bool = False  # a session file that ended before its footer
    elapsed: float = 0.0  # s of wall time spent checking

    @property
    def ok(self) -> bool:
        return not self.findings

    def count(self, kind: str) -> int:
        return sum(1 for f in self.findings if f.kind == kind)

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "ok": self.ok,
            "frames": self.frames,
            "duration_s": _num(self.end - self.start),
            "engaged_command_frames": self.engaged_frames,
            "violations": self.count("limit"),
            "e2e_errors": self.count("e2e"),
            "gaps": self.count("gap"),
            "truncated": self.truncated,
            "ids": [s.to_dict() for s in self.ids],
            "findings": [f.to_dict() for f in self.findings],
            "elapsed_s": self.elapsed,
        }

    def format(self) -> list[str]:
        """The summary table, the findings, and one verdict line."""
        lines = [
            f"{self.path}: {self.frames} frames, {self.end - self.start:.3f} s"
            + (" (truncated session)" if self.truncated else ""),
            f"{'ID':>5}  {'name':<20} {'frames':>8} {'period':>8} {'mean':>8} {'max':>8} "
            f"{'gaps':>5} {'crc':>5} {'cnt':>5} {'len':>5}",
        ]
        for s in self.ids:
            lines.append(
                f"{s.frame_id:>5X}  {(s.name or '?'):<20} {s.frames:>8} {_ms(s.nominal_period):>8} "
                f"{_ms(s.mean_period):>8} {_ms(s.max_period):>8} {s.gaps:>5} "
                f"{s.e2e.bad_crc:>5} {s.e2e.bad_counter:>5} {s.e2e.wrong_length:>5}"
            )
        lines.append("(periods in ms)")
        for f in self.findings:
            where = "" if f.frame_id is None else f"{f.frame_id:03X} "
            extra = ""
            if f.kind == "limit":
                extra = f": {f.value:.6g} beyond {f.bound:.6g}"
            lines.append(f"{f.time:.6f}  {f.kind:<5} {where}{f.name}  {f.detail}{extra}")
        lines.append(
            f"{'OK' if self.ok else 'FAILED'}: {self.engaged_frames} engaged command frames "
            f"checked, {self.count('limit')} limit violations, {self.count('e2e')} E2E errors, "
            f"{self.count('gap')} gaps"
        )
        return lines


def _num(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _ms(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value * 1e3:.1f}"


class _Progress:
    """A one-line progress bar on a terminal (nothing when the stream is not one)."""

    def __init__(self, stream: TextIO | None, source: FrameSource) -> None:
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


def _tolerances(codec: CanCodec) -> tuple[float, float]:
    """(angle, longitudinal) tolerance: 1.5 quantisation steps of the command signals."""
    steer = codec.message(0x0A0)
    long = codec.message(0x0A1)
    angle = steer.get_signal_by_name("STEER_ANGLE_CMD").scale if steer else 1e-4
    accel = long.get_signal_by_name("ACCEL_CMD").scale if long else 1e-3
    speed = long.get_signal_by_name("SPEED_CMD").scale if long else 1e-3
    return _TOLERANCE_STEPS * float(angle), _TOLERANCE_STEPS * float(max(accel, speed))


def check_frames(
    frames: Iterable[can.Message],
    limits: SafetyLimits,
    *,
    path: str = "",
    gap_periods: float = DEFAULT_GAP_PERIODS,
    dbw_dbc: str | None = None,
    car_dbc: str | None = None,
    progress: _Progress | None = None,
    vehicle: VehicleConfig | None = None,
) -> CheckReport:
    """Check a sequence of frames (the core of :func:`check_log`; see the module notes).

    :param frames: the frames in recorded order
    :param limits: the safety gate's limits the commands must respect
    :param gap_periods: an interval longer than this many nominal periods is a gap
    """
    t_start = time.perf_counter()
    template = CanCodec(dbw_dbc, car_dbc)
    codecs: dict[object, CanCodec] = {}
    angle_tol, long_tol = _tolerances(template)
    times: dict[int, list[float]] = {}
    e2e_findings: list[tuple[int, float, int, str, str]] = []  # (index in ID, t, id, name, error)
    limit_findings: list[Finding] = []
    last_steer = SteerCommand(angle=0.0)
    last_long = LongCommand()
    steer_time = long_time = -math.inf  # s, timestamps of the last steer / long command frames
    invalid_before: set[int] = set()  # IDs whose previous frame was invalid (bad CRC, length)
    long_report: LongReport | None = None
    vehicle = vehicle or VehicleConfig()
    judge = _ReportJudge(vehicle)
    engaged = 0
    n = 0
    first = last = math.nan
    ended = False
    for msg in frames:
        if is_end_marker(msg):
            ended = True
            continue
        ended = False  # frames after a marker: a later file or session segment
        n += 1
        if progress is not None and not n & 0x3FF:
            progress.update(n)
        t = msg.timestamp
        if n == 1:
            first = t
        last = t
        frame_id = msg.arbitration_id
        stamps = times.get(frame_id)
        if stamps is None:
            stamps = times[frame_id] = []
        stamps.append(t)
        codec = codecs.get(msg.channel)
        if codec is None:
            codec = codecs[msg.channel] = template if not codecs else CanCodec(dbw_dbc, car_dbc)
        decoded = codec.decode(msg)
        if not decoded.valid:
            error: str = decoded.error or "?"
            if error == "unknown_id":
                continue
            # A frame with a bad CRC or length never reaches the counter check, so the next good
            # frame of its ID sees a skipped counter: one corrupted frame, one finding.
            if not (error == "bad_counter" and frame_id in invalid_before):
                e2e_findings.append((len(stamps) - 1, t, frame_id, decoded.name or "?", error))
            if error != "bad_counter":
                invalid_before.add(frame_id)
            else:
                invalid_before.discard(frame_id)
            continue
        invalid_before.discard(frame_id)
        value = decoded.value
        if isinstance(value, (SteerReport, LongReport, WheelSpeeds, SteeringWheelAngle)):
            plausible = judge.take(t, frame_id, decoded.name or "", value)
            if isinstance(value, LongReport) and plausible:
                long_report = value
            limit_findings.extend(judge.findings)
            judge.findings.clear()
            continue
        elif isinstance(value, SteerCommand):
            if value.enable:
                engaged += 1
                measured = _measured(long_report, limits)
                lim = _over(limits, t - steer_time)
                found = _violations(
                    value, last_long, last_steer, last_long, measured, lim, angle_tol, STEER_KINDS
                )
                for v in found:
                    limit_findings.append(
                        Finding(t, "limit", frame_id, decoded.name or "", v.kind, v.value, v.bound)
                    )
                if found:  # continue from what the gate would have sent
                    value = apply_limits(
                        value, last_long, last_steer, last_long, measured, lim
                    ).steer
            last_steer, steer_time = value, t
        elif isinstance(value, LongCommand):
            if value.enable:
                engaged += 1
                measured = _measured(long_report, limits)
                lim = _over(limits, t - long_time)
                found = _violations(
                    last_steer, value, last_steer, last_long, measured, lim, long_tol, LONG_KINDS
                )
                for v in found:
                    limit_findings.append(
                        Finding(t, "limit", frame_id, decoded.name or "", v.kind, v.value, v.bound)
                    )
                if found:
                    value = apply_limits(
                        last_steer, value, last_steer, last_long, measured, lim
                    ).long
            last_long, long_time = value, t
    if progress is not None:
        progress.done()

    names = {}
    merged: dict[int, FrameStats] = {}
    for codec in codecs.values():
        for frame_id, s in codec.stats.items():
            if s.frames:
                merged[frame_id] = merged.get(frame_id, FrameStats()) + s
                names[frame_id] = codec.name_of(frame_id)
    skips = {
        (frame_id, index) for index, _, frame_id, _, error in e2e_findings if error == "bad_counter"
    }
    ids, gaps = _timing(times, template, names, merged, gap_periods, skips)
    findings = list(limit_findings)
    gap_firsts = {(frame_id, index) for frame_id, index, _, _ in gaps}
    for index, t, frame_id, name, kind in e2e_findings:
        if kind == "bad_counter" and (frame_id, index) in gap_firsts:
            continue  # the frames lost in a gap, reported as the gap
        findings.append(Finding(t, "e2e", frame_id, name, kind))
    findings.extend(_merge_gaps(gaps, names))
    if not ended:
        findings.append(
            Finding(
                last,
                "incomplete",
                None,
                "",
                f"no end-of-recording marker: the recording stops after frame {n} at {last:.3f} s",
            )
        )
    findings.sort(key=lambda f: (f.time, f.kind))
    return CheckReport(
        path=path,
        frames=n,
        start=first,
        end=last,
        engaged_frames=engaged,
        ids=ids,
        findings=findings,
        elapsed=time.perf_counter() - t_start,
    )


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
) -> tuple[list[IdStats], list[_Gap]]:
    """Per-ID period statistics and the gaps of every ID with a known or measurable period.

    A gap is an interval over ``gap_periods`` nominal periods, or one over 1.5 periods that
    ends in a skipped alive counter (``skips``: (ID, index of the frame)) — frames were lost.
    """
    stats: list[IdStats] = []
    gaps: list[_Gap] = []
    for frame_id in sorted(times):
        t = np.asarray(times[frame_id], dtype=np.float64)
        dt = np.diff(t)
        message = codec.message(frame_id)
        nominal: float | None = None
        if message is not None and message.cycle_time:
            nominal = message.cycle_time / 1000.0  # ms in the DBC
        elif message is not None and dt.size >= 3:
            nominal = float(np.median(dt))  # known ID without a cycle time: what it does
        id_gaps = 0
        if nominal is not None and nominal > 0.0 and dt.size:
            long_gap = dt > gap_periods * nominal
            lost = dt > _LOST_FRAME_PERIODS * nominal
            for i in np.flatnonzero(lost):
                if long_gap[i] or (frame_id, int(i) + 1) in skips:
                    gaps.append((frame_id, int(i) + 1, float(t[i]), float(t[i + 1])))
                    id_gaps += 1
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
            )
        )
    return stats, gaps


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
        label = ", ".join(f"{i:03X}" for i in ids)
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
    path: str | Path,
    config: LeafgateConfig | None = None,
    *,
    gap_periods: float = DEFAULT_GAP_PERIODS,
    progress: TextIO | None = None,
) -> CheckReport:
    """Check a recorded log or session (see the module notes).

    :param path: a python-can log, or a ``.mcap`` session (whose recorded configuration gives
        the limits unless ``config`` is given)
    :param config: the configuration whose safety limits apply (default: the built-in one)
    :param progress: a stream for the progress bar (drawn only when it is a terminal)
    :raises ReplayError: the file is missing, of an unknown format or unreadable
    :raises ConfigError: a session's recorded configuration does not load
    """
    path = Path(path)
    if config is None and is_session(path):
        with SessionReader(path) as reader:
            reader.read_metadata()
            config = reader.config() if reader.config_yaml is not None else None
    config = config or LeafgateConfig()
    limits = SafetyLimits.from_config(config.gateway.safety, config.vehicle, config.gateway.period)
    source = FrameSource(path, markers=True)
    report = check_frames(
        source,
        limits,
        path=str(path),
        gap_periods=gap_periods,
        dbw_dbc=config.can.dbw_dbc,
        car_dbc=config.can.car_dbc,
        progress=_Progress(progress, source),
        vehicle=config.vehicle,
    )
    report.truncated = source.truncated
    return report


def main_check(
    log: str | Path,
    *,
    config: str | Path | None = None,
    as_json: bool = False,
    gap_periods: float = DEFAULT_GAP_PERIODS,
    out: TextIO | None = None,
    err: TextIO | None = None,
) -> int:
    """``leafgate replay check LOG [--config FILE] [--json] [--gap-periods N]``.

    :return: 0 when the log has no finding, 1 otherwise
    :raises LeafgateError: unreadable log or configuration (the CLI prints it)
    """
    out = out or sys.stdout
    err = err or sys.stderr
    cfg = load_config(config) if config is not None else None
    report = check_log(log, cfg, gap_periods=gap_periods, progress=err)
    if as_json:
        json.dump(report.to_dict(), out, indent=2)
        out.write("\n")
    else:
        for line in report.format():
            out.write(line + "\n")
    return 0 if report.ok else 1
