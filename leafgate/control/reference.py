"""The reference: loading and checking trajectories, nearest waypoint, resampling to the horizon.

A trajectory is a list of rear-axle waypoints ``(x, y, heading, speed)``, 0.5–1.0 m apart as
a planner sends them (paper §II.B; any spacing is followed). Speeds are signed; where the sign changes (a cusp) the trajectory is split into
*direction segments* and the controller tracks one segment to its end, stops there, and moves
on to the next (:class:`ReferencePath`).

Resampling (paper §I.B): the horizon's reference points are placed along the path by the
planned speed profile — the time to travel each waypoint interval is precomputed once per
trajectory, so the ``Np`` points of a cycle are found with one vectorised interpolation
starting at the vehicle's projection on the path. Positions and headings are then evaluated
with third-order (cubic Lagrange) interpolation on four waypoints, one behind and three ahead,
parametrised by arc length; the speed is interpolated linearly (no overshoot). A segment's last
point always has zero reference speed, so the reference stops on it; so does a *stop point*,
where the plan comes to rest before the segment's end (:func:`stop_point`, as Autoware's
planners stop a car at a stop line): the reference stops there and waits.

Rows in error messages are waypoint numbers counted from 1 (in a CSV file, row 1 is the line
after the header).
"""

from __future__ import annotations

import bisect
import collections
import csv
import itertools
import math
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import yaml

from leafgate.config import read_text, safe_load_yaml, yaml_error_text
from leafgate.errors import TrajectoryError
from leafgate.geometry import wrap_angle
from leafgate.messages import FloatArray, Trajectory

try:  # the compiled loop behind np.interp (float64 only): skips ~1 µs of wrapper checks a call
    from numpy._core.multiarray import interp as _interp
except ImportError:  # numpy < 2 keeps it elsewhere; the public function gives the same values
    _interp = np.interp

FIELDS = ("x", "y", "heading", "speed")
# The largest magnitude of each field that can mean anything, and its unit: map coordinates
# (UTM northings reach 1e7 m), a heading unwrapped over many turns, a speed. A finite 1e300
# passed every check and overflowed in the reference's arithmetic.
LIMITS = {"x": (1e8, "m"), "y": (1e8, "m"), "heading": (1e4, "rad"), "speed": (1e3, "m/s")}
MIN_POINTS = 4  # the cubic resampling needs four waypoints
OVERLAP_DISTANCE = 0.01  # m: a waypoint closer than this to the previous one overlaps it and
# is removed (Autoware's removeOverlapPoints uses the same 1 cm)


@dataclass(frozen=True, slots=True)
class Spacing:
    """Distances between consecutive waypoints, m."""

    min: float
    median: float
    max: float

    def __str__(self) -> str:
        return f"{self.min:.2f}-{self.max:.2f} m (median {self.median:.2f} m)"


# --- loading and validation -------------------------------------------------------------------


def load_trajectory(
    path: str | Path, *, max_speed: float = math.inf, max_points: int | None = None
) -> Trajectory:
    """Read a trajectory from CSV (header ``x,y,heading,speed``) or YAML, and check it by the
    rule for a usable plan (:func:`trajectory_problem`, with ``max_speed`` and ``max_points``).

    YAML holds either a list of mappings with the four keys or a mapping of the four keys to
    lists of equal length. Units are SI (m, rad, m/s). A user's file is read with
    :func:`load_plan_file`, which adds the rule for a file that is the whole plan.

    :raises TrajectoryError: naming the file, the row and the problem
    """
    return _read_checked(Path(path), max_speed, max_points)[0]


def load_plan_file(
    path: str | Path, *, max_speed: float = math.inf, max_points: int | None = None
) -> Trajectory:
    """Read a user's trajectory file, **the** rule for whether one is acceptable: every command
    that takes one (``sim --trajectory``, ``publish-trajectory``) reads it here.

    The file is checked by the rule the gateway applies to a plan (:func:`load_trajectory`),
    and, being all the car will get, refused when it comes to rest before the end of a
    direction segment (:func:`stop_point`): the car would stop there and wait for a plan that
    moves on, and none comes (a re-published file is the same plan again).

    :param max_speed: m/s, the safety gate's limit
    :param max_points: the transport's limit on a plan's waypoints
    :raises TrajectoryError: naming the file, the row and the problem
    """
    path = Path(path)
    traj, rows = _read_checked(path, max_speed, max_points)
    _refuse_stop_points(traj, str(path), rows)
    return traj


def _read_checked(
    path: Path, max_speed: float, max_points: int | None
) -> tuple[Trajectory, list[int] | None]:
    """The trajectory in ``path``, checked (:func:`trajectory_problem`), and the file row of
    each waypoint (None: waypoint ``i`` is row ``i + 1``)."""
    text = read_text(path, TrajectoryError)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        columns, rows = _parse_csv(text, str(path))
    elif suffix in (".yaml", ".yml"):
        columns, rows = _parse_yaml(text, str(path)), None
    else:
        raise TrajectoryError(f"{path}: unknown trajectory format {suffix!r} (use .csv or .yaml)")
    traj = Trajectory(
        x=np.asarray(columns["x"], dtype=np.float64),
        y=np.asarray(columns["y"], dtype=np.float64),
        heading=np.asarray(columns["heading"], dtype=np.float64),
        speed=np.asarray(columns["speed"], dtype=np.float64),
    )
    problem = trajectory_problem(
        traj, str(path), max_speed=max_speed, max_points=max_points, rows=rows
    )
    if problem is not None:
        raise TrajectoryError(problem)
    return traj, rows


def _refuse_stop_points(traj: Trajectory, source: str, rows: Sequence[int] | None) -> None:
    """Raise when the plan comes to rest before a direction segment's end
    (:func:`load_plan_file`)."""
    kept = _kept_points(traj)
    plan = _subset(traj, kept)
    for seg in split_segments(plan):
        stop = stop_point(np.maximum(seg.direction * plan.speed[seg.start : seg.end + 1], 0.0))
        if stop is None:
            continue
        i = int(kept[seg.start + stop])
        row = int(rows[i]) if rows is not None else i + 1
        leg = "forward" if seg.direction > 0 else "reverse"
        speed = float(traj.speed[i])
        way = "forward" if seg.direction > 0 else "backward"
        if speed != 0.0:  # a sign against the leg the geometry says: no cusp here, no motion
            raise TrajectoryError(
                f"{source}: row {row}: speed {speed:g} m/s runs against the {leg} leg the path "
                f"drives here (the chords run {way} along the headings; a change of direction is "
                "a cusp, where the path turns back): the car would stop here and wait for "
                "another plan; give each leg's waypoints speeds of its sign up to its end"
            )
        raise TrajectoryError(
            f"{source}: row {row}: the plan comes to rest here, before the end of its {leg} "
            "leg (speed 0: the car stops at the first waypoint at rest, as at a planner's stop "
            "line, whatever speeds follow): it would stop and wait for another plan; a file is "
            "one plan, so give speeds above 0 up to each cusp and the end"
        )


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _number(text: object, source: str, row: int, name: str) -> float:
    if isinstance(text, bool):
        raise TrajectoryError(f"{source}: row {row}: {name} is not a number: {_show(text)}")
    try:
        if isinstance(text, (int, float)):
            return float(text)
        if isinstance(text, str):
            return float(text.strip())
    except OverflowError:  # an integer beyond float range
        raise TrajectoryError(
            f"{source}: row {row}: {name} is out of range: {_show(text)}"
        ) from None
    except ValueError:
        pass
    raise TrajectoryError(f"{source}: row {row}: {name} is not a number: {_show(text)}")


