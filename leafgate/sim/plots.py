"""PNG plots of a drive, like the paper's Figs. 2–4: path, steering, speed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from leafgate.messages import FloatArray, Trajectory


@dataclass(frozen=True)
class Trace:
    """One drive's time series for plotting (SI units; plotted in degrees where readable)."""

    label: str
    t: FloatArray
    x: FloatArray
    y: FloatArray
    speed: FloatArray
    steer_actual: FloatArray
    steer_target: FloatArray
    speed_ref: FloatArray


REFERENCE = "black"  # the plan, on every plot
#: Pairs of (actual, target) colours: a drive's target is a lighter shade of its actual colour
#: (matplotlib's tab20 pairs), so the two never share a colour yet belong together.
_TAB20 = (
    ("#1f77b4", "#aec7e8"),
    ("#d62728", "#ff9896"),
    ("#2ca02c", "#98df8a"),
    ("#9467bd", "#c5b0d5"),
    ("#ff7f0e", "#ffbb78"),
    ("#8c564b", "#c49c94"),
)
START, GOAL, CUSP = "tab:green", "tab:red", "tab:orange"


def actual_colour(i: int) -> str:
    """The colour of drive ``i``'s measured values."""
    return _TAB20[i % len(_TAB20)][0]


def target_colour(i: int) -> str:
    """The colour of drive ``i``'s targets: black for the first (as the plan on the path plot),
    a lighter shade of the drive's own colour for the others."""
    return _TAB20[i % len(_TAB20)][1] if i else REFERENCE


def lateral_error(traj: Trajectory, trace: Trace) -> FloatArray:
    """Signed cross-track error of a drive against the plan, m (left of the path positive)."""
    from leafgate.sim.metrics import path_errors

    heading = np.zeros_like(trace.x)  # the lateral error needs positions only
    return path_errors(traj, trace.x, trace.y, heading, trace.speed).lateral


def _mark_plan(ax: Any, traj: Trajectory) -> None:
    """Start, goal and cusps (where the plan changes direction) on the path plot."""
    from leafgate.control.reference import split_segments

    ax.plot(traj.x[0], traj.y[0], "o", ms=9, color=START, label="start", zorder=5)
    ax.plot(traj.x[-1], traj.y[-1], "X", ms=10, color=GOAL, label="goal", zorder=5)
    cusps = [seg.end for seg in split_segments(traj)[:-1]]
    if cusps:
        ax.plot(traj.x[cusps], traj.y[cusps], "D", ms=8, color=CUSP, label="cusp", zorder=5)


def _pyplot():  # imported lazily: matplotlib costs ~0.3 s and the daemon never plots
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(plt: Any, fig: Any, ax: Any, path: Path, xlabel: str, ylabel: str, title: str) -> Path:
    """Label, grid and legend an axis, save its figure as PNG and close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(title.strip())
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_drive(
    out_dir: Path,
    traj: Trajectory | None,
    traces: Sequence[Trace],
    title: str = "",
    obstacles: Sequence[Any] = (),
) -> Mapping[str, Path]:
    """Write path.png, steering.png and speed.png into ``out_dir``; return their paths.

    path.png has the plan with its start, goal and cusps, each drive's path, and below them
    each drive's lateral error over time. Targets are dashed, in another colour than the
    measured values they go with.

    :param obstacles: boxes with ``x_min, x_max, y_min, y_max`` (m) drawn grey on the path
        plot (parked cars, kerb)
    """
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}

    fig, (ax, err_ax) = plt.subplots(
        2, 1, figsize=(9, 6.5), gridspec_kw={"height_ratios": (3, 1.3)}
    )
    for box in obstacles:
        ax.add_patch(
            plt.Rectangle(
                (box.x_min, box.y_min),
                box.x_max - box.x_min,
                box.y_max - box.y_min,
                color="0.8",
                zorder=0,
            )
        )
    if traj is not None:
        ax.plot(traj.x, traj.y, color=REFERENCE, ls="--", lw=1.2, label="reference")
        _mark_plan(ax, traj)
    for i, tr in enumerate(traces):
        ax.plot(tr.x, tr.y, lw=1.6, color=actual_colour(i), label=f"driven ({tr.label})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(f"Path {title}".strip())
    if traj is not None and len(traj) > 1:
        for i, tr in enumerate(traces):
            lateral = lateral_error(traj, tr)
            err_ax.plot(tr.t, lateral, lw=1.3, color=actual_colour(i), label=tr.label)
        err_ax.axhline(0.0, color=REFERENCE, lw=0.8)
    err_ax.set_xlabel("t [s]")
    err_ax.set_ylabel("lateral error [m]")
    err_ax.grid(True, alpha=0.3)
    fig.tight_layout()
    files["path"] = out_dir / "path.png"
    fig.savefig(files["path"], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    for i, tr in enumerate(traces):  # the target dashed on top: visible where they agree
        ax.plot(
            tr.t,
            np.degrees(tr.steer_actual),
            lw=2.2,
            color=actual_colour(i),
            label=f"actual ({tr.label})",
        )
        ax.plot(
            tr.t,
            np.degrees(tr.steer_target),
            lw=1.1,
            ls="--",
            color=target_colour(i),
            label=f"target ({tr.label})",
            zorder=3,
        )
    files["steering"] = _finish(
        plt,
        fig,
        ax,
        out_dir / "steering.png",
        "t [s]",
        "road-wheel angle [deg]",
        f"Steering {title}",
    )

    fig, ax = plt.subplots(figsize=(9, 4))
    for i, tr in enumerate(traces):
        ax.plot(tr.t, tr.speed, lw=2.2, color=actual_colour(i), label=f"actual ({tr.label})")
        ax.plot(
            tr.t,
            tr.speed_ref,
            lw=1.1,
            ls="--",
            color=target_colour(i),
            label=f"reference ({tr.label})",
            zorder=3,
        )
    files["speed"] = _finish(
        plt, fig, ax, out_dir / "speed.png", "t [s]", "speed [m/s]", f"Speed {title}"
    )
    return files
