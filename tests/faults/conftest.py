"""Fixtures of the fault-injection suite: one :class:`~harness.FaultRun` per test, always closed."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # harness.py, next to the tests

from harness import FaultRun


@pytest.fixture
def make_run(tmp_path: Path) -> Iterator[Callable[..., FaultRun]]:
    """``make_run(fault, **options)``: a run in this test's directory, closed after the test."""
    runs: list[FaultRun] = []

    def factory(fault: str, **options: Any) -> FaultRun:
        run = FaultRun(tmp_path, fault, **options)
        runs.append(run)
        return run

    yield factory
    for run in runs:
        run.close()
