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

    :param obstacles: boxes with ``x_min, x_max, y_min, y_max`` (m) drawn grey on the path
        plot (parked cars, kerb)
    """
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}

    fig, ax = plt.subplots(figsize=(9, 4.5))
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
        ax.plot(traj.x, traj.y, "k--", lw=1.2, label="reference")
        ax.plot(traj.x, traj.y, "k.", ms=3)
    for tr in traces:
        ax.plot(tr.x, tr.y, lw=1.5, label=f"driven ({tr.label})")
    ax.set_aspect("equal", adjustable="datalim")
    files["path"] = _finish(plt, fig, ax, out_dir / "path.png", "x [m]", "y [m]", f"Path {title}")

    fig, ax = plt.subplots(figsize=(9, 4))
    for tr in traces:
        line = ax.plot(
            tr.t, np.degrees(tr.steer_target), lw=1.0, ls="--", label=f"target ({tr.label})"
        )
        ax.plot(
            tr.t,
            np.degrees(tr.steer_actual),
            lw=1.5,
            color=line[0].get_color(),
            label=f"actual ({tr.label})",
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
    for tr in traces:
        line = ax.plot(tr.t, tr.speed_ref, lw=1.0, ls="--", label=f"reference ({tr.label})")
        ax.plot(tr.t, tr.speed, lw=1.5, color=line[0].get_color(), label=f"actual ({tr.label})")
    files["speed"] = _finish(
        plt, fig, ax, out_dir / "speed.png", "t [s]", "speed [m/s]", f"Speed {title}"
    )
    return files
