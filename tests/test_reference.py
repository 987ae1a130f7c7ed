"""Trajectory files, validation, the nearest-point search, segments and cubic resampling."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from leafgate.control.reference import (
    STOP_DECEL,
    TIGHT_TURN_SPEED,
    TURN_WINDOW,
    Progress,
    ReferencePath,
    _interp_scalar,
    chord_directions,
    load_trajectory,
    split_segments,
    tightest_turn,
    turn_radius,
    validate,
)
from leafgate.errors import TrajectoryError
from leafgate.messages import Trajectory
from tests import routes

GOOD_ROWS = [(0.5 * i, 0.0, 0.0, 1.0) for i in range(8)]


def _write_csv(path: Path, rows: list[tuple], header: str = "x,y,heading,speed") -> Path:
    lines = [header] + [",".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _line(n: int = 20, spacing: float = 0.5, speed: float = 1.0) -> Trajectory:
    s = spacing * np.arange(n)
    return Trajectory(x=s, y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, speed))


# --- loading ---


def test_csv_loads_in_any_column_order(tmp_path: Path) -> None:
    rows = [(r[3], r[2], r[1], r[0]) for r in GOOD_ROWS]
    traj = load_trajectory(_write_csv(tmp_path / "t.csv", rows, "speed,heading,y,x"))
    np.testing.assert_allclose(traj.x, [r[0] for r in GOOD_ROWS])
    np.testing.assert_allclose(traj.speed, 1.0)


def test_yaml_list_and_yaml_columns_load_the_same(tmp_path: Path) -> None:
    as_list = [dict(zip(("x", "y", "heading", "speed"), r, strict=True)) for r in GOOD_ROWS]
    as_columns = {
        k: [r[i] for r in GOOD_ROWS] for i, k in enumerate(("x", "y", "heading", "speed"))
    }
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(as_list))
    (tmp_path / "b.yml").write_text(yaml.safe_dump(as_columns))
    a = load_trajectory(tmp_path / "a.yaml")
    b = load_trajectory(tmp_path / "b.yml")
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.heading, b.heading)


@pytest.mark.parametrize(
    ("header", "rows", "message"),
    [
        (
            "x,y,heading,speed,curvature",
            [(*r, 0.0) for r in GOOD_ROWS],
            "unknown column(s) 'curvature'",
        ),
        ("x,y,heading", [r[:3] for r in GOOD_ROWS], "missing column(s) speed"),
        ("0,0,0,1", GOOD_ROWS, "no header"),
    ],
)
def test_csv_header_problems_are_named(
    tmp_path: Path, header: str, rows: list[tuple], message: str
) -> None:
    path = _write_csv(tmp_path / "traj.csv", rows, header)
    with pytest.raises(TrajectoryError, match=r"traj\.csv") as info:
        load_trajectory(path)
    assert message in str(info.value)


@pytest.mark.parametrize(
    ("row", "bad", "message"),
    [
        (7, (3.0, 0.0, "nan", 1.0), "row 7: heading is not finite"),
        (3, (1.0, "inf", 0.0, 1.0), "row 3: y is not finite"),
        (5, (2.0, 0.0, 0.0, "fast"), "row 5: speed is not a number"),
        (2, (0.5, 0.0, 0.0), "row 2: 3 values"),
    ],
)
def test_bad_rows_are_named(tmp_path: Path, row: int, bad: tuple, message: str) -> None:
    rows: list[tuple] = list(GOOD_ROWS)
    rows[row - 1] = bad
    path = _write_csv(tmp_path / "traj.csv", rows)
    with pytest.raises(TrajectoryError) as info:
        load_trajectory(path)
    assert str(info.value).startswith("traj.csv") or "traj.csv: " in str(info.value)
    assert message in str(info.value)


def test_too_few_waypoints(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "short.csv", GOOD_ROWS[:3])
    with pytest.raises(TrajectoryError, match=r"short.csv: 3 waypoint\(s\), at least 4"):
        load_trajectory(path)


def test_yaml_problems_are_named(tmp_path: Path) -> None:
    (tmp_path / "ragged.yaml").write_text(
        yaml.safe_dump({"x": [0, 1, 2, 3], "y": [0, 0, 0], "heading": [0] * 4, "speed": [1] * 4})
    )
    with pytest.raises(TrajectoryError, match=r"ragged\.yaml: the lists differ in length"):
        load_trajectory(tmp_path / "ragged.yaml")
    (tmp_path / "extra.yaml").write_text(
        yaml.safe_dump([{"x": 0, "y": 0, "heading": 0, "speed": 1, "t": 0}] * 4)
    )
    with pytest.raises(TrajectoryError, match=r"extra.yaml: row 1: unknown column\(s\) 't'"):
        load_trajectory(tmp_path / "extra.yaml")


def test_unknown_format_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match="no such file"):
        load_trajectory(tmp_path / "nope.csv")
    (tmp_path / "t.json").write_text("[]")
    with pytest.raises(TrajectoryError, match="unknown trajectory format"):
        load_trajectory(tmp_path / "t.json")


def test_spacing_is_reported() -> None:
    x = np.array([0.0, 0.5, 1.5, 2.0, 2.7])
    traj = Trajectory(x=x, y=np.zeros(5), heading=np.zeros(5), speed=np.ones(5))
    spacing = validate(traj, "t")
    assert (spacing.min, spacing.median, spacing.max) == pytest.approx((0.5, 0.6, 1.0))


# --- nearest point ---


# --- segments and resampling ---


def _back_and_forth(speed: list[float]) -> Trajectory:
    """Waypoints on the x axis, heading +x, each 1 m from the last in the direction its speed
    (or, at rest, the motion it ends) drives: a plan whose geometry agrees with its speeds."""
    x, d = [0.0], 1.0
    for v in speed[1:]:
        d = math.copysign(1.0, v) if v else d
        x.append(x[-1] + d)
    n = len(speed)
    return Trajectory(np.array(x), np.zeros(n), np.zeros(n), np.array(speed))


def test_cusps_split_into_direction_segments() -> None:
    segs = split_segments(_back_and_forth([0.0, 1.0, 1.0, 0.0, -1.0, -1.0, 0.0]))
    assert [(s.start, s.end, s.direction) for s in segs] == [(0, 3, 1), (3, 6, -1)]
    segs = split_segments(_back_and_forth([1.0, 1.0, -1.0, -1.0, 2.0, 2.0]))
    assert [(s.start, s.end, s.direction) for s in segs] == [(0, 1, 1), (1, 3, -1), (3, 5, 1)]


def test_a_cusp_without_a_waypoint_at_rest_is_placed_by_the_geometry() -> None:
    """PythonRobotics' courses give each waypoint the speed of the chord that leaves it: the
    chord into the cusp still carries the forward sign at its start, the reverse one at its end.
    The cusp is where the car turns back, the chord's far end, not its start (there the car
    would have to reverse to a point ahead of it, and made no progress)."""
    x = np.array([0.0, 1.0, 2.0, 3.0, 2.0, 1.0])  # forward to x = 3, then back
    n = len(x)
    speed = np.array([1.0, 1.0, 1.0, -1.0, -1.0, 0.0])  # the sign of the chord leaving each
    traj = Trajectory(x, np.zeros(n), np.zeros(n), speed)
    assert chord_directions(traj).tolist() == [1.0, 1.0, 1.0, -1.0, -1.0]
    segs = split_segments(traj)
    assert [(s.start, s.end, s.direction) for s in segs] == [(0, 3, 1), (3, 5, -1)]
    # the same speeds on a plan whose chord at the flip runs backward: the cusp is its start
    x2 = np.array([0.0, 1.0, 2.0, 1.0, 0.0, -1.0])
    segs = split_segments(Trajectory(x2, np.zeros(n), np.zeros(n), speed))
    assert [(s.start, s.end, s.direction) for s in segs] == [(0, 2, 1), (2, 5, -1)]


def test_cubic_resampling_reproduces_a_cubic_path() -> None:
    """Four-point cubic interpolation is exact for a cubic y(x) parametrised by arc length."""
    s = np.linspace(0.0, 6.0, 13)  # pretend arc length (x) with y, heading as cubics of it
    traj = Trajectory(x=s, y=0.01 * s**3 - 0.05 * s, heading=0.02 * s**2, speed=np.ones_like(s))
    path = ReferencePath(traj)
    path.s = s.copy()  # use x as the parameter so the cubic is exact
    path._coefs.clear()
    seg = path.segments[0]
    q = np.linspace(0.0, 6.0, 37)
    out = path.sample(seg, q)
    np.testing.assert_allclose(out[:, 0], q, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], 0.01 * q**3 - 0.05 * q, atol=1e-12)
    np.testing.assert_allclose(out[:, 2], 0.02 * q**2, atol=1e-12)


def test_resampling_passes_through_the_waypoints() -> None:
    angle = np.linspace(0.0, math.pi, 15)
    traj = Trajectory(
        x=5 * np.sin(angle), y=5 * (1 - np.cos(angle)), heading=angle, speed=np.ones(15)
    )
    path = ReferencePath(traj)
    out = path.sample(path.segments[0], path.s)
    np.testing.assert_allclose(out[:, 0], traj.x, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], traj.y, atol=1e-12)


def test_horizon_reaches_ahead_from_rest_and_stops_on_the_last_point() -> None:
    traj = Trajectory(
        x=0.5 * np.arange(10),
        y=np.zeros(10),
        heading=np.zeros(10),
        speed=np.array([0.0, 0.5, 1, 1, 1, 1, 1, 1, 0.5, 0.0]),
    )
    path = ReferencePath(traj, creep_speed=0.3)
    seg = path.segments[0]
    s = path.horizon_arclength(seg, 0.0, 0.1 * np.arange(1, 101))
    assert s[0] > 0.0  # a standing start still looks ahead
    assert np.all(np.diff(s) >= 0.0)
    assert s[-1] == pytest.approx(4.5)  # the reference waits on the final waypoint
    assert path.reference_speed(np.array([4.5]))[0] == 0.0


@pytest.mark.parametrize("spacing", [0.05, 0.1, 0.3])
@pytest.mark.parametrize("direction", [1, -1])
def test_a_point_some_chords_from_the_waypoint_projects_where_it_is(
    spacing: float, direction: int
) -> None:
    """The steering-aware model projects the pose predicted over the dead time (0.2 m ahead
    at 2 m/s) from the waypoint nearest the car: on a dense plan several chords on. The
    projection walks there; it stopped at the next waypoint, and the reference stalled and
    jumped there every tick (steering blips on plans spaced closer than the dead time's
    travel)."""
    n = round(20.0 / spacing)
    k = 0.15  # 1/m: an arc, the point 1 cm outside it (as a car that tracks it)
    th = k * spacing * np.arange(n)
    heading = th if direction > 0 else th + math.pi  # reversing: the car faces backward
    traj = Trajectory(
        x=np.sin(th) / k,
        y=(1.0 - np.cos(th)) / k,
        heading=heading,
        speed=np.full(n, 1.0 * direction),
    )
    assert split_segments(traj)[0].direction == direction
    path = ReferencePath(traj)
    seg = path.segments[0]
    i = n // 2
    for ahead in (-0.45, -0.25, -0.12, 0.0, 0.12, 0.25, 0.45):
        a = th[i] + k * ahead
        r = 1.0 / k + 0.01
        x, y = r * math.sin(a), 1.0 / k - r * math.cos(a)
        assert path.project(seg, i, x, y) == pytest.approx(path.s[i] + ahead, abs=2e-3)


def test_the_chord_walk_is_bounded() -> None:
    """A point far beyond the waypoint (a bad projection source) costs at most CHORD_WALK
    chords per tick: the walk stops there and the projection is clamped to that chord's end."""
    path = ReferencePath(_line(n=500, spacing=0.02))
    seg = path.segments[0]
    i, t = path.chord(seg, 10, 5.0, 0.3)  # 250 chords ahead
    assert i == 10 + ReferencePath.CHORD_WALK and t > 1.0
    assert path.project(seg, 10, 5.0, 0.3) == pytest.approx(path.s[i + 1])
    assert path.project(seg, 300, 5.0, 0.3) == pytest.approx(5.0)  # near: walked to it


