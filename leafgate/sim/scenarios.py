"""Built-in maneuvers: reference trajectories and start poses for the simulator.

Every scenario is a path of the rear-axle centre sampled at equal arc length (0.5 m, the paper's
waypoint spacing) with a heading and a signed speed per waypoint, and a start pose at rest on the
first waypoint.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from leafgate.config import VehicleConfig
from leafgate.config.control import ControllerConfig
from leafgate.control import plan_rules
from leafgate.control.reference import TIGHT_TURN_SPEED, split_segments, tight_turn_ceiling
from leafgate.messages import FloatArray, Pose, Trajectory

SPACING = 0.5  # m, waypoint spacing (paper: 0.5–1.0 m)
START_SPEED = 0.3  # m/s, reference speed at the first waypoint: a standing start needs a pull


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    trajectory: Trajectory
    start: Pose
    duration: float  # s, simulated time limit
    # False: geometry the car cannot follow (a hairpin tighter than its turning circle); it is
    # driven slowly as well as it can be, or stopped with a reason, never reported as followed
    feasible: bool = True


def time_budget(traj: Trajectory) -> float:
    """Simulated time limit for driving ``traj``: its planned travel time (at least 0.2 m/s on
    every interval), ``CUSP_PAUSE`` per cusp and 10 s to spare, s.

    Where the plan turns tighter than the default car can, the time is taken at the reference's
    slower speed there, and each such turn adds ``TIGHT_TURN_SPARE``: a car that cannot follow
    it leaves the plan, and its projection lingers on the slow stretch until it is back.
    """
    gaps = np.hypot(np.diff(traj.x), np.diff(traj.y))
    speed = traj.speed
    s = np.concatenate(([0.0], np.cumsum(gaps)))
    car = plan_rules(ControllerConfig(), VehicleConfig()).min_turn_radius
    ceiling = tight_turn_ceiling(s, np.unwrap(traj.heading), car)
    tight_turns = 0
    if ceiling is not None:
        speed = np.clip(speed, -ceiling, ceiling)
        on = ceiling <= TIGHT_TURN_SPEED  # the waypoints of the tight turns themselves
        tight_turns = int(np.count_nonzero(np.diff(on.astype(np.int8), prepend=0) == 1))
    mean = np.maximum(0.5 * np.abs(speed[1:] + speed[:-1]), 0.2)
    cusps = len(split_segments(traj)) - 1
    spare = CUSP_PAUSE * max(cusps, 0) + TIGHT_TURN_SPARE * tight_turns + 10.0
    return float(np.sum(gaps / mean)) + spare


def _resample_path(
    xs: FloatArray, ys: FloatArray, spacing: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Resample a dense polyline at equal arc length; return x, y, heading, arc length."""
    seg = np.hypot(np.diff(xs), np.diff(ys))
    s_dense = np.concatenate(([0.0], np.cumsum(seg)))
    s = np.arange(0.0, s_dense[-1] + 1e-9, spacing)
    if s_dense[-1] - s[-1] > 1e-6:
        s = np.append(s, s_dense[-1])  # keep the exact end point
        if s[-1] - s[-2] < 0.5 * spacing:
            s = np.delete(s, -2)
    x = np.interp(s, s_dense, xs)
    y = np.interp(s, s_dense, ys)
    # Heading from the dense path's tangent, so it is exact rather than a chord direction.
    tangent = np.arctan2(np.gradient(ys), np.gradient(xs))
    heading = np.interp(s, s_dense, np.unwrap(tangent))
    return x, y, heading, s


def _speed_profile(s: FloatArray, v_max: float, accel: float, decel: float) -> FloatArray:
    """Trapezoid over arc length: pull away from START_SPEED, cruise, stop exactly at the end."""
    total = s[-1]
    up = np.sqrt(START_SPEED**2 + 2.0 * accel * s)
    down = np.sqrt(np.maximum(0.0, 2.0 * decel * (total - s)))
    return np.minimum(np.minimum(up, down), v_max)


