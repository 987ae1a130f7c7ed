"""Many independent tasks on Dask distributed: a local cluster by default, or an existing one.

One task per case. A task function returns a row (a dict); the engine adds a failed row for a
task that raised on its worker, or that ran longer than the timeout (its future is cancelled
and, since a running Python call cannot be interrupted, its worker is restarted). Nothing a case
does stops the batch.

A worker that dies while it holds a task (killed, out of memory) is not a failure of the task:
Dask's scheduler gives the task to another worker, up to ``distributed.scheduler.allowed-failures``
times (3 by default), then fails it with ``KilledWorker``. The re-run is legitimate (a case is
deterministic: the same numbers on any worker) but never silent: each row says in ``attempts``
how often it was started, from the scheduler's count of the workers that died holding it.

A batch that stops early (Ctrl-C, the scheduler lost) keeps what finished: the rows received,
and a ``not run`` row for every other task, with ``EngineRun.stopped`` saying why. A scheduler
is lost when its connection closes, and also when it stops answering (frozen, or behind a
network that drops its packets without closing the connection): every question the batch asks
it is bounded by :data:`ANSWER_S`.

The local cluster runs worker *processes* with one thread each: the controllers hold the GIL.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import re
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TextIO

from leafgate.errors import LeafgateError
from leafgate.text import plural

__all__ = ["NOT_RUN", "BatchError", "EngineRun", "run_plain", "run_tasks"]

POLL_S = 0.5  # s between looks at the futures (progress, timeouts)
CONNECT_TIMEOUT_S = 10.0  # s to reach an existing scheduler
WORKERS_WAIT_S = 60.0  # s an existing scheduler may take to get its first worker
#: s a running scheduler may take to answer the batch (a look at it every PROBE_S while tasks
#: run, the questions after them) before it counts as lost. Twice Dask's own comm timeout
#: (distributed.comm.timeouts.tcp, 30 s): a scheduler taking in a large graph stays silent for
#: seconds, one that is stopped or cut off never answers, and a connection that is cut without
#: being closed never tells the client.
ANSWER_S = 60.0
PROBE_S = 5.0  # s between looks at whether the scheduler still answers
#: s the questions after a Ctrl-C may take (the attempts, the workers): the user wants out
ANSWER_AFTER_CTRL_C_S = 5.0
#: ``status`` of a task the batch never got a result for: it stopped first (Ctrl-C, scheduler lost)
NOT_RUN = "not run"
INTERRUPTED = "interrupted (Ctrl-C)"


class BatchError(LeafgateError):
    """The batch cannot run (no scheduler, no output folder)."""


@dataclass
class EngineRun:
    """What the engine did: one row per task key, and how."""

    rows: dict[str, dict[str, Any]] = field(default_factory=dict)
    wall_s: float = 0.0
    workers: int = 0  # 0: not known (the scheduler was lost before it could be asked)
    scheduler: str = "local"
    #: why the batch ended before every task had a row (:data:`INTERRUPTED`, the scheduler
    #: lost); those tasks have a ``not run`` row. None: every task ran or failed on its own.
    stopped: str | None = None

    @property
    def interrupted(self) -> bool:
        return self.stopped == INTERRUPTED

    @property
    def rerun(self) -> int:
        """Tasks started more than once: a worker died while it held them."""
        return sum(1 for r in self.rows.values() if (r.get("attempts") or 1) > 1)


def dask_setup(worker: object) -> None:
    """Run by each local worker process at start (a Dask preload): it ignores SIGINT.

    A Ctrl-C at the terminal reaches the whole process group. The batch process handles it
    and closes the cluster, which stops the workers in order; a worker taking it itself would
    end in a KeyboardInterrupt traceback on the terminal.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class _DeferredInterrupt:
    """Ctrl-C during a batch is noted, and acted on where the cluster can close in order.

    A KeyboardInterrupt raised wherever the main thread happens to be (inside Dask's start-up,
    a submit, or its close) leaves the cluster half open: a task recorded as failed, or a
    traceback from Dask's exit handler. Here the signal only sets a flag; :meth:`check` raises
    between polls, so the ``with`` blocks close the client and the cluster, and the caller
    reports the interrupt. Only the main thread can own a signal handler; elsewhere this does
    nothing.
    """

    def __init__(self) -> None:
        self._set = threading.Event()
        self._owned = False
        self._previous: Any = signal.SIG_DFL

    def __enter__(self) -> _DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT, lambda *_: self._set.set())
            self._owned, self._previous = True, previous if previous is not None else signal.SIG_DFL
        return self

    def __exit__(self, *exc: object) -> None:
        if self._owned:
            signal.signal(signal.SIGINT, self._previous)
        if exc[0] is None:
            self.check()  # a Ctrl-C that came during the close

    def check(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came since the start."""
        if self._set.is_set():
            raise KeyboardInterrupt

    def clear(self) -> None:
        """The Ctrl-C is handled (the batch stopped and keeps what finished): forget it."""
        self._set.clear()


def failed(error: str) -> dict[str, Any]:
    """The row of a task that produced no result."""
    return {"status": "failed", "error": " ".join(error.split())}


def not_run(reason: str) -> dict[str, Any]:
    """The row of a task the batch stopped before: not a failure of the case, and not a pass."""
    return {"status": NOT_RUN, "error": f"not run: {reason}"}


class _OneLineLogs(logging.Filter):
    """Distributed's log records without their tracebacks, and without the empty ones.

    A client whose scheduler goes away logs ``CancelledError`` tracebacks (an empty message
    and a traceback) while it reconnects and closes; the batch says itself, in one line, that
    it lost the scheduler. Records that carry a message keep it, on one line.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith(("distributed", "tornado", "asyncio")):
            return True  # leafgate's own records as they are
        if record.exc_info is not None or record.exc_text:
            record.exc_info, record.exc_text, record.stack_info = None, None, None
        return bool(record.getMessage().strip())


@contextmanager
def _one_line_logs() -> Iterator[None]:
    """:class:`_OneLineLogs` on the handlers distributed's records reach, for the batch."""
    handlers = {*logging.getLogger("distributed").handlers, *logging.getLogger().handlers}
    one_line = _OneLineLogs()
    for handler in handlers:
        handler.addFilter(one_line)
    try:
        yield
    finally:
        for handler in handlers:
            handler.removeFilter(one_line)


class Progress:
    """``[#####.....] 12/20 cases, 1 failed`` on a terminal; nothing when not a TTY."""

    def __init__(self, stream: TextIO | None, total: int, what: str) -> None:
        self.stream = stream if stream is not None and stream.isatty() else None
        self.total, self.what = total, what
        self.done = self.failed = 0
        self.t0 = time.monotonic()

    def add(self, row: Mapping[str, Any]) -> None:
        self.done += 1
        self.failed += row.get("status") != "ok"
        self.draw()

    def draw(self) -> None:
        if self.stream is None:
            return
        fraction = self.done / max(self.total, 1)
        filled = int(30 * fraction)
        elapsed = time.monotonic() - self.t0
        self.stream.write(
            f"\r[{'#' * filled}{'.' * (30 - filled)}] {self.done}/{self.total} {self.what}, "
            f"{self.failed} failed, {elapsed:.0f} s "
        )
        self.stream.flush()

    def close(self) -> None:
        if self.stream is not None:
            self.stream.write("\r" + " " * 78 + "\r")
            self.stream.flush()


def run_plain(fn: Callable[..., dict[str, Any]], tasks: Mapping[str, Sequence[Any]]) -> EngineRun:
    """The same tasks one after another in this process (the baseline of ``bench_batch``)."""
    run = EngineRun(workers=1, scheduler="none (plain loop)")
    t0 = time.perf_counter()
    for key, args in tasks.items():
        try:
            run.rows[key] = fn(*args)
        except Exception as exc:
            run.rows[key] = failed(f"{type(exc).__name__}: {exc}")
    run.wall_s = time.perf_counter() - t0
    return run


def run_tasks(
    fn: Callable[..., dict[str, Any]],
    tasks: Mapping[str, Sequence[Any]],
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    timeout: float | None = None,
    progress: TextIO | None = None,
    what: str = "cases",
    wait_workers: float = WORKERS_WAIT_S,
) -> EngineRun:
    """Run ``fn(*args)`` for every ``key: args`` of ``tasks``, one Dask task each.

    :param fn: a module-level function (workers import it); returns the task's row
    :param scheduler: ``tcp://HOST:PORT`` of a running ``dask scheduler``; None starts a local
        cluster of ``workers`` processes (default: this machine's cores) and closes it after
    :param timeout: s a task may run (counted from when the scheduler hands it to a worker)
    :param progress: the stream for the progress bar (drawn when it is a terminal)
    :param wait_workers: s a running scheduler may take to have a worker. A scheduler with
        none accepts the tasks and holds them: the batch would wait forever, and ``timeout``
        never starts, since no task starts.
    :raises BatchError: the scheduler cannot be reached, has no worker within
        ``wait_workers``, or the local cluster does not start
    """
    from distributed import Client, LocalCluster

    run = EngineRun()
    t0 = time.perf_counter()
    logging.getLogger("distributed").setLevel(logging.WARNING)  # not every start and stop
    with _one_line_logs(), _DeferredInterrupt() as interrupt:
        if scheduler is None:
            n = max(1, workers or os.cpu_count() or 1)
            try:
                cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    # its HTTP server (health, no dashboard without bokeh) on a free loopback
                    # port: on 8787 it would warn whenever another cluster holds that port
                    dashboard_address="127.0.0.1:0",
                    # Workers log only what is critical: a task's error comes back in its row,
                    # and a closing cluster races their heartbeats, which log the closed
                    # stream as an ERROR with a traceback.
                    silence_logs=logging.CRITICAL,
                    preload=[__name__],  # dask_setup below: Ctrl-C is this process's to handle
                )
            except (OSError, RuntimeError) as exc:  # ports, processes
                raise BatchError(f"the local Dask cluster did not start: {exc}") from None
            with cluster, Client(cluster) as client:
                processes = plural(n, "worker process", "worker processes")
                run.workers, run.scheduler = n, f"local cluster ({processes})"
                _submit_and_wait(client, fn, tasks, timeout, progress, what, run, interrupt)
        else:
            port = re.search(r":(\d+)$", scheduler)
            if port is not None and not 0 < int(port[1]) < 65536:  # no connection can say it
                raise BatchError(f"--scheduler {scheduler}: port {port[1]} is not 1–65535")
            try:
                client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError, ValueError) as exc:
                reason = " ".join(str(exc).split()) or type(exc).__name__
                raise BatchError(f"--scheduler {scheduler}: cannot connect: {reason}") from None
            with client, _quiet_if_lost(run):
                run.scheduler = scheduler
                _wait_for_workers(client, scheduler, wait_workers, progress, interrupt)
                _submit_and_wait(
                    client, fn, tasks, timeout, progress, what, run, interrupt, count_workers=True
                )
    run.wall_s = time.perf_counter() - t0
    return run


