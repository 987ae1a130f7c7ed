"""Results of a batch: one row per case in Parquet (pyarrow) or CSV, thresholds, the report."""

from __future__ import annotations

import csv
import json
import math
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from leafgate.batch.engine import NOT_RUN, BatchError

__all__ = [
    "SIM_METRICS",
    "crossings",
    "make_out_dir",
    "read_table",
    "threshold_error",
    "write_report",
    "write_table",
]

#: The metrics the report's distributions and worst cases are about, in order of preference.
ERROR_METRICS = ("lateral_error_max_m", "lateral_error_rms_m", "heading_error_max_rad")
WORST_SHOWN = 5
#: The numbers and flags of a ``batch sim`` row that a sweep's ``thresholds`` may bound: the
#: numeric keys ``leafgate sim`` writes to metrics.json (the clearance ones only in scenes with
#: obstacles) and the case's ``exit_status`` and ``case_wall_s``. Named here, not read off the
#: results, so that a typo in a threshold is refused when the sweep is read, before any case
#: runs; ``crossings`` checks the same names. ``tests/test_batch.py`` holds it to what a real
#: case writes, so a metric added to the simulator without this list fails there.
SIM_METRICS = (
    *ERROR_METRICS,
    "final_position_error_m",
    "final_heading_error_rad",
    "speed_error_rms_mps",
    "steer_rate_max_radps",
    "steer_rate_rms_radps",
    "steer_rate_sign_changes",
    "path_steer_sign_changes",
    "overspeed_max_mps",
    "start_progress_m",
    "progress_m",
    "route_length_m",
    "plan_min_turn_radius_m",
    "solve_time_median_s",
    "solve_time_p99_s",
    "solver_not_converged",
    "input_clips",
    "duration_s",
    "wall_time_s",
    "finished",
    "can_frames_sent",
    "can_frames_received",
    "can_frames_rejected",
    "can_own_echoes",
    "can_foreign_frames",
    "ecu_frames_rejected",
    "clearance_min_m",
    "clearance_min_t_s",
    "exit_status",
    "case_wall_s",
)


def make_out_dir(path: str | Path) -> Path:
    """Create the output folder and make sure a file can be written in it (a read-only one
    found before the run, not after every case has run), or one line saying why not."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BatchError(
            f"--out {out}: cannot create the output folder: {exc.strerror or exc}"
        ) from None
    try:
        with tempfile.NamedTemporaryFile(dir=out, prefix=".leafgate-write-check-"):
            pass
    except OSError as exc:
        raise BatchError(
            f"--out {out}: cannot write in the output folder: {exc.strerror or exc}"
        ) from None
    return out


def flat(row: Mapping[str, Any]) -> dict[str, Any]:
    """Scalars as they are; lists and mappings (transitions, timeline) as JSON text."""
    return {k: json.dumps(v) if isinstance(v, (list, dict, tuple)) else v for k, v in row.items()}


def _columns(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    names: dict[str, None] = {}
    for row in rows:
        names.update(dict.fromkeys(row))
    return list(names)


def write_table(rows: Sequence[Mapping[str, Any]], out: Path, stem: str = "results") -> Path:
    """``stem.parquet`` when pyarrow is installed, else ``stem.csv``; one row per case."""
    flat_rows = [flat(r) for r in rows]
    names = _columns(flat_rows)
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        path = out / f"{stem}.csv"
        with path.open("w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=names)
            writer.writeheader()
            writer.writerows(flat_rows)
        return path
    arrays = {}
    for name in names:
        values = [r.get(name) for r in flat_rows]
        try:
            arrays[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError):  # mixed types: keep them as text
            arrays[name] = pa.array([None if v is None else str(v) for v in values])
    path = out / f"{stem}.parquet"
    pq.write_table(pa.table(arrays), path)
    return path


def read_table(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a results file written by :func:`write_table`."""
    path = Path(path)
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        return list(pq.read_table(path).to_pylist())
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def threshold_error(thresholds: Mapping[str, float | bool], source: str) -> str | None:
    """The one-line error of the first threshold naming no metric of :data:`SIM_METRICS`."""
    for name in thresholds:
        if name not in SIM_METRICS:
            known = ", ".join(SIM_METRICS)
            return f"{source}: thresholds.{name}: no such metric (known: {known})"
    return None


def crossings(
    rows: Sequence[Mapping[str, Any]], thresholds: Mapping[str, float | bool], source: str
) -> list[str]:
    """One line per case and threshold it crosses (a number is an upper bound, a bool the
    required value); a failed case crosses them all. A case the batch stopped before (``not
    run``) crosses none: it is counted apart, not as a verdict on the case.

    :raises BatchError: a threshold names no metric (names the file and the key); a sweep
        file's are checked when it is read (``load_sweep``), with the same names
    """
    error = threshold_error(thresholds, source)
    if error is not None:
        raise BatchError(error)
    lines = []
    for row in rows:
        case = row.get("case_id", row.get("path"))
        if row.get("status") == NOT_RUN:
            continue
        if row.get("status") != "ok":
            lines.append(f"case {case}: failed: {row.get('error')}")
            continue
        for name, bound in thresholds.items():
            value = row.get(name)
            if isinstance(bound, bool):
                if value is not bound:
                    lines.append(f"case {case}: {name} is {value}, required {bound}")
            elif not isinstance(value, (int, float)) or not value <= bound:
                if name == "exit_status":  # the sweep's default bound, 0: say what it means
                    lines.append(
                        f"case {case}: leafgate sim exited {value} (the drive did not finish or "
                        f"the car hit something; thresholds.exit_status: {bound:g})"
                    )
                else:
                    lines.append(f"case {case}: {name} = {value} above {bound:g}")
    return lines