def _forward(
    name: str,
    description: str,
    path: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    length: float,
    v_max: float,
    spacing: float = SPACING,
) -> Scenario:
    u = np.linspace(0.0, length, int(length / 0.01) + 1)
    xs, ys = path(u)
    x, y, heading, s = _resample_path(xs, ys, spacing)
    speed = _speed_profile(s, v_max, accel=0.5, decel=0.5)
    traj = Trajectory(x=x, y=y, heading=heading, speed=speed)
    start = Pose(x=float(x[0]), y=float(y[0]), heading=float(heading[0]), speed=0.0)
    return Scenario(name, description, traj, start, duration=time_budget(traj))


def s_curve() -> Scenario:
    """The paper's maneuver: a 3.5 m lateral displacement over 25 m, 0 → 2 m/s → stop."""
    lead_in, curve, lead_out, offset = 3.0, 25.0, 4.0, 3.5  # m

    def path(u: FloatArray) -> tuple[FloatArray, FloatArray]:
        t = np.clip((u - lead_in) / curve, 0.0, 1.0)
        # Quintic smoothstep: continuous curvature at both ends of the S.
        return u, offset * (10 * t**3 - 15 * t**4 + 6 * t**5)

    return _forward(
        "s-curve",
        "lateral displacement of 3.5 m over 25 m at 2 m/s (the paper's maneuver)",
        path,
        lead_in + curve + lead_out,
        2.0,
    )


def straight() -> Scenario:
    """40 m straight ahead at up to 3 m/s."""
    return _forward(
        "straight", "40 m straight at 3 m/s", lambda u: (u, np.zeros_like(u)), 40.0, 3.0
    )


def slalom() -> Scenario:
    """Sinusoidal slalom ±1.5 m, 30 m wavelength, at 3 m/s."""
    lead, wave, amplitude, periods = 5.0, 30.0, 1.5, 2  # m, m, m, -

    def path(u: FloatArray) -> tuple[FloatArray, FloatArray]:
        span = wave * periods
        t = np.clip(u - lead, 0.0, span)
        # A smoothstep window over the first and last half wave: the sine then starts and ends
        # with zero slope and curvature, so there is no heading kink at the straights.
        ramp = np.clip(np.minimum(t, span - t) / (0.5 * wave), 0.0, 1.0)
        window = ramp * ramp * (3.0 - 2.0 * ramp)
        return u, amplitude * window * np.sin(2.0 * math.pi * t / wave)

    return _forward(
        "slalom", "slalom ±1.5 m, 30 m wavelength, at 3 m/s", path, 2 * lead + wave * periods, 3.0
    )


# --- parking manoeuvres (reverse, cusps) --------------------------------------------------------

LEAF_LENGTH = 4.45  # m, bumper to bumper
LEAF_WIDTH = 1.77  # m, body without mirrors
LEAF_REAR_OVERHANG = 0.80  # m, rear axle to rear bumper
PARK_CURVATURE = 0.2  # 1/m, tan(δ)/L of the tightest arc planned: R = 5 m at the rear axle,
# δ ≈ 28.4°, inside the MPC's 30° so it keeps steering margin (the Leaf's 31° gives R ≈ 4.5 m)
PARK_ACCEL = 0.4  # m/s², planned speed-up and slow-down in a parking move
CUSP_PAUSE = 4.0  # s per cusp in the time budget: stop, turn the wheel at rest, shift gear
TIGHT_TURN_SPARE = 10.0  # s per turn tighter than the car's in the time budget