def test_reverse_segment_speeds_are_negative_and_end_at_zero() -> None:
    traj = Trajectory(
        x=np.array([0.0, 0.5, 1.0, 1.5, 1.0, 0.5, 0.0]),
        y=np.array([0.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3]),
        heading=np.zeros(7),
        speed=np.array([0.5, 1.0, 0.5, 0.0, -0.5, -1.0, -0.5]),
    )
    path = ReferencePath(traj)
    assert [s.direction for s in path.segments] == [1, -1]
    assert path.speed[3] == 0.0 and path.speed[-1] == 0.0
    assert np.all(path.speed[4:6] < 0.0)


# --- the per-tick queries of ReferencePath ---


def _parking_like() -> Trajectory:
    """A forward arc, a cusp, and a reverse arc (two segments, curved, uneven spacing)."""
    a = np.linspace(0.0, 1.2, 14)
    fwd_x, fwd_y = 6 * np.sin(a), 6 * (1 - np.cos(a))
    b = np.linspace(0.0, 0.9, 11)[1:]
    rev_x = fwd_x[-1] - 4 * np.sin(b) * np.cos(a[-1])
    rev_y = fwd_y[-1] - 4 * np.sin(b) * np.sin(a[-1]) + 0.3 * b**2
    speed = np.concatenate((np.full(13, 1.2), [0.0], np.full(9, -0.6), [0.0]))
    heading = np.concatenate((a, np.full(10, a[-1])))
    return Trajectory(
        x=np.concatenate((fwd_x, rev_x)),
        y=np.concatenate((fwd_y, rev_y)),
        heading=heading,
        speed=speed,
    )


