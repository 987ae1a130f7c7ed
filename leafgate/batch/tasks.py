"""The functions a worker runs: one case of ``batch sim``, ``batch check`` or ``batch rerun``.

Each returns a row (a flat dict) and never raises: an error becomes ``status: failed`` with the
error's one-line text. ``status: ok`` says that the task ran and the row holds its result, not
that the result is good: a checked log with findings is ``ok`` with ``ok: False``, a re-run
that diverged ``ok`` with ``identical: False``. (The engine adds ``not run`` for a task the
batch stopped before, and ``attempts``.)
"""

from __future__ import annotations

import functools
import io
import json
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

from leafgate.batch.engine import failed
from leafgate.errors import LeafgateError

__all__ = ["check_case", "rerun_case", "sim_case"]


@functools.cache
def _parser() -> Any:
    from leafgate.cli import build_parser

    return build_parser()


def _error(exc: BaseException) -> dict[str, Any]:
    text = str(exc) if isinstance(exc, LeafgateError) else f"{type(exc).__name__}: {exc}"
    return failed(text)


def sim_case(argv: Sequence[str]) -> dict[str, Any]:
    """``leafgate sim ARGV`` in this process, into a scratch folder; its metrics.json as the row.

    The row holds ``status`` (ok/failed), ``error``, ``exit_status`` (the command's: not 0 when
    the drive did not finish) and every key of metrics.json.
    """
    t0 = time.perf_counter()
    out, err = io.StringIO(), io.StringIO()
    with tempfile.TemporaryDirectory(prefix="leafgate-case-") as tmp:
        try:
            with redirect_stdout(out), redirect_stderr(err):
                args = _parser().parse_args(["sim", *argv, "--out", tmp, "--no-plots"])
                exit_status = int(args.func(args))
        except SystemExit:  # argparse refused the command line
            lines = err.getvalue().strip().splitlines()
            return failed(lines[-1] if lines else "leafgate sim: bad command line")
        except Exception as exc:  # recorded as the case's failure, never raised to the batch
            return _error(exc)
        metrics_file = Path(tmp) / "metrics.json"
        if not metrics_file.is_file():
            return failed(f"leafgate sim exited with {exit_status} and wrote no metrics.json")
        metrics = json.loads(metrics_file.read_text(encoding="utf-8"))
    row: dict[str, Any] = {"status": "ok", "error": None, "exit_status": exit_status}
    row.update(metrics)
    row["case_wall_s"] = time.perf_counter() - t0
    return row


def check_case(
    paths: str | list[str], config: str | None, gap_periods: float, profile: str | None = None
) -> dict[str, Any]:
    """``leafgate replay check PATH…`` of one log (a file, or a rotated log's parts): the
    summary counts of its report."""
    from leafgate.record.logs import group_parts
    from leafgate.replay.check import check_log
    from leafgate.settings import load_config

    try:
        cfg = load_config(config) if config is not None else None
        (log,) = group_parts([paths] if isinstance(paths, str) else paths)
        report = check_log(log, cfg, profile=profile, gap_periods=gap_periods).to_dict()
    except Exception as exc:
        return _error(exc)
    findings = report.pop("findings")
    report.pop("ids")
    report.pop("path")
    first = findings[0] if findings else None
    kinds = Counter(str(f["kind"]) for f in findings)  # in the order they first occur
    return {
        "status": "ok",
        "error": None,
        **report,
        "findings": len(findings),
        "finding_kinds": ", ".join(f"{kind} {n}" for kind, n in kinds.items()),
        "first_finding": None if first is None else json.dumps(first),
    }


def rerun_case(path: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """``leafgate replay rerun PATH --set …``: whether the commands reproduce, where they diverge."""
    from leafgate.replay.rerun import rerun_session

    try:
        report = rerun_session(path, overrides)
    except Exception as exc:
        return _error(exc)
    diverged = [s for s in report.signals if s.differing]
    return {
        "status": "ok",
        "error": None,
        "ticks": report.ticks,
        "identical": report.identical,
        "first_divergence_s": report.first_divergence,
        "diverging_signals": ", ".join(
            f"{s.name} (from {s.first_divergence:.3f} s, max |diff| {s.max_abs:.6g})"
            for s in diverged
        ),
        "truncated": report.truncated,
        # ticks missing from the session: the re-run ended there (None: none missing)
        "gap": None if report.gap is None else report.gap.text(),
        "ticks_not_rerun": report.not_rerun,
        "ticks_numbered": report.numbered,
    }