def _check_header(names: list[str], source: str) -> None:
    missing = [f for f in FIELDS if f not in names]
    extra = [n for n in names if n not in FIELDS]
    if extra:
        raise TrajectoryError(
            f"{source}: unknown column(s) {', '.join(map(repr, extra))} "
            f"(expected exactly {', '.join(FIELDS)})"
        )
    if missing:
        raise TrajectoryError(f"{source}: missing column(s) {', '.join(missing)}")
    if len(set(names)) != len(names):
        raise TrajectoryError(f"{source}: a column is given twice in the header")


def _parse_csv(text: str, source: str) -> tuple[dict[str, list[float]], list[int]]:
    """The columns, and the row (line after the header = 1) of each waypoint."""
    reader = csv.reader(text.splitlines())
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise TrajectoryError(
            f"{source}: empty file (a header x,y,heading,speed is required)"
        ) from None
    except csv.Error as exc:  # a field over the csv module's size limit
        raise TrajectoryError(f"{source}: line 1 (the header): {exc}") from None
    if all(_is_number(h) for h in header if h):
        raise TrajectoryError(f"{source}: no header (the first line must be x,y,heading,speed)")
    _check_header(header, source)
    columns: dict[str, list[float]] = {name: [] for name in FIELDS}
    rows: list[int] = []
    header_lines = reader.line_num
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:  # a field over the csv module's size limit
            raise TrajectoryError(
                f"{source}: row {reader.line_num - header_lines}: {exc}"
            ) from None
        row = reader.line_num - header_lines  # lines, so blank lines keep their number
        if not cells or all(not c.strip() for c in cells):
            continue  # blank line
        if len(cells) != len(header):
            raise TrajectoryError(
                f"{source}: row {row}: {len(cells)} values, the header has {len(header)}"
            )
        for name, cell in zip(header, cells, strict=True):
            columns[name].append(_number(cell, source, row, name))
        rows.append(row)
    return columns, rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _parse_yaml(text: str, source: str) -> dict[str, list[float]]:
    try:
        data = safe_load_yaml(text)
    except yaml.YAMLError as exc:
        raise TrajectoryError(f"{source}: {yaml_error_text(exc, text)}") from None
    columns: dict[str, list[float]] = {name: [] for name in FIELDS}
    if isinstance(data, list):
        for row, item in enumerate(data, start=1):
            if not isinstance(item, dict):
                raise TrajectoryError(f"{source}: row {row}: expected a mapping of {FIELDS}")
            _check_header([str(k) for k in item], f"{source}: row {row}")
            for name in FIELDS:
                columns[name].append(_number(item[name], source, row, name))
    elif isinstance(data, dict):
        _check_header([str(k) for k in data], source)
        lengths = set()
        for name in FIELDS:
            values = data[name]
            if not isinstance(values, list):
                raise TrajectoryError(f"{source}: {name}: expected a list of numbers")
            lengths.add(len(values))
            columns[name] = [_number(v, source, row, name) for row, v in enumerate(values, 1)]
        if len(lengths) != 1:
            sizes = ", ".join(f"{n}: {len(columns[n])}" for n in FIELDS)
            raise TrajectoryError(f"{source}: the lists differ in length ({sizes})")
    else:
        raise TrajectoryError(
            f"{source}: expected a list of waypoints or a mapping of x, y, heading, speed lists"
        )
    return columns


def validate(traj: Trajectory, source: str, rows: Sequence[int] | None = None) -> Spacing:
    """Check a trajectory and report its waypoint spacing: **the** rule for a usable plan.

    Checks: every value finite and within :data:`LIMITS`, and at least four waypoints once overlapping points (closer
    than :data:`OVERLAP_DISTANCE` to the previous kept one) are removed — those are dropped by
    :func:`remove_overlap_points`, not refused (Autoware's planners emit them). The transport,
    the gateway's engage check and every controller use this same rule, through
    :func:`trajectory_problem`.

    :param source: the file or topic the trajectory came from, for messages
    :param rows: the row of the file each waypoint came from (a CSV file's blank lines keep
        their numbers); None when waypoint ``i`` is row ``i + 1``
    :returns: min / median / max spacing of the kept waypoints, m
    :raises TrajectoryError: ``"<source>: row <n>: <problem>"`` or ``"<source>: <problem>"``
    """
    n = len(traj)

    def row_of(index: int) -> int:
        return int(rows[index]) if rows is not None else index + 1

    for name in FIELDS:
        values = getattr(traj, name)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise TrajectoryError(f"{source}: row {row_of(int(bad[0]))}: {name} is not finite")
        limit, unit = LIMITS[name]
        bad = np.flatnonzero(np.abs(values) > limit)
        if bad.size:
            i = int(bad[0])
            raise TrajectoryError(
                f"{source}: row {row_of(i)}: {name} {float(values[i]):g} {unit} is beyond "
                f"±{limit:g} {unit}"
            )
    kept = _kept_points(traj)
    if kept.size < MIN_POINTS:
        dropped = f" ({n - kept.size} overlapping removed)" if kept.size < n else ""
        raise TrajectoryError(
            f"{source}: {kept.size} waypoint(s){dropped}, at least {MIN_POINTS} are needed"
        )
    with np.errstate(over="ignore", invalid="ignore"):  # huge finite values: inf gaps are fine
        gaps = np.hypot(np.diff(traj.x[kept]), np.diff(traj.y[kept]))
    return Spacing(float(gaps.min()), float(np.median(gaps)), float(gaps.max()))


STOP_DECEL = 1.0  # m/s², the reference speed needs no harder braking to stop at a segment's end
# (or to slow to TIGHT_TURN_SPEED before a turn tighter than the car can follow)
TIGHT_TURN_SPEED = 1.0  # m/s, the fastest reference speed on a turn tighter than the car's: the
# car leaves the plan there, and the off-the-plan watchdog's stop then ends under 1 m past its
# limit (0.75 m on PythonRobotics' courses; from their 10 km/h it was 3-3.7 m)
TURN_WINDOW = 0.5  # m, the shortest stretch of path a turn's radius is measured over
MAX_HEADING_STEP = math.pi / 2  # rad between neighbouring kept waypoints: more is a flip
HEADING_CHORD = 0.05  # m, the shortest chord whose direction is compared with the headings
MAX_HEADING_OFF = math.radians(45.0)  # rad, a chord running farther off its headings: wrong
AT_REST_SPEED = 1e-3  # m/s, a planned speed at most this is a waypoint at rest (stop_point)
STOP_WAIT = 1e9  # s, the planned time added past a stop point: the reference never gets there


def trajectory_problem(
    traj: Trajectory,
    source: str = "trajectory",
    *,
    max_speed: float = math.inf,
    max_points: int | None = None,
    rows: Sequence[int] | None = None,
) -> str | None:
    """Why ``traj`` cannot be driven, in one line, or None when it is usable (:func:`validate`).

    The one rule for a usable trajectory (transport, engage check, controllers). Returns a
    reason rather than raising so that more checks can be added without changing callers.
    Besides :func:`validate` (issue 17, finding 10):

    - more than ``max_points`` waypoints (the reference is built from every one of them);
    - a waypoint speed above ``max_speed`` (the maneuver limit, m/s; the engage check passes
      the safety gate's, which the car would never be allowed to reach);
    - a heading flip: neighbouring kept waypoints whose headings differ by more than
      :data:`MAX_HEADING_STEP` (a car cannot turn 90° within one waypoint spacing of ≤ 1 m; a
      change of direction keeps the heading, only the speed's sign changes); the first one is
      named, and headings that look like degrees (:func:`_in_degrees`) are told so;
    - a heading that disagrees with the way the path runs: each chord of at least
      :data:`HEADING_CHORD` between kept waypoints runs along the mean of its two headings (as
      on any circular arc), forward or, driven in reverse, backward; off by more than
      :data:`MAX_HEADING_OFF`, the headings are not the vehicle's in radians (degrees, or the
      path's tangent on a reverse leg).

    :param rows: the row of the file each waypoint came from (:func:`validate`)
    """
    if max_points is not None and len(traj) > max_points:
        return f"{source}: {len(traj)} waypoints, at most {max_points} (zenoh.max_plan_points)"
    try:
        validate(traj, source, rows)
    except TrajectoryError as exc:
        return str(exc)

    def row_of(index: int) -> int:
        return int(rows[index]) if rows is not None else index + 1

    fastest = int(np.argmax(np.abs(traj.speed)))
    if abs(float(traj.speed[fastest])) > max_speed:
        return (
            f"{source}: row {row_of(fastest)}: speed {float(traj.speed[fastest]):.2f} m/s above "
            f"the maneuver limit {max_speed:g} m/s"
        )
    kept = _kept_points(traj)
    heading = traj.heading[kept]
    steps = np.abs(np.angle(np.exp(1j * np.diff(heading))))
    flips = np.flatnonzero(steps > MAX_HEADING_STEP)
    if flips.size:
        i = int(flips[0])
        return (
            f"{source}: row {row_of(int(kept[i + 1]))}: heading turns "
            f"{math.degrees(float(steps[i])):.0f}° from the waypoint before (a flip)"
            + _in_degrees(_subset(traj, kept))
        )
    return _heading_problem(_subset(traj, kept), kept, source, row_of)