def test_horizon_is_sample_of_horizon_arclength_and_reference_speed() -> None:
    """The fused per-tick query returns exactly what the three separate queries return."""
    traj = _parking_like()
    path = ReferencePath(traj, creep_speed=0.3)
    steps = 0.1 * np.arange(1, 31)
    rng = np.random.default_rng(5)
    for seg in path.segments:
        for s0 in np.concatenate(
            (
                [path.s[seg.start], path.s[seg.end]],
                rng.uniform(path.s[seg.start], path.s[seg.end], 40),
            )
        ):
            s_ref = path.horizon_arclength(seg, float(s0), steps)
            expected = path.sample(seg, np.concatenate(([s0], s_ref)))
            pts, speed = path.horizon(seg, float(s0), steps)
            np.testing.assert_array_equal(pts, expected.T)
            np.testing.assert_array_equal(speed, path.reference_speed(s_ref))


def test_speed_and_slope_is_the_reference_speed_and_its_chord_slope() -> None:
    """The baselines' speed lookup is the reference speed (one interpolation), held to the
    segment, with the slope of the chord it lies on, signed along the direction of travel."""
    path = ReferencePath(_parking_like(), creep_speed=0.3)
    rng = np.random.default_rng(3)
    for seg in path.segments:
        lo, hi = float(path.s[seg.start]), float(path.s[seg.end])
        for s in rng.uniform(lo, hi, 60):
            speed, slope = path.speed_and_slope(seg, float(s))
            ref = seg.direction * float(path.reference_speed(np.array([s]))[0])
            assert speed == pytest.approx(max(ref, 0.0), abs=1e-12)
            h = 1e-6
            a, b = max(s - h, lo), min(s + h, hi)
            fd = seg.direction * float(np.diff(path.reference_speed(np.array([a, b])))[0]) / (b - a)
            assert slope == pytest.approx(fd, abs=1e-5)
        # held to the segment: beyond its end it is the end's speed
        assert path.speed_and_slope(seg, hi + 5.0)[0] == pytest.approx(
            max(seg.direction * float(path.speed[seg.end]), 0.0)
        )


