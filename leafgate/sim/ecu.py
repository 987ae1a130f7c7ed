"""The simulated drive-by-wire ECU: the vehicle side of the leafgate CAN protocol.

:class:`SimulatedEcu` is the pure core. It is stepped on a simulated clock (``now`` in s): it
receives decoded command frames, applies the ECU semantics of docs/can-protocol.md,
actuates a plant from :mod:`leafgate.sim.plant`, and produces the report frames due at ``now``
through its own :class:`~leafgate.can.codec.CanCodec`. It reads no clock and opens no socket,
so the same object runs in the deterministic closed-loop simulation and, wrapped by
:func:`run_ecu_realtime`, as the ``leafgate sim-ecu`` process on a real-time bus.

Semantics (defaults from :class:`~leafgate.config.sim.EcuConfig`):

- Engage needs a 0→1 edge of ENABLE (on both DBW_STEER_CMD and DBW_LONG_CMD, taken together)
  while both commands are fresh and valid. ENABLE held at 1 from the first frame, or on the first
  frames after a timeout, does not engage. ENABLE back to 0 disengages (READY).
- A frame with a bad CRC, a counter that does not advance or a wrong length is dropped and
  counted by kind; the kinds seen are also latched as fault bits on DBW_SYSTEM_RPT until a
  DBW_SYSTEM_CMD with CLEAR_FAULTS. With authenticated frames (``leafgate-dbw-auth``), a bad
  MAC (latched as FAULT_BAD_CRC) or a stale or repeated freshness value (FAULT_BAD_COUNTER)
  is dropped and counted the same way.
- Counter race: more than ``race_drops`` command frames dropped for their alive counter, their
  freshness or their MAC within ``race_window`` → FAULT (disengage, brake to rest at ``timeout_decel``), latched until a
  CLEAR_FAULTS once no counter drop has been seen for a window. Two senders on the command IDs
  (a second gateway, a replayed stream) make exactly this pattern; whichever wins the race, it
  can stop the car but not drive it.
- No valid steer or long command for ``cmd_timeout`` → CMD_TIMEOUT, disengage, and brake at
  ``timeout_decel`` to a stop (kept until the next engage).
- Driver override while engaged — steering torque above ``override_torque`` for
  ``override_time``, or the brake pedal pressed — → OVERRIDE, latched (disengaged) until a
  command with CLEAR_OVERRIDE arrives once the driver has let go.
- Gear changes only at standstill (``|v| < standstill_speed``) with the brake held by the ECU;
  a request while moving is refused and counted.
- Engaged: the steering target and its rate limit (0 → ``default_steer_rate``) go to the plant;
  acceleration mode passes the gear-relative acceleration (within the vehicle's limits), speed
  mode runs the vehicle's :class:`~leafgate.sim.plant.SpeedController`.
- Not engaged, the car is in the driver's hands: the steering angle is held where it was and
  the driver brakes to rest at ``driver_decel``.

The frames are those of the vehicle profile of the ECU's codec (``vehicle.profile``): with
``sze-hlc`` the ECU is the research Leaf's low-level controller (steering and target speed in
one frame, no counter or checksum, no state report); with ``leaf-ze1-lkas`` it is the ZE1's
steering (EPS) only, and a simulated driver holds the planned speed while the lane-keeping is
active (:meth:`SimulatedEcu.set_driver_path`).

Report frames carry the plant's measured values (road-wheel angle and rate, signed speed,
acceleration, gear, driver torque, pedals, flags, received-error count), and the Leaf CAR-CAN
frames are emitted too so simulated and real logs look alike.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import can

from leafgate.can import e2e
from leafgate.can.codec import CanCodec, Decoded
from leafgate.config import VehicleConfig
from leafgate.config.sim import EcuConfig
from leafgate.errors import CanCodecError, ConfigError, InjectionError, LeafgateError
from leafgate.geometry import clip_abs as _clip
from leafgate.messages import (
    EcuState,
    Gear,
    GearPosition,
    LongCommand,
    LongMode,
    LongReport,
    MotorSpeed,
    Pose,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    Trajectory,
    WheelSpeeds,
)
from leafgate.sim.plant import KinematicPlant, SpeedController, gear_direction, make_plant

if TYPE_CHECKING:
    from leafgate.settings import LeafgateConfig

__all__ = [
    "INJECTION_KINDS",
    "EcuCounters",
    "Injection",
    "InjectionError",
    "RealtimeStats",
    "SimulatedEcu",
    "run_ecu_realtime",
]


# Injectable driver actions and faults: kind → its parameters with their defaults.
INJECTION_KINDS: Mapping[str, Mapping[str, float]] = {
    "override-torque": {"torque": 3.0},  # N·m on the steering wheel
    "brake-pedal": {"pedal_pct": 30.0},  # % of brake pedal travel
    "report-dropout": {},  # no report frames at all
    "corrupt-crc": {},  # DBW reports sent with a wrong CRC
    "stuck-counter": {},  # DBW reports repeat the previous alive counter
    "actuator-fault": {},  # the steering/brake actuator reports a fault → FAULT
}

# The simulated sensors saturate inside the DBC signal ranges, as real ones do: an instant
# steering step of the kinematic plant has an unbounded rate.
_SENSOR_STEER_RATE = 5.0  # rad/s
_SENSOR_ACCEL = 15.0  # m/s²
_SENSOR_SPEED = 40.0  # m/s
_SENSOR_TORQUE = 40.0  # N·m
_RX_ERROR_COUNT_MAX = 0xFFFF  # the DBC field is 16 bits
_EPS = 1e-9  # s, tolerance of "due at now" against float sums
# Command drops that count toward a race (a second sender): a counter that did not advance,
# and an authenticated frame replayed (stale freshness) or forged (bad MAC).
_RACE_ERRORS = frozenset({"bad_counter", "stale_freshness", "bad_mac"})


@dataclass(frozen=True)
class Injection:
    """One injected driver action or fault, active for ``start <= now < end``."""

    kind: str
    start: float  # s
    end: float  # s, math.inf when it lasts
    params: Mapping[str, float] = field(default_factory=dict)

    def active(self, now: float) -> bool:
        """Whether the injection acts at ``now``."""
        return self.start <= now < self.end


@dataclass
class EcuCounters:
    """Event counters of the ECU (diagnostics and tests)."""

    bad_crc: int = 0  # command frames dropped for their CRC
    bad_counter: int = 0  # … for an alive counter that did not advance by one
    wrong_length: int = 0  # … for their length
    other_invalid: int = 0  # … for any other decode error
    timeouts: int = 0  # CMD_TIMEOUT episodes
    overrides: int = 0  # OVERRIDE latches
    engagements: int = 0
    gear_changes: int = 0
    gear_refused: int = 0  # gear requests refused while moving (once per request)
    encode_errors: int = 0  # report frames that could not be encoded (a bug if non-zero)
    counter_races: int = 0  # race faults (a second sender: counter, freshness or MAC drops)
    malformed: int = 0  # datagrams the bus could not parse as a CAN frame (real-time loop)
    bad_mac: int = 0  # authenticated command frames dropped for their MAC (forged)
    stale_freshness: int = 0  # … for an old or repeated freshness value (replayed)

    @property
    def rx_errors(self) -> int:
        """All dropped command frames."""
        return (
            self.bad_crc
            + self.bad_counter
            + self.wrong_length
            + self.other_invalid
            + self.bad_mac
            + self.stale_freshness
        )


class SimulatedEcu:
    """The drive-by-wire ECU with its vehicle, stepped on a simulated clock.

    Typical use, one tick of ``dt`` seconds::

        for msg in frames_received: ecu.receive_frame(now, msg)
        bus_frames = ecu.reports(now)
        ecu.step(now, dt)

    :param config: the ECU's settings
    :param plant: the plant to actuate (it is owned and stepped by the ECU)
    :param vehicle: the vehicle's limits (steering angle, acceleration)
    :param codec: the ECU's own codec (alive counters are per codec); when None, a new one for
        ``vehicle.profile``
    """

    def __init__(
        self,
        config: EcuConfig,
        plant: KinematicPlant,
        vehicle: VehicleConfig,
        codec: CanCodec | None = None,
    ) -> None:
        self.config = config
        self.vehicle = vehicle
        self.plant = plant
        self.codec = codec if codec is not None else CanCodec(profile=vehicle.profile)
        if self.codec.authenticated and not self.codec.verifies:
            raise ConfigError(
                f"profile {self.codec.profile.name} authenticates its command frames: the "
                "simulated ECU needs the key (can.auth_key_file) to verify them"
            )
        self.counters = EcuCounters()
        profile = self.codec.profile
        # The gateway only decodes the reports (a DBC may have more signals in them than the
        # profile maps); the ECU sends them: one it can never encode is a start-up error, not a
        # report that silently never comes (the gateway would then say it is "missing").
        never = self.codec.unsendable_reports()
        if never:
            raise CanCodecError(
                f"{profile.where}: the simulated ECU cannot send report frame "
                f"{'; '.join(never)} (give each such signal a value in the frame's signals, "
                "e.g. NAME: {value: 0})"
            )
        #: why the last report frame that could not be encoded was left out (None: none was)
        self.last_encode_error: str | None = None
        self._encode_warned: set[str] = set()  # frames whose encode error was logged
        self._command_ids = self.codec.receive_ids("commands")
        # frames whose counter and CRC the E2E injections break (leafgate's own protection)
        self._report_ids = frozenset(
            self.codec.frame_id(f.name) for f in profile.frames_of("report") if f.e2e == "leafgate"
        )
        # Lateral-only vehicles take no longitudinal command: a simulated driver drives.
        self._needs_long = profile.capabilities.longitudinal
        self._driver_path: Trajectory | None = None
        self._driver_index = 0
        self._speed_ctl = SpeedController(
            kp=config.speed_kp,
            ki=config.speed_ki,
            min_accel=-min(config.speed_max_decel, -vehicle.min_accel),
            max_accel=min(config.speed_max_accel, vehicle.max_accel),
        )
        # latest valid commands and when they arrived (s)
        self._steer: SteerCommand | None = None
        self._long: LongCommand | None = None
        self._steer_rx = -math.inf
        self._long_rx = -math.inf
        self._first_rx: float | None = None  # s, first valid command since start
        self._clear_override_req = False
        self._clear_faults_req = False
        # state
        self._engaged = False
        self._override = False
        self._fault = False
        self._race = False  # counter race: latched FAULT until CLEAR_FAULTS after a quiet window
        self._counter_drops: deque[float] = deque()  # s, times of counter drops in the window
        self._cmd_timeout = False
        self._timeout_stop = False  # braking at timeout_decel until the next engage
        self._prev_enable: bool | None = None  # None: no fresh commands, no edge possible
        self._torque_since: float | None = None  # s, when the torque went above the threshold
        self._held_angle = plant.steer_angle  # rad, what the "driver" holds when not engaged
        self._mode: LongMode | None = None
        self._last_refused_gear: Gear | None = None
        self._fault_bits = {"cmd_timeout": False, "bad_crc": False, "bad_counter": False}
        # injections and report schedule
        self._injections: list[Injection] = []
        self._report_base: float | None = None  # s, time of the first reports() call
        self.report_periods = {  # s, per report frame of the profile
            f.name: f.period for f in profile.frames_of("report")
        }
        self._report_index = dict.fromkeys(self.report_periods, 0)  # next due: base + index·period
        # frames the car also sends soon after their payload changes (0x421 on a gear change)
        self._event_frames = tuple(f.name for f in profile.frames_of("report") if f.on_change)
        self._last_payload: dict[str, bytes] = {}  # of each event frame, as last sent
        self._last_counter: dict[int, int] = {}  # alive counter last sent, per report ID

    # -- inputs ------------------------------------------------------------------------------

    def receive(self, now: float, decoded: Decoded) -> None:
        """Take one decoded frame received at ``now`` (s).

        Command frames that failed decoding (bad CRC, stale counter, wrong length) are dropped
        and counted by kind; frames that are not commands are ignored.
        """
        if decoded.frame_id not in self._command_ids:
            return
        if not decoded.valid:
            self._count_invalid(decoded.error)
            if decoded.error in _RACE_ERRORS:
                self._counter_drop(now)
            return
        for value in decoded.values:  # a frame may carry steering and speed together
            if isinstance(value, SteerCommand):
                self._steer, self._steer_rx = value, now
                self._clear_override_req |= value.clear_override
            elif isinstance(value, LongCommand):
                self._long, self._long_rx = value, now
                self._clear_override_req |= value.clear_override
            elif isinstance(value, SystemCommand):
                self._clear_faults_req |= value.clear_faults
        if not decoded.values:  # a frame that only folds into a later one
            return
        if self._first_rx is None:
            self._first_rx = now

    def receive_frame(self, now: float, msg: can.Message) -> Decoded:
        """Decode ``msg`` with the ECU's codec and :meth:`receive` it; returns the decode."""
        decoded = self.codec.decode(msg)
        self.receive(now, decoded)
        return decoded

    def _counter_drop(self, now: float) -> None:
        """Count a command frame dropped for its counter, freshness or MAC: a second sender.

        More than ``race_drops`` in ``race_window`` is a race: FAULT, brake to rest. One rule
        for a counter race (CRC + counter) and for replayed or forged authenticated frames.
        """
        drops = self._counter_drops
        drops.append(now)
        while drops and now - drops[0] > self.config.race_window:
            drops.popleft()
        if len(drops) > self.config.race_drops and not self._race:
            self._race = True
            self.counters.counter_races += 1
            self._timeout_stop = True  # brake to rest, as after a command timeout
            self._disengage()

    def _count_invalid(self, error: str | None) -> None:
        if error == "bad_crc":
            self.counters.bad_crc += 1
            self._fault_bits["bad_crc"] = True
        elif error == "bad_counter":
            self.counters.bad_counter += 1
            self._fault_bits["bad_counter"] = True
        elif error == "bad_mac":  # latched as the integrity bit, as a bad CRC
            self.counters.bad_mac += 1
            self._fault_bits["bad_crc"] = True
        elif error == "stale_freshness":  # latched as the sequence bit, as a bad counter
            self.counters.stale_freshness += 1
            self._fault_bits["bad_counter"] = True
        elif error == "wrong_length":
            self.counters.wrong_length += 1
        else:
            self.counters.other_invalid += 1

    def inject(self, kind: str, at: float, duration: float | None = None, **params: float) -> None:
        """Schedule a driver action or a fault (see :data:`INJECTION_KINDS`).

        :param kind: ``override-torque`` (``torque`` N·m), ``brake-pedal`` (``pedal_pct`` %),
            ``report-dropout``, ``corrupt-crc``, ``stuck-counter`` or ``actuator-fault``
        :param at: start time, s (simulated clock)
        :param duration: how long it lasts, s; None for ever
        :raises InjectionError: unknown kind or parameter, or a bad time or value
        """
        defaults = INJECTION_KINDS.get(kind)
        if defaults is None:
            raise InjectionError(
                f"unknown injection {kind!r} (known: {', '.join(sorted(INJECTION_KINDS))})"
            )
        unknown = sorted(set(params) - set(defaults))
        if unknown:
            known = ", ".join(sorted(defaults)) or "none"
            raise InjectionError(f"injection {kind!r}: unknown parameter {unknown[0]!r} ({known})")
        if not math.isfinite(at) or (duration is not None and not duration > 0.0):
            raise InjectionError(f"injection {kind!r}: bad time at={at!r} duration={duration!r}")
        merged = {**defaults, **{k: float(v) for k, v in params.items()}}
        if not all(math.isfinite(v) for v in merged.values()):
            raise InjectionError(f"injection {kind!r}: parameters must be finite: {merged}")
        end = math.inf if duration is None else at + duration
        self._injections.append(Injection(kind, at, end, merged))

    def _active(self, now: float, kind: str) -> Injection | None:
        """The last-scheduled injection of ``kind`` active at ``now``."""
        for inj in reversed(self._injections):
            if inj.kind == kind and inj.active(now):
                return inj
        return None

    def set_driver_path(self, path: Trajectory | None) -> None:
        """The plan the simulated driver follows the speed of (lateral-only vehicles).

        While the steering is engaged the driver holds the planned speed at the car's nearest
        point of ``path`` (looking 0.5 s ahead, as a driver anticipates a stop); otherwise,
        and without a path, the driver brakes to rest.
        """
        self._driver_path = path
        self._driver_index = 0

    def _driver_speed(self) -> float:
        """The speed the simulated driver aims for now, m/s (magnitude)."""
        path = self._driver_path
        if path is None or not self._engaged:
            return 0.0
        x, y = self.plant.x, self.plant.y
        lo = self._driver_index
        hi = min(lo + 50, len(path.x))  # a forward window: the driver does not jump back
        d2 = (path.x[lo:hi] - x) ** 2 + (path.y[lo:hi] - y) ** 2
        self._driver_index = lo + int(d2.argmin())
        step = float(math.hypot(path.x[1] - path.x[0], path.y[1] - path.y[0])) or 0.1
        ahead = int(abs(self.plant.speed) * 0.5 / step) + 1
        i = min(self._driver_index + ahead, len(path.x) - 1)
        return abs(float(path.speed[i]))

    def driver_torque(self, now: float) -> float:
        """Steering-wheel torque applied by the (simulated) driver at ``now``, N·m."""
        inj = self._active(now, "override-torque")
        return inj.params["torque"] if inj is not None else 0.0

    def brake_pedal(self, now: float) -> float:
        """Brake pedal travel at ``now``, %."""
        inj = self._active(now, "brake-pedal")
        return min(max(inj.params["pedal_pct"], 0.0), 100.0) if inj is not None else 0.0

    # -- state -------------------------------------------------------------------------------

    @property
    def state(self) -> EcuState:
        """The ECU state as on DBW_SYSTEM_RPT."""
        if self._fault or self._race:
            return EcuState.FAULT
        if self._override:
            return EcuState.OVERRIDE
        if self._engaged:
            return EcuState.ENGAGED
        if self._steer is not None and self._long_ok and not self._cmd_timeout:
            return EcuState.READY
        return EcuState.NOT_READY

    @property
    def _long_ok(self) -> bool:
        """A longitudinal command has arrived, or the vehicle takes none."""
        return self._long is not None or not self._needs_long

    @property
    def engaged(self) -> bool:
        """Whether the ECU drives the car from the commands."""
        return self._engaged

    @property
    def override(self) -> bool:
        """Whether a driver override is latched."""
        return self._override

    @property
    def rejected_frames(self) -> int:
        """Command frames dropped as invalid (bad CRC, counter, length), all kinds together."""
        return self.counters.rx_errors

    @property
    def cmd_timeout(self) -> bool:
        """Whether the commands are currently timed out."""
        return self._cmd_timeout

    # -- the step ----------------------------------------------------------------------------

    def step(self, now: float, dt: float) -> None:
        """Apply the ECU semantics at ``now`` and actuate the plant for ``dt`` seconds.

        In order: command freshness (timeout), driver override, latched faults, engagement,
        then the plant follows the commands (engaged) or the driver (not engaged).
        """
        speed = self.plant.speed
        fresh = self._check_freshness(now)
        self._check_override(now)
        self._check_faults(now)
        self._update_engagement(fresh)
        self._actuate(dt, speed)

    def _check_freshness(self, now: float) -> bool:
        """Whether the commands are fresh at ``now``; a command timeout disengages and brakes.

        A command kind never seen ages from the first command of any kind.
        """
        if self._first_rx is None:
            return False
        cfg = self.config
        steer_age = now - (self._steer_rx if self._steer is not None else self._first_rx)
        long_age = now - (self._long_rx if self._long is not None else self._first_rx)
        if not self._needs_long:
            long_age = 0.0
        timed_out = max(steer_age, long_age) > cfg.cmd_timeout
        fresh = not timed_out and self._steer is not None and self._long_ok
        if timed_out and not self._cmd_timeout:
            self.counters.timeouts += 1
            self._fault_bits["cmd_timeout"] = True
            self._timeout_stop = True
            self._disengage()
            # The sender may restart: accept its next counter instead of dropping one frame.
            for frame_id in self._command_ids:
                self.codec.reset_counters(frame_id)
        self._cmd_timeout = timed_out
        return fresh

    def _check_override(self, now: float) -> None:
        """Driver override: torque above the threshold long enough, or the brake pedal.

        Latches OVERRIDE while engaged; a CLEAR_OVERRIDE request clears it once the driver has
        let go.
        """
        cfg = self.config
        torque = self.driver_torque(now)
        if abs(torque) > cfg.override_torque:
            if self._torque_since is None:
                self._torque_since = now
        else:
            self._torque_since = None
        torque_override = (
            self._torque_since is not None and now - self._torque_since >= cfg.override_time - _EPS
        )
        pedal_pressed = self.brake_pedal(now) > cfg.override_brake_pedal
        if self._engaged and (torque_override or pedal_pressed):
            self._override = True
            self.counters.overrides += 1
            self._disengage()
        if self._clear_override_req and self._override:
            driver_let_go = self._torque_since is None and not pedal_pressed
            if driver_let_go:
                self._override = False
        self._clear_override_req = False

    def _check_faults(self, now: float) -> None:
        """Actuator fault and the rejection race: latched until CLEAR_FAULTS once gone."""
        actuator_fault = self._active(now, "actuator-fault") is not None
        if actuator_fault:
            self._fault = True
            self._disengage()
        if self._race:
            self._disengage()
        if self._clear_faults_req:
            self._fault = self._fault and actuator_fault
            drops = self._counter_drops
            if self._race and not (drops and now - drops[-1] <= self.config.race_window):
                self._race = False
            self._fault_bits = dict.fromkeys(self._fault_bits, False)
        self._clear_faults_req = False

    def _update_engagement(self, fresh: bool) -> None:
        """Engage on a 0→1 edge of ENABLE while the commands are fresh; ENABLE=0 disengages."""
        steer, long = self._steer, self._long
        long_enable = long.enable if long is not None else not self._needs_long
        enable = fresh and steer is not None and steer.enable and long_enable
        edge = self._prev_enable is False and enable
        self._prev_enable = enable if fresh else None
        if self._engaged and not enable:
            self._disengage()
        elif edge and not (self._override or self._fault or self._race or self._cmd_timeout):
            self._engaged = True
            self._timeout_stop = False
            self._mode = None
            self.counters.engagements += 1

    def _actuate(self, dt: float, speed: float) -> None:
        """Step the plant ``dt`` s: toward the commands when engaged, else the driver's hold."""
        cfg = self.config
        steer, long = self._steer, self._long
        if self._engaged and steer is not None and (long is not None or not self._needs_long):
            steer_target = min(
                max(steer.angle, -self.vehicle.max_steer_angle), self.vehicle.max_steer_angle
            )
            rate = steer.rate_limit if steer.rate_limit > 0.0 else cfg.default_steer_rate
            if long is not None and self._needs_long:
                accel = self._longitudinal(long, dt, speed)
            else:  # the simulated driver holds the planned speed
                along_gear = gear_direction(self.plant.gear) * speed  # m/s
                accel = self._speed_ctl.step(dt, self._driver_speed(), along_gear)
        else:
            steer_target, rate = self._held_angle, cfg.default_steer_rate
            accel = -(cfg.timeout_decel if self._timeout_stop else cfg.driver_decel)
        if dt > 0.0:  # a zero step would divide by zero in the plant's rate estimate
            self.plant.step(dt, steer_target, accel, None, rate)

    def _disengage(self) -> None:
        if self._engaged:
            self._engaged = False
            self._held_angle = self.plant.steer_angle

    def _longitudinal(self, long: LongCommand, dt: float, speed: float) -> float:
        """Gear-relative acceleration for the plant while engaged, m/s²."""
        cfg = self.config
        if long.gear != Gear.NONE and long.gear != self.plant.gear:
            if abs(speed) < cfg.standstill_speed:
                # Shift with the brake held; the plant takes the gear once fully at rest.
                if self.plant.set_gear(long.gear):
                    self.counters.gear_changes += 1
                    self._speed_ctl.reset()
                self._last_refused_gear = None
                return -cfg.driver_decel
            if self._last_refused_gear != long.gear:
                self.counters.gear_refused += 1
                self._last_refused_gear = long.gear
        else:
            self._last_refused_gear = None
        if long.mode != self._mode:
            self._speed_ctl.reset()
            self._mode = long.mode
        if long.mode == LongMode.SPEED:
            along_gear = gear_direction(self.plant.gear) * speed  # m/s
            return self._speed_ctl.step(dt, abs(long.speed), along_gear)
        return min(max(long.accel, self.vehicle.min_accel), self.vehicle.max_accel)

    # -- reports -----------------------------------------------------------------------------

    def report_values(self, now: float) -> dict[str, Any]:
        """The values of every report frame at ``now`` (measured plant values and flags)."""
        plant = self.plant
        state = self.state
        enabled = state == EcuState.ENGAGED
        fault = state == EcuState.FAULT
        speed = plant.speed
        abs_speed = min(abs(speed), _SENSOR_SPEED)
        front_speed = min(abs(speed) / max(math.cos(plant.steer_angle), 0.1), _SENSOR_SPEED)
        return {
            "steer": SteerReport(
                angle=plant.steer_angle,
                rate=_clip(plant.steer_rate, _SENSOR_STEER_RATE),
                driver_torque=_clip(self.driver_torque(now), _SENSOR_TORQUE),
                enabled=enabled,
                override=self._override,
                fault=fault,
                cmd_timeout=self._cmd_timeout,
            ),
            "long": LongReport(
                speed=_clip(speed, _SENSOR_SPEED),
                accel=_clip(plant.accel, _SENSOR_ACCEL),
                gear=plant.gear,
                brake_pedal_pct=self.brake_pedal(now),
                accel_pedal_pct=0.0,
                enabled=enabled,
                override=self._override,
                fault=fault,
                cmd_timeout=self._cmd_timeout,
            ),
            "system": SystemReport(
                state=state,
                fault_cmd_timeout=self._fault_bits["cmd_timeout"],
                fault_bad_crc=self._fault_bits["bad_crc"],
                fault_bad_counter=self._fault_bits["bad_counter"],
                fault_actuator=self._fault,
                rx_error_count=min(self.counters.rx_errors, _RX_ERROR_COUNT_MAX),
            ),
            "steering_wheel": SteeringWheelAngle(
                angle=plant.steer_angle * self.vehicle.steering_ratio
            ),
            # Rear-axle centre speed; the front axle centre moves faster by 1/cos δ in a turn.
            "wheels_front": WheelSpeeds(left=front_speed, right=front_speed, axle="front"),
            "wheels_rear": WheelSpeeds(left=abs_speed, right=abs_speed, axle="rear"),
            "gear": GearPosition(gear=plant.gear),
            "motor": MotorSpeed(speed=abs_speed),
        }

    def reports(self, now: float) -> list[can.Message]:
        """The report frames due at ``now``, encoded with the ECU's codec.

        Each frame is due every period from the first call; missed periods (a late caller) are
        skipped rather than sent in a burst. A frame the profile marks ``on_change`` (the
        Leaf's 0x421) is also sent, between its cyclic times, at the first call after its
        payload changed, as the car sends an event frame after a gear change. Active
        ``report-dropout``, ``corrupt-crc`` and ``stuck-counter`` injections act here.
        """
        if self._report_base is None:
            self._report_base = now
        base = self._report_base
        due = []
        for name, period in self.report_periods.items():
            index = self._report_index[name]
            if base + index * period > now + _EPS:
                continue
            due.append(name)
            # Next due time strictly after now: skip missed periods.
            self._report_index[name] = max(index + 1, math.floor((now - base) / period + _EPS) + 1)
        # A silent ECU: nothing encoded, so the alive counters resume in sequence afterwards.
        # An event frame is looked for only when another frame is due (every 10 ms on the
        # Leaf): cheap at the ECU's 1 kHz tick, and within the car's 5.8-55 ms.
        if not due or self._active(now, "report-dropout"):
            return []
        values = self.report_values(now)
        for name in self._event_frames:
            if name in due:
                continue
            try:  # event frames carry no counter (the profile checks): encoding is free
                payload = bytes(self.codec.encode_frame(name, values, timestamp=now).data)
            except LeafgateError:
                continue
            if payload != self._last_payload.get(name, payload):
                due.append(name)
        corrupt = self._active(now, "corrupt-crc") is not None
        stuck = self._active(now, "stuck-counter") is not None
        frames = []
        for name in due:
            try:
                msg = self.codec.encode_frame(name, values, timestamp=now)
            except LeafgateError as exc:  # out-of-range values: count, never raise in the loop
                self.counters.encode_errors += 1
                self.last_encode_error = str(exc)
                if name not in self._encode_warned:  # once per frame: the loop runs at 1 kHz
                    self._encode_warned.add(name)
                    log.warning("simulated ECU: report frame not sent: %s", exc)
                continue
            if msg.arbitration_id in self._report_ids:
                msg = self._e2e_faults(msg, corrupt, stuck)
            if name in self._event_frames:
                self._last_payload[name] = bytes(msg.data)
            frames.append(msg)
        return frames

    def _e2e_faults(self, msg: can.Message, corrupt: bool, stuck: bool) -> can.Message:
        """Apply the injected E2E faults to one DBW report frame."""
        frame_id = msg.arbitration_id
        data = bytes(msg.data)
        if stuck and frame_id in self._last_counter:
            data = e2e.apply(frame_id, data, self._last_counter[frame_id])
        self._last_counter[frame_id] = e2e.counter_of(data)
        if corrupt:
            broken = bytearray(data)
            broken[e2e.CRC_BYTE] ^= 0xFF  # any change of the CRC byte breaks the check
            data = bytes(broken)
        msg.data = bytearray(data)
        return msg


