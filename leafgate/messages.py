"""Messages passed between the parts of leafgate.

Frozen dataclasses in SI units (m, s, rad, m/s, m/s²). Angles are road-wheel angles unless a
name says otherwise; speeds are signed (negative when reversing). Nothing here knows about CAN
bit layouts or Zenoh payloads: the codecs translate at the edge.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class Gear(enum.IntEnum):
    """Gear as on DBW_LONG_CMD.GEAR_REQ / DBW_LONG_RPT.GEAR."""

    NONE = 0
    P = 1
    R = 2
    N = 3
    D = 4


class LongMode(enum.IntEnum):
    """Longitudinal command mode: the paper's two variants (§II.B)."""

    ACCELERATION = 0
    SPEED = 1


class GatewayState(enum.IntEnum):
    """Engagement state of the gateway (docs/state-machine.md)."""

    STANDBY = 0
    ENGAGED = 1
    STOPPING = 2
    FAULT = 3


class EcuState(enum.IntEnum):
    """State of the drive-by-wire ECU as reported on DBW_SYSTEM_RPT."""

    NOT_READY = 0
    READY = 1
    ENGAGED = 2
    OVERRIDE = 3
    FAULT = 4


class OperatorRequest(enum.Enum):
    """What an operator asks of the gateway through `gateway/engage`."""

    ENGAGE = "engage"
    DISENGAGE = "disengage"
    RESET = "reset"


# Requests that bring the car to rest: they overtake every other pending request.
STOP_REQUESTS: frozenset[OperatorRequest] = frozenset({OperatorRequest.DISENGAGE})