def test_scalar_interpolation_is_numpys_bit_for_bit() -> None:
    """The per-tick scalar lookup gives np.interp's exact value: inside, on and beyond knots."""
    rng = np.random.default_rng(11)
    for n in (2, 5, 40):
        xp = np.cumsum(rng.uniform(0.01, 3.0, n))
        fp = np.cumsum(rng.uniform(0.0, 2.0, n))
        queries = np.concatenate((rng.uniform(xp[0] - 1.0, xp[-1] + 1.0, 500), xp))
        got = [_interp_scalar(float(x), xp.tolist(), fp.tolist()) for x in queries]
        np.testing.assert_array_equal(got, np.interp(queries, xp, fp))


def test_a_stop_just_short_of_a_cusp_ends_the_segment() -> None:
    """A stop 1 mm before the cusp's end line, 0.5 m aside: the progress is at the end, so the
    next segment starts (the old half-plane test held the car there for good)."""
    traj = routes.with_reverse(routes.leg([(6.0, 0.0)]), [(4.0, 0.0)])
    path = ReferencePath(traj)
    prog = Progress(path, window=20)
    end = path.segments[0].end
    for i in range(end):
        prog.update(float(traj.x[i]), 0.5, 0.0)
    prog.update(float(traj.x[end]) - 0.001, 0.5, 0.0)
    assert not prog.passed and not prog.at_end(float(traj.x[end]) - 0.001, 0.5, 0.15)
    assert prog.ended(float(traj.x[end]) - 0.001, 0.5, 0.15)
    assert prog.next_segment() and prog.segment.direction == -1
    # the last segment needs the goal tolerance: progress alone does not finish the route
    for i in range(prog.segment.start, prog.segment.end + 1):
        prog.update(float(traj.x[i]), 0.5, 0.0)
    assert not prog.ended(float(traj.x[-1]), 0.5, 0.15)
    assert prog.ended(float(traj.x[-1]), 0.05, 0.15)