# --- the real-time process body ---------------------------------------------------------------


@dataclass(frozen=True)
class RealtimeStats:
    """What a real-time run did, for logs and benchmarks."""

    ticks: int
    duration: float  # s, wall time of the loop
    frames_received: int
    frames_sent: int
    send_errors: int
    overruns: int  # ticks that started more than one period late (skipped ahead)
    max_lateness: float  # s, worst wake-up after a tick's deadline
    mean_lateness: float  # s
    counters: EcuCounters


MAX_DRAIN = 2000  # frames read per tick at most, so a flood cannot hold a tick for ever
MALFORMED_LOGGED = 5  # malformed datagrams logged one by one, then only counted

log = logging.getLogger(__name__)


def _drain(bus: can.BusABC, counters: EcuCounters) -> list[can.Message]:
    """The frames waiting on ``bus`` (at most :data:`MAX_DRAIN`), without blocking.

    A datagram that is not a CAN frame (python-can raises ``CanOperationError`` for it on
    ``udp_multicast``) is counted in ``counters.malformed`` and skipped: it must not end the ECU.
    """
    frames: list[can.Message] = []
    for _ in range(MAX_DRAIN):
        try:
            msg = bus.recv(timeout=0.0)
        except can.CanError as exc:
            counters.malformed += 1
            if counters.malformed <= MALFORMED_LOGGED:
                log.warning(
                    "malformed frame on the bus dropped (%d so far): %s", counters.malformed, exc
                )
            continue
        if msg is None:
            break
        frames.append(msg)
    return frames


