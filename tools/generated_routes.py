"""Routes nobody wrote by hand: drawn by hypothesis for the tests, and from a seed for a sweep.

A Leaf-drivable route: 1–3 legs of alternating direction (cusps between them), each a straight
start, then up to three turns — a clothoid ramp, an arc of radius ≥ 5 m of up to 1.5 turns (so
routes loop and cross themselves), a ramp back — and straights; waypoints at uneven gaps of
0.2–1.0 m (cycled), the vehicle's heading, signed speeds that pull away at 0.3 m/s and stop at
each cusp and at the end (:func:`route`, one definition for both draws).
``tests/test_generated_routes.py`` uses :func:`routes` (hypothesis) and :func:`plan`; run as a
script, this drives ``--count`` routes drawn from ``--seed`` (:class:`Seeded`, Python's
``random``) through the whole simulated gateway on one plant and prints JSON: per route its
goal figures, then a summary against the route goals
(``leafgate.sim.metrics.route_goal_misses``). A seed gives the same routes in every process, on
every plant and for every version of the controller, so a before/after comparison drives the
same routes. (Hypothesis's own draw with a fixed seed did not: the same seed gave other routes
from the 2nd on when the file was imported instead of run, and from the 8th on in a run of
the same script a quarter of an hour later.) Needs hypothesis (``.[test]``) for the import.

    .venv/bin/python tools/generated_routes.py --plant steer-lag --count 40 --seed 1
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
from dataclasses import dataclass
from typing import Protocol

import numpy as np

try:
    from hypothesis import strategies as st
except ModuleNotFoundError as exc:  # the plain install has no hypothesis: say which extra
    if __name__ != "__main__":
        raise
    print(
        f"generated_routes.py: needs {exc.name}, from the test extra: pip install -e '.[test]'",
        file=sys.stderr,
    )
    raise SystemExit(2) from None

from leafgate.messages import FloatArray, Pose, Trajectory
from leafgate.sim.scenarios import Scenario, time_budget

K_MAX = 0.2  # 1/m: R = 5 m, inside the Leaf's 4.68 m at the MPC's 30°
STEP = 0.01  # m, the dense integration step
TOP_SPEED = (1.0, 2.5)  # m/s, the range a route's top speed is drawn from


@dataclass(frozen=True)
class Leg:
    """One direction segment: pieces ``(length m, curvature at start, at end)``."""

    direction: int
    pieces: tuple[tuple[float, float, float], ...]


def dense_path(legs: list[Leg]) -> list[FloatArray]:
    """``(s, x, y, heading)`` every ``STEP`` m of each leg, in driving order; the vehicle's
    heading (a reverse leg turns it the other way for the same curvature)."""
    x = y = h = 0.0
    out = []
    for leg in legs:
        rows = [(0.0, x, y, h)]
        s = 0.0
        for length, k0, k1 in leg.pieces:
            n = max(1, math.ceil(length / STEP))
            ds = length / n
            for i in range(n):
                k = k0 + (k1 - k0) * (i + 0.5) / n
                mid = h + 0.5 * leg.direction * ds * k
                x += leg.direction * ds * math.cos(mid)
                y += leg.direction * ds * math.sin(mid)
                h += leg.direction * ds * k
                s += ds
                rows.append((s, x, y, h))
        out.append(np.array(rows))
    return out


def plan(legs: list[Leg], gaps: list[float], v_max: float) -> tuple[Trajectory, list[FloatArray]]:
    """Waypoints at the cumulative ``gaps`` (cycled) along each leg, its end included; signed
    speeds that pull away at 0.3 m/s and stop at each cusp and the end (0.5 m/s²)."""
    dense = dense_path(legs)
    cols: list[list[FloatArray]] = [[], [], [], []]
    g = 0
    for m, (leg, d) in enumerate(zip(legs, dense, strict=True)):
        length = float(d[-1, 0])
        s = [0.0]
        while s[-1] < length:
            s.append(s[-1] + gaps[g % len(gaps)])
            g += 1
        s[-1] = length
        if length - s[-2] < 0.1:  # no waypoint a hair before the end
            del s[-2]
        q = np.array(s)
        speed = np.minimum(np.sqrt(0.09 + q), np.sqrt(np.maximum(length - q, 0.0)))
        speed = np.minimum(speed, v_max)
        speed[-1] = 0.0
        first = 0 if m == 0 else 1  # the cusp waypoint ends the previous leg
        for c, values in enumerate(
            (*(np.interp(q, d[:, 0], d[:, i]) for i in (1, 2, 3)), leg.direction * speed + 0.0)
        ):
            cols[c].append(values[first:])
    x, y, heading, speed = (np.concatenate(c) for c in cols)
    traj = Trajectory(x=x, y=y, heading=heading, speed=speed)
    return traj, dense


class Draw(Protocol):
    """Where a route's numbers come from: hypothesis (the tests) or a seeded generator (the
    sweep)."""

    def real(self, low: float, high: float) -> float: ...
    def whole(self, low: int, high: int) -> int: ...


def route(draw: Draw, max_legs: int = 3) -> tuple[list[Leg], list[float]]:
    """1–3 legs of alternating direction; each a straight start, then turns (clothoid, arc,
    clothoid) and straights; the waypoint gaps."""
    legs = []
    for i in range(draw.whole(1, max_legs)):
        pieces = [(draw.real(3.0, 10.0), 0.0, 0.0)]
        for _ in range(draw.whole(1, 3)):
            k = draw.real(0.02, K_MAX)  # a turn, not a straight, either way
            if draw.whole(0, 1):
                k = -k
            ramp = draw.real(0.5, 4.0)
            arc = draw.real(0.0, min(3.0 * math.pi / abs(k), 60.0))  # ≤ 1.5 turns
            pieces += [(ramp, 0.0, k), (arc, k, k), (ramp, k, 0.0)]
            pieces.append((draw.real(0.5, 8.0), 0.0, 0.0))
        legs.append(Leg(1 if i % 2 == 0 else -1, tuple(pieces)))
    gaps = [draw.real(0.2, 1.0) for _ in range(draw.whole(1, 7))]
    return legs, gaps


@st.composite
def routes(draw: st.DrawFn, max_legs: int = 3) -> tuple[list[Leg], list[float]]:
    """:func:`route` drawn by hypothesis (which leans to the ends of every range)."""

    class _Hypothesis:
        def real(self, low: float, high: float) -> float:
            return draw(st.floats(low, high))

        def whole(self, low: int, high: int) -> int:
            return draw(st.integers(low, high))

    return route(_Hypothesis(), max_legs)


class Seeded:
    """:class:`Draw` from ``random.Random(seed)``: the same numbers for a seed in every process
    and on every machine (hypothesis's own draw with a fixed seed was not: module notes)."""

    def __init__(self, seed: int) -> None:
        self._random = random.Random(seed)

    def real(self, low: float, high: float) -> float:
        return self._random.uniform(low, high)

    def whole(self, low: int, high: int) -> int:
        return self._random.randint(low, high)


def scenario(traj: Trajectory) -> Scenario:
    """The plan as a scenario: from rest on its first waypoint, the time budget of its length."""
    start = Pose(float(traj.x[0]), float(traj.y[0]), float(traj.heading[0]), 0.0)
    return Scenario("generated", "a generated route", traj, start, time_budget(traj))


GOALS = (  # how route_goal_misses' messages start, one per goal
    "not finished",
    "lateral error",
    "final position",
    "final heading",
    "steering sign changes",
    "overspeed",
)
FIGURES = (
    "finished",
    "not_finished_reason",
    "lateral_error_max_m",
    "final_position_error_m",
    "final_heading_error_rad",
    "overspeed_max_mps",
    "steer_rate_sign_changes",
    "path_steer_sign_changes",
    "start_progress_m",
    "progress_m",
    "route_length_m",
)


def drawn(count: int, draw_seed: int) -> list[tuple[list[Leg], list[float], float]]:
    """``count`` routes and top speeds drawn with ``draw_seed`` (:class:`Seeded`): the same for
    a seed whatever the controller does with them, in any process."""
    draw = Seeded(draw_seed)
    found = []
    for _ in range(count):
        legs, gaps = route(draw)
        found.append((legs, gaps, draw.real(*TOP_SPEED)))
    return found


def sweep(plant: str, count: int, draw_seed: int) -> list[dict[str, object]]:
    """Drive the ``count`` routes :func:`drawn` with ``draw_seed`` on ``plant`` (the simulator's
    default model for it); each route's figures and the route goals it missed."""
    from leafgate.settings import load_config
    from leafgate.sim.metrics import route_goal_misses
    from leafgate.sim.runner import default_model, run

    config = load_config(
        None, {"sim.plant.kind": plant, "controller.mpc.model": default_model(plant)}
    )
    rows: list[dict[str, object]] = []
    for legs, gaps, v_max in drawn(count, draw_seed):
        traj, _ = plan(legs, gaps, v_max)
        metrics = run(config, scenario(traj)).metrics
        row: dict[str, object] = {key: metrics.get(key) for key in FIGURES}
        row["missed"] = route_goal_misses(metrics, plant, feasible=True)
        row["v_max"] = v_max
        row["legs"] = [[leg.direction, [list(p) for p in leg.pieces]] for leg in legs]
        row["gaps"] = gaps
        rows.append(row)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--plant", choices=("kinematic", "steer-lag", "dynamic"), default="kinematic"
    )
    parser.add_argument("--count", type=int, default=40, help="routes to draw and drive")
    parser.add_argument("--seed", type=int, default=1, help="hypothesis seed of the draw")
    args = parser.parse_args()
    if args.count < 1:
        print("generated_routes: --count must be at least 1", file=sys.stderr)
        return 2
    rows = sweep(args.plant, args.count, args.seed)
    missed: dict[str, int] = {}
    for row in rows:
        for miss in row["missed"]:  # type: ignore[attr-defined]
            goal = next((g for g in GOALS if str(miss).startswith(g)), "collision")
            missed[goal] = missed.get(goal, 0) + 1
    summary = {
        "plant": args.plant,
        "routes": len(rows),
        "finished": sum(bool(row["finished"]) for row in rows),
        "met_every_goal": sum(not row["missed"] for row in rows),
        "misses_by_goal": missed,
        "lateral_error_max_m": max(float(row["lateral_error_max_m"]) for row in rows),  # type: ignore[arg-type]
    }
    try:
        print(json.dumps({"summary": summary, "routes": rows}, indent=1), flush=True)
    except BrokenPipeError:  # the reader went away: say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return 0


if __name__ == "__main__":
    sys.exit(main())