@dataclass(frozen=True)
class Box:
    """An axis-aligned obstacle (parked car, kerb, wall) in the scenario's frame, m."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    name: str = "an obstacle"  # as a sentence names it: "the parked car ahead"

    def corners(self) -> FloatArray:
        """(4, 2): the corners, counter-clockwise."""
        return np.array(
            [
                (self.x_min, self.y_min),
                (self.x_max, self.y_min),
                (self.x_max, self.y_max),
                (self.x_min, self.y_max),
            ]
        )


def footprints(x: FloatArray, y: FloatArray, heading: FloatArray) -> FloatArray:
    """(n, 4, 2): the corners of the Leaf's body (no mirrors), in order around it, with its rear
    axle at ``(x[i], y[i])`` and heading ``heading[i]``."""
    front = LEAF_LENGTH - LEAF_REAR_OVERHANG
    along = np.array([front, front, -LEAF_REAR_OVERHANG, -LEAF_REAR_OVERHANG])
    across = np.array([LEAF_WIDTH / 2, -LEAF_WIDTH / 2, -LEAF_WIDTH / 2, LEAF_WIDTH / 2])
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    return np.stack(
        (x[:, None] + c * along - s * across, y[:, None] + s * along + c * across), axis=-1
    )


def footprint(x: float, y: float, heading: float) -> FloatArray:
    """(4, 2): :func:`footprints` of one pose."""
    return footprints(np.array([x]), np.array([y]), np.array([heading]))[0]


def gaps(cars: FloatArray, box: Box) -> FloatArray:
    """(n,): the separating-axis gap between each car rectangle of ``cars`` (n, 4, 2; as
    :func:`footprints`) and ``box``, m: the distance along the axis that separates them best;
    negative when they overlap, then minus the depth along the axis that parts them with the
    least push. Two rectangles have four such axes: the box's x and y, and the car's own two."""
    rect = box.corners()
    edge1 = cars[:, 1] - cars[:, 0]  # the car's front edge: across the car
    edge2 = cars[:, 2] - cars[:, 1]  # its right side: along it
    axes = [np.broadcast_to(np.array(v, dtype=float), edge1.shape) for v in ((1, 0), (0, 1))]
    axes += [e / np.hypot(e[:, :1], e[:, 1:]) for e in (edge1, edge2)]
    best = np.full(cars.shape[0], -np.inf)
    for axis in axes:
        a = np.einsum("nkd,nd->nk", cars, axis)  # the car's corners on the axis
        b = rect @ axis.T  # (4, n): the box's
        sep = np.maximum(a.min(axis=1) - b.max(axis=0), b.min(axis=0) - a.max(axis=1))
        np.maximum(best, sep, out=best)
    return best


def clearance(
    scenario_name: str, x: FloatArray, y: FloatArray, heading: FloatArray
) -> tuple[float, Box, int] | None:
    """The Leaf's smallest gap (:func:`gaps`) to the obstacles of ``scenario_name`` over the
    poses ``(x[i], y[i], heading[i])``: the gap, the obstacle and the pose's index; None when
    the scenario has no obstacles (or there are no poses)."""
    boxes = OBSTACLES.get(scenario_name, ())
    if not boxes or len(x) == 0:
        return None
    cars = footprints(np.asarray(x, float), np.asarray(y, float), np.asarray(heading, float))
    nearest: tuple[float, Box, int] | None = None
    for box in boxes:
        g = gaps(cars, box)
        i = int(np.argmin(g))
        if nearest is None or g[i] < nearest[0]:
            nearest = (float(g[i]), box, i)
    return nearest


@dataclass(frozen=True)
class _Piece:
    """A stretch driven with the steering ramped linearly (a clothoid; an arc when k0 == k1)."""

    length: float  # m, distance travelled
    k0: float  # 1/m, path curvature tan(δ)/L at its start (sign of δ: left positive)
    k1: float  # 1/m, at its end


@dataclass(frozen=True)
class _Move:
    """One direction segment: driven forward (+1) or in reverse (−1) from rest to rest."""

    direction: int
    pieces: tuple[_Piece, ...]
    v_max: float  # m/s, speed magnitude cap


def _drive_backward(
    goal: tuple[float, float, float], moves: tuple[_Move, ...], step: float = 0.005
) -> list[FloatArray]:
    """Dense ``(x, y, θ)`` of each move in driving order, ending exactly on ``goal``.

    The manoeuvre is integrated backward in time from the goal (each piece driven the other way
    with its curvature ramp reversed), so the final pose — the one that must be exact — is the
    integration's start and the start pose follows. ``θ̇ = v tan δ / L``: a reverse move turns
    the heading the opposite way for the same curvature.
    """
    x, y, th = goal
    dense: list[FloatArray] = []
    for move in reversed(moves):
        pts = [(x, y, th)]
        back = -move.direction  # driving the move backward in time
        for piece in reversed(move.pieces):
            n = max(1, math.ceil(piece.length / step))
            h = piece.length / n
            for i in range(n):
                k = piece.k1 + (piece.k0 - piece.k1) * (i + 0.5) / n  # curvature at the midpoint
                th_mid = th + 0.5 * back * h * k
                x += back * h * math.cos(th_mid)
                y += back * h * math.sin(th_mid)
                th += back * h * k
                pts.append((x, y, th))
        dense.append(np.array(pts[::-1]))
    return dense[::-1]


def _maneuver(
    name: str,
    description: str,
    goal: tuple[float, float, float],
    moves: tuple[_Move, ...],
    spacing: float = SPACING,
) -> Scenario:
    """Waypoints ≤ ``spacing`` apart on each move (equal spacing within a move), cusps shared.

    Headings are the vehicle's (also in reverse); speeds are signed, exactly 0 at each cusp and
    at the end; the first waypoint carries the START_SPEED pull in the first move's direction.
    """
    xs: list[FloatArray] = []
    ys: list[FloatArray] = []
    hs: list[FloatArray] = []
    vs: list[FloatArray] = []
    for m, (move, pts) in enumerate(zip(moves, _drive_backward(goal, moves), strict=True)):
        s_dense = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(pts[:, :2], axis=0).T))))
        length = float(s_dense[-1])
        n = max(1, math.ceil(length / spacing - 1e-9))
        s = np.linspace(0.0, length, n + 1)
        up = np.sqrt(START_SPEED**2 + 2.0 * PARK_ACCEL * s)
        down = np.sqrt(np.maximum(0.0, 2.0 * PARK_ACCEL * (length - s)))
        speed = np.minimum(np.minimum(up, down), move.v_max)
        speed[-1] = 0.0  # a cusp or the goal: exactly at rest
        first = 0 if m == 0 else 1  # the cusp waypoint already ends the previous move
        xs.append(np.interp(s, s_dense, pts[:, 0])[first:])
        ys.append(np.interp(s, s_dense, pts[:, 1])[first:])
        hs.append(np.interp(s, s_dense, pts[:, 2])[first:])
        vs.append(move.direction * speed[first:] + 0.0)  # + 0.0: no negative zeros
    traj = Trajectory(
        x=np.concatenate(xs),
        y=np.concatenate(ys),
        heading=np.concatenate(hs),
        speed=np.concatenate(vs),
    )
    start = Pose(x=float(traj.x[0]), y=float(traj.y[0]), heading=float(traj.heading[0]), speed=0.0)
    return Scenario(name, description, traj, start, duration=time_budget(traj))


#: Obstacles of the parking scenarios (plots, clearances of plans, starts and drives), m.
PARALLEL_SLOT = (
    # 0.2 m from the kerb; the slot between the two parked cars is 6.0 m long
    Box(-4.5, 0.0, 0.2, 1.97, "the parked car behind the slot"),
    Box(6.0, 10.5, 0.2, 1.97, "the parked car ahead of the slot"),
    Box(-5.0, 11.0, -1.0, 0.0, "the kerb"),  # y < 0
)
PERPENDICULAR_BAY = (
    # Leafs parked centred in the bays either side; the bays are 5 m deep, the aisle 6.5 m wide
    Box(-2.135, -0.365, -4.8, -0.35, "the Leaf in the bay to the left"),
    Box(2.865, 4.635, -4.8, -0.35, "the Leaf in the bay to the right"),
    Box(-5.0, 11.0, -6.0, -5.0, "the wall at the back of the bays"),
    Box(-5.0, 11.0, 6.5, 7.5, "the far side of the aisle"),
)
OBSTACLES: dict[str, tuple[Box, ...]] = {
    "parallel-park": PARALLEL_SLOT,
    "perpendicular-park": PERPENDICULAR_BAY,
}


def parallel_park() -> Scenario:
    """Reverse into a 6 m slot beside the kerb: reverse S-bend, pull forward, back up; two cusps.

    Geometry (frame of the slot): the kerb line is ``y = 0`` (kerb at ``y < 0``); two parked cars
    stand 0.2 m from it (``0.2 ≤ y ≤ 1.97``), the one behind ends at ``x = 0``, the one ahead
    starts at ``x = 6``, so the slot is 6.0 m long, 1.55 m more than the Leaf. The car starts at
    rest in the lane beside the car ahead (rear axle at ``x ≈ 7.4, y ≈ 3.18``, 0.33 m of side
    clearance) and ends centred in the slot with its rear axle at ``(1.55, 1.20)``, heading 0
    (0.32 m from the kerb, 0.75 m to each parked car).

    1. Reverse 6.8 m: straight 0.5 m, ramp to full right curvature (0.2 1/m, R = 5 m) over
       0.9 m, arc 2.0 m, ramp through zero to full left over 1.8 m, arc 1.6 m. The rear swings
       in; the car stops 9.7° nose-out with its rear 0.3 m from the car behind.
    2. Forward 1.15 m with the wheel turned right at rest: arc 0.55 m, ramp to straight 0.6 m;
       the heading comes back to 0.
    3. Reverse 0.65 m straight into the centre of the slot.

    The planned footprint keeps ≥ 0.11 m from both parked cars and the kerb (checked by
    ``tests/test_parking.py``); a one-move S-bend would need about 7 m at this curvature.
    """
    k = PARK_CURVATURE
    moves = (
        _Move(
            -1,
            (
                _Piece(0.5, 0.0, 0.0),
                _Piece(0.9, 0.0, -k),
                _Piece(2.0, -k, -k),
                _Piece(1.8, -k, k),
                _Piece(1.6, k, k),
            ),
            0.6,
        ),
        _Move(+1, (_Piece(0.55, -k, -k), _Piece(0.6, -k, 0.0)), 0.4),
        _Move(-1, (_Piece(0.65, 0.0, 0.0),), 0.4),
    )
    return _maneuver(
        "parallel-park",
        "reverse into a 6 m slot beside the kerb (two cusps)",
        (1.55, 1.20, 0.0),
        moves,
    )


def perpendicular_park() -> Scenario:
    """Drive past a 2.5 m wide bay, stop, and reverse into it; one cusp.

    Geometry: the bays open onto an aisle along ``x``; their entrance line is ``y = 0`` and they
    are 5 m deep (wall at ``y = −5``). The target bay spans ``0 ≤ x ≤ 2.5``; Leafs are parked
    centred in the bays either side (``−2.135 ≤ x ≤ −0.365`` and ``2.865 ≤ x ≤ 4.635``, front
    0.35 m inside the entrance). The aisle is 6.5 m wide (far side at ``y = 6.5``).

    1. Forward 10 m along the aisle at ``y ≈ 3.61`` (heading 0), past the bay.
    2. Reverse 10.74 m: straight 0.5 m, ramp to full right curvature (0.2 1/m) over 1.2 m, arc
       6.65 m, ramp back to straight over 1.2 m — a quarter turn — then straight 2.0 m into the
       bay. The goal is the bay's centre line with the rear axle at ``y = −4.0`` (rear bumper
       0.2 m from the wall), heading +90° (nose out).
    """
    k = PARK_CURVATURE
    ramp = 1.2  # m, curvature ramp (clothoid) length
    arc = 0.5 * math.pi / k - ramp  # m: the two ramps and the arc turn by exactly 90°
    moves = (
        _Move(+1, (_Piece(10.0, 0.0, 0.0),), 1.0),
        _Move(
            -1,
            (
                _Piece(0.5, 0.0, 0.0),
                _Piece(ramp, 0.0, -k),
                _Piece(arc, -k, -k),
                _Piece(ramp, -k, 0.0),
                _Piece(2.0, 0.0, 0.0),
            ),
            0.6,
        ),
    )
    return _maneuver(
        "perpendicular-park",
        "reverse into a 2.5 m wide bay after driving past it (one cusp)",
        (1.25, -4.0, 0.5 * math.pi),
        moves,
    )


# --- the route library: routes a planner sends that the maneuvers above do not contain -----------

ROUTE_CURVATURE = 1.0 / 6.0  # 1/m, R = 6 m: a tight hairpin the car can still drive (δ ≈ 24°)
ROUTE_RAMP = 4.0  # m, curvature ramp (clothoid) into and out of a turn


def _turn(angle: float, k: float = ROUTE_CURVATURE, ramp: float = ROUTE_RAMP) -> tuple[_Piece, ...]:
    """A turn by ``angle`` (rad, left positive) at curvature ``k``, entered and left on ramps."""
    k = math.copysign(k, angle)
    arc = abs(angle) / abs(k) - ramp  # the two ramps turn by k·ramp/2 each
    if arc < 0.0:
        raise ValueError(f"a turn of {math.degrees(angle):.0f}° is too short for its ramps")
    return (_Piece(ramp, 0.0, k), _Piece(arc, k, k), _Piece(ramp, k, 0.0))


def _line(length: float) -> _Piece:
    return _Piece(length, 0.0, 0.0)


def _at_origin(sc: Scenario) -> Scenario:
    """The scenario moved so that its first waypoint lies at (0, 0) heading along +x."""
    t = sc.trajectory
    x0, y0, h0 = float(t.x[0]), float(t.y[0]), float(t.heading[0])
    c, s_ = math.cos(-h0), math.sin(-h0)
    dx, dy = t.x - x0, t.y - y0
    traj = Trajectory(
        x=c * dx - s_ * dy + 0.0, y=s_ * dx + c * dy + 0.0, heading=t.heading - h0, speed=t.speed
    )
    start = Pose(x=0.0, y=0.0, heading=0.0, speed=0.0)
    return Scenario(sc.name, sc.description, traj, start, sc.duration, sc.feasible)


def switch_back() -> Scenario:
    """About 110 m forward through a tight hairpin and a corner, a cusp, then 60 m in reverse.

    Forward: 25 m straight, a 180° hairpin (R = 6 m between 4 m clothoids), 25 m back, a 90°
    left corner (R = 8 m), 20 m straight: 109 m. Reverse: a 90° arc (R = 10 m) and 40 m
    straight: 60 m. Issue 13: this reported ``finished`` on the second tick.
    """
    moves = (
        _Move(
            +1,
            (_line(25.0), *_turn(math.pi), _line(25.0), *_turn(0.5 * math.pi, 1 / 8), _line(20.0)),
            2.0,
        ),
        _Move(-1, (*_turn(0.5 * math.pi, 1 / 10), _line(40.0)), 1.5),
    )
    sc = _maneuver(
        "switch-back",
        "109 m forward through a hairpin, a cusp, 60 m in reverse",
        (0.0, 0.0, 0.0),
        moves,
    )
    return _at_origin(sc)


def figure_eight() -> Scenario:
    """A lemniscate of Bernoulli (a = 20 m, 105 m, R ≥ 6.7 m) that crosses itself and ends on
    its start, waypoints 1.0 m apart (issue 13: stopped after 21 of 199 m)."""
    a = 20.0

    def path(u: FloatArray) -> tuple[FloatArray, FloatArray]:
        t = 0.5 * math.pi - 2.0 * math.pi * u / u[-1]  # from the crossing, first lobe to the left
        d = 1.0 + np.sin(t) ** 2
        return a * np.cos(t) / d, a * np.sin(t) * np.cos(t) / d

    sc = _forward(
        "figure-eight",
        "a figure-eight crossing itself, ending on its start",
        path,
        110.0,
        2.0,
        spacing=1.0,
    )
    return _at_origin(sc)


def closed_loop() -> Scenario:
    """A stadium: 20 m straights and two 180° turns (R = 7 m), 92 m; the end is the start."""
    turn = _turn(math.pi, 1 / 7)
    moves = (_Move(+1, (_line(10.0), *turn, _line(20.0), *turn, _line(10.0)), 2.0),)
    sc = _maneuver(
        "closed-loop", "a closed loop (stadium, 92 m), ending on its start", (0.0, 0.0, 0.0), moves
    )
    return _at_origin(sc)


def u_turn() -> Scenario:
    """20 m out, a 180° turn (R = 6 m), 15 m back: the end lies 5 m short of the start, in the
    other lane (issue 13: reported ``finished`` on the first tick)."""
    moves = (_Move(+1, (_line(20.0), *_turn(math.pi), _line(15.0)), 2.0),)
    sc = _maneuver("u-turn", "a U-turn ending 5 m short of its start", (0.0, 0.0, 0.0), moves)
    return _at_origin(sc)


def corner() -> Scenario:
    """10 m straight, a 90° left corner of 5 m radius (no clothoid: δ steps to 28.4°), 10 m
    straight, at 1 m/s."""
    moves = (_Move(+1, (_line(10.0), _Piece(0.5 * math.pi * 5.0, 0.2, 0.2), _line(10.0)), 1.0),)
    sc = _maneuver("corner", "a 90° corner of 5 m radius at 1 m/s", (0.0, 0.0, 0.0), moves)
    return _at_origin(sc)


def cusp_retrace() -> Scenario:
    """15 m forward with a 30° bend, a cusp, and the same waypoints back in reverse, exactly
    (issue 13: the car stalled 3 m into the reverse leg and stayed ENGAGED)."""
    moves = (_Move(+1, (_line(6.0), *_turn(math.radians(30.0), 1 / 8), _line(3.0)), 1.0),)
    fwd = _maneuver("cusp-retrace", "", (0.0, 0.0, 0.0), moves).trajectory
    back = slice(-2, None, -1)  # the cusp waypoint is shared
    speed = np.concatenate((fwd.speed, -fwd.speed[back] + 0.0))
    speed[-1] = 0.0  # at rest on the goal (the forward leg's start carries its pull-away speed)
    traj = Trajectory(
        x=np.concatenate((fwd.x, fwd.x[back])),
        y=np.concatenate((fwd.y, fwd.y[back])),
        heading=np.concatenate((fwd.heading, fwd.heading[back])),
        speed=speed,
    )
    start = Pose(x=float(traj.x[0]), y=float(traj.y[0]), heading=float(traj.heading[0]), speed=0.0)
    sc = Scenario(
        "cusp-retrace",
        "a cusp whose reverse leg retraces the forward leg exactly",
        traj,
        start,
        time_budget(traj),
    )
    return _at_origin(sc)


def tight_hairpin() -> Scenario:
    """The infeasible case: a 180° hairpin of R = 3 m (δ ≈ 42°, beyond the Leaf's 31°) at
    1 m/s. The car must not sprint through it nor report it finished before its end."""
    moves = (_Move(+1, (_line(10.0), _Piece(math.pi * 3.0, 1 / 3, 1 / 3), _line(10.0)), 1.0),)
    sc = _maneuver(
        "tight-hairpin",
        "a hairpin tighter than the car can turn (infeasible)",
        (0.0, 0.0, 0.0),
        moves,
    )
    sc = _at_origin(sc)
    return Scenario(sc.name, sc.description, sc.trajectory, sc.start, sc.duration, feasible=False)


def offset_start(sc: Scenario, lateral: float, heading: float) -> Scenario:
    """``sc`` started ``lateral`` m to the left of its first waypoint (right when negative) and
    turned ``heading`` rad from its heading, at rest (engage-envelope starts)."""
    x0, y0, h0 = float(sc.trajectory.x[0]), float(sc.trajectory.y[0]), sc.start.heading
    start = Pose(
        x=x0 - lateral * math.sin(h0),
        y=y0 + lateral * math.cos(h0),
        heading=h0 + heading,
        speed=0.0,
    )
    return Scenario(sc.name, sc.description, sc.trajectory, start, sc.duration, sc.feasible)


def file_scenario(
    path: str,
    start: Pose | None = None,
    *,
    max_speed: float = math.inf,
    max_points: int | None = None,
) -> Scenario:
    """A user's route from a trajectory file, refused at once by the rule for a file
    (:func:`~leafgate.control.reference.load_plan_file`, which ``publish-trajectory`` applies
    too): when the gateway would refuse it (``max_speed``: the safety gate's, m/s;
    ``max_points``: the transport's limit), or when the car could never reach its end.

    :param start: the start pose; None starts at rest on the first waypoint
    :raises TrajectoryError: naming the file, the row and the problem
    """
    from leafgate.control.reference import load_plan_file

    traj = load_plan_file(path, max_speed=max_speed, max_points=max_points)
    if start is None:
        start = Pose(
            x=float(traj.x[0]), y=float(traj.y[0]), heading=float(traj.heading[0]), speed=0.0
        )
    return Scenario(str(path), f"trajectory file {path}", traj, start, time_budget(traj))


SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "s-curve": s_curve,
    "straight": straight,
    "slalom": slalom,
    "parallel-park": parallel_park,
    "perpendicular-park": perpendicular_park,
    # the route library (issue 13)
    "switch-back": switch_back,
    "figure-eight": figure_eight,
    "closed-loop": closed_loop,
    "u-turn": u_turn,
    "corner": corner,
    "cusp-retrace": cusp_retrace,
    "tight-hairpin": tight_hairpin,
}


def get_scenario(name: str) -> Scenario:
    """Build the named scenario.

    :raises KeyError: naming the known scenarios when ``name`` is not one of them
    """
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise KeyError(
            f"unknown scenario {name!r} (known: {', '.join(sorted(SCENARIOS))})"
        ) from None
    return factory()