def run_ecu_realtime(
    config: LeafgateConfig,
    stop: threading.Event | None = None,
    *,
    start: Pose | None = None,
    duration: float | None = None,
    on_tick: Callable[[float, SimulatedEcu], None] | None = None,
) -> RealtimeStats:
    """Run the simulated ECU and its plant in real time on the configured CAN bus(es).

    Ticks at ``config.sim.ecu.tick_rate_hz`` on absolute :func:`time.perf_counter` deadlines
    (sleeping between ticks, no drift); each tick drains the received command frames without
    blocking, sends the reports due and steps the ECU and plant. The ECU's clock is the
    nominal tick time, so the plant advances exactly as the deadlines do; after an overrun the
    missed ticks are skipped and the plant is stepped over the gap at once.

    :param config: the deployment config (``can``, ``sim.plant``, ``sim.ecu``, ``vehicle``)
    :param stop: set it to end the loop; the buses are shut down on the way out
    :param start: the plant's initial pose (the origin at rest when None)
    :param duration: stop after this many seconds (run until ``stop`` when None)
    :param on_tick: called after each step with ``(now, ecu)``, e.g. to publish the pose
    :raises BusError: when a bus cannot be opened
    """
    from leafgate.can.bus import open_bus  # the runtime edge only: the core needs no bus

    stop = stop if stop is not None else threading.Event()
    ecu_cfg = config.sim.ecu
    plant = make_plant(config.sim.plant, config.vehicle, start or Pose(0.0, 0.0, 0.0, 0.0))
    codec = CanCodec.for_config(config)
    ecu = SimulatedEcu(ecu_cfg, plant, config.vehicle, codec)
    car_ids = codec.receive_ids("car")
    command_ids = codec.receive_ids("commands")
    # Every frame is read and the command IDs picked here: python-can's software filter makes
    # recv(timeout=0) return None at the first unrelated frame, so a busy bus would leave the
    # commands queued behind it (the ECU fell behind and timed out at 20,000 frames/s).
    dbw_bus = open_bus(config.can.dbw, None)
    car_bus = dbw_bus
    try:
        if config.can.car is not None:
            car_bus = open_bus(config.can.car, frozenset())
    except BaseException:
        dbw_bus.shutdown()
        raise

    period = 1.0 / ecu_cfg.tick_rate_hz  # s
    received = sent = send_errors = overruns = ticks = 0
    max_late = total_late = 0.0
    t0 = time.perf_counter()
    tick = 0
    last_now = 0.0
    try:
        while not stop.is_set():
            deadline = t0 + tick * period
            remaining = deadline - time.perf_counter()
            if remaining > 0.0:
                time.sleep(remaining)
            late = time.perf_counter() - deadline
            max_late = max(max_late, late)
            total_late += late
            now = tick * period  # s, nominal time since start
            if duration is not None and now >= duration:
                break
            for msg in _drain(dbw_bus, ecu.counters):
                if msg.arbitration_id in command_ids and not msg.is_extended_id:
                    received += 1
                    ecu.receive_frame(now, msg)
            for msg in ecu.reports(now):
                bus = car_bus if msg.arbitration_id in car_ids else dbw_bus
                try:
                    bus.send(msg)
                    sent += 1
                except can.CanError:
                    send_errors += 1
            # The previous step covered [last_now, last_now + period]; after skipped ticks this
            # one also covers the gap.
            ecu.step(now, now - last_now if ticks else period)
            last_now = now
            if on_tick is not None:
                on_tick(now, ecu)
            ticks += 1
            tick += 1
            behind = time.perf_counter() - (t0 + tick * period)
            if behind > period:  # more than one tick late: skip ahead, do not burst
                overruns += 1
                tick += int(behind / period)
    finally:
        if car_bus is not dbw_bus:
            car_bus.shutdown()
        dbw_bus.shutdown()
    return RealtimeStats(
        ticks=ticks,
        duration=time.perf_counter() - t0,
        frames_received=received,
        frames_sent=sent,
        send_errors=send_errors,
        overruns=overruns,
        max_lateness=max_late,
        mean_lateness=total_late / ticks if ticks else 0.0,
        counters=ecu.counters,
    )
