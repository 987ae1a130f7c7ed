"""The engagement state machine: STANDBY → ENGAGED → STOPPING · FAULT (docs/state-machine.md).

The transitions are a table (:data:`TRANSITIONS`) of (state, event) → state; an event that is not
in the table for a state does not change it. The preconditions of an engage request are a pure
function (:func:`engage_refusal`) over the watchdogs' verdicts, the ECU's reports and the
vehicle's deviation from the trajectory (:func:`path_deviation`), so every refusal can be tested
on its own. :class:`EngagementMachine` holds the state, the reason for it, the latched fault's
causes and the transitions of the current tick.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from leafgate.config.gateway import EngageConfig
from leafgate.gateway.watchdog import Status, WatchdogReport, ecu_fault
from leafgate.geometry import wrap_angle
from leafgate.messages import EcuState, GatewayState, Gear, OperatorRequest, Pose, Trajectory


class Event(enum.Enum):
    """What can move the engagement state."""

    ENGAGE = "engage"  # an accepted engage request
    DISENGAGE = "disengage"  # operator: hand back now (ENABLE=0)
    STOP = "stop"  # a watchdog or the controller asks for a controlled stop
    AT_REST = "at_rest"  # the controlled stop is complete / the trajectory's end is reached
    ABORT = "abort"  # an engage could not complete (override not cleared, ECU did not enable)
    OVERRIDE = "override"  # the driver took over
    FAULT = "fault"  # a watchdog latched a fault
    RESET = "reset"  # an accepted reset request


S = GatewayState
E = Event

#: Every allowed transition; anything not listed leaves the state unchanged.
TRANSITIONS: dict[tuple[GatewayState, Event], GatewayState] = {
    (S.STANDBY, E.ENGAGE): S.ENGAGED,
    (S.STANDBY, E.FAULT): S.FAULT,
    (S.ENGAGED, E.DISENGAGE): S.STANDBY,
    (S.ENGAGED, E.STOP): S.STOPPING,
    (S.ENGAGED, E.AT_REST): S.STANDBY,
    (S.ENGAGED, E.ABORT): S.STANDBY,
    (S.ENGAGED, E.OVERRIDE): S.STANDBY,
    (S.ENGAGED, E.FAULT): S.FAULT,
    (S.STOPPING, E.DISENGAGE): S.STANDBY,
    (S.STOPPING, E.AT_REST): S.STANDBY,
    (S.STOPPING, E.OVERRIDE): S.STANDBY,
    (S.STOPPING, E.FAULT): S.FAULT,
    (S.FAULT, E.RESET): S.STANDBY,
}


def next_state(state: GatewayState, event: Event) -> GatewayState | None:
    """The state after ``event`` in ``state``; None when the event does not apply there."""
    return TRANSITIONS.get((state, event))


@dataclass(frozen=True, slots=True)
class Transition:
    """One change of state, for diagnostics and the session record."""

    time: float  # s, gateway clock
    source: GatewayState
    target: GatewayState
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "time": self.time,
            "from": self.source.name,
            "to": self.target.name,
            "reason": self.reason,
        }


#: The state each operator request asks for: a reply is ``accepted`` only when the gateway is
#: in it, or entering it (ENGAGED while the override is cleared), after the tick that handled it.
REQUESTED_STATE: dict[OperatorRequest, GatewayState] = {
    OperatorRequest.ENGAGE: GatewayState.ENGAGED,
    OperatorRequest.DISENGAGE: GatewayState.STANDBY,
    OperatorRequest.RESET: GatewayState.STANDBY,
}


@dataclass(frozen=True, slots=True)
class EngageReply:
    """The answer to an operator request (``gateway/engage`` queryable).

    - ``accepted``: the request was carried out: the gateway is in the requested state or
      entering it, because of this request;
    - ``changed``: the request changed something (a state, or the ECU's faults cleared): what
      is accepted did; a refusal did not, except a disengage in FAULT that stopped the fault
      braking;
    - ``already``: the request found the gateway where it asks (disengage in STANDBY, engage
      while ENGAGED, reset with no fault): nothing to do, ``accepted: false`` with a reason
      that says so. The CLI exits 3 on it rather than 1, and ``engage --wait`` stops waiting.
    """

    accepted: bool
    state: GatewayState  # the state after the request was handled
    reason: str
    changed: bool = False
    already: bool = False

    @classmethod
    def done(cls, state: GatewayState, reason: str) -> EngageReply:
        """A request carried out: accepted, and it changed something."""
        return cls(True, state, reason, changed=True)

    @classmethod
    def unchanged(cls, state: GatewayState, reason: str) -> EngageReply:
        """A request that finds nothing to do."""
        return cls(False, state, reason, already=True)

    def after_tick(self, request: OperatorRequest, state: GatewayState, reason: str) -> EngageReply:
        """The reply as the tick ended: an accepted request whose state did not hold (an
        engage at the trajectory's end, which the same tick ends) is not accepted."""
        if self.accepted and state != REQUESTED_STATE[request]:
            # the engagement started and ended within the tick: it changed the state twice
            text = f"not {REQUESTED_STATE[request].name}: {reason}"
            return EngageReply(False, state, text, changed=True)
        return EngageReply(self.accepted, state, self.reason, self.changed, self.already)

    def to_dict(self) -> dict[str, Any]:
        """The JSON reply ``{accepted, state, reason, changed, already}``."""
        return _reply(self.accepted, self.state.name, self.reason, self.changed, self.already)


def _reply(accepted: bool, state: str, reason: str, changed: bool, already: bool) -> dict[str, Any]:
    """The one spelling of a reply's five fields (:class:`EngageReply` and :func:`refusal`)."""
    return {
        "accepted": accepted,
        "state": state,
        "reason": reason,
        "changed": changed,
        "already": already,
    }


#: the state a refusal names before the gateway's first tick published one
STATE_UNKNOWN = "UNKNOWN"


def refusal(state: str, reason: str) -> dict[str, Any]:
    """A refusal in the reply format of :meth:`EngageReply.to_dict`, made where no
    :class:`GatewayState` is at hand (:data:`STATE_UNKNOWN` before the gateway's first tick)."""
    return _reply(False, state, reason, changed=False, already=False)


def path_deviation(
    pose: Pose, trajectory: Trajectory, within: float | None = None
) -> tuple[float, float]:
    """Distance to the nearest point of the trajectory polyline and the heading error there.

    The heading of the path at the nearest point is interpolated between the segment's two
    waypoints (the shorter way round). With ``within``, a route that passes the vehicle more
    than once (it crosses itself, closes on its start, retraces a leg after a cusp) is judged
    by the pass that fits best: among the segments closer than ``within``, the one whose
    heading is nearest the vehicle's; the nearest point when none is that close.

    :returns: (distance in m, absolute heading error in rad)
    """
    x, y = trajectory.x, trajectory.y
    if len(trajectory) == 1:
        d = math.hypot(pose.x - float(x[0]), pose.y - float(y[0]))
        return d, abs(wrap_angle(pose.heading - float(trajectory.heading[0])))
    dx, dy = np.diff(x), np.diff(y)
    length2 = dx * dx + dy * dy
    px, py = pose.x - x[:-1], pose.y - y[:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(length2 > 0.0, (px * dx + py * dy) / length2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    dist = np.hypot(px - t * dx, py - t * dy)
    h0, h1 = trajectory.heading[:-1], trajectory.heading[1:]
    dh = (h1 - h0 + math.pi) % (2.0 * math.pi) - math.pi  # the shorter way round
    err = np.abs((pose.heading - (h0 + t * dh) + math.pi) % (2.0 * math.pi) - math.pi)
    close = dist <= within if within is not None else np.zeros(dist.shape, dtype=bool)
    i = int(np.argmin(np.where(close, err, np.inf))) if close.any() else int(np.argmin(dist))
    return float(dist[i]), float(err[i])


def engage_refusal(
    state: GatewayState,
    fault_reason: str,
    watchdogs: WatchdogReport,
    config: EngageConfig,
) -> str | None:
    """Why an engage request must be refused now, or None when it may be accepted.

    Checked in order: state, latched fault, inputs (localization, trajectory, each ECU report:
    present, valid, fresh), report error counter, the ECU's state and flags, and the vehicle's
    distance and heading to the trajectory.
    """
    if state == GatewayState.FAULT:
        return f"fault latched ({fault_reason}); reset first"
    if state == GatewayState.STOPPING:
        return "stopping; engage again in STANDBY"
    if state != GatewayState.STANDBY:
        return f"not in STANDBY (state {state.name})"
    for name in ("localization", "trajectory", "steer_report", "long_report", "system_report"):
        check = watchdogs.get(name)
        if check.status is not Status.OK:
            return f"{name} not fresh and valid: {check.detail or check.status.value}"
    errors = watchdogs.get("report_errors")
    if not errors.ok:
        return errors.detail
    # Engage needs fresh samples, and the watchdogs keep the last valid one of each.
    assert watchdogs.pose is not None and watchdogs.trajectory is not None
    assert watchdogs.steer is not None and watchdogs.long is not None
    steer, long = watchdogs.steer.value, watchdogs.long.value
    # A vehicle without an ECU state report (a profile without one) has no system sample.
    system = None if watchdogs.system is None else watchdogs.system.value
    if long.gear == Gear.NONE:
        return "gear unknown: no gear received from the car yet"
    fault = ecu_fault(steer, long, system)
    if fault is not None:
        return f"{fault}; reset first"
    if system is not None and system.state not in (EcuState.READY, EcuState.OVERRIDE):
        return f"ECU not ready (state {system.state.name})"
    if not config.allow_reverse and bool((watchdogs.trajectory.value.speed < 0.0).any()):
        return "the trajectory has reverse segments and this vehicle cannot request a gear"
    distance, heading_error = path_deviation(
        watchdogs.pose.value, watchdogs.trajectory.value, within=config.max_distance
    )
    if distance > config.max_distance:
        return f"vehicle {distance:.2f} m from the trajectory (limit {config.max_distance:g} m)"
    if heading_error > config.max_heading_error:
        return (
            f"heading {math.degrees(heading_error):.1f}° off the trajectory "
            f"(limit {math.degrees(config.max_heading_error):g}°)"
        )
    return None


class EngagementMachine:
    """Holds the engagement state, why it is so, and what a latched fault waits for.

    :param start: the initial state (STANDBY)
    """

    def __init__(self, start: GatewayState = GatewayState.STANDBY) -> None:
        self.state = start
        self.reason = "start"
        self.fault_reason = ""
        #: names of the causes of the latched fault (watchdog names or "ecu", "bus")
        self.fault_causes: frozenset[str] = frozenset()
        self.transitions: list[Transition] = []  # of the current tick

    def begin_tick(self) -> None:
        """Forget the previous tick's transitions."""
        self.transitions = []

    def fire(
        self, event: Event, now: float, reason: str, causes: frozenset[str] = frozenset()
    ) -> bool:
        """Apply ``event``; True when the state changed.

        A FAULT in FAULT adds its causes to the latched ones (the fault stays until all are gone).
        """
        if event is Event.FAULT and self.state == GatewayState.FAULT:
            self.fault_causes |= causes
            return False
        target = next_state(self.state, event)
        if target is None or target == self.state:
            return False
        self.transitions.append(Transition(now, self.state, target, reason))
        self.state = target
        self.reason = reason
        if target == GatewayState.FAULT:
            self.fault_reason = reason
            self.fault_causes = causes
        elif event is Event.RESET:
            self.fault_reason = ""
            self.fault_causes = frozenset()
        return True