def _in_degrees(traj: Trajectory) -> str:
    """``"; headings are … radians …"`` when the headings of ``traj`` (without overlapping
    points) read as degrees are the vehicle's along the path — no flip between neighbours and
    every chord of at least :data:`HEADING_CHORD` along them (:func:`_chord_offsets`) — and
    read as radians, fewer than half the chords are; "" otherwise. The geometry decides, not
    the size: unwrapped headings in radians pass 2π (a loop driven twice, PythonRobotics'
    ``smooth_yaw``), and headings of a few degrees, read as radians, are near the path's."""
    as_radians = np.radians(traj.heading)
    steps = np.abs(np.angle(np.exp(1j * np.diff(as_radians))))
    if (steps > MAX_HEADING_STEP).any():
        return ""
    off, long = _chord_offsets(replace(traj, heading=as_radians))
    if not long.any() or (off > MAX_HEADING_OFF).any():
        return ""
    off, _ = _chord_offsets(traj)
    if 2 * np.count_nonzero(off[long] <= MAX_HEADING_OFF) >= np.count_nonzero(long):
        return ""  # as radians half the chords or more run along them: radians, flipped
    largest = float(np.abs(traj.heading).max())
    return (
        "; headings are the vehicle's, in radians, and these look like degrees (read as "
        f"degrees they run along the path; up to {largest:.4g})"
    )


def _chord_offsets(traj: Trajectory) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """How far (rad, 0–π) each chord's direction is from the way its waypoints' headings say
    the vehicle faces on it, driven forward or in reverse (:func:`chord_directions`), 0 for a
    chord shorter than :data:`HEADING_CHORD`; and which chords are that long. ``traj`` is
    without overlapping points, and its neighbours' headings differ by under 90° (no flip)."""
    dx, dy = np.diff(traj.x), np.diff(traj.y)
    along = np.arctan2(dy, dx)  # the chord's direction
    # the heading half way: the mean of the two (their difference is under 90°, no flip)
    mid = traj.heading[:-1] + 0.5 * np.angle(np.exp(1j * np.diff(traj.heading)))
    reverse = chord_directions(traj) < 0.0
    facing = np.where(reverse, along + math.pi, along)  # where the vehicle faces on the chord
    off = np.abs(np.angle(np.exp(1j * (facing - mid))))
    long = np.hypot(dx, dy) >= HEADING_CHORD
    off[~long] = 0.0
    return off, long


def _heading_problem(
    traj: Trajectory, kept: npt.NDArray[np.intp], source: str, row_of: Any
) -> str | None:
    """The first chord whose direction disagrees with its waypoints' headings
    (:func:`trajectory_problem`), or None. ``traj`` is without overlapping points, ``kept``
    their indices in the trajectory as given."""
    off, _ = _chord_offsets(traj)
    bad = np.flatnonzero(off > MAX_HEADING_OFF)
    if not bad.size:
        return None
    i = int(bad[0])
    reverse = chord_directions(traj)[i] < 0.0
    way = "backward (reverse: the speed is negative)" if reverse else "forward"
    return (
        f"{source}: row {row_of(int(kept[i]))}: heading {float(traj.heading[i]):.3f} rad is "
        f"{math.degrees(float(off[i])):.0f}° off the way the path runs from it to the next "
        f"waypoint, driven {way}"
        + (_in_degrees(traj) or "; headings are the vehicle's, in radians")
    )


def _kept_points(traj: Trajectory) -> npt.NDArray[np.intp]:
    """Indices of the waypoints kept by :func:`remove_overlap_points` (finite input)."""
    x, y = traj.x.tolist(), traj.y.tolist()
    if not x:
        return np.zeros(0, dtype=np.intp)
    kept = [0]
    lx, ly = x[0], y[0]
    limit = OVERLAP_DISTANCE
    for i in range(1, len(x)):
        if math.hypot(x[i] - lx, y[i] - ly) >= limit:
            kept.append(i)
            lx, ly = x[i], y[i]
    return np.asarray(kept, dtype=np.intp)


def remove_overlap_points(traj: Trajectory) -> Trajectory:
    """The trajectory without waypoints closer than :data:`OVERLAP_DISTANCE` to the previous
    kept one (as Autoware's ``removeOverlapPoints``: the first of a group stays).

    Returns ``traj`` itself when nothing overlaps.
    """
    return _subset(traj, _kept_points(traj))


def _subset(traj: Trajectory, kept: npt.NDArray[np.intp]) -> Trajectory:
    """``traj``'s waypoints ``kept`` (:func:`_kept_points`); ``traj`` itself when all are."""
    if kept.size == len(traj):
        return traj
    return Trajectory(
        x=traj.x[kept],
        y=traj.y[kept],
        heading=traj.heading[kept],
        speed=traj.speed[kept],
        stamp=traj.stamp,
    )


# --- direction segments and the path ----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Segment:
    """Waypoints ``start … end`` (inclusive) driven in one direction (+1 forward, −1 reverse)."""

    start: int
    end: int
    direction: int


def chord_directions(traj: Trajectory) -> FloatArray:
    """The driving direction (+1 forward, −1 reverse) of each chord ``i → i + 1`` of the plan:
    the one rule for where a plan changes direction, used by the controller, the rolling-window
    check, the metrics and the plots.

    A chord is driven in the direction of the speed at its end: a zero speed belongs to the
    motion it ends (Autoware puts a waypoint at rest on the cusp), and waypoints at rest before
    the first motion take its direction. Where the sign flips from one waypoint to the next
    with no waypoint at rest between them, the speeds alone cannot say which of the two is the
    cusp: planners differ (PythonRobotics' courses give each waypoint the speed of the chord
    that leaves it, so the chord into the cusp still carries the old sign). The chord's own
    geometry then decides: when it runs along both of its waypoints' headings the way the old
    motion went, it belongs to the old motion and the cusp is its far end.
    """
    speed = traj.speed
    sign = np.sign(speed)
    nonzero = np.flatnonzero(sign)
    if nonzero.size == 0:
        return np.ones(max(len(speed) - 1, 0))
    # index of the last non-zero at or before each point (or the first non-zero)
    last = np.maximum.accumulate(np.where(sign != 0, np.arange(len(speed)), -1))
    last[last < 0] = nonzero[0]
    chords = sign[last][1:]
    # chord i flips the direction although waypoint i still moves the old way: its geometry
    flips = np.flatnonzero(sign[1:] * sign[:-1] < 0.0)
    for i in flips.tolist():
        old = sign[i]
        dx, dy = traj.x[i + 1] - traj.x[i], traj.y[i + 1] - traj.y[i]
        along = [
            dx * math.cos(h) + dy * math.sin(h) for h in (traj.heading[i], traj.heading[i + 1])
        ]
        if all(old * a > 0.0 for a in along):
            chords[i] = old
    return chords


