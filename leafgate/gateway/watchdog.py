"""Watchdogs: freshness and plausibility of every input, evaluated without a clock.

Each watchdog is a small class fed with the latest input slot (and the gateway's ``now``) once
per tick and answering a :class:`Check`: how old the last valid sample is, its status, and the
reaction the table of docs/watchdogs.md asks for while the gateway is engaged or stopping.

=============================  ======================================  ===========
watchdog                       threshold (``WatchdogConfig``)          reaction
=============================  ======================================  ===========
localization age               > ``localization_stop_age`` (100 ms)    STOP
localization age / jump        > ``localization_fault_age`` (500 ms),  FAULT
                               > ``localization_max_jump`` (1 m)
localization covariance        std > ``localization_max_position_std``  pose invalid
                               (0.5 m) / ``…_heading_std`` (5°)
localization sources           > 1 publisher heard within 1 s          FAULT
ECU report age (each report)   > 3 periods (10, 20, 100 ms)            FAULT
report CRC/counter errors      counter ≥ 5 (+1 bad, −1 good, floor 0)  FAULT
control loop overrun           3 ticks in a row                        FAULT
ECU reports OVERRIDE           —                                       STANDBY
no progress along the plan     < ``no_progress_distance`` (0.1 m) in   STOP
                               ``no_progress_time`` (3 s) while
                               engaged and commanded to move
off the plan                   > ``max_path_deviation`` (2 m) from it  STOP
                               while engaged
=============================  ======================================  ===========

The engagement logic decides *when* a reaction applies (staleness of inputs matters only while
the gateway drives; bus errors and overruns latch a fault in any state).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass
from typing import Generic, NamedTuple, TypeVar

from leafgate.config.gateway import WatchdogConfig
from leafgate.control.reference import trajectory_problem
from leafgate.messages import (
    EcuState,
    LongReport,
    Pose,
    Stamped,
    SteerReport,
    SystemReport,
    Trajectory,
)

T = TypeVar("T")

TIME_EPS = 1e-9  # s, ages within this of a threshold count as at it (times are sums of periods)


class Status(enum.Enum):
    """Status of one watchdog."""

    OK = "ok"
    MISSING = "missing"  # no valid sample received yet
    INVALID = "invalid"  # samples arrive but none was valid yet
    STALE = "stale"  # older than the stop threshold
    LOST = "lost"  # older than the fault threshold
    JUMP = "jump"  # implausible change in one sample
    INCONSISTENT = "inconsistent"  # disagrees with dead reckoning from the ECU's reports
    ERRORS = "errors"  # error counter at or above its threshold
    OVERRUN = "overrun"  # too many late ticks in a row
    SOURCES = "sources"  # samples from more than one publisher on the input's key
    OFF_PLAN = "off-plan"  # the car farther from the plan than allowed


class Reaction(enum.IntEnum):
    """What a watchdog asks of the engagement state machine; ordered by severity."""

    NONE = 0
    STOP = 1
    FAULT = 2


class Check(NamedTuple):
    """The verdict of one watchdog for one tick (immutable, so a verdict can be shared)."""

    name: str
    status: Status
    age: float | None  # s since the last valid sample was received; None: never (or no age)
    limit: float  # the threshold that applies (s, m or a count)
    reaction: Reaction  # what it asks for while engaged
    detail: str = ""  # human-readable reason, empty when OK
    value: float | None = None  # jump (m), error counter, overruns in a row, deviation (m)

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def freshness(age: float | None, stale_after: float, lost_after: float) -> Status:
    """OK, STALE (older than ``stale_after``), LOST (older than ``lost_after``) or MISSING."""
    if age is None:
        return Status.MISSING
    if age > lost_after + TIME_EPS:
        return Status.LOST
    if age > stale_after + TIME_EPS:
        return Status.STALE
    return Status.OK


def pose_problem(
    pose: Pose, max_position_std: float = math.inf, max_heading_std: float = math.inf
) -> str | None:
    """Why a localization sample cannot be used, or None: the one rule, for the transport's
    subscriber (which knows no bounds) and the core's watchdog (which applies the configured
    ones).

    Position, heading, speed and yaw rate must be finite. The reported variances
    (:attr:`Pose.var_x`, ``var_y``, ``var_heading``) must be finite, not negative, and their
    standard deviations within the bounds: a localization that says it is lost (1e12) is not
    followed. A variance of 0 is "not given" (many publishers leave the covariance zero) and
    passes; so does any variance while the bound is infinite.

    :param max_position_std: m, bound on ``sqrt(max(var_x, var_y))``
    :param max_heading_std: rad, bound on ``sqrt(var_heading)``
    """
    isfinite = math.isfinite  # chained, not all(<generator>): this runs on every pose
    if not (
        isfinite(pose.x)
        and isfinite(pose.y)
        and isfinite(pose.heading)
        and isfinite(pose.speed)
        and isfinite(pose.yaw_rate)
    ):
        return "localization not finite"
    var_x, var_y, var_h = pose.var_x, pose.var_y, pose.var_heading
    if var_x == 0.0 and var_y == 0.0 and var_h == 0.0:  # the common case: not given
        return None
    if not (
        0.0 <= var_x < math.inf and 0.0 <= var_y < math.inf and 0.0 <= var_h < math.inf
    ):  # negative, NaN or infinite
        return (
            f"localization covariance: variances x {var_x:g} m², y {var_y:g} m², "
            f"yaw {var_h:g} rad² (not finite, or negative)"
        )
    position_std = math.sqrt(max(var_x, var_y))
    if position_std > max_position_std:
        return f"localization covariance: position std {position_std:g} m > {max_position_std:g} m"
    heading_std = math.sqrt(var_h)
    if heading_std > max_heading_std:
        return (
            f"localization covariance: heading std {math.degrees(heading_std):g}° > "
            f"{math.degrees(max_heading_std):g}°"
        )
    return None


def pose_is_valid(
    pose: Pose, max_position_std: float = math.inf, max_heading_std: float = math.inf
) -> bool:
    """A pose is usable (:func:`pose_problem` finds nothing)."""
    return pose_problem(pose, max_position_std, max_heading_std) is None


def trajectory_is_valid(trajectory: Trajectory) -> bool:
    """A trajectory is usable by the controller's one rule (:func:`~leafgate.control.reference.
    trajectory_problem`): finite, and four or more waypoints once overlapping ones are removed."""
    return trajectory_problem(trajectory) is None


def position_jump(previous: Stamped[Pose], current: Stamped[Pose]) -> float:
    """Distance between a new position and the previous one carried forward, m.

    The previous sample is moved on by its own speed and heading over the time between the two
    receptions, so normal motion is no jump even when a sample or two went missing.
    """
    p, c = previous.value, current.value
    dt = max(current.received - previous.received, 0.0)
    x = p.x + p.speed * dt * math.cos(p.heading)
    y = p.y + p.speed * dt * math.sin(p.heading)
    return math.hypot(c.x - x, c.y - y)


class _SlotWatchdog(Generic[T]):
    """Keeps the last valid sample of a latest-value slot."""

    def __init__(self) -> None:
        self.last: Stamped[T] | None = None  # last valid sample
        self.seen_invalid = False

    def _is_valid(self, sample: Stamped[T]) -> bool:
        return sample.valid

    def _take(self, sample: Stamped[T] | None) -> bool:
        """Record the sample; True when it is a new valid one."""
        if sample is None:
            return False
        if self.last is not None and sample.received == self.last.received:
            return False
        if not (sample.valid and self._is_valid(sample)):
            self.seen_invalid = True
            return False
        self.last = sample
        return True

    def _missing_status(self) -> Status:
        return Status.INVALID if self.seen_invalid else Status.MISSING


class DeadReckoning:
    """Localization's displacement against dead reckoning, over a sliding window.

    Each new sample advances a dead-reckoned point by the ECU's measured speed along the
    sample's heading over the time since the previous sample (sender stamps when both have
    them, else receive times). The speed is the mean of the reports received between the two
    samples' times on the gateway clock (a pose's receive time already goes back by what its
    stamp says it is old, so a late pose meets the speeds of its own time, not today's). Over
    the window, the localization's displacement and the dead reckoning's must agree: the sum
    telescopes, so the localization's own noise counts once at each end, not per sample, while
    a source that drifts a little every sample, or a second source interleaved with the first,
    shows as the difference.
    """

    def __init__(self, window: float) -> None:
        self.window = window  # s
        # (t, x, y, heading, received) of each sample and the dead-reckoned point (dx, dy) at it
        self._points: deque[tuple[float, float, float, float, float, float, float]] = deque()
        self._speeds: deque[tuple[float, float]] = deque()  # (received, speed) of the reports

    def reset(self) -> None:
        self._points.clear()
        self._speeds.clear()

    def note_speed(self, received: float, speed: float) -> None:
        """A measured speed (m/s) received at ``received`` (gateway clock, s)."""
        speeds = self._speeds
        if speeds and received <= speeds[-1][0]:
            return  # the same report again
        speeds.append((received, speed))
        while received - speeds[0][0] > 2 * self.window + 1.0:
            speeds.popleft()

    def _speed_between(self, t0: float, t1: float) -> float | None:
        inside = [v for t, v in self._speeds if t0 <= t <= t1]
        if inside:
            return sum(inside) / len(inside)
        before = [v for t, v in self._speeds if t <= t1]
        return before[-1] if before else None

    def add(self, sample: Stamped[Pose]) -> tuple[float, float]:
        """Take a new sample; (disagreement m, span s) of the window, (0, 0) without speed."""
        pose = sample.value
        points = self._points
        t = pose.stamp if math.isfinite(pose.stamp) else sample.received
        if points:
            t0, _, _, h0, r0, dx0, dy0 = points[-1]
            speed = self._speed_between(r0, sample.received)
            if speed is None or not math.isfinite(speed):
                points.clear()
                return 0.0, 0.0
            t = max(t, t0)  # out-of-order stamps advance nothing (their position still counts)
            step = speed * min(t - t0, self.window)
            h = math.atan2(
                math.sin(h0) + math.sin(pose.heading), math.cos(h0) + math.cos(pose.heading)
            )
            dx, dy = dx0 + step * math.cos(h), dy0 + step * math.sin(h)
        else:
            dx = dy = 0.0
        points.append((t, pose.x, pose.y, pose.heading, sample.received, dx, dy))
        while t - points[0][0] > self.window:
            points.popleft()
        first, last = points[0], points[-1]
        error = math.hypot(
            (last[1] - first[1]) - (last[5] - first[5]), (last[2] - first[2]) - (last[6] - first[6])
        )
        return error, last[0] - first[0]


class PoseWatchdog(_SlotWatchdog[Pose]):
    """Localization: age (stop, then fault), position jumps, and agreement with dead
    reckoning from the ECU's measured speed (:class:`DeadReckoning`)."""

    name = "localization"

    def __init__(self, config: WatchdogConfig) -> None:
        super().__init__()
        self.config = config
        self.dead_reckoning = DeadReckoning(config.localization_drift_window)
        self.drift = 0.0  # m, the last disagreement with dead reckoning
        self.problem = ""  # why the last refused sample was refused (pose_problem)
        self.problem_at = -math.inf  # s, its receive time

    def _is_valid(self, sample: Stamped[Pose]) -> bool:
        cfg = self.config
        problem = pose_problem(
            sample.value, cfg.localization_max_position_std, cfg.localization_max_heading_std
        )
        if problem is not None:
            self.problem = problem
            self.problem_at = sample.received
        return problem is None

    def _take(self, sample: Stamped[Pose] | None) -> bool:
        if (
            sample is not None
            and not sample.valid
            and (self.last is None or sample.received != self.last.received)
        ):  # refused on arrival by the transport: say why, as far as the pose tells
            self.problem = pose_problem(sample.value) or "localization stamped in the future"
            self.problem_at = sample.received
        return super()._take(sample)

    def _refused(self) -> str:
        """Why the newest sample was refused, for a reason ("" when it was not)."""
        if not self.problem or (self.last is not None and self.problem_at <= self.last.received):
            return ""
        return f" (newest sample refused: {self.problem})"

    def update(
        self, now: float, sample: Stamped[Pose] | None, long: Stamped[LongReport] | None = None
    ) -> Check:
        """Feed this tick's slot content and judge it.

        :param long: the latest DBW_LONG_RPT (its speed drives the dead reckoning)
        """
        if long is not None and long.valid and math.isfinite(long.value.speed):
            self.dead_reckoning.note_speed(long.received, long.value.speed)
        cfg = self.config
        previous = self.last
        jump: float | None = None
        span = 0.0
        if self._take(sample) and self.last is not None:
            if previous is not None:
                jump = position_jump(previous, self.last)
            self.drift, span = self.dead_reckoning.add(self.last)
        sources = sample.sources if sample is not None else ()
        if len(sources) > 1:
            # More than one publisher on the localization key within the transport's window:
            # which one the car follows depends on who published last.
            named = ", ".join(s or "unidentified" for s in sources)
            return Check(
                self.name,
                Status.SOURCES,
                None if self.last is None else now - self.last.received,
                1.0,
                Reaction.FAULT,
                f"localization from {len(sources)} publishers: {named} (a second source)",
                float(len(sources)),
            )
        if self.last is None:
            status = self._missing_status()
            return Check(
                self.name,
                status,
                None,
                cfg.localization_fault_age,
                Reaction.FAULT,
                f"localization {status.value}" + self._refused(),
            )
        age = now - self.last.received
        if jump is not None and jump > cfg.localization_max_jump:
            return Check(
                self.name,
                Status.JUMP,
                age,
                cfg.localization_max_jump,
                Reaction.FAULT,
                f"localization jumped {jump:.2f} m > {cfg.localization_max_jump:g} m in one sample",
                jump,
            )
        if span > 0.0 and self.drift > cfg.localization_max_drift:
            return Check(
                self.name,
                Status.INCONSISTENT,
                age,
                cfg.localization_max_drift,
                Reaction.FAULT,
                f"localization disagrees with dead reckoning by {self.drift:.2f} m over "
                f"{span:.2f} s (> {cfg.localization_max_drift:g} m): spoofed or second source?",
                self.drift,
            )
        status = freshness(age, cfg.localization_stop_age, cfg.localization_fault_age)
        if status is Status.LOST:
            return Check(
                self.name,
                status,
                age,
                cfg.localization_fault_age,
                Reaction.FAULT,
                f"localization age {age:.3f} s > {cfg.localization_fault_age:g} s"
                + self._refused(),
                jump,
            )
        if status is Status.STALE:
            return Check(
                self.name,
                status,
                age,
                cfg.localization_stop_age,
                Reaction.STOP,
                f"localization age {age:.3f} s > {cfg.localization_stop_age:g} s" + self._refused(),
                jump,
            )
        refused = self._refused()
        if refused:  # the last valid sample is still fresh, but the newest one is not usable
            return Check(
                self.name,
                Status.INVALID,
                age,
                cfg.localization_stop_age,
                Reaction.NONE,
                f"localization invalid{refused}",
                jump,
            )
        return Check(self.name, Status.OK, age, cfg.localization_stop_age, Reaction.NONE, "", jump)


class TrajectoryWatchdog(_SlotWatchdog[Trajectory]):
    """Trajectory: present, valid, and fresh enough to engage on (no reaction while engaged)."""

    name = "trajectory"

    def __init__(self, config: WatchdogConfig, max_speed: float = math.inf) -> None:
        super().__init__()
        self.config = config
        self.max_speed = max_speed  # m/s, the maneuver limit a plan must respect
        self.problem = ""  # why the last unusable plan was refused (the controller's reason)
        self.problem_at = -math.inf  # s, when that plan arrived

    def _is_valid(self, sample: Stamped[Trajectory]) -> bool:
        if self.last is not None and sample.value is self.last.value:
            return True  # the same plan re-received: its (read-only) arrays were checked
        problem = trajectory_problem(sample.value, max_speed=self.max_speed)
        if problem is not None:
            self.problem = problem  # shown while no usable plan has been received
        return problem is None

    def _take(self, sample: Stamped[Trajectory] | None) -> bool:
        new = sample is not None and (self.last is None or sample.received != self.last.received)
        taken = super()._take(sample)
        if new and not taken and sample is not None:  # refused, here or by the transport
            if not sample.valid:  # the transport's refusal: the same rule says why
                self.problem = trajectory_problem(sample.value, max_speed=self.max_speed) or (
                    "refused by the transport"
                )
            self.problem_at = sample.received
        return taken

    def refused_since(self, received: float) -> str:
        """Why a plan that arrived after ``received`` (s, the followed plan's arrival) was
        refused; "" when none was."""
        return self.problem if self.problem_at > received else ""

    def update(self, now: float, sample: Stamped[Trajectory] | None) -> Check:
        """Feed this tick's slot content and judge it."""
        self._take(sample)
        max_age = self.config.trajectory_max_age
        limit = math.inf if max_age is None else max_age
        if self.last is None:
            status = self._missing_status()
            detail = f"trajectory {status.value}"
            if status is Status.INVALID and self.problem:
                detail += f": {self.problem}"
            return Check(self.name, status, None, limit, Reaction.NONE, detail)
        age = now - self.last.received
        if age > limit + TIME_EPS:
            return Check(
                self.name,
                Status.STALE,
                age,
                limit,
                Reaction.NONE,
                f"trajectory age {age:.3f} s > {limit:g} s",
            )
        return Check(self.name, Status.OK, age, limit, Reaction.NONE)


class ReportWatchdog(_SlotWatchdog[T]):
    """One ECU report: FAULT when older than ``periods`` report periods.

    :param name: diagnostics name (``steer_report`` …)
    :param period: the report's period, s; None when the vehicle sends no such report (the
        check is then always OK and says so)
    :param periods: how many periods may pass without a report
    """

    def __init__(self, name: str, period: float | None, periods: float) -> None:
        super().__init__()
        self.name = name
        self.timeout = math.inf if period is None else period * periods  # s
        self._absent = (
            Check(name, Status.OK, None, math.inf, Reaction.NONE, "not sent by this vehicle")
            if period is None
            else None
        )

    def update(self, now: float, sample: Stamped[T] | None) -> Check:
        """Feed this tick's slot content and judge it."""
        if self._absent is not None:
            return self._absent
        self._take(sample)
        if self.last is None:
            status = self._missing_status()
            return Check(
                self.name, status, None, self.timeout, Reaction.FAULT, f"{self.name} {status.value}"
            )
        age = now - self.last.received
        if age > self.timeout + TIME_EPS:
            return Check(
                self.name,
                Status.LOST,
                age,
                self.timeout,
                Reaction.FAULT,
                f"{self.name} age {age:.3f} s > {self.timeout:g} s",
            )
        return Check(self.name, Status.OK, age, self.timeout, Reaction.NONE)


def update_error_counter(count: int, good: int, bad: int) -> tuple[int, int]:
    """panda-style error counter over one tick: +1 per bad frame, −1 per good one, floor 0.

    The order of the frames within a tick is unknown, so both results are the highest any order
    could give: the peak when the bad frames come first, the value after the tick when the good
    ones do. The counter therefore never lags a frame-by-frame one.

    :returns: (peak within the tick, value after the tick)
    """
    good, bad = max(good, 0), max(bad, 0)
    return count + bad, max(count - good, 0) + bad


class ErrorCounter:
    """Report CRC/counter/length errors (``max_report_errors``, as panda does)."""

    name = "report_errors"

    def __init__(self, threshold: int) -> None:
        self.threshold = threshold
        self.count = 0

    def update(self, good: int, bad: int, cause: str = "") -> Check:
        """Count this tick's good and bad report frames.

        :param cause: what the receiver makes of the errors (e.g. a second sender), for the
            reason
        """
        peak, self.count = update_error_counter(self.count, good, bad)
        if peak >= self.threshold or self.count >= self.threshold:
            return Check(
                self.name,
                Status.ERRORS,
                None,
                self.threshold,
                Reaction.FAULT,
                f"report frame errors reached {peak} (limit {self.threshold})"
                + (f": {cause}" if cause else ""),
                peak,
            )
        return Check(self.name, Status.OK, None, self.threshold, Reaction.NONE, "", self.count)


class OverrunWatchdog:
    """Control loop overruns: ``max_overruns`` late ticks in a row, or one tick that started
    more than ``stall_limit`` s late → FAULT."""

    name = "overrun"

    def __init__(self, limit: int, stall_limit: float = math.inf) -> None:
        self.limit = limit
        self.stall_limit = stall_limit  # s
        self.in_row = 0

    def update(self, overrun: bool, lateness: float = 0.0) -> Check:
        """Count this tick (``overrun``: it started late, by ``lateness`` s)."""
        self.in_row = self.in_row + 1 if overrun else 0
        if lateness > self.stall_limit + TIME_EPS:
            return Check(
                self.name,
                Status.OVERRUN,
                lateness,
                self.stall_limit,
                Reaction.FAULT,
                f"control loop stalled {lateness:.3f} s > {self.stall_limit:g} s",
                self.in_row,
            )
        if self.in_row >= self.limit:
            return Check(
                self.name,
                Status.OVERRUN,
                None,
                self.limit,
                Reaction.FAULT,
                f"control loop overran {self.in_row} ticks in a row",
                self.in_row,
            )
        return Check(self.name, Status.OK, None, self.limit, Reaction.NONE, "", self.in_row)


def override_active(
    steer: SteerReport | None, long: LongReport | None, system: SystemReport | None
) -> bool:
    """The ECU reports a driver override on any of its reports."""
    return bool(
        (steer is not None and steer.override)
        or (long is not None and long.override)
        or (system is not None and system.state == EcuState.OVERRIDE)
    )


def ecu_fault(
    steer: SteerReport | None, long: LongReport | None, system: SystemReport | None
) -> str | None:
    """Why the ECU cannot drive (fault or command timeout flags, FAULT state), or None."""
    reasons = []
    if system is not None and system.state == EcuState.FAULT:
        reasons.append("state FAULT")
    if (steer is not None and steer.fault) or (long is not None and long.fault):
        reasons.append("actuator fault")
    if (steer is not None and steer.cmd_timeout) or (long is not None and long.cmd_timeout):
        reasons.append("command timeout")
    return "ECU reports " + ", ".join(reasons) if reasons else None


#: Names of the checks in the order :meth:`Watchdogs.update` reports them.
CHECK_ORDER: tuple[str, ...] = (
    "localization",
    "trajectory",
    "steer_report",
    "long_report",
    "system_report",
    "report_errors",
    "overrun",
    "progress",  # judged after the controller ran (ProgressWatchdog), not by Watchdogs.update
)


@dataclass(frozen=True)
class WatchdogReport:
    """All watchdogs' checks for one tick and the last valid sample of each input."""

    checks: tuple[Check, ...]
    pose: Stamped[Pose] | None
    trajectory: Stamped[Trajectory] | None
    steer: Stamped[SteerReport] | None
    long: Stamped[LongReport] | None
    system: Stamped[SystemReport] | None

    def get(self, name: str) -> Check:
        """The check named ``name``.

        :raises KeyError: no such watchdog
        """
        for c in self.checks:
            if c.name == name:
                return c
        raise KeyError(name)

    def failing(self, at_least: Reaction) -> tuple[Check, ...]:
        """The checks asking for ``at_least`` this severe a reaction."""
        return tuple(c for c in self.checks if c.reaction >= at_least)


class Watchdogs:
    """Every input watchdog of the gateway, updated together once per tick."""

    def __init__(
        self, config: WatchdogConfig, period: float = math.inf, max_speed: float = math.inf
    ) -> None:
        self.config = config
        self.pose = PoseWatchdog(config)
        self.trajectory = TrajectoryWatchdog(config, max_speed)
        n = config.report_timeout_periods
        self.steer: ReportWatchdog[SteerReport] = ReportWatchdog(
            "steer_report", config.steer_report_period, n
        )
        self.long: ReportWatchdog[LongReport] = ReportWatchdog(
            "long_report", config.long_report_period, n
        )
        self.system: ReportWatchdog[SystemReport] = ReportWatchdog(
            "system_report", config.system_report_period, n
        )
        self.errors = ErrorCounter(config.max_report_errors)
        self.overrun = OverrunWatchdog(config.max_overruns, config.max_stall_periods * period)

    def update(
        self,
        now: float,
        pose: Stamped[Pose] | None,
        trajectory: Stamped[Trajectory] | None,
        steer: Stamped[SteerReport] | None,
        long: Stamped[LongReport] | None,
        system: Stamped[SystemReport] | None,
        good_frames: int,
        bad_frames: int,
        overrun: bool,
        lateness: float = 0.0,
        reports_as_of: float | None = None,
        report_error_cause: str = "",
    ) -> WatchdogReport:
        """Feed one tick's inputs to every watchdog.

        :param reports_as_of: the time up to which the bus has been read (frames arriving
            later still wait in the socket); the reports' ages count to it, not to ``now``
        """
        as_of = now if reports_as_of is None else min(now, reports_as_of)
        checks = (  # in CHECK_ORDER
            self.pose.update(now, pose, long),
            self.trajectory.update(now, trajectory),
            self.steer.update(as_of, steer),
            self.long.update(as_of, long),
            self.system.update(as_of, system),
            self.errors.update(good_frames, bad_frames, report_error_cause),
            self.overrun.update(overrun, lateness),
        )
        return WatchdogReport(
            checks=checks,
            pose=self.pose.last,
            trajectory=self.trajectory.last,
            steer=self.steer.last,
            long=self.long.last,
            system=self.system.last,
        )


STEER_SETTLE_BAND = math.radians(0.5)  # rad, the measured angle moving beyond this is turning
STEER_SETTLE_TIME = 0.5  # s, steering still within the band this long has stopped turning
STOP_COMMAND_SPEED = 0.05  # m/s, a target speed below this while moving is a stop being made


def off_plan(deviation: float, progress: float, route_length: float, limit: float) -> str | None:
    """The one rule for a car that has left its plan: farther than ``limit`` (m,
    ``max_path_deviation``) from it (``deviation``, m; NaN: unknown, not judged). The reason,
    naming where along the plan (``progress`` of ``route_length``, m), or None when on the plan.
    The progress watchdog stops the car on it; ``sim --direct``, which has no gateway, reports it.
    """
    if not deviation > limit:  # NaN: not judged
        return None
    return (
        f"off the plan: {deviation:.2f} m from it at {progress:.1f} of {route_length:.1f} m "
        f"(limit {limit:g} m)"
    )


class ProgressWatchdog:
    """No progress along the plan: ENGAGED, commanded to move, yet stuck → STOP.

    Fed once per tick the controller ran (``now`` from the gateway, no clock) with the
    controller's arc-length ``progress`` along the plan (:class:`~leafgate.messages.ControlOutput`).
    The car must gain at least ``no_progress_distance`` along the plan within every
    ``no_progress_time``; otherwise the check asks for a controlled stop, naming it.

    The timer does not run while the car legitimately waits: while a gear change is pending
    (cusp), while the steering is still turning at standstill (the MPC sets the wheel before it
    drives off), while the car brakes to a stop the controller asked for (target speed zero,
    still moving: a stop ends by itself), and while the car creeps along the last
    ``no_progress_distance`` of the plan, where the controller's goal check decides, and while
    the car stands at the plan's stop point (where the plan comes to rest before its segment's
    end, as a planner stops a car at a stop line: it waits there for a plan that moves on).
    "Turning" means the measured angle left a ±0.5°
    band within the last 0.5 s, so a steering actuator that does not move is no excuse, and a
    car at rest with nothing to wait for is judged whatever the controller says. A new plan object
    (a planner's rolling window) changes where progress is counted from: the progress gained on
    the old plan within the window is carried over, so a re-sent plan neither resets the timer
    nor counts as progress. A controller that reports no route (``route_length`` 0, unknown) is
    not judged.
    """

    name = "progress"

    def __init__(self, config: WatchdogConfig) -> None:
        self.time_limit = config.no_progress_time
        self.distance = config.no_progress_distance
        self.max_deviation = config.max_path_deviation
        self._ok = Check(self.name, Status.OK, None, self.time_limit, Reaction.NONE, "", None)
        self.reset()

    def reset(self) -> None:
        """Forget the engagement (called whenever the gateway does not drive)."""
        self._plan: object | None = None
        self._since: float | None = None  # s, start of the current window
        self._base = 0.0  # m, progress on the current plan at the start of the window
        self._carried = 0.0  # m, progress gained on earlier plans within the window
        self._last_progress = 0.0  # m, on the current plan, last tick
        self._steer_anchor: float | None = None  # rad, the measured angle when it last moved
        self._steer_moved = -math.inf  # s, when the measured angle last left the band

    def idle(self) -> Check:
        """Not driving: reset and report OK."""
        if self._since is not None or self._plan is not None:
            self.reset()
        return self._ok

    def update(
        self,
        now: float,
        plan: object,
        progress: float,
        route_length: float,
        steer_angle: float,
        standstill: bool,
        gear_change: bool,
        commanded_speed: float = math.inf,
        deviation: float = math.nan,
        stop_distance: float = math.nan,
    ) -> Check:
        """Judge one tick of an engagement in which the controller drives.

        :param plan: the trajectory object followed (identity tells a new plan)
        :param progress: m along ``plan`` (the controller's, monotone on one plan)
        :param route_length: m, the plan's length; 0 when the controller does not report it
        :param steer_angle: rad, the measured road-wheel angle
        :param standstill: the car stands still
        :param gear_change: a gear change is pending (the gateway holds the brake for it)
        :param commanded_speed: m/s, the controller's target speed; zero while the car still
            moves is a stop being made (at a cusp, at the end, after an overshoot), not a stall
        :param deviation: m, the car's distance from the plan (the controller's; NaN: unknown,
            not judged): beyond ``max_path_deviation`` the car has left the plan → STOP
        :param stop_distance: m along the plan to where it comes to rest before its segment's
            end (NaN: no such stop point): a car at rest within ``no_progress_distance`` of it,
            or past it, waits there as the plan says, for a plan that moves on
        """
        if not (route_length > 0.0 and math.isfinite(progress)):
            return self.idle()
        left = off_plan(deviation, progress, route_length, self.max_deviation)
        if left is not None:
            return Check(
                self.name, Status.OFF_PLAN, None, self.max_deviation, Reaction.STOP, left, deviation
            )
        if self._steer_anchor is None:
            self._steer_anchor = steer_angle
        elif abs(steer_angle - self._steer_anchor) > STEER_SETTLE_BAND:
            self._steer_anchor, self._steer_moved = steer_angle, now
        if plan is not self._plan:
            if self._plan is not None:
                self._carried += max(self._last_progress - self._base, 0.0)
            self._plan, self._base = plan, progress
        self._last_progress = progress
        turning_at_rest = standstill and now - self._steer_moved < STEER_SETTLE_TIME - TIME_EPS
        braking = not standstill and abs(commanded_speed) < STOP_COMMAND_SPEED
        # creeping onto the goal: nothing left to progress along (at rest there, the goal
        # check must have decided within the time)
        at_end = not standstill and route_length - progress < self.distance
        gained = self._carried + max(progress - self._base, 0.0)
        at_stop = standstill and stop_distance < self.distance  # False for NaN
        waiting = gear_change or turning_at_rest or braking or at_end or at_stop
        if self._since is None or gained >= self.distance or waiting:
            self._since, self._base, self._carried = now, progress, 0.0  # a new window
            return self._ok
        waited = now - self._since
        if waited >= self.time_limit - TIME_EPS:
            return Check(
                self.name,
                Status.STALE,
                waited,
                self.time_limit,
                Reaction.STOP,
                f"no progress: {gained:.2f} m along the plan in {waited:.1f} s "
                f"(needs {self.distance:g} m in {self.time_limit:g} s; at {progress:.1f} of "
                f"{route_length:.1f} m)",
                gained,
            )
        return Check(self.name, Status.OK, waited, self.time_limit, Reaction.NONE, "", gained)
