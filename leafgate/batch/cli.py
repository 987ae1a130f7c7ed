"""``leafgate batch sim|check|rerun``: the command line of the batch jobs."""

from __future__ import annotations

import argparse
import contextlib
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from leafgate.batch import sweep as sweep_module
from leafgate.batch.engine import NOT_RUN, WORKERS_WAIT_S, BatchError, EngineRun, run_tasks
from leafgate.batch.results import crossings, make_out_dir, write_report, write_table
from leafgate.cliargs import (
    add_overrides,
    add_profile_options,
    non_negative_seconds,
    positive_int,
    positive_seconds,
)
from leafgate.text import plural

__all__ = ["add_arguments", "cmd_batch"]

SHOWN = 20  # crossings and failures printed to the terminal (all are in report.md)


def _common(p: argparse.ArgumentParser, out: str) -> None:
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="run on this running Dask cluster (default: a local cluster on this machine)",
    )
    p.add_argument(
        "--wait-workers",
        type=non_negative_seconds,
        default=WORKERS_WAIT_S,
        metavar="S",
        help="with --scheduler: s to wait for a first worker to join before failing "
        f"(default: {WORKERS_WAIT_S:g}); --timeout starts only when a worker takes a case",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        help="worker processes of the local cluster (default: CPU count)",
    )
    # dest is not `out`: `leafgate` creates every `out` before a command runs, and a batch whose
    # inputs are refused would leave an empty folder behind; make_out_dir creates it once they
    # are checked, before any case runs
    p.add_argument("--out", dest="out_dir", default=out, help=f"output folder (default: ./{out}/)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="batch_command", metavar="JOB", required=True)
    p = sub.add_parser(
        "sim",
        help="Monte-Carlo sweep of `leafgate sim` cases from a sweep file",
        description="Run every case of a sweep file (one Dask task each) and write "
        "results.parquet (or .csv without pyarrow), report.md and errors.png. Exit 1 when a "
        "case fails or crosses a threshold.",
        epilog=sweep_module.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sweep", help="sweep file (YAML), e.g. config/sweep.yaml")
    p.add_argument(
        "--timeout",
        type=positive_seconds,
        help="s per case, counted from when a worker starts it (default: the sweep's timeout_s)",
    )
    _common(p, "leafgate-batch")
    from leafgate.record.logs import readable_suffixes_text

    p = sub.add_parser("check", help="`replay check` of every CAN log and session under DIR")
    p.add_argument("dir", help="folder searched recursively")
    p.add_argument(
        "--glob",
        metavar="PATTERN",
        help="only files whose name matches, e.g. '*.mcap' (default: every file with a "
        f"readable suffix: {readable_suffixes_text()})",
    )
    add_profile_options(p, "the deployment config whose limits and profile apply")
    from leafgate.replay.check import add_gap_periods

    add_gap_periods(p)
    p.add_argument("--timeout", type=positive_seconds, help="s per log")
    _common(p, "leafgate-batch-check")
    p = sub.add_parser("rerun", help="`replay rerun` of every session (.mcap) under DIR")
    p.add_argument("dir", help="folder searched recursively")
    add_overrides(p)
    p.add_argument("--timeout", type=positive_seconds, help="s per session")
    _common(p, "leafgate-batch-rerun")


def _engine_text(run: EngineRun) -> str:
    workers = plural(run.workers, "worker") if run.workers else "workers unknown"
    return f"{run.scheduler}, {workers}, {run.wall_s:.1f} s wall time"


def _counts(rows: list[dict[str, Any]], run: EngineRun) -> str:
    """``, 1 re-run after a worker holding it died, 20 not run (interrupted (Ctrl-C))``:
    what the summary line adds when a task did not simply run once ("" when all did)."""
    text = ""
    if run.rerun:
        text += f", {run.rerun} re-run after a worker holding it died"
    not_run = sum(1 for r in rows if r.get("status") == NOT_RUN)
    if not_run:
        text += f", {not_run} not run ({run.stopped})"
    return text


def _files(directory: str, suffixes: tuple[str, ...], pattern: str | None = None) -> list[Path]:
    root = Path(directory)
    if not root.is_dir():
        raise BatchError(f"{root}: no such folder")
    files = sorted(
        p for p in root.rglob(pattern or "*") if p.is_file() and p.suffix.lower() in suffixes
    )
    if not files:
        kinds = ", ".join(suffixes)
        raise BatchError(
            f"{root}: no {pattern} file in it is a log ({kinds})"
            if pattern
            else f"{root}: no {kinds} files in it"
        )
    return files


@contextlib.contextmanager
def _output(path: str) -> Iterator[Path]:
    """The ``--out`` folder, created before the run; removed again if this batch created it
    and ends with nothing in it (the scheduler unreachable, no workers)."""
    existed = Path(path).exists()
    out = make_out_dir(path)
    try:
        yield out
    except BaseException:
        if not existed:
            with contextlib.suppress(OSError):  # not empty: it holds what the batch kept
                out.rmdir()
        raise


def _save(out: Path, rows: list[dict[str, Any]], run: EngineRun, extra: dict[str, Any]) -> Path:
    table = write_table(rows, out)
    info = {
        "scheduler": run.scheduler,
        "workers": run.workers,
        "wall_time_s": run.wall_s,
        "cases": len(rows),
        "failed": sum(1 for r in rows if r.get("status") == "failed"),
        "not_run": sum(1 for r in rows if r.get("status") == NOT_RUN),
        "rerun": run.rerun,
        "stopped": run.stopped,
        **extra,
    }
    (out / "batch.json").write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
    return table


def _write(out: Path, write: Callable[[], str], unshown: list[str]) -> str:
    """``write()`` (the files, named in the returned text); when the disk refuses, the lines
    not printed yet go to stdout first, so that the summary is kept, then one error line."""
    try:
        return write()
    except OSError as exc:
        for line in unshown:
            print(f"  {line}")
        reason = exc.strerror or str(exc)
        raise BatchError(
            f"--out {out}: cannot write the results: {reason}; the lines above are all that is kept"
        ) from None


def _stopped(run: EngineRun, rows: list[dict[str, Any]], out: Path) -> None:
    """After the rows are written: Ctrl-C as Ctrl-C (exit 130), a lost scheduler as one line."""
    if run.stopped is None:
        return
    if run.interrupted:
        raise KeyboardInterrupt
    not_run = sum(1 for r in rows if r.get("status") == NOT_RUN)
    raise BatchError(f"{run.stopped}: {not_run} of {len(rows)} not run; what finished is in {out}")


def cmd_batch_sim(args: argparse.Namespace) -> int:
    from leafgate.batch.tasks import sim_case

    sweep = sweep_module.load_sweep(args.sweep)
    cases = sweep_module.expand(sweep)
    timeout = args.timeout if args.timeout is not None else sweep.timeout_s
    with _output(args.out_dir) as out:
        print(f"{sweep.path}: {plural(len(cases), 'case')}", flush=True)
        run = run_tasks(
            sim_case,
            {c.case_id: (list(c.argv),) for c in cases},
            scheduler=args.scheduler,
            workers=args.workers,
            timeout=timeout,
            wait_workers=args.wait_workers,
        )
        rows = []
        for c in cases:
            rows.append(
                {
                    "case_id": c.case_id,
                    "route": c.route,
                    **run.rows[c.case_id],
                    # the case's names win over metrics.json's (its controller is the kind)
                    "plant": c.plant,
                    "controller": c.controller,
                    "seed": c.seed,
                    "command": c.command,
                }
            )
        rows = [_ordered(r) for r in rows]
        crossed = crossings(rows, sweep.thresholds, sweep.path)
        # the summary before the files: a disk that refuses them loses no verdict
        failed = sum(1 for r in rows if r["status"] == "failed")
        print(
            f"{plural(len(rows), 'case')}, {failed} failed{_counts(rows, run)}; {_engine_text(run)}"
        )
        for line in crossed[:SHOWN]:
            print(f"  {line}")

        def write() -> str:
            table = _save(out, rows, run, {"sweep": sweep.path, "crossings": len(crossed)})
            md, png = write_report(
                rows,
                out,
                title=f"Sweep {sweep.name} ({sweep.path})",
                engine=_engine_text(run),
                crossed=crossed,
                stopped=run.stopped,
            )
            more = f"  … {len(crossed) - SHOWN} more in {md}\n" if len(crossed) > SHOWN else ""
            return f"{more}wrote {table}, {md}" + (f", {png}" if png else "")

        print(_write(out, write, crossed[SHOWN:]))
        _stopped(run, rows, out)
    if crossed:
        print(
            f"FAILED: {plural(len(crossed), 'threshold crossing or failed case', 'threshold crossings or failed cases')}"
        )
        return 1
    rerun = f" ({run.rerun} re-run after a worker died)" if run.rerun else ""
    print(f"PASSED: every case ran{rerun} and stayed within the thresholds of {sweep.path}")
    return 0


_FIRST = ("case_id", "route", "plant", "controller", "seed", "status", "error", "exit_status")


def _ordered(row: dict[str, Any]) -> dict[str, Any]:
    first = {k: row.get(k) for k in _FIRST}
    return {**first, **{k: v for k, v in row.items() if k not in first}}


def _per_file(
    args: argparse.Namespace,
    fn: Any,
    files: list[Path],
    extra: tuple[Any, ...],
    what: str,
) -> tuple[EngineRun, list[dict[str, Any]]]:
    """``fn(path, *extra)`` for every file, one task each; rows in file order (each with the
    path as given: the task gets it absolute, see :func:`_on_worker`)."""
    run = run_tasks(
        fn,
        {str(f): (_on_worker(f), *extra) for f in files},
        scheduler=args.scheduler,
        workers=args.workers,
        timeout=args.timeout,
        what=what,
        wait_workers=args.wait_workers,
    )
    return run, [{"path": str(f), **run.rows[str(f)]} for f in files]


def _on_worker(path: str | Path) -> str:
    """``path`` as a worker must be given it: absolute. A worker resolves a relative path in
    its own working directory, not the batch's (a cluster's workers are started elsewhere):
    every file would be missing there, or another file of the same name checked instead."""
    return str(Path(path).absolute())


def _not_run_line(row: dict[str, Any]) -> str:
    return f"NOT RUN: {str(row['error']).removeprefix('not run: ')}"


def cmd_batch_check(args: argparse.Namespace) -> int:
    from leafgate.batch.tasks import check_case
    from leafgate.record.logs import READABLE_SUFFIXES

    files = _files(args.dir, READABLE_SUFFIXES, args.glob)
    config = str(Path(args.config).resolve()) if args.config else None
    if config is not None:
        from leafgate.settings import load_config

        load_config(config)  # a bad config is one error, not one per log
    from leafgate.record.logs import group_parts

    # a rotated log's parts are one log, checked as one (as `replay check` does with them)
    logs = {parts.name: [str(f) for f in parts.paths] for parts in group_parts(files)}
    with _output(args.out_dir) as out:
        run = run_tasks(
            check_case,
            {
                name: ([_on_worker(p) for p in paths], config, args.gap_periods, args.profile)
                for name, paths in logs.items()
            },
            scheduler=args.scheduler,
            workers=args.workers,
            timeout=args.timeout,
            what="logs",
            wait_workers=args.wait_workers,
        )
        rows = [{"path": name, **run.rows[name]} for name in logs]
        bad = 0
        for r in rows:
            if r["status"] == NOT_RUN:
                verdict = _not_run_line(r)
            elif r["status"] != "ok":
                verdict = f"FAILED: {r['error']}"
            else:
                counts = (
                    f"{plural(r['frames'], 'frame')}, {plural(r['violations'], 'limit violation')}, "
                    f"{plural(r['e2e_errors'], 'E2E error')}, {plural(r['gaps'], 'gap')}"
                )
                if r["ok"]:
                    verdict = f"OK: {counts}"
                else:  # every kind of finding, not only the counted ones (coverage, incomplete …)
                    verdict = f"FINDINGS: {r.get('finding_kinds') or r['findings']}; {counts}"
                    first = json.loads(r["first_finding"]) if r.get("first_finding") else None
                    if first:
                        where = ": ".join(str(v) for v in (first["kind"], first["name"]) if v)
                        verdict += f"; first: {where}: {first['detail']}"
            bad += r["status"] == "failed" or (r["status"] == "ok" and not r["ok"])
            print(f"{r['path']}: {verdict}")
        print(
            f"{plural(len(rows), 'log')}, {bad} with findings or unreadable{_counts(rows, run)}; "
            f"{_engine_text(run)}"
        )
        table = _write(out, lambda: f"wrote {_save(out, rows, run, {'dir': args.dir})}", [])
        print(table)
        _stopped(run, rows, out)
    return 1 if bad else 0


def cmd_batch_rerun(args: argparse.Namespace) -> int:
    from leafgate.batch.tasks import rerun_case
    from leafgate.config import parse_overrides
    from leafgate.replay.rerun import check_rerun_overrides

    overrides = parse_overrides(args.set)
    check_rerun_overrides(overrides)  # once, up front, not as a failure of every session
    files = _files(args.dir, (".mcap",))
    with _output(args.out_dir) as out:
        run, rows = _per_file(args, rerun_case, files, (overrides,), "sessions")
        differing = truncated = 0
        for r in rows:
            if r["status"] == NOT_RUN:
                verdict = _not_run_line(r)
            elif r["status"] != "ok":
                verdict = f"FAILED: {r['error']}"
            elif r["identical"] and r.get("truncated"):
                # the session ends where its recording was cut: the rest of the drive is unchecked
                verdict = (
                    f"IDENTICAL up to the cut (truncated session): {plural(r['ticks'], 'tick')}, every "
                    "recorded command reproduced"
                )
            elif r["identical"]:
                verdict = f"IDENTICAL: {plural(r['ticks'], 'tick')}, every command reproduced"
                if r.get("ticks_numbered") is False:
                    verdict += " (ticks not numbered: ticks the recorder lost not looked for)"
            elif r["first_divergence_s"] is None:  # not diverged: ticks missing ended it
                verdict = (
                    f"INCOMPLETE: {r['gap']}; {plural(r['ticks'], 'tick')} before it reproduced, "
                    f"{plural(r['ticks_not_rerun'], 'tick')} after it not re-run"
                )
            else:
                verdict = f"DIVERGED at {r['first_divergence_s']:.3f} s: {r['diverging_signals']}"
                if r.get("truncated"):
                    verdict += " (truncated session)"
                if r.get("gap"):
                    verdict += f"; then {r['gap']} (not re-run after it)"
            differing += r["status"] == "failed" or (r["status"] == "ok" and not r["identical"])
            truncated += r["status"] == "ok" and bool(r.get("identical") and r.get("truncated"))
            print(f"{r['path']}: {verdict}")
        cut = f", {truncated} reproduced only up to a cut (truncated)" if truncated else ""
        print(
            f"{plural(len(rows), 'session')}, {differing} not reproduced{cut}{_counts(rows, run)}; "
            f"{_engine_text(run)}"
        )
        extra = {"dir": args.dir, "overrides": overrides}
        print(_write(out, lambda: f"wrote {_save(out, rows, run, extra)}", []))
        _stopped(run, rows, out)
    return 1 if differing else 0


def cmd_batch(args: argparse.Namespace) -> int:
    job = {"sim": cmd_batch_sim, "check": cmd_batch_check, "rerun": cmd_batch_rerun}
    return job[args.batch_command](args)
