"""``leafgate batch sim --scheduler``: the same sweep on a real ``dask scheduler`` and two
``dask worker`` processes on loopback gives the local run's numbers and single runs' numbers."""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from leafgate.batch.results import read_table
from leafgate.cli import main
from leafgate.sim.runner import WALL_CLOCK_METRICS
from tests.conftest import free_port, process_cluster

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent

SWEEP = """\
name: cluster
seed: 5
samples: 2
routes: [straight]
plants: [kinematic, steer-lag]
controllers: [stanley]
disturbances:
  sim.localization.position_noise: [0.01, 0.03]
  sim.plant.steer_bias_deg: [-0.5, 0.5]
  sim.start_heading_offset: [-0.05, 0.05]
"""


def comparable(row: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in row.items() if k not in WALL_CLOCK_METRICS | {"case_wall_s"}}


@contextlib.contextmanager
def dask_cluster(log_dir: Path, pids: list[int] | None = None) -> Iterator[str]:
    """``dask scheduler`` and two ``dask worker`` processes on loopback, free ports, no
    dashboard; every process stopped after. ``pids``: filled with the scheduler's and the
    workers' process ids, in that order."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs: list[subprocess.Popen[bytes]] = []

    def start(name: str, *args: str) -> None:
        with (log_dir / f"{name}.log").open("wb") as log:
            procs.append(
                subprocess.Popen(
                    [str(BIN / "dask"), *args],
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env=env,
                    start_new_session=True,  # its own process group: stopped as a whole
                )
            )

    try:
        start(
            "scheduler", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"
        )
        for i in range(2):
            start(
                f"worker{i}",
                "worker",
                address,
                "--host",
                "127.0.0.1",
                "--nworkers",
                "1",
                "--nthreads",
                "1",
                "--no-dashboard",
                "--name",
                f"w{i}",
            )
        _wait_for_workers(address, 2, timeout=120.0)
        if pids is not None:
            pids.extend(p.pid for p in procs)
        yield address
    finally:
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)


def _wait_for_workers(address: str, n: int, timeout: float) -> None:
    from distributed import Client

    deadline = time.monotonic() + timeout
    with Client(address, timeout=timeout) as client:
        while len(client.scheduler_info()["workers"]) < n:
            assert time.monotonic() < deadline, f"{n} workers did not join {address}"
            time.sleep(0.5)


def test_scheduler_and_workers_give_the_local_and_single_run_numbers(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP, encoding="utf-8")
    assert (
        main(["batch", "sim", str(sweep), "--workers", "2", "--out", str(tmp_path / "local")]) == 0
    )
    local = read_table(tmp_path / "local" / "results.parquet")
    with dask_cluster(tmp_path) as address:
        status = main(
            ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "remote")]
        )
        info = json.loads((tmp_path / "remote" / "batch.json").read_text())
    assert status == 0
    assert info["scheduler"] == address and info["workers"] == 2
    remote = read_table(tmp_path / "remote" / "results.parquet")
    assert len(remote) == len(local) == 4
    assert all(r["status"] == "ok" for r in remote)
    assert [comparable(r) for r in remote] == [comparable(r) for r in local]
    # and a case run alone, as its command line says, in a process of its own
    for row in (remote[0], remote[-1]):
        argv = shlex.split(row["command"])
        argv[argv.index("--out") + 1] = str(tmp_path / row["case_id"])
        done = subprocess.run(
            [str(BIN / "leafgate"), *argv[1:], "--no-plots"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr
        alone = json.loads((tmp_path / row["case_id"] / "metrics.json").read_text())
        for key, value in alone.items():
            if key in WALL_CLOCK_METRICS or key in ("controller", "plant"):
                continue
            expected = json.dumps(value) if isinstance(value, (list, dict)) else value
            assert row[key] == expected, key


def test_unreachable_scheduler_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP, encoding="utf-8")
    address = f"tcp://127.0.0.1:{free_port()}"  # nobody listens there
    status = main(
        ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err.strip()
    assert status == 1
    assert err.count("\n") == 0 and "Traceback" not in err
    assert f"--scheduler {address}: cannot connect" in err


def test_a_scheduler_port_out_of_range_is_one_line_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: "cannot connect: Timed out … after 10 s" for a port no address can have."""
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP, encoding="utf-8")
    address = "tcp://127.0.0.1:99999"
    status = main(
        ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "o")]
    )
    assert status == 1
    assert (
        capsys.readouterr().err
        == f"leafgate: error: --scheduler {address}: port 99999 is not 1–65535\n"
    )
    assert not (tmp_path / "o").exists()