def test_the_reference_speed_stands_at_a_cusp_without_a_waypoint_at_rest() -> None:
    """Both segments share the cusp waypoint: the reverse one must not write its speed over
    the forward one's end (its horizon then asked for −1 m/s at the end of a forward drive,
    and the MPC would not drive the last half metre on)."""
    x = np.array([0.0, 1.0, 2.0, 3.0, 2.0, 1.0, 0.0])
    n = len(x)
    speed = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0, 0.0])  # the chord leaving each
    path = ReferencePath(Trajectory(x, np.zeros(n), np.zeros(n), speed))
    forward, reverse = path.segments
    assert forward.end == reverse.start == 3
    assert path.speed[3] == 0.0
    assert path.speed_at(forward, float(path.s[3])) == 0.0
    assert path.speed_at(reverse, float(path.s[3])) == 0.0


def test_the_reference_speed_slows_in_time_for_a_stop_the_plan_leaves_too_late() -> None:
    """A plan at 2.8 m/s up to a waypoint 1 m before its goal asks for 3.9 m/s² of braking:
    the reference never needs more than STOP_DECEL, and a plan within it is kept as sent."""
    x = np.arange(0.0, 21.0)
    n = len(x)
    late = np.full(n, 2.8)
    late[-1] = 0.0
    path = ReferencePath(Trajectory(x, np.zeros(n), np.zeros(n), late))
    to_end = path.s[-1] - path.s
    assert np.all(path.speed <= np.sqrt(2.0 * STOP_DECEL * to_end) + 1e-12)
    assert path.speed[0] == 2.8 and path.speed[-2] == pytest.approx(math.sqrt(2.0 * STOP_DECEL))
    gentle = np.minimum(2.8, np.sqrt(STOP_DECEL * to_end))  # half the braking: unchanged
    path = ReferencePath(Trajectory(x, np.zeros(n), np.zeros(n), gentle))
    assert np.array_equal(path.speed, gentle)


