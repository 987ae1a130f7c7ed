"""``leafgate status`` shows the vehicle (speed, road-wheel angle, progress on the plan), not
only watchdog ages (issue 19, item 5)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

from leafgate.cli import vehicle_text
from leafgate.messages import Gear, LongReport, Stamped, SteerReport
from leafgate.runtime.daemon import VehicleView
from leafgate.sim.scenarios import get_scenario


def test_vehicle_text() -> None:
    text = vehicle_text(
        {
            "speed": 1.234,
            "steer_angle": math.radians(-2.1),
            "plan_index": 120,
            "plan_waypoints": 286,
            "plan_progress": 120 / 285,
        }
    )
    assert text == " 1.23 m/s, wheel  -2.1°, plan  42 % (120/286)"
    assert vehicle_text(None) == "  ? m/s, wheel ?, no plan"


def _result(nearest: int | None) -> Any:
    controller = None if nearest is None else SimpleNamespace(nearest_index=nearest)
    return SimpleNamespace(diagnostics=SimpleNamespace(controller=controller))


def test_vehicle_view_from_the_ticks() -> None:
    plan = get_scenario("s-curve").trajectory
    inputs = SimpleNamespace(
        long_report=Stamped(LongReport(1.5, 0.0, Gear.D, 0.0, 0.0, True, False, False, False), 0.0),
        steer_report=Stamped(SteerReport(0.1, 0.0, 0.0, True, False, False, False), 0.0),
        trajectory=Stamped(plan, 0.0),
    )
    view = VehicleView(period=0.1)
    view.on_tick(0.0, inputs, _result(len(plan) - 1), [])
    assert view.latest["speed"] == 1.5 and view.latest["steer_angle"] == 0.1
    assert view.latest["plan_progress"] == 1.0
    view.on_tick(0.05, inputs, _result(0), [])  # within the period: not refreshed
    assert view.latest["plan_progress"] == 1.0
    view.on_tick(
        0.2,
        SimpleNamespace(long_report=None, steer_report=None, trajectory=None),
        _result(None),
        [],
    )
    assert view.latest == {
        "speed": None,
        "steer_angle": None,
        "plan_waypoints": 0,
        "plan_index": None,
        "plan_progress": None,
    }