def test_scheduler_without_workers_fails_in_one_line_after_the_stated_wait(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A scheduler with no worker holds the tasks forever (``--timeout`` never starts): the
    batch waits ``--wait-workers`` s, says so, then fails in one line and runs no case."""
    from distributed import LocalCluster

    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP, encoding="utf-8")
    with LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp://",  # a real address, as `dask scheduler` gives (not inproc)
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        address = cluster.scheduler_address
        argv = ["batch", "sim", str(sweep), "--scheduler", address, "--timeout", "5"]
        status = main([*argv, "--wait-workers", "3", "--out", str(tmp_path / "o")])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert status == 1
    assert "Traceback" not in captured.err
    assert f"{address}: no workers yet; waiting up to 3 s" in err[0]
    assert err[-1].endswith(f"--scheduler {address}: no workers joined in 3 s")
    assert "cases, " not in captured.out  # no summary: no case ran


def _finished_tasks(address: str) -> int:
    """Tasks whose results the scheduler holds (asked from a client of its own)."""
    from distributed import Client

    def count(dask_scheduler: Any = None) -> int:
        return sum(ts.state == "memory" for ts in dask_scheduler.tasks.values())

    with Client(address, timeout=30) as client:
        return int(client.run_on_scheduler(count))


class _Terminal:
    """A pseudo-terminal for a child's stderr, so that the batch draws its progress bar
    (``… 3/60 cases, 0 failed …``: what the batch itself has received, not the scheduler)."""

    def __init__(self) -> None:
        import pty

        self.master, self.slave = pty.openpty()
        self.text = ""

    def read(self, wait: float = 0.2) -> str:
        """What the child wrote since, waiting up to ``wait`` s for something."""
        import select

        while select.select([self.master], [], [], wait)[0]:
            try:
                chunk = os.read(self.master, 65536)
            except OSError:  # the child has gone and closed its side
                break
            if not chunk:
                break
            self.text += chunk.decode(errors="replace")
            wait = 0.0
        return self.text

    def received(self) -> int:
        """The cases the progress bar last said the batch has received."""
        import re

        counts = re.findall(r"\] (\d+)/\d+ ", self.text)
        return int(counts[-1]) if counts else 0

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def test_a_lost_scheduler_keeps_the_finished_cases_in_one_line(tmp_path: Path) -> None:
    """The scheduler killed mid-batch: the cases received are written, the others listed as
    not run, and stderr holds one line. Before: CancelledError tracebacks from the client, then
    "Timed out trying to connect", exit 1, and no --out: the finished cases were lost.

    The kill waits for the batch's own progress bar (stderr on a pseudo-terminal) to count
    three cases received: the scheduler's count of finished tasks runs ahead of the batch,
    which looks every 50 ms, and a kill in between left it fewer than three."""
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP.replace("samples: 2", "samples: 30"), encoding="utf-8")
    pids: list[int] = []
    terminal = _Terminal()
    try:
        with dask_cluster(tmp_path, pids) as address:
            argv = [
                "batch",
                "sim",
                str(sweep),
                "--scheduler",
                address,
                "--out",
                str(tmp_path / "o"),
            ]
            with (tmp_path / "out").open("w+") as out:
                batch = subprocess.Popen(
                    [str(BIN / "leafgate"), *argv],
                    stdout=out,
                    stderr=terminal.slave,
                    start_new_session=True,
                )
                try:
                    deadline = time.monotonic() + 120
                    while terminal.received() < 3:
                        terminal.read()
                        assert batch.poll() is None and time.monotonic() < deadline
                    os.killpg(pids[0], signal.SIGKILL)  # the scheduler
                    status = batch.wait(timeout=120)
                finally:
                    if batch.poll() is None:
                        os.killpg(batch.pid, signal.SIGKILL)
                        batch.wait()
                out.seek(0)
                stdout = out.read()
        everything = terminal.read().replace("\r\n", "\n")
        # the bar's redraws end in a blank line drawn over it: the lines after are the messages
        stderr = everything.split("\r")[-1]
    finally:
        terminal.close()
    assert status == 1, everything
    assert "Traceback" not in everything + stdout and "CancelledError" not in everything + stdout
    lines = stderr.strip().splitlines()
    assert lines, stdout  # before: cases recorded as "failed: cancelled", and nothing said
    assert lines[-1].startswith(f"leafgate: error: lost the scheduler {address}: "), stderr
    assert "not run; what finished is in" in lines[-1]
    rows = read_table(tmp_path / "o" / "results.parquet")
    assert len(rows) == 60
    statuses = [r["status"] for r in rows]
    assert statuses.count("ok") >= 3 and "not run" in statuses
    assert set(statuses) <= {"ok", "not run"}


def test_a_result_lost_in_transit_is_the_lost_scheduler_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scheduler dies while the client gathers a result: distributed raises
    ``CommClosedError`` from ``Future.result()``. That is the lost scheduler too: one line, exit
    1, the rows received kept, every other case ``not run``. Before (07779e5) the batch ended in
    ``leafgate: error: in <TCP (closed) …>: Stream is closed`` and wrote nothing.

    The test above reaches this path only when its kill happens to fall during a gather; here
    the third gather fails, whatever the timing."""
    from distributed.client import Future
    from distributed.comm.core import CommClosedError

    gathered = 0
    real_result = Future.result

    def result_lost_on_the_third(self: Future[Any], timeout: float | None = None) -> Any:
        nonlocal gathered
        gathered += 1
        if gathered == 3:
            raise CommClosedError("in <TCP (closed) ConnectionPool.gather>: Stream is closed")
        return real_result(self, timeout)

    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP.replace("samples: 2", "samples: 3"), encoding="utf-8")
    # a worker process: a case in a thread of this one would redirect this process's stderr
    with process_cluster() as cluster:
        address = cluster.scheduler_address
        monkeypatch.setattr(Future, "result", result_lost_on_the_third)
        status = main(
            ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "o")]
        )
        monkeypatch.undo()
    captured = capsys.readouterr()
    assert gathered == 3
    assert status == 1
    assert "Traceback" not in captured.err + captured.out
    assert "Stream is closed" not in captured.err + captured.out
    err = captured.err.strip().splitlines()
    assert err == [
        f"leafgate: error: lost the scheduler {address}: 4 of 6 not run; "
        f"what finished is in {tmp_path / 'o'}"
    ], captured.err
    rows = read_table(tmp_path / "o" / "results.parquet")
    assert len(rows) == 6
    statuses = [r["status"] for r in rows]
    assert statuses.count("ok") == 2 and statuses.count("not run") == 4
    assert all(
        r["error"] == f"not run: lost the scheduler {address}"
        for r in rows
        if r["status"] == "not run"
    )
    assert "4 not run (lost the scheduler" in captured.out