def _kinked(spacing: float, kink: float) -> Trajectory:
    """40 m east at 10 km/h with one heading jump of ``kink`` rad at x = 20 m (then north-east),
    waypoints ``spacing`` m apart, stopping at the end: the turn is the chord into x = 20 m."""
    s = np.arange(0.0, 40.0 + 1e-9, spacing)
    heading = np.where(s < 20.0, 0.0, kink)
    x = np.where(s < 20.0, s, 20.0 + (s - 20.0) * math.cos(kink))
    y = np.where(s < 20.0, 0.0, (s - 20.0) * math.sin(kink))
    speed = np.full(len(s), 2.78)
    speed[-1] = 0.0
    return Trajectory(x, y, heading, speed)


def test_a_turn_tighter_than_the_car_is_approached_at_the_tight_turn_speed() -> None:
    """A 60° kink (radius 1 m over 1 m) on a 10 km/h plan, for a car turning no tighter than
    4.7 m: before, the car reached it at 2.9 m/s and braked to 5 m off the plan once the
    off-the-plan watchdog stopped it. The reference slows to TIGHT_TURN_SPEED there, braking
    no harder than STOP_DECEL, and speeds up again after it at the same rate."""
    traj = _kinked(1.0, math.pi / 3)
    car = turn_radius(2.7, math.radians(30.0))
    path = ReferencePath(traj, min_turn_radius=car)
    assert tightest_turn(traj)[0] == pytest.approx(1.0 / (math.pi / 3))
    at = np.linspace(19.0, 20.0, 11)  # along the chord that turns
    assert np.all(path.reference_speed(at) <= TIGHT_TURN_SPEED + 1e-12)
    distance = np.minimum(np.abs(path.s - 19.0), np.abs(path.s - 20.0))
    ceiling = np.sqrt(TIGHT_TURN_SPEED**2 + 2.0 * STOP_DECEL * distance)
    assert np.all(np.abs(path.speed) <= ceiling + 1e-12)
    assert path.speed[0] == 2.78 and path.speed[30] == 2.78  # far from it: the plan's speed
    # the planned time follows the slower speed (the horizon's points are placed by it)
    plain = ReferencePath(traj)
    assert path.time[-1] > plain.time[-1] + 1.0
    # without a car's radius, or for a car that turns tighter than the kink: as sent
    assert np.array_equal(plain.speed, ReferencePath(traj, min_turn_radius=0.9).speed)


def test_heading_jitter_on_a_dense_plan_is_no_tight_turn() -> None:
    """0.02 rad of jitter between waypoints 0.1 m apart is a radius of 5 m from one waypoint
    to the next; over TURN_WINDOW it is a straight road, and the plan keeps its speed."""
    s = np.arange(0.0, 30.0 + 1e-9, 0.1)
    n = len(s)
    jitter = 0.01 * (-1.0) ** np.arange(n)  # ±0.01 rad: 0.02 between neighbours
    speed = np.full(n, 2.0)
    speed[-1] = 0.0
    traj = Trajectory(s, np.zeros(n), jitter, speed)
    assert TURN_WINDOW > 0.1
    assert tightest_turn(traj)[0] > 20.0
    car = turn_radius(2.7, math.radians(30.0))
    assert np.array_equal(ReferencePath(traj, min_turn_radius=car).speed, ReferencePath(traj).speed)