# --- inputs -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Pose:
    """Localization of the rear-axle centre in the global frame."""

    x: float  # m
    y: float  # m
    heading: float  # rad, counter-clockwise from +x
    speed: float  # m/s, signed: negative when reversing
    yaw_rate: float = 0.0  # rad/s
    stamp: float = math.nan  # s, the sender's time of the measurement (not the receive time)
    # Variances the localization reports for its estimate: the x, y and yaw diagonal of the
    # 6×6 row-major pose covariance (ROS geometry_msgs/PoseWithCovariance: indices 0, 7, 35).
    # 0 means "not given" (publishers that leave the covariance zero, as leafgate's own do).
    var_x: float = 0.0  # m²
    var_y: float = 0.0  # m²
    var_heading: float = 0.0  # rad²


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A planned trajectory: waypoints of the rear-axle centre (a planner sends them 0.5–1.0 m
    apart; the controller follows any spacing).

    Arrays are float64 of equal length and made read-only. Validation of content (finite
    values, enough points once overlapping ones are dropped) lives in
    :func:`leafgate.control.reference.validate`.
    """

    x: FloatArray  # m
    y: FloatArray  # m
    heading: FloatArray  # rad
    speed: FloatArray  # m/s, signed: negative for reverse segments
    stamp: float = math.nan  # s, the planner's time of the trajectory

    def __post_init__(self) -> None:
        n = None
        for name in ("x", "y", "heading", "speed"):
            arr = np.array(getattr(self, name), dtype=np.float64)  # a private, read-only copy
            if arr.ndim != 1:
                raise ValueError(
                    f"Trajectory.{name} must be one-dimensional, got shape {arr.shape}"
                )
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(f"Trajectory.{name} has {arr.shape[0]} points, x has {n}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.x.shape[0])


# --- reports from the drive-by-wire ECU (DBW CAN) ----------------------------------------------


@dataclass(frozen=True, slots=True)
class SteerReport:
    """DBW_STEER_RPT."""

    angle: float  # rad, measured road-wheel angle
    rate: float  # rad/s
    driver_torque: float  # N·m
    enabled: bool
    override: bool
    fault: bool
    cmd_timeout: bool


@dataclass(frozen=True, slots=True)
class LongReport:
    """DBW_LONG_RPT."""

    speed: float  # m/s, signed
    accel: float  # m/s²
    gear: Gear
    brake_pedal_pct: float  # % of travel (edge unit kept: it is what the pedal sensor reports)
    accel_pedal_pct: float  # % of travel
    enabled: bool
    override: bool
    fault: bool
    cmd_timeout: bool


@dataclass(frozen=True, slots=True)
class SystemReport:
    """DBW_SYSTEM_RPT."""

    state: EcuState
    fault_cmd_timeout: bool
    fault_bad_crc: bool
    fault_bad_counter: bool
    fault_actuator: bool
    rx_error_count: int


# --- Leaf CAR-CAN feedback (read-only) ---------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SteeringWheelAngle:
    """0x002: steering-wheel angle (not road-wheel), left positive."""

    angle: float  # rad, at the steering wheel


@dataclass(frozen=True, slots=True)
class WheelSpeeds:
    """0x284 (front) / 0x285 (rear): unsigned wheel speeds."""

    left: float  # m/s
    right: float  # m/s
    axle: str  # "front" or "rear"


@dataclass(frozen=True, slots=True)
class GearPosition:
    """0x421: gear lever position."""

    gear: Gear


@dataclass(frozen=True, slots=True)
class MotorSpeed:
    """0x176: vehicle speed derived from the traction motor."""

    speed: float  # m/s, unsigned


# --- commands to the drive-by-wire ECU -------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SteerCommand:
    """DBW_STEER_CMD."""

    angle: float  # rad, road-wheel angle target
    rate_limit: float = 0.0  # rad/s, 0 = ECU default
    enable: bool = False
    clear_override: bool = False


@dataclass(frozen=True, slots=True)
class LongCommand:
    """DBW_LONG_CMD."""

    mode: LongMode = LongMode.ACCELERATION
    accel: float = 0.0  # m/s²
    speed: float = 0.0  # m/s, magnitude target (direction comes from the gear)
    gear: Gear = Gear.NONE  # NONE: no change requested
    enable: bool = False
    clear_override: bool = False


@dataclass(frozen=True, slots=True)
class SystemCommand:
    """DBW_SYSTEM_CMD."""

    state: GatewayState
    clear_faults: bool = False


# --- controller interface -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ControlOutput:
    """What a lateral/longitudinal controller asks for, before the safety gate.

    ``steer_angle`` is derived from the MPC's tan(δ) input; ``accel`` is the acceleration
    command (acceleration mode) and ``speed`` the target speed for the vehicle's own speed
    controller (velocity mode). Both are always filled so either mode can be sent.
    """

    steer_angle: float  # rad
    accel: float  # m/s²
    speed: float  # m/s, signed target speed
    gear: Gear = Gear.D  # the gear the controller needs for the current segment
    converged: bool = True
    iterations: int = 0
    solve_time: float = 0.0  # s, wall time spent in the controller (diagnostic only)
    clips: int = 0  # first-move clips applied in this step
    cost: float = math.nan
    finished: bool = False  # the end of the trajectory is reached and the vehicle is at rest
    nearest_index: int = 0
    predicted_xy: FloatArray | None = None  # (Np, 2) predicted positions, m
    status: str = "ok"
    progress: float = 0.0  # m, arc length along the plan from its first point, over all
    # segments, monotone (never decreases while the same plan is followed)
    route_length: float = 0.0  # m, total arc length of the plan
    deviation: float = math.nan  # m, the car's distance from the plan where it projects onto
    # it (NaN: not known)
    stop_distance: float = math.nan  # m along the plan from the car to where the plan comes to
    # rest before its segment's end (a stop point; < 0: past it); NaN: no stop point ahead


T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Stamped(Generic[T]):
    """An input with the time it was received (gateway clock, s) and its validity."""

    value: T
    received: float  # s
    valid: bool = True
    # The publishers heard on the input's key within the recent window up to this sample,
    # this one's included (transport identities, "" for a sample that carries none); () when
    # the input's source does not tell (the CAN reports, the simulator).
    sources: tuple[str, ...] = ()


@dataclass(frozen=True)
class Commands:
    """The command frames' values for one control tick. ``system`` is None when not due."""

    steer: SteerCommand
    long: LongCommand
    system: SystemCommand | None = None
    extra: dict[str, float] = field(default_factory=dict)
