"""Plots an engineer reads at a glance: a lateral-error subplot, target and actual in distinct
colours, start, goal and cusp markers on the path (issue 19, item 6)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from leafgate.sim import plots
from leafgate.sim.plots import Trace, actual_colour, lateral_error, plot_drive, target_colour
from leafgate.sim.scenarios import get_scenario


def _trace(traj: Any, offset: float = 0.0) -> Trace:
    n = len(traj)
    t = np.linspace(0.0, 10.0, n)
    # left of the path: along the normal of each waypoint's heading
    x = traj.x - offset * np.sin(traj.heading)
    y = traj.y + offset * np.cos(traj.heading)
    steer = np.linspace(0.0, 0.2, n)
    return Trace("drive", t, x, y, traj.speed.copy(), steer, steer + 0.01, traj.speed.copy())


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """The figures plot_drive made, kept open (keyed by file name)."""
    plt = plots._pyplot()
    plt.close("all")
    kept: dict[str, Any] = {}
    real_savefig = plt.Figure.savefig

    def savefig(fig: Any, path: Any, *args: Any, **kwargs: Any) -> None:
        kept[Path(path).name] = fig
        real_savefig(fig, path, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", savefig)
    monkeypatch.setattr(plt, "close", lambda *_: None)
    return kept


def test_path_has_markers_and_a_lateral_error_subplot(
    tmp_path: Path, figures: dict[str, Any]
) -> None:
    traj = get_scenario("parallel-park").trajectory
    plot_drive(tmp_path, traj, [_trace(traj, offset=0.3)], title="test")
    path = figures["path.png"]
    top, bottom = path.axes  # old code: one axis, no error plot
    labels = [line.get_label() for line in top.get_lines()]
    assert {"start", "goal", "cusp"} <= set(labels)
    cusp = next(line for line in top.get_lines() if line.get_label() == "cusp")
    assert len(cusp.get_xdata()) == 2  # parallel-park reverses in, then pulls forward
    assert bottom.get_ylabel() == "lateral error [m]"
    error = bottom.get_lines()[0].get_ydata()
    assert np.allclose(np.abs(error), 0.3, atol=0.02)  # 0.3 m beside the plan all along
    assert (tmp_path / "path.png").stat().st_size > 0


def test_target_and_actual_never_share_a_colour(tmp_path: Path, figures: dict[str, Any]) -> None:
    traj = get_scenario("s-curve").trajectory
    plot_drive(tmp_path, traj, [_trace(traj), _trace(traj, 0.1)])
    for name in ("steering.png", "speed.png"):
        lines = figures[name].axes[0].get_lines()
        colours = [(line.get_label(), line.get_color()) for line in lines]
        actual = [c for label, c in colours if label.startswith("actual")]
        target = [c for label, c in colours if not label.startswith("actual")]
        assert len(actual) == len(target) == 2
        assert not set(actual) & set(target), (name, colours)  # old code: the same colour


def test_colours_and_lateral_error_helpers() -> None:
    for i in range(8):
        assert actual_colour(i) != target_colour(i)
    traj = get_scenario("straight").trajectory
    assert np.allclose(lateral_error(traj, _trace(traj, -0.5)), -0.5, atol=1e-6)
