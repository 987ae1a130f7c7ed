"""``leafgate replay plot LOG|SESSION --out DIR``: path, steering and speed plots of a drive.

The same three PNGs as the simulator (:func:`leafgate.sim.plots.plot_drive`):

- from a **session**: the localization's path against the recorded trajectory, the steering
  command against the measured road-wheel angle (DBW_STEER_RPT), and the measured speed
  against the trajectory's speed at the nearest point; each stretch of ticks missing from the
  session (the recorder dropped or lost them, :class:`~leafgate.record.session.TickContinuity`),
  which the plots' lines bridge, is printed as a note (``note: 50 ticks missing (#812–#861)
  between the ticks at 8.110 s and 8.610 s …``), and so are Zenoh inputs the recorder dropped;
- from a **CAN log**: one sample per DBW_STEER_CMD frame, with the latest reports before it.
  A CAN log holds no localization, so the path is dead-reckoned from the reported speed and
  road-wheel angle with the kinematic bicycle (``θ̇ = v tan δ / L``) and starts at the origin;
  the speed reference is the commanded speed (meaningful in velocity mode).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Final, TextIO

import numpy as np

from leafgate.can.profile import Profile
from leafgate.config import VehicleConfig
from leafgate.errors import ReplayError
from leafgate.jsonconv import float_from_json
from leafgate.messages import (
    FloatArray,
    LongCommand,
    LongReport,
    SteerCommand,
    SteerReport,
    Trajectory,
)
from leafgate.record.logs import FrameSource, is_session, recording_context
from leafgate.record.session import (
    META_SESSION,
    TOPIC_LOST,
    TOPIC_TICK,
    TOPIC_TRAJECTORY,
    SessionReader,
    TickContinuity,
    decode_trajectory,
)
from leafgate.sim.plots import Trace, plot_drive

__all__ = ["main_plot", "plot_recording", "trace_from_log", "trace_from_session"]

MAX_POINTS: Final = 5000  # samples plotted (and projected onto the path): more is not visible


def _thin(n: int) -> slice:
    return slice(None, None, max(1, math.ceil(n / MAX_POINTS)))


def trace_from_session(
    path: str | Path, notes: list[str] | None = None
) -> tuple[Trace, Trajectory | None]:
    """The drive of a session and the last trajectory it followed.

    :param notes: gets a line for each stretch of ticks missing from the session and each
        record of Zenoh inputs the recorder dropped
    :raises ReplayError: the file is not a readable session
    """
    from leafgate.sim.metrics import path_errors

    t: list[float] = []
    x: list[float] = []
    y: list[float] = []
    heading: list[float] = []
    speed: list[float] = []
    actual: list[float] = []
    target: list[float] = []
    trajectory: Trajectory | None = None
    with SessionReader(path) as reader:
        # a session resuming another after a recording failure starts at an unknown number
        resumed = reader.read_metadata().get(META_SESSION, {}).get("resumes")
        continuity = TickContinuity(first_seq=None if resumed else 0)
        for record in reader.records(frozenset({TOPIC_TICK, TOPIC_TRAJECTORY, TOPIC_LOST})):
            data = record.json()
            if record.topic == TOPIC_TRAJECTORY:
                trajectory = decode_trajectory(data)
                continue
            if record.topic == TOPIC_LOST:
                lost = continuity.take_lost(data)
                if lost.what != "tick" and notes is not None:
                    notes.append(f"{lost.text()}: the recorder dropped them")
                continue
            continuity.take_tick(data)
            pose = data["inputs"]["pose"]
            steer = data["inputs"]["steer_report"]
            if pose is None:
                continue
            p = pose["value"]
            t.append(float_from_json(data["now"]))
            x.append(float_from_json(p["x"]))
            y.append(float_from_json(p["y"]))
            heading.append(float_from_json(p["heading"]))
            speed.append(float_from_json(p["speed"]))
            actual.append(math.nan if steer is None else float_from_json(steer["value"]["angle"]))
            target.append(float_from_json(data["commands"]["steer"]["angle"]))
    if notes is not None:
        notes += [f"{gap.text()}; the plots' lines bridge the gap" for gap in continuity.gaps]
    arrays = {
        k: np.asarray(v, dtype=np.float64)[_thin(len(t))]
        for k, v in {
            "t": t,
            "x": x,
            "y": y,
            "heading": heading,
            "speed": speed,
            "actual": actual,
            "target": target,
        }.items()
    }
    if trajectory is not None and len(trajectory) >= 2 and arrays["t"].size:
        speed_ref = path_errors(
            trajectory, arrays["x"], arrays["y"], arrays["heading"], arrays["speed"]
        ).speed_ref
    else:
        speed_ref = np.full_like(arrays["t"], math.nan)
    trace = Trace(
        label=Path(path).stem,
        t=arrays["t"],
        x=arrays["x"],
        y=arrays["y"],
        speed=arrays["speed"],
        steer_actual=arrays["actual"],
        steer_target=arrays["target"],
        speed_ref=speed_ref,
    )
    return trace, trajectory


def trace_from_log(
    path: str | Path, profile: Profile | str, vehicle: VehicleConfig | None = None
) -> Trace:
    """The drive of a CAN log, sampled at each steering command; the path dead-reckoned.

    :param profile: the vehicle profile the frames follow
    :raises ReplayError: the file is missing or unreadable
    """
    from leafgate.can.codec import CanCodec

    wheelbase = (vehicle or VehicleConfig()).wheelbase
    codecs: dict[object, CanCodec] = {}
    steer: SteerReport | None = None
    long: LongReport | None = None
    cmd_speed = math.nan
    rows: list[tuple[float, float, float, float, float]] = []  # t, v, δ measured, δ cmd, v cmd
    for msg in FrameSource(path):
        codec = codecs.get(msg.channel)
        if codec is None:
            codec = codecs[msg.channel] = CanCodec(profile=profile)
        decoded = codec.decode(msg)
        if not decoded.valid:
            continue
        for value in decoded.values:  # a frame may carry steering and speed together
            if isinstance(value, SteerReport):
                steer = value
            elif isinstance(value, LongReport):
                long = value
            elif isinstance(value, LongCommand):
                cmd_speed = value.speed
            elif isinstance(value, SteerCommand):
                rows.append(
                    (
                        msg.timestamp,
                        math.nan if long is None else long.speed,
                        math.nan if steer is None else steer.angle,
                        value.angle,
                        cmd_speed,
                    )
                )
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 5)
    t, v, delta, target, v_cmd = data.T
    x, y = _dead_reckon(t, np.nan_to_num(v), np.nan_to_num(delta), wheelbase)
    thin = _thin(t.size)
    return Trace(
        label=Path(path).stem,
        t=t[thin] - (t[0] if t.size else 0.0),
        x=x[thin],
        y=y[thin],
        speed=v[thin],
        steer_actual=delta[thin],
        steer_target=target[thin],
        speed_ref=v_cmd[thin],
    )


def _dead_reckon(
    t: FloatArray, v: FloatArray, delta: FloatArray, wheelbase: float
) -> tuple[FloatArray, FloatArray]:
    """Rear-axle path of the kinematic bicycle from speed and road-wheel angle (Euler steps)."""
    if t.size == 0:
        return t.copy(), t.copy()
    dt = np.diff(t, prepend=t[0])
    theta = np.cumsum(v * np.tan(delta) / wheelbase * dt)  # θ̇ = v tan δ / L
    x = np.cumsum(v * np.cos(theta) * dt)
    y = np.cumsum(v * np.sin(theta) * dt)
    return x, y


def plot_recording(
    path: str | Path,
    out_dir: str | Path,
    profile: Profile | str | None = None,
    notes: list[str] | None = None,
) -> Mapping[str, Path]:
    """Write path.png, steering.png and speed.png of a log or session into ``out_dir``.

    :param profile: the vehicle profile of a CAN log (a session's is read from it)
    :param notes: gets what a session lacks (:func:`trace_from_session`)
    :raises ReplayError: nothing to plot: no steering command in the recording
    """
    if is_session(path):
        trace, trajectory = trace_from_session(path, notes)
        title = f"({Path(path).name})"
    else:
        if profile is None:
            raise ReplayError(f"{path}: a CAN log needs a vehicle profile to plot")
        trace, trajectory = trace_from_log(path, profile), None
        title = f"({Path(path).name}, path dead-reckoned)"
    if trace.t.size == 0:
        what = "no gateway tick" if is_session(path) else "no steering command frame"
        name = getattr(profile, "name", profile)
        raise ReplayError(
            f"{path}: nothing to plot: {what} in the recording"
            + ("" if is_session(path) else f" (read with profile {name})")
        )
    return plot_drive(Path(out_dir), trajectory, [trace], title)


def main_plot(
    log: str | Path,
    *,
    out: str | Path,
    config: str | Path | None = None,
    profile: str | None = None,
    stdout: TextIO | None = None,
) -> int:
    """``leafgate replay plot LOG|SESSION --out DIR [--config FILE] [--profile NAME|FILE]``.

    :return: 0 when the plots were written
    :raises LeafgateError: unreadable log or session, no profile for a CAN log, or nothing to
        plot (the CLI prints it and exits non-zero)
    """
    stdout = stdout or sys.stdout
    chosen = None
    if not is_session(log):
        chosen = recording_context(log, config=config, profile=profile).profile
    notes: list[str] = []
    for name, file in plot_recording(log, out, chosen, notes).items():
        stdout.write(f"{name}: {file}\n")
    for note in notes:
        stdout.write(f"note: {note}\n")
    return 0