@contextmanager
def _quiet_if_lost(run: EngineRun) -> Iterator[None]:
    """Closing a client whose scheduler is gone logs its own failed reconnects and
    cancellations: nothing the batch has not said in one line. (The next batch sets the level
    back.)"""
    try:
        yield
    finally:
        if run.stopped is not None and run.stopped != INTERRUPTED:
            logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)


def _wait_for_workers(
    client: Any,
    scheduler: str,
    wait_s: float,
    progress: TextIO | None,
    interrupt: _DeferredInterrupt,
) -> None:
    """Return once the scheduler has a worker; BatchError after ``wait_s`` without one.

    Waits in short steps so that Ctrl-C is acted on, and says once on ``progress`` (stderr)
    that it waits, so a batch that is waiting does not look hung.
    """
    if _ask(client, client.scheduler.identity, ANSWER_S).get("workers"):
        return
    stream = progress if progress is not None else sys.stderr
    stream.write(f"{scheduler}: no workers yet; waiting up to {wait_s:g} s for one to join\n")
    stream.flush()
    deadline = time.monotonic() + wait_s
    while True:
        interrupt.check()
        step = min(POLL_S, deadline - time.monotonic())
        if step <= 0:
            raise BatchError(f"--scheduler {scheduler}: no workers joined in {wait_s:g} s")
        try:
            client.wait_for_workers(1, timeout=step)
            return
        except TimeoutError:
            continue