def _metric(rows: Sequence[Mapping[str, Any]]) -> str | None:
    for name in ERROR_METRICS:
        if any(isinstance(r.get(name), (int, float)) for r in rows):
            return name
    return None


def _stats(values: list[float]) -> str:
    import numpy as np

    if not values:
        return "| - | - | - | - |"
    a = np.asarray(values)
    return f"| {np.median(a):.3f} | {np.percentile(a, 95):.3f} | {a.max():.3f} | {np.mean(a):.3f} |"


def write_report(
    rows: Sequence[Mapping[str, Any]],
    out: Path,
    *,
    title: str,
    engine: str,
    crossed: Sequence[str],
    stopped: str | None = None,
) -> tuple[Path, Path | None]:
    """``report.md`` and ``errors.png``: error distributions per controller and plant, the
    worst cases with the command line that runs each alone, the failures and crossings, and
    the cases not run when the batch stopped early (``stopped``: why) or re-run after a worker
    died."""
    ok_rows = [r for r in rows if r.get("status") == "ok"]
    failed_rows = [r for r in rows if r.get("status") == "failed"]
    not_run = [r for r in rows if r.get("status") == NOT_RUN]
    rerun = [r for r in rows if (r.get("attempts") or 1) > 1]
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in ok_rows:
        groups.setdefault((str(r["controller"]), str(r["plant"])), []).append(r)
    lines = [
        f"# {title}",
        "",
        f"{len(rows)} cases: {len(ok_rows)} ran, {len(failed_rows)} failed"
        + (f", {len(not_run)} not run ({stopped})" if not_run else "")
        + (f", {len(rerun)} re-run after a worker died" if rerun else "")
        + f"; {engine}.",
        "",
    ]
    png: Path | None = None
    metrics = [m for m in ERROR_METRICS if any(isinstance(r.get(m), float) for r in ok_rows)]
    for name in metrics:
        lines += [
            f"## {name} per controller and plant",
            "",
            "| controller | plant | cases | finished | median | p95 | max | mean |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        for (controller, plant), group in sorted(groups.items()):
            values = [float(r[name]) for r in group if isinstance(r.get(name), (int, float))]
            finished = sum(1 for r in group if r.get("finished") is True)
            lines.append(f"| {controller} | {plant} | {len(group)} | {finished} " + _stats(values))
        lines.append("")
    key = _metric(ok_rows)
    if key is not None:
        worst = sorted(
            (r for r in ok_rows if isinstance(r.get(key), (int, float))),
            key=lambda r: -float(r[key]) if math.isfinite(float(r[key])) else -math.inf,
        )[:WORST_SHOWN]
        lines += [f"## The {len(worst)} worst cases by {key}", ""]
        for r in worst:
            lines += [
                f"- case {r['case_id']}: {key} = {float(r[key]):.3f} ({r['route']}, "
                f"{r['controller']}, {r['plant']}, seed {r['seed']}, "
                f"finished {r.get('finished')})",
                "",
                "  ```sh",
                f"  {r['command']}",
                "  ```",
            ]
        lines.append("")
        png = out / "errors.png"
        _plot(groups, metrics, png)
        lines += [f"![error distributions]({png.name})", ""]
    if failed_rows:
        lines += ["## Failed cases", ""]
        for r in failed_rows:
            lines.append(f"- case {r.get('case_id')}: {r.get('error')}  \n  `{r.get('command')}`")
        lines.append("")
    if rerun:
        lines += ["## Cases re-run after a worker died while running them", ""]
        lines += [f"- case {r.get('case_id')}: {r.get('attempts')} attempts" for r in rerun]
        lines.append("")
    if not_run:
        lines += [f"## Cases not run ({stopped})", ""]
        lines += [f"- case {r.get('case_id')}  \n  `{r.get('command')}`" for r in not_run]
        lines.append("")
    lines += ["## Thresholds", ""]
    lines += [f"- {c}" for c in crossed] if crossed else ["No case crosses a threshold."]
    md = out / "report.md"
    md.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return md, png


def _plot(
    groups: Mapping[tuple[str, str], Sequence[Mapping[str, Any]]], metrics: list[str], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{c}\n{p}" for c, p in sorted(groups)]
    fig, axes = plt.subplots(
        len(metrics), 1, figsize=(max(6.0, 1.2 * len(labels) + 2), 3.2 * len(metrics))
    )
    axes_list = list(axes) if len(metrics) > 1 else [axes]
    for ax, name in zip(axes_list, metrics, strict=True):
        data = [
            [float(r[name]) for r in groups[g] if isinstance(r.get(name), (int, float))]
            for g in sorted(groups)
        ]
        ax.boxplot(data, tick_labels=labels, showfliers=True)
        ax.set_ylabel(name)
        ax.grid(True, axis="y", alpha=0.3)
    axes_list[0].set_title("error distributions per controller and plant")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
