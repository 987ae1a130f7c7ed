"""Gateway section of the configuration (``gateway:``): loop rate, watchdogs, safety gate.

Every threshold of the watchdog and safety-gate tables (docs/watchdogs.md) lives here with its
default. Angles may be written in degrees in YAML with the ``_deg``/``_degps`` suffixes
(``max_heading_error_deg: 30``, ``rate_up_degps: [34, 29, 11]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from leafgate.config import positive


@dataclass(frozen=True)
class WatchdogConfig:
    """Freshness and plausibility thresholds (docs/watchdogs.md, the watchdog table)."""

    localization_stop_age: float = 0.100  # s, localization older than this → STOPPING
    localization_fault_age: float = 0.500  # s, localization older than this → FAULT
    localization_max_jump: float = 1.0  # m, position jump in one sample → FAULT
    # m, localization's displacement over localization_drift_window s may differ from dead
    # reckoning on the ECU's measured speed by this much; more → FAULT (a spoofed or second
    # localization source: a 2 cm-per-sample drift is caught at 0.2 m, before 0.3 m off path).
    localization_max_drift: float = 0.2
    localization_drift_window: float = 1.0  # s
    # Bounds on the uncertainty a localization reports with each pose (its covariance): a pose
    # whose position std (m, the larger of x and y) or heading std (rad; _deg in YAML) is
    # beyond them is invalid, as is a NaN or negative variance. A covariance of zeros is "not
    # given" and accepted. 0.5 m is Autoware's localization_error_monitor bound (an error
    # ellipse of 1.5 m at 3 sigma).
    localization_max_position_std: float = 0.5  # m
    localization_max_heading_std: float = math.radians(5.0)  # rad
    # s, a trajectory older than this cannot be engaged on; None: a plan never goes stale (for
    # planners that publish a parking maneuver once). While engaged, the accepted plan is followed.
    trajectory_max_age: float | None = 1.0
    steer_report_period: float = 0.010  # s, DBW_STEER_RPT
    long_report_period: float = 0.020  # s, DBW_LONG_RPT
    # s, DBW_SYSTEM_RPT; None: the vehicle profile has no ECU state report (nothing to watch)
    system_report_period: float | None = 0.100
    report_timeout_periods: float = 3.0  # report periods; an older report → FAULT
    max_report_errors: int = 5  # bad-frame counter (+1 bad, −1 good, floor 0) at which → FAULT
    max_overruns: int = 3  # consecutive late control ticks → FAULT
    # One tick that starts later than this many periods → FAULT (a single long stall counts as
    # one overrun only, so max_overruns alone would never see it). 5 periods = 100 ms at 50 Hz,
    # the ECU's command timeout: a longer stall has already left the ECU without commands.
    max_stall_periods: float = 5.0
    # s the CAN receive thread may lag behind frames already waiting in the socket: report ages
    # are judged up to where it has read (a starved thread must not fake a stale ECU), and a
    # thread further behind than this is a FAULT of its own.
    max_receive_lag: float = 0.2
    # Engaged and commanded to move, the car must gain no_progress_distance along the plan within
    # every no_progress_time (waiting for a gear change or the wheel, braking to a commanded
    # stop and the plan's last no_progress_distance excepted) → STOP
    no_progress_time: float = 3.0  # s
    no_progress_distance: float = 0.1  # m
    # Engaged, the car farther than this from the plan (where it projects onto it) → STOP: the
    # planner checked a corridor along its path, not where the car has gone (geometry tighter
    # than the car can turn). Above the engage envelope's max_distance.
    max_path_deviation: float = 2.0  # m

    def __post_init__(self) -> None:
        positive(
            self,
            "localization_stop_age",
            "localization_fault_age",
            "localization_max_jump",
            "localization_max_drift",
            "localization_drift_window",
            "localization_max_position_std",
            "localization_max_heading_std",
            "steer_report_period",
            "long_report_period",
            "report_timeout_periods",
            "max_report_errors",
            "max_overruns",
            "max_stall_periods",
            "max_receive_lag",
            "no_progress_time",
            "no_progress_distance",
            "max_path_deviation",
        )
        if self.trajectory_max_age is not None:
            positive(self, "trajectory_max_age")
        if self.system_report_period is not None:
            positive(self, "system_report_period")
        if self.localization_fault_age < self.localization_stop_age:
            raise ValueError("localization_fault_age must not be below localization_stop_age")


@dataclass(frozen=True)
class EngageConfig:
    """Preconditions of an engage request and the hand-shake with the ECU."""

    max_distance: float = 1.0  # m, from the nearest point of the trajectory polyline
    max_heading_error: float = math.radians(30.0)  # rad, from the trajectory's heading there
    # s, time the ECU has to clear a latched override and then to report ENABLED after the
    # ENABLE 0→1 edge (system reports come every 100 ms, so a few of them)
    confirm_timeout: float = 0.5
    # Trajectories with reverse segments may be engaged on (False when the vehicle profile
    # cannot request a gear).
    allow_reverse: bool = True

    def __post_init__(self) -> None:
        positive(self, "max_distance", "max_heading_error", "confirm_timeout")


@dataclass(frozen=True)
class StopConfig:
    """Controlled stop (STOPPING) and the brake held while a fault stops the car."""

    decel: float = 1.5  # m/s², comfort deceleration of a controlled stop
    jerk: float = 2.0  # m/s³, comfort jerk while building up the stop deceleration
    fault_decel: float = 3.0  # m/s², deceleration after a fault (as the ECU's own timeout stop)
    standstill_time: float = 0.2  # s, |v| below the standstill speed this long = at rest

    def __post_init__(self) -> None:
        positive(self, "decel", "jerk", "fault_decel", "standstill_time")


@dataclass(frozen=True)
class SafetyConfig:
    """Limits of the safety gate (the last word on every command).

    The angle-rate tables are interpolated over ``rate_speeds`` like opendbc's
    ``apply_std_steer_angle_limits``: ``rate_up`` when |angle| grows (wind-up), ``rate_down``
    when it shrinks (unwind).
    """

    max_steer_angle: float | None = None  # rad, road-wheel; None: the vehicle's limit (±31°)
    rate_speeds: tuple[float, ...] = (0.0, 3.0, 10.0)  # m/s, breakpoints of the rate tables
    rate_up: tuple[float, ...] = (0.6, 0.5, 0.2)  # rad/s, wind-up rate limit at each breakpoint
    rate_down: tuple[float, ...] = (0.6, 0.6, 0.3)  # rad/s, unwind rate limit at each breakpoint
    max_lateral_accel: float = 3.0  # m/s², |tan δ / L| v² bound
    max_accel: float | None = None  # m/s²; None: the vehicle's limit (+3.0)
    min_accel: float | None = None  # m/s², negative; None: the vehicle's limit (−6.0)
    max_jerk: float = 5.0  # m/s³, |Δaccel| per second between two sent commands
    max_speed: float = 3.0  # m/s, maneuver speed limit
    standstill_speed: float = 0.05  # m/s, below this the car counts as standing still

    def __post_init__(self) -> None:
        positive(self, "max_lateral_accel", "max_jerk", "max_speed", "standstill_speed")
        if self.max_steer_angle is not None and not 0.0 < self.max_steer_angle < math.pi / 2:
            raise ValueError("max_steer_angle must lie in (0, 90°)")
        if self.max_accel is not None:
            positive(self, "max_accel")
        if self.min_accel is not None and not self.min_accel < 0.0:
            raise ValueError("min_accel must be negative")
        n = len(self.rate_speeds)
        if n == 0 or len(self.rate_up) != n or len(self.rate_down) != n:
            raise ValueError(
                "rate_speeds, rate_up and rate_down must be non-empty and of equal length, got "
                f"{n}, {len(self.rate_up)}, {len(self.rate_down)}"
            )
        if any(b <= a for a, b in zip(self.rate_speeds, self.rate_speeds[1:], strict=False)):
            raise ValueError("rate_speeds must be strictly increasing")
        if any(s < 0.0 for s in self.rate_speeds):
            raise ValueError("rate_speeds must not be negative")
        if not all(math.isfinite(r) and r > 0.0 for r in (*self.rate_up, *self.rate_down)):
            raise ValueError("rate_up and rate_down must be positive numbers")


@dataclass(frozen=True)
class GatewayConfig:
    rate_hz: float = 50.0  # Hz, control loop rate (DBW_STEER_CMD period 20 ms)
    system_period: float = 0.100  # s, DBW_SYSTEM_CMD period
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    engage: EngageConfig = field(default_factory=EngageConfig)
    stop: StopConfig = field(default_factory=StopConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    # SCHED_FIFO priority of the control thread only (1–99; 0: normal scheduling). The daemon
    # sets it from inside, on the loop's own thread, so Zenoh, CAN receive and recorder threads
    # keep normal priority and cannot starve the loop while holding the GIL.
    rt_priority: int = 0

    def __post_init__(self) -> None:
        positive(self, "rate_hz", "system_period")
        if not 0 <= self.rt_priority <= 99:
            raise ValueError("rt_priority must lie in 0–99 (0: normal scheduling)")
        if self.stop.jerk > self.safety.max_jerk:
            raise ValueError("stop.jerk must not exceed safety.max_jerk (the gate would clamp it)")
        if self.watchdog.max_path_deviation <= self.engage.max_distance:
            raise ValueError(
                "watchdog.max_path_deviation must exceed engage.max_distance (a car engaged at "
                "the edge of the envelope would be stopped at once)"
            )

    @property
    def period(self) -> float:
        """Control tick period, s."""
        return 1.0 / self.rate_hz