@contextlib.contextmanager
def _frozen_after_two_cases(address: str, scheduler_pid: int) -> Iterator[threading.Event]:
    """A thread that stops the scheduler (SIGSTOP: it keeps its connections and never answers,
    as a frozen host or a network that drops its packets does) once it holds two finished
    cases; the event is set then. The scheduler is continued after, so that it can be stopped."""
    frozen = threading.Event()
    done = threading.Event()

    def freeze() -> None:
        deadline = time.monotonic() + 120
        while not done.is_set() and time.monotonic() < deadline:
            if _finished_tasks(address) >= 2:
                os.killpg(scheduler_pid, signal.SIGSTOP)
                frozen.set()
                return
            time.sleep(0.2)

    thread = threading.Thread(target=freeze, daemon=True)
    thread.start()
    try:
        yield frozen
    finally:
        done.set()
        thread.join(timeout=150)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(scheduler_pid, signal.SIGCONT)


def test_a_scheduler_that_stops_answering_is_lost_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scheduler that keeps its connection open and never answers (stopped, or cut off by a
    network that drops packets): the batch waited forever, and Ctrl-C did not end it either.
    Now it counts the scheduler lost after ANSWER_S without an answer (here 3 s)."""
    from leafgate.batch import engine

    monkeypatch.setattr(engine, "ANSWER_S", 3.0)
    monkeypatch.setattr(engine, "PROBE_S", 0.5)
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP.replace("samples: 2", "samples: 30"), encoding="utf-8")
    pids: list[int] = []
    with dask_cluster(tmp_path, pids) as address:
        with _frozen_after_two_cases(address, pids[0]) as frozen:
            status = main(
                ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "o")]
            )
        assert frozen.is_set()
    captured = capsys.readouterr()
    assert status == 1
    assert "Traceback" not in captured.err + captured.out
    err = captured.err.strip().splitlines()
    assert err[-1].startswith(
        f"leafgate: error: lost the scheduler {address} (no answer in 3 s): "
    ), captured.err
    rows = read_table(tmp_path / "o" / "results.parquet")
    assert len(rows) == 60
    statuses = [r["status"] for r in rows]
    assert "not run" in statuses and set(statuses) <= {"ok", "not run"}


def test_ctrl_c_ends_a_batch_whose_scheduler_stopped_answering(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while the scheduler is silent: the questions after it (attempts, workers) are
    bounded, so the batch writes what it received and exits 130. Before, it asked the silent
    scheduler for the attempts and waited forever."""
    from leafgate.batch import engine

    monkeypatch.setattr(engine, "ANSWER_S", 3600.0)  # not lost by silence: Ctrl-C ends it
    monkeypatch.setattr(engine, "ANSWER_AFTER_CTRL_C_S", 2.0)
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(SWEEP.replace("samples: 2", "samples: 30"), encoding="utf-8")
    pids: list[int] = []

    def ctrl_c_once_frozen(frozen: threading.Event) -> None:
        if frozen.wait(timeout=150):
            os.kill(os.getpid(), signal.SIGINT)  # the batch's handler takes it

    with dask_cluster(tmp_path, pids) as address:
        with _frozen_after_two_cases(address, pids[0]) as frozen:
            sender = threading.Thread(target=ctrl_c_once_frozen, args=(frozen,), daemon=True)
            sender.start()
            status = main(
                ["batch", "sim", str(sweep), "--scheduler", address, "--out", str(tmp_path / "o")]
            )
            sender.join(timeout=10)
        assert frozen.is_set()
    captured = capsys.readouterr()
    assert status == 130, captured.err
    assert "Traceback" not in captured.err + captured.out
    rows = read_table(tmp_path / "o" / "results.parquet")
    assert len(rows) == 60
    statuses = [r["status"] for r in rows]
    assert "not run" in statuses and set(statuses) <= {"ok", "not run"}