class _Liveness:
    """Whether the scheduler still answers, asked every :data:`PROBE_S` without blocking the
    wait: a question is sent to the client's event loop and looked at on the next polls."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.asked: concurrent.futures.Future[Any] | None = None
        self.since = 0.0  # when the question now open was asked
        self.next = time.monotonic() + PROBE_S

    def silent(self, now: float) -> bool:
        """True once a question has gone :data:`ANSWER_S` without an answer."""
        if self.asked is None:
            if now >= self.next:
                loop = self.client.loop.asyncio_loop
                self.asked = asyncio.run_coroutine_threadsafe(self._ask(), loop)
                self.since = now
            return False
        if self.asked.done():  # answered, or refused: a closed connection is seen elsewhere
            self.asked, self.next = None, now + PROBE_S
            return False
        return now - self.since > ANSWER_S

    async def _ask(self) -> None:
        with contextlib.suppress(Exception):
            await self.client.scheduler.identity()

    def close(self) -> None:
        if self.asked is not None:
            self.asked.cancel()


def _ask(client: Any, method: Callable[..., Any], wait_s: float, **kwargs: Any) -> Any:
    """``method(**kwargs)`` (a coroutine of the client's) run on the client's loop, or
    TimeoutError after ``wait_s``: the batch never waits without bound on a scheduler."""
    return client.sync(method, callback_timeout=wait_s, **kwargs)


def _submit_and_wait(
    client: Any,
    fn: Callable[..., dict[str, Any]],
    tasks: Mapping[str, Sequence[Any]],
    timeout: float | None,
    progress: TextIO | None,
    what: str,
    run: EngineRun,
    interrupt: _DeferredInterrupt,
    count_workers: bool = False,
) -> None:
    """Submit one task per key and collect the rows; ``count_workers``: set ``run.workers``
    to the workers that ran them (a running cluster's, whose size is not known before).

    Ctrl-C, or a scheduler that goes away, ends the wait: the rows received stay, every other
    task gets a ``not run`` row and ``run.stopped`` says why.
    """
    from distributed import as_completed

    if not tasks:
        return
    token = uuid.uuid4().hex[:8]  # keys stay unique when batches share a cluster
    names = list(tasks)
    columns = list(zip(*tasks.values(), strict=True)) if tasks else []
    futures = client.map(
        fn, *columns, key=[f"leafgate-{token}-{name}" for name in names], pure=False
    )
    pending = dict(zip(futures, names, strict=True))
    bar = Progress(progress if progress is not None else sys.stderr, len(pending), what)
    started: dict[str, float] = {}  # dask key → when first seen on a worker
    done = as_completed(futures)
    next_look = time.monotonic() + POLL_S
    alive = _Liveness(client)
    try:
        while pending and run.stopped is None:
            interrupt.check()
            if alive.silent(time.monotonic()):
                run.stopped = _lost(client, f"no answer in {ANSWER_S:g} s")
                break
            batch = done.next_batch(block=False) if done.has_ready() else []
            for future in batch:
                key = pending.pop(future, None)
                if key is None:  # timed out before, cancelled since
                    continue
                if future.status == "cancelled" and client.status != "running":
                    # not cancelled by the batch (that was a time-out): the client lost the
                    # scheduler, which took the task's state with it
                    pending[future] = key
                    run.stopped = _lost(client)
                    break
                try:
                    row = _row(future)
                except OSError:  # CommClosedError: the scheduler went away while it sent this
                    pending[future] = key
                    run.stopped = _lost(client)
                    break
                run.rows[key] = row
                bar.add(run.rows[key])
            if not batch:
                time.sleep(0.05)
            if time.monotonic() >= next_look and run.stopped is None:
                # not while reconnecting to a scheduler gone away: its calls would wait, then fail
                if client.status == "running" and timeout is not None and pending:
                    try:
                        _time_out(client, pending, started, timeout, run, bar)
                    except (OSError, TimeoutError):  # the scheduler went away during the look
                        run.stopped = _lost(client)
                bar.draw()
                next_look = time.monotonic() + POLL_S
    except KeyboardInterrupt:
        run.stopped = INTERRUPTED
        interrupt.clear()  # the caller writes what finished, then reports the interrupt
    finally:
        alive.close()
        bar.close()
    for key in pending.values():
        run.rows[key] = not_run(run.stopped or "the batch stopped")
    if run.stopped is not None and run.stopped != INTERRUPTED:
        return  # the scheduler is gone: nothing more to ask it
    # every task has its row: a scheduler gone or silent now only leaves these unknown
    wait_s = ANSWER_AFTER_CTRL_C_S if run.interrupted else ANSWER_S
    _count_attempts(client, futures, names, run, wait_s)
    if count_workers:
        run.workers = _workers_that_ran(client, futures, run.workers, wait_s)


def _lost(client: Any, why: str | None = None) -> str:
    return f"lost the scheduler {client.scheduler.address}" + (f" ({why})" if why else "")


def _row(future: Any) -> dict[str, Any]:
    """A finished task's row, or the failed row of one that raised or whose workers died."""
    if future.status == "finished":
        row: dict[str, Any] = future.result()
        return row
    exc = future.exception() if future.status == "error" else None
    if exc is None:
        return failed(future.status)  # cancelled on the cluster by someone else
    if type(exc).__name__ == "KilledWorker":
        # a task queued on a worker that another task kills counts as well: the scheduler
        # cannot tell which of the tasks a worker held killed it
        allowed = getattr(exc, "allowed_failures", None)
        attempts = None if allowed is None else allowed + 1
        row = failed(
            f"KilledWorker: {attempts} workers died while holding it ({allowed} re-runs allowed "
            "by distributed.scheduler.allowed-failures); see the workers' logs"
        )
        row["attempts"] = attempts
        return row
    return failed(f"{type(exc).__name__}: {exc}")


def _suspicious_on_scheduler() -> Callable[..., dict[str, int]]:
    """A function run on the scheduler: each key's count of workers that died holding it.

    Made here, not at module level, so that cloudpickle sends its code (by value): a
    scheduler of your own need not have leafgate installed.
    """

    def suspicious(keys: list[str], dask_scheduler: Any = None) -> dict[str, int]:
        tasks = dask_scheduler.tasks
        return {k: tasks[k].suspicious for k in keys if k in tasks}

    return suspicious


def _count_attempts(
    client: Any, futures: list[Any], names: list[str], run: EngineRun, wait_s: float
) -> None:
    """Set each row's ``attempts``: 1, plus one per worker that died while it held the task,
    running or queued (the scheduler then gave it to another). Read before the futures are
    released, while the scheduler still knows the tasks; None if it cannot be asked."""
    keys = [f.key for f in futures]
    try:
        counts = client.run_on_scheduler(_suspicious_on_scheduler(), keys, callback_timeout=wait_s)
    except Exception:  # refused to run code, gone or silent: the rows say nothing of it
        counts = None
    for key, name in zip(keys, names, strict=True):
        row = run.rows.get(name)
        if row is None or row.get("status") == NOT_RUN or "attempts" in row:
            continue
        row["attempts"] = None if counts is None else 1 + int(counts.get(key, 0))


def _workers_that_ran(client: Any, futures: list[Any], default: int, wait_s: float) -> int:
    """How many workers hold a finished task's result: those that ran the tasks (a result
    stays on the worker that computed it). Read at the end: a cluster's workers may join after
    the batch starts, and a count read at the start missed them. ``default`` when none is
    held (every task failed or timed out): then the scheduler's count at the end."""
    finished = [f for f in futures if f.status == "finished"]
    try:
        if not finished:
            identity = _ask(client, client.scheduler.identity, wait_s)
            return len(identity.get("workers", {})) or default
        holders = _ask(client, client.scheduler.who_has, wait_s, keys=[f.key for f in finished])
    except (OSError, TimeoutError):  # gone or silent after the last task: not known
        return default
    ran = {address for addresses in holders.values() for address in addresses}
    return len(ran) or default


def _time_out(
    client: Any,
    pending: dict[Any, str],
    started: dict[str, float],
    timeout: float,
    run: EngineRun,
    bar: Progress,
) -> None:
    """Record tasks running longer than ``timeout`` as failed; free their workers."""
    now = time.monotonic()
    where: dict[str, str] = {}
    for worker, keys in _ask(client, client.scheduler.processing, ANSWER_S, workers=None).items():
        for k in keys:
            started.setdefault(k, now)
            where[k] = worker
    restart = set()
    for future, key in list(pending.items()):
        since = started.get(future.key)
        if since is not None and now - since > timeout:
            del pending[future]
            future.cancel()
            row = failed(f"timed out after {timeout:g} s")
            run.rows[key] = row
            bar.add(row)
            if future.key in where:
                restart.add(where[future.key])
    if restart:  # a running call cannot be stopped: restart its worker process
        client.restart_workers(sorted(restart), raise_for_error=False)