def turn_radius(wheelbase: float, steer_max: float) -> float:
    """The radius of the tightest turn of a car, m (rear axle): ``L / tan δ_max``."""
    return wheelbase / math.tan(steer_max)


def turn_radii(
    s: FloatArray, heading: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """The radius of the turn measured at each waypoint, m, and the waypoints it starts and
    ends at.

    A turn runs from a waypoint to the first one at least ``TURN_WINDOW`` farther along the
    path (the next, on a plan sampled every 0.5 m or more); near the path's end, where there
    is none, it is the last such stretch, up to the end. Its radius is the arc length over the
    heading change between its ends (inf when straight). The window keeps a densely sampled
    plan's heading jitter from reading as a tight turn: 0.02 rad between waypoints 0.1 m apart
    is a radius of 5 m, but accumulates to nothing over the window.

    :param s: m, arc length of the waypoints (non-decreasing)
    :param heading: rad, their headings, unwrapped
    """
    last = len(s) - 1
    end = np.minimum(np.searchsorted(s, s + TURN_WINDOW, side="left"), last)
    start = np.searchsorted(s, s[end] - TURN_WINDOW, side="right") - 1
    np.clip(start, 0, np.arange(len(s)), out=start)  # back from the end only: never past i
    turn = np.abs(heading[end] - heading[start])
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(turn > 0.0, (s[end] - s[start]) / turn, np.inf)
    return radius, start, end


def tightest_turn(traj: Trajectory) -> tuple[float, int]:
    """The radius of the plan's tightest turn, m (inf: straight), and the waypoint it starts
    at (:func:`turn_radii`)."""
    if len(traj) < 2:
        return math.inf, 0
    s = np.concatenate(([0.0], np.cumsum(np.hypot(np.diff(traj.x), np.diff(traj.y)))))
    radius, start, _ = turn_radii(s, np.unwrap(traj.heading))
    i = int(np.argmin(radius))
    return float(radius[i]), int(start[i])


CHORD_SAGITTA_WARN = 0.01  # m, a chord cutting its curve by more makes the chord metrics coarse


def chord_sagitta(traj: Trajectory) -> tuple[float, int, float]:
    """How far the plan's straight chords cut the curve through its waypoints, m, the
    waypoint the worst chord starts at, and that chord's length, m.

    The controller follows a cubic through the waypoints; the simulator's lateral error is
    measured from the chords (:func:`leafgate.sim.metrics.path_errors`). On a circular arc
    that turns by Δθ over a chord of length L the two are ``L/2 · tan(Δθ/4)`` apart at the
    middle: 2.5 cm for 1 m on a 5 m radius, 23 cm for 3 m. Overlapping points are left out.
    """
    kept = _kept_points(traj)
    if kept.size < 2:
        return 0.0, 0, 0.0
    gaps = np.hypot(np.diff(traj.x[kept]), np.diff(traj.y[kept]))
    turn = np.abs(np.asarray(wrap_angle(np.diff(traj.heading[kept]))))
    sagitta = 0.5 * gaps * np.tan(0.25 * turn)
    i = int(np.argmax(sagitta))
    return float(sagitta[i]), int(kept[i]), float(gaps[i])


def tight_turn_ceiling(s: FloatArray, heading: FloatArray, min_radius: float) -> FloatArray | None:
    """The speed ceiling of the waypoints near turns tighter than ``min_radius`` m
    (:func:`turn_radii`), m/s: ``TIGHT_TURN_SPEED`` on them, rising at ``STOP_DECEL`` with the
    distance from them; None when the path has no such turn.

    :param s: m, arc length of the waypoints (of one segment: the reference's)
    :param heading: rad, their headings, unwrapped
    """
    radius, start, end = turn_radii(s, heading)
    tight_turns = np.flatnonzero(radius < min_radius)
    if tight_turns.size == 0:
        return None
    marks = np.zeros(len(s) + 1)  # +1 where a tight turn starts, −1 after its end waypoint
    np.add.at(marks, start[tight_turns], 1.0)
    np.add.at(marks, end[tight_turns] + 1, -1.0)
    tight = s[np.cumsum(marks[:-1]) > 0.0]  # arc lengths of the waypoints on a tight turn
    k = np.searchsorted(tight, s)
    before = tight[np.maximum(k - 1, 0)]
    after = tight[np.minimum(k, len(tight) - 1)]
    distance = np.minimum(np.abs(s - before), np.abs(after - s))
    return np.sqrt(TIGHT_TURN_SPEED**2 + 2.0 * STOP_DECEL * distance)


def stop_point(speed: FloatArray) -> int | None:
    """Where a segment's plan stops short of the segment's end: the first waypoint at rest
    (speed magnitude at most :data:`AT_REST_SPEED`) after the motion has started, or the
    segment's start when the plan never moves; None when the plan moves on to the last waypoint.

    Autoware's planners stop the car so, at a stop line or before an obstacle: the speeds are
    zero from the stop point on, for as far as the trajectory reaches. The car stops there and
    waits for a plan that moves on; it does not creep on towards the trajectory's end. Waypoints
    at rest before the motion starts are a start from rest, not a stop: the car pulls away.

    :param speed: m/s, the magnitudes of the segment's planned speeds, in driving order
    """
    moving = speed > AT_REST_SPEED
    first = int(np.argmax(moving))
    if not moving[first]:
        return 0
    rest = np.flatnonzero(~moving[first:-1])
    return first + int(rest[0]) if rest.size else None


def directions(traj: Trajectory) -> FloatArray:
    """Driving direction of each waypoint: that of the chord arriving at it (the first
    waypoint: of the chord leaving it), by :func:`chord_directions`."""
    chords = chord_directions(traj)
    if chords.size == 0:
        return np.ones(len(traj))
    return np.concatenate((chords[:1], chords))


def split_segments(traj: Trajectory) -> list[Segment]:
    """Split at cusps. Consecutive segments share the cusp waypoint (end of one, start of next)."""
    dirs = directions(traj)
    changes = np.flatnonzero(dirs[1:] != dirs[:-1])  # direction changes after these points
    bounds = [0, *[int(c) for c in changes], len(traj) - 1]
    return [
        Segment(a, b, int(dirs[a + 1]))  # the shared start point carries the old direction
        for a, b in itertools.pairwise(bounds)
        if b > a  # a direction held for one point only is no segment
    ]


@dataclass(frozen=True, slots=True)
class _SegmentArrays:
    """One segment's slices of the path, for :meth:`ReferencePath.horizon`."""

    s: FloatArray  # m, arc length of the segment's waypoints
    time: FloatArray  # s, planned time at them
    speed: FloatArray  # m/s, signed reference speed at them
    coefs: FloatArray  # (4, 3, intervals): cubic coefficients, power first
    starts: FloatArray  # m, ``s`` without the last waypoint: where each interval starts
    s_list: list[float]  # ``s``, ``time`` and ``speed`` as Python floats, for the scalar
    time_list: list[float]  # interpolation
    speed_list: list[float]


class ReferencePath:
    """A validated trajectory prepared for fast per-cycle queries.

    Built once per trajectory object: arc length, unwrapped heading, direction segments, the
    cubic interpolation denominators and the planned time to reach each waypoint.

    The reference speed is the plan's, within two ceilings: it needs no more than
    ``STOP_DECEL`` of braking to stop at a segment's end or its stop point (:attr:`stops`), nor
    to slow to ``TIGHT_TURN_SPEED`` where the plan turns tighter than ``min_turn_radius`` (a
    turn the car cannot follow is approached and driven slowly, never at the plan's speed).
    Past a stop point the reference is at rest, and its planned time does not come: the
    horizon's points wait on the stop point.

    :param traj: the trajectory (validated by the caller)
    :param creep_speed: m/s, the slowest speed assumed when placing horizon points, so that a
        profile starting at rest still reaches ahead
    :param min_turn_radius: m, the car's tightest turn (:func:`turn_radius`); 0: none is too
        tight
    """

    CHORD_WALK = 64  # chords a projection walks at most from its waypoint (:meth:`chord`)

    def __init__(
        self, traj: Trajectory, creep_speed: float = 0.3, min_turn_radius: float = 0.0
    ) -> None:
        self.traj = traj
        n = len(traj)
        self.n = n
        gaps = np.hypot(np.diff(traj.x), np.diff(traj.y))
        self.s = np.concatenate(([0.0], np.cumsum(gaps)))  # m, arc length of each waypoint
        self.segments = split_segments(traj)
        heading = np.unwrap(traj.heading)
        # signed speed clipped to each segment's direction, zero at each segment's end and at
        # its start after a cusp (the two share that waypoint)
        speed = np.zeros(n)
        # s, planned time from the trajectory's start. Cumulative over the segments so that it
        # increases strictly within each one: consecutive segments share their cusp waypoint,
        # and restarting the clock there would break the previous segment's time axis.
        time = np.zeros(n)
        self.stops: dict[Segment, float] = {}  # m, arc length of a segment's stop point
        for seg in self.segments:
            sl = slice(seg.start, seg.end + 1)
            mag = np.maximum(seg.direction * traj.speed[sl], 0.0)
            stop = stop_point(mag)
            if stop is not None:  # the plan stands from there on: so does the reference
                mag[stop:] = 0.0
                self.stops[seg] = float(self.s[seg.start + stop])
            # no faster than a stop at ``STOP_DECEL`` reaches the segment's end or its stop
            # point (zero there): a plan that keeps its speed up to a cusp or its goal is
            # slowed in time
            to_end = np.maximum(self.stops.get(seg, self.s[seg.end]) - self.s[sl], 0.0)
            np.minimum(mag, np.sqrt(2.0 * STOP_DECEL * to_end), out=mag)
            if min_turn_radius > 0.0:  # slowed in time before a turn the car cannot follow
                ceiling = tight_turn_ceiling(self.s[sl], heading[sl], min_turn_radius)
                if ceiling is not None:
                    np.minimum(mag, ceiling, out=mag)
            mag[-1] = 0.0
            if seg.start > 0:  # a cusp: the car stands there, also as the next segment starts
                mag[0] = 0.0
            speed[sl] = seg.direction * mag
            interval = np.diff(self.s[sl]) / np.maximum(0.5 * (mag[1:] + mag[:-1]), creep_speed)
            if stop is not None:  # past a stop point the plan's time does not come: the
                interval[stop] += STOP_WAIT  # horizon's reference points wait on it
            time[seg.start + 1 : seg.end + 1] = time[seg.start] + np.cumsum(interval)
        self.speed = speed
        self.time = time
        self.values = np.column_stack((traj.x, traj.y, heading))  # (n, 3)
        self._coefs: dict[tuple[int, int], FloatArray] = {}
        # the per-tick scalar queries (nearest waypoint, projection) run on Python floats:
        # indexing numpy arrays element by element costs more than the arithmetic
        self._x: list[float] = traj.x.tolist()
        self._y: list[float] = traj.y.tolist()
        self._s: list[float] = self.s.tolist()
        self._horizon_cache: dict[tuple[int, int], _SegmentArrays] = {}

    # --- queries ---

    def project(self, seg: Segment, index: int, x: float, y: float) -> float:
        """Arc length of the point's projection on the chords around waypoint ``index``."""
        s = self._s
        i, t = self.chord(seg, index, x, y)
        t = min(max(t, 0.0), 1.0)
        return s[i] + t * (s[i + 1] - s[i])

    def chord(self, seg: Segment, index: int, x: float, y: float) -> tuple[int, float]:
        """The chord ``i → i + 1`` the point projects on, found from waypoint ``index``, and
        the (unclamped) fraction ``t`` along it.

        From the chord after ``index``: the chords before it while the point lies behind
        (``t < 0``), or the chords after it while the point lies beyond (``t > 1``), within
        the segment. One direction only: outside a corner, where the point lies beyond one
        chord and behind the next, the walk ends on the next (its start, the corner, is the
        nearest point). The walk matters for a point some way from ``index``: the pose
        predicted over the dead time is 0.2 m ahead at 2 m/s, several chords of a dense plan.
        It takes at most :attr:`CHORD_WALK` chords (a bounded loop on the control path); past
        them the fraction stays beyond the last chord tried, and the caller clamps it.
        """
        tx, ty = self._x, self._y

        def fraction(i: int) -> float:
            dx, dy = tx[i + 1] - tx[i], ty[i + 1] - ty[i]
            return ((x - tx[i]) * dx + (y - ty[i]) * dy) / (dx * dx + dy * dy)

        i = min(max(index, seg.start), seg.end - 1)
        t = fraction(i)
        if t < 0.0:
            for _ in range(self.CHORD_WALK):
                if t >= 0.0 or i <= seg.start:
                    break
                i -= 1
                t = fraction(i)
        else:
            for _ in range(self.CHORD_WALK):
                if t <= 1.0 or i >= seg.end - 1:
                    break
                i += 1
                t = fraction(i)
        return i, t

    def horizon(
        self, seg: Segment, s0: float, steps: FloatArray, reach: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """The horizon's reference in one call: :meth:`horizon_arclength`, :meth:`sample` at
        ``s0`` and those arc lengths, and :meth:`reference_speed` there (the same values).

        :param s0: m, arc length of the vehicle's projection, inside the segment
        :param reach: m, the farthest the car can get from ``s0`` by each horizon step (its
            speed and acceleration limit); a plan faster than that is placed no farther. None:
            where the plan's time puts them.
        :returns: rows ``x, y, heading`` at ``s0`` and at the ``len(steps)`` horizon points,
            shape (3, len(steps) + 1) — the transpose of :meth:`sample`'s — and the signed
            reference speed at the horizon points
        """
        arrays = self._arrays(seg)
        s_seg, t_seg = arrays.s, arrays.time
        sq = np.empty(steps.shape[0] + 1)
        sq[0] = s0
        # within the segment already (projection and interpolation both clamp): no clipping
        t0 = _interp_scalar(s0, arrays.s_list, arrays.time_list)
        sq[1:] = _interp(t0 + steps, t_seg, s_seg)
        if reach is not None:  # a view: capped in place
            np.minimum(sq[1:], reach + s0, out=sq[1:])
        # interval i: s_i ≤ s < s_{i+1}, the last one also for s at the segment's end (the
        # search over the interval starts only caps i there without an extra call)
        i = np.searchsorted(arrays.starts, sq, side="right")
        i -= 1
        ds = sq - s_seg[i]
        c = arrays.coefs.take(i, axis=2)  # (4, 3, q): contiguous rows, cheap to broadcast
        # Horner, ((c₃ ds + c₂) ds + c₁) ds + c₀, in place: no temporaries
        pts = c[3] * ds
        pts += c[2]
        pts *= ds
        pts += c[1]
        pts *= ds
        pts += c[0]
        return pts, _interp(sq[1:], s_seg, arrays.speed)

    def speed_at(self, seg: Segment, s: float) -> float:
        """The signed reference speed at arc length ``s`` of ``seg`` (clamped to it), m/s:
        linear in s, as :meth:`horizon`'s."""
        arrays = self._arrays(seg)
        return _interp_scalar(s, arrays.s_list, arrays.speed_list)

    def _arrays(self, seg: Segment) -> _SegmentArrays:
        """The segment's slices, made once per segment."""
        arrays = self._horizon_cache.get((seg.start, seg.end))
        if arrays is None:
            arrays = self._horizon_cache[(seg.start, seg.end)] = self._segment_arrays(seg)
        return arrays

    def _segment_arrays(self, seg: Segment) -> _SegmentArrays:
        coefs = self._coefs.get((seg.start, seg.end))
        if coefs is None:
            coefs = self._coefs[(seg.start, seg.end)] = self._cubic_coefficients(seg)
        sl = slice(seg.start, seg.end + 1)
        return _SegmentArrays(
            self.s[sl],
            self.time[sl],
            self.speed[sl],
            np.ascontiguousarray(coefs.transpose(1, 2, 0)),
            self.s[seg.start : seg.end],
            self._s[sl],
            self.time[sl].tolist(),
            self.speed[sl].tolist(),
        )

    def _cubic_coefficients(self, seg: Segment) -> FloatArray:
        """Per waypoint interval of ``seg``: the cubic through four waypoints, one behind and
        three ahead (fewer in a short segment), as coefficients in ``s − s_i``.

        :returns: (intervals, 4, 3) — powers 0…3 for x, y and heading
        """
        k = min(4, seg.end - seg.start + 1)
        i = np.arange(seg.start, seg.end)  # interval i runs from waypoint i to i + 1
        w = np.clip(i - 1, seg.start, seg.end - k + 1)  # window kept inside the segment
        idx = w[:, None] + np.arange(k)[None, :]
        rel = self.s[idx] - self.s[i][:, None]  # knots relative to the interval start
        vander = rel[:, :, None] ** np.arange(k)[None, None, :]  # (intervals, k, k)
        coefs = np.zeros((len(i), 4, 3))
        coefs[:, :k, :] = np.linalg.solve(vander, self.values[idx])
        return coefs

    def sample(self, seg: Segment, s_query: FloatArray) -> FloatArray:
        """Cubic (four-waypoint) interpolation of ``[x, y, heading]`` at arc lengths ``s_query``.

        Within the segment only (never across a cusp); shorter segments use fewer waypoints.

        :returns: array of shape (len(s_query), 3)
        """
        coefs = self._coefs.get((seg.start, seg.end))
        if coefs is None:
            coefs = self._coefs[(seg.start, seg.end)] = self._cubic_coefficients(seg)
        s = self.s
        sq = np.minimum(np.maximum(s_query, s[seg.start]), s[seg.end])
        i = np.minimum(np.maximum(np.searchsorted(s, sq, side="right") - 1, seg.start), seg.end - 1)
        ds = (sq - s[i])[:, None]
        c = coefs[i - seg.start]  # (q, 4, 3)
        return ((c[:, 3] * ds + c[:, 2]) * ds + c[:, 1]) * ds + c[:, 0]  # Horner

    def reference_speed(self, s_query: FloatArray) -> FloatArray:
        """Signed reference speed at arc lengths ``s_query`` (linear in s)."""
        return np.interp(s_query, self.s, self.speed)

    def speed_and_slope(self, seg: Segment, s: float) -> tuple[float, float]:
        """The planned speed magnitude at arc length ``s`` on ``seg`` (m/s), as
        :meth:`reference_speed` gives it, and its slope along the direction of travel,
        d|v|/ds (1/s).

        The speed is linear in ``s`` between waypoints, so the slope is that of the chord the
        car is on (the one ahead, on a waypoint), and ``s`` is held to the segment.
        """
        j = int(np.searchsorted(self.s, s, side="right")) - 1
        j = min(max(j, seg.start), seg.end - 1)
        s_j, s_k = float(self.s[j]), float(self.s[j + 1])
        v_j = seg.direction * float(self.speed[j])
        v_k = seg.direction * float(self.speed[j + 1])
        slope = (v_k - v_j) / (s_k - s_j) if s_k > s_j else 0.0
        t = min(max(s - s_j, 0.0), s_k - s_j)
        return max(v_j + slope * t, 0.0), slope

    def horizon_arclength(self, seg: Segment, s0: float, steps: FloatArray) -> FloatArray:
        """Arc lengths reached at times ``steps`` (s) after ``s0`` along the planned profile.

        Clamped to the segment's end: beyond it the reference waits on the stop point.
        """
        sl = slice(seg.start, seg.end + 1)
        s_seg = self.s[sl]
        t_seg = self.time[sl]
        t0 = float(np.interp(s0, s_seg, t_seg))
        return np.interp(t0 + steps, t_seg, s_seg)


def _interp_scalar(x: float, xp: list[float], fp: list[float]) -> float:
    """``np.interp(x, xp, fp)`` for one finite ``x``, on Python floats.

    The same operations in the same order as numpy's C loop (so the same bits), without the
    call overhead of ``np.interp`` for a single value (once per control tick).
    """
    j = bisect.bisect_right(xp, x) - 1  # xp[j] ≤ x < xp[j + 1]
    if j < 0:
        return fp[0]
    if j >= len(xp) - 1:
        return fp[-1]
    if xp[j] == x:
        return fp[j]
    return (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) * (x - xp[j]) + fp[j]


# --- progress along the plan ------------------------------------------------------------------


class Progress:
    """Where the car is along a plan: the current direction segment and how far along it.

    One implementation for every controller (MPC, Pure Pursuit, Stanley). *Progress* is the arc
    length reached on the current segment: monotone (it never goes back), bounded to the
    segment, and found by a nearest-waypoint search windowed around it — the search starts at
    the waypoint just behind the progress, never in an earlier segment, and stops once the path
    has led more than :attr:`BASIN` metres farther from the car than the best waypoint found.
    So a path that comes back to the same place later (a figure-eight's crossing, a closed
    loop's end on its start, a U-turn's return leg, the reverse leg of a cusp retracing the
    forward one) is not taken for where the car is now: to get there, the path must first lead
    away from the car.

    A segment *ends* only by progress: the car has reached the segment's last chord and is level
    with or beyond its end point (:attr:`beyond` ≥ 0), or has come within ``goal_tolerance`` of
    the end with the progress there (:meth:`at_end`).

    On a new plan the car starts from :func:`start_waypoint` on the first segment: the pass
    nearest in progress to the plan's start, not merely the nearest in space. A closed loop
    starts at its start, not at its end, and a car engaged beside a figure-eight's crossing
    starts on the first pass through it, not the later one.

    A plan that continues the previous one (a planner's rolling window re-sent with the same
    waypoints over the overlap) keeps the progress, mapped onto the new plan
    (:meth:`continued_on`): the segment the car is on and how far along it.

    :param path: the plan
    :param window: waypoints examined ahead of the progress per update
    """

    BASIN = 2.0  # m, the search stops once the path is this much farther than the best point
    MATCH_HEADING = 0.01  # rad, a continued plan's waypoints match the previous plan's this well
    RESUME_DISTANCE = 0.1  # m, a re-sampled plan passes this close to the previous progress
    RESUME_HEADING = 0.2  # rad, and heads the same way there within this
    RESUME_TIE = 0.01  # m, passes this much farther than the nearest count as near

    def __init__(self, path: ReferencePath, window: int) -> None:
        self.path = path
        self.window = window
        self.seg_index = 0
        self.index = path.segments[0].start  # the waypoint nearest the car (diagnostic)
        self.s = float(path.s[path.segments[0].start])  # m, progress on the current segment
        self.beyond = -math.inf  # m, along-track distance past the segment's end (< 0: before)
        self.deviation = math.nan  # m, the car's distance from its projection (NaN: none yet)
        self._started = False

    @property
    def segment(self) -> Segment:
        return self.path.segments[self.seg_index]

    @property
    def route_length(self) -> float:
        """Total arc length of the plan, m."""
        return float(self.path.s[-1])

    def next_segment(self) -> bool:
        """Move on to the next segment (after a cusp); False when this was the last one."""
        if self.seg_index + 1 >= len(self.path.segments):
            return False
        self.seg_index += 1
        seg = self.segment
        self.index = seg.start
        self.s = float(self.path.s[seg.start])
        self.beyond = -math.inf
        return True

    def to_end(self, x: float, y: float) -> float:
        """Distance from ``(x, y)`` to the current segment's end point, m."""
        end = self.segment.end
        return math.hypot(self.path._x[end] - x, self.path._y[end] - y)

    def at_end(self, x: float, y: float, tolerance: float) -> bool:
        """The progress has reached the segment's end and the car is within ``tolerance`` of it."""
        seg_end = float(self.path.s[self.segment.end])
        return self.s >= seg_end - tolerance and self.to_end(x, y) <= tolerance

    @property
    def passed(self) -> bool:
        """The progress has reached the segment's end: level with or beyond its end point."""
        return self.beyond >= 0.0

    def ended(self, x: float, y: float, tolerance: float) -> bool:
        """Whether a car at rest at ``(x, y)`` has finished the current segment.

        By progress and within ``tolerance`` of the end (:meth:`at_end`); a segment before a
        cusp also ends with a stop past its end, or with the progress within ``tolerance`` of
        the end however far aside the car stopped (the next segment corrects what is left).
        """
        if self.at_end(x, y, tolerance):
            return True
        if self.seg_index + 1 == len(self.path.segments):
            return False
        return self.passed or self.s >= float(self.path.s[self.segment.end]) - tolerance

    def update(self, x: float, y: float, heading: float) -> float:
        """Advance the progress to the car at ``(x, y)``; the arc length of its projection, m.

        The projection (on the chords around the nearest waypoint, clamped to the segment) may
        lie slightly behind the progress — it is the reference for this tick — while the
        progress itself only grows.
        """
        path, seg = self.path, self.segment
        tx, ty, s = path._x, path._y, path._s
        if not self._started:
            self._started = True
            i = self._first_nearest(seg, x, y, heading)
        else:
            # the waypoint at or just behind the progress, never before the segment's start
            lo = max(bisect.bisect_right(s, self.s, seg.start, seg.end + 1) - 1, seg.start)
            hi = min(lo + self.window, seg.end + 1)
            i, best = lo, math.inf
            for k in range(lo, hi):
                dx, dy = tx[k] - x, ty[k] - y
                d = math.sqrt(dx * dx + dy * dy)
                if d < best:
                    i, best = k, d
                elif d > best + self.BASIN:
                    break  # the path leads away: a later pass is not where the car is
        self.index = i
        j, t = path.chord(seg, i, x, y)  # the chord before or after the nearest waypoint
        chord = s[j + 1] - s[j]
        if j == seg.end - 1:
            self.beyond = (t - 1.0) * chord  # on the last chord: past the end when ≥ 0
        t = min(max(t, 0.0), 1.0)
        s0 = s[j] + t * chord
        self.deviation = math.hypot(
            x - (tx[j] + t * (tx[j + 1] - tx[j])), y - (ty[j] + t * (ty[j + 1] - ty[j]))
        )
        if s0 > self.s:
            self.s = s0
        return s0

    def continued_on(self, path: ReferencePath) -> Progress | None:
        """This progress carried over to ``path`` when that plan continues this one, else None.

        ``path`` continues the plan when its first waypoint is one of this plan's, from which on
        the two agree waypoint by waypoint (within :data:`OVERLAP_DISTANCE` and
        :attr:`MATCH_HEADING`, in the same driving direction) for as long as both last, and the
        car's progress lies inside that overlap. The carried progress is on the new plan's
        segment of the same direction there, at the same place: a rolling window re-sent while
        the car stands at a cusp does not start the cusp over.
        """
        if not self._started:
            return None
        old, new = self.path.traj, path.traj
        seg = self.segment
        near = np.hypot(old.x - new.x[0], old.y - new.y[0]) < OVERLAP_DISTANCE
        old_dirs, new_dirs = directions(self.path.traj), directions(path.traj)
        for j in np.flatnonzero(near).tolist():
            m = min(len(old) - j, len(new))
            if m < 2 or not (self.path.s[j] <= self.s <= self.path.s[j + m - 1]):
                continue
            if not self._same_points(path, j, m, old_dirs, new_dirs):
                continue
            s = self.s - float(self.path.s[j])  # the same place, in the new plan's arc length
            for k, new_seg in enumerate(path.segments):
                inside = path.s[new_seg.start] - 1e-9 <= s <= path.s[new_seg.end] + 1e-9
                if new_seg.direction == seg.direction and inside:
                    carried = Progress(path, self.window)
                    carried.seg_index = k
                    carried.s = min(
                        max(s, float(path.s[new_seg.start])), float(path.s[new_seg.end])
                    )
                    carried.index = min(max(self.index - j, new_seg.start), new_seg.end)
                    carried._started = True
                    return carried
        return None

    def resumed_on(self, path: ReferencePath) -> Progress | None:
        """This progress carried over to ``path`` when that plan runs through the place the
        progress has reached, in the same direction, without sharing its waypoints; else None.

        A planner re-samples its path on every cycle (Autoware's keeps a few metres behind the
        car, at new points each time): :meth:`continued_on` finds no common waypoint, and a
        plan taken as new restarts on its first segment. At a cusp that segment is the one the
        car has just finished, and each new plan sent it back to the stop, its brake hold and
        its wheel alignment: the car never drove off. Here the progress's point on the old plan
        is looked up on the new one: on a segment of the same direction that passes within
        :attr:`RESUME_DISTANCE` of it, heading within :attr:`RESUME_HEADING`: the nearest
        such pass, and of passes as near the first (a closed loop's end lies on its start, and
        is not where the car is; a parking maneuver's two reverse moves lie side by side, and
        the nearer is).
        """
        if not self._started:
            return None
        old, seg = self.path, self.segment
        j = min(max(bisect.bisect_right(old._s, self.s) - 1, seg.start), seg.end - 1)
        chord = old._s[j + 1] - old._s[j]
        t = (self.s - old._s[j]) / chord if chord > 0.0 else 0.0
        px = old._x[j] + t * (old._x[j + 1] - old._x[j])
        py = old._y[j] + t * (old._y[j + 1] - old._y[j])
        heading = float(old.values[j, 2])
        passes: list[tuple[float, int, int, float]] = []  # distance, segment, chord, fraction
        for k, new_seg in enumerate(path.segments):
            if new_seg.direction != seg.direction:
                continue
            a, b = new_seg.start, new_seg.end
            ax, ay = path.traj.x[a:b], path.traj.y[a:b]
            dx, dy = path.traj.x[a + 1 : b + 1] - ax, path.traj.y[a + 1 : b + 1] - ay
            u = np.clip(
                ((px - ax) * dx + (py - ay) * dy) / np.maximum(dx * dx + dy * dy, 1e-12), 0.0, 1.0
            )
            dist = np.hypot(px - ax - u * dx, py - ay - u * dy)
            turn = np.abs(np.angle(np.exp(1j * (path.values[a:b, 2] - heading))))
            near = (dist <= self.RESUME_DISTANCE) & (turn <= self.RESUME_HEADING)
            # each run of near chords is one pass of the plan by the point: its nearest chord
            starts = np.flatnonzero(near & ~np.r_[False, near[:-1]])
            ends = np.flatnonzero(near & ~np.r_[near[1:], False]) + 1
            for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
                i = lo + int(np.argmin(dist[lo:hi]))
                passes.append((float(dist[i]), k, a + i, float(u[i])))
        if not passes:
            return None
        # the nearest pass; of passes as near (a closed loop's end lies on its start), the first
        nearest = min(d for d, _, _, _ in passes)
        _, k, i, frac = next(p for p in passes if p[0] <= nearest + self.RESUME_TIE)
        resumed = Progress(path, self.window)
        resumed.seg_index = k
        resumed.s = float(path.s[i] + frac * (path.s[i + 1] - path.s[i]))
        resumed.index = i
        resumed._started = True
        return resumed

    def _same_points(
        self, path: ReferencePath, j: int, m: int, old_dirs: FloatArray, new_dirs: FloatArray
    ) -> bool:
        """Waypoints ``j … j + m − 1`` of this plan are waypoints ``0 … m − 1`` of ``path``."""
        old, new = self.path.traj, path.traj
        sl = slice(j, j + m)
        close = np.hypot(old.x[sl] - new.x[:m], old.y[sl] - new.y[:m]) < OVERLAP_DISTANCE
        turn = np.abs(np.angle(np.exp(1j * (old.heading[sl] - new.heading[:m]))))
        # each waypoint interval is driven the way its end point's speed says (Segment)
        same_way = old_dirs[j + 1 : j + m] == new_dirs[1:m]
        return bool(close.all() and (turn < self.MATCH_HEADING).all() and same_way.all())

    def fields(self, finished: bool) -> dict[str, Any]:
        """The :class:`~leafgate.messages.ControlOutput` fields of the progress:
        ``nearest_index``, ``progress`` (the route length once finished), ``route_length`` and
        ``deviation``; and ``stop_distance`` while the segment has a stop point."""
        length = self.route_length
        fields = {
            "nearest_index": self.index,
            "progress": length if finished else self.s,
            "route_length": length,
            "deviation": self.deviation,
        }
        stop = self.path.stops.get(self.segment)
        if stop is not None and not finished:
            fields["stop_distance"] = stop - self.s
        return fields

    def _first_nearest(self, seg: Segment, x: float, y: float, heading: float) -> int:
        """The waypoint of ``seg`` the car starts from on a new plan (see the class notes)."""
        return start_waypoint(self.path.traj, seg, x, y, heading)


START_TIE = 0.5  # m, the earliest waypoint this close to the nearest distance is the start
START_REACH = 1.5  # m, the earliest waypoint this close to the car is the start (the engage
# envelope is 1 m from the path: a car engaged there is on the earliest pass within reach)


def start_waypoint(traj: Trajectory, seg: Segment, x: float, y: float, heading: float) -> int:
    """The waypoint of ``seg`` a car at ``(x, y)``, heading ``heading`` (rad), starts from on a
    new plan: the one rule for where a drive starts on a route, the controller's
    (:class:`Progress`) and the simulator's metrics'.

    Of the waypoints whose heading is within 90° of the car's, the earliest one within
    :data:`START_REACH` m of the car (or within :data:`START_TIE` m of the nearest distance,
    when none is that close), moved on to the nearest of its neighbourhood: the pass nearest in
    progress to the segment's start, not merely the nearest in space.
    """
    sl = slice(seg.start, seg.end + 1)
    d = np.hypot(traj.x[sl] - x, traj.y[sl] - y)
    aligned = np.cos(traj.heading[sl] - heading) > 0.0
    if aligned.any():
        d = np.where(aligned, d, np.inf)
    best = float(d.min())
    k = int(np.argmax(d <= max(best + START_TIE, START_REACH)))
    while k + 1 < d.shape[0] and d[k + 1] < d[k]:
        k += 1  # down to the bottom of that waypoint's basin
    return seg.start + k


class _PathLimits(Protocol):
    """What :meth:`PathRules.of` reads of a controller's config."""

    @property
    def creep_speed(self) -> float: ...
    @property
    def steer_max(self) -> float: ...


@dataclass(frozen=True, slots=True)
class PathRules:
    """What a controller's :class:`ReferencePath` is built with (its ``creep_speed`` and
    ``min_turn_radius``): one value, so that a path built where a plan arrives
    (:func:`prebuild`) is taken only by a controller that would build the same."""

    creep_speed: float = 0.3  # m/s
    min_turn_radius: float = 0.0  # m, the car's tightest turn; 0: none is too tight

    @classmethod
    def of(cls, cfg: _PathLimits, wheelbase: float) -> PathRules:
        """The rules of a controller with config ``cfg`` (``controller.<kind>``) on a car with
        ``wheelbase`` (m): its creep speed, and the turn it makes at ``steer_max``."""
        return cls(cfg.creep_speed, turn_radius(wheelbase, cfg.steer_max))

    def build(self, trajectory: Trajectory) -> ReferencePath:
        """The reference path of a usable ``trajectory`` (overlapping points removed)."""
        return ReferencePath(
            remove_overlap_points(trajectory), self.creep_speed, self.min_turn_radius
        )


def prepare_plan(
    trajectory: Trajectory, rules: PathRules, window: int, previous: Progress | None = None
) -> tuple[ReferencePath | None, Progress | None, str]:
    """A controller's view of a new plan: the path without overlapping points, its progress
    tracker and ``""``; or ``None, None`` and why the plan cannot be driven
    (:func:`trajectory_problem`).

    :param previous: the progress on the plan driven so far; carried over when the new plan
        continues it (:meth:`Progress.continued_on`), else the new plan starts afresh
    """
    built = _prebuilt(trajectory, rules)  # built where the plan arrived: see prebuild
    if built is not None:
        prebuilt, why = built
        if prebuilt is None:
            return None, None, why
        path = prebuilt
    else:
        problem = trajectory_problem(trajectory)
        if problem is not None:
            return None, None, problem
        path = rules.build(trajectory)
    carried = None
    if previous is not None:
        carried = previous.continued_on(path) or previous.resumed_on(path)
    return path, carried or Progress(path, window), ""


# --- built off the control thread (issue 17, finding 5) --------------------------------------
# A new plan's reference path takes milliseconds to build (1.8 ms for 2000 points); built in the
# controller's first step it delays a control tick. The gateway's transport therefore builds it
# where the plan arrives (on Zenoh's thread: GatewayTransport.on_plan) and leaves it here, keyed
# by the trajectory object; prepare_plan takes it instead of building one. A plan nobody built
# beforehand is built by prepare_plan as before. Bounded: only the newest few plans are kept.

PREBUILT_PLANS = 4  # plans whose reference is kept for the controller

_prebuilt_plans: collections.deque[
    tuple[weakref.ref[Trajectory], PathRules, ReferencePath | None, str]
]
_prebuilt_plans = collections.deque(maxlen=PREBUILT_PLANS)
_prebuilt_lock = threading.Lock()
_HORIZON_PROBE = np.zeros(1)  # one horizon point: enough to build a segment's interpolation


def prebuild(trajectory: Trajectory, rules: PathRules) -> None:
    """Build ``trajectory``'s reference path now, on the caller's thread, for the controller.

    Also builds each segment's interpolation tables (else built by the first horizon query).

    :param rules: the controller's (:meth:`PathRules.of` its config): a path is taken only by
        a controller with the same rules
    """
    problem = trajectory_problem(trajectory)
    path = None
    if problem is None:
        path = rules.build(trajectory)
        for seg in path.segments:
            path.horizon(seg, float(path.s[seg.start]), _HORIZON_PROBE)
    with _prebuilt_lock:
        _prebuilt_plans.append((weakref.ref(trajectory), rules, path, problem or ""))


def _prebuilt(trajectory: Trajectory, rules: PathRules) -> tuple[ReferencePath | None, str] | None:
    with _prebuilt_lock:
        for ref, built_with, path, problem in reversed(_prebuilt_plans):
            if ref() is trajectory and built_with == rules:
                return path, problem
    return None
