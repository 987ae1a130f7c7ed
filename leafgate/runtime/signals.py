"""Stop signals: SIGINT, SIGTERM and SIGHUP ask for the daemon's controlled stop.

SIGHUP is one of them because README section 2 runs the daemon as a shell job: a closed
terminal or ssh session sends SIGHUP, whose default action kills the process at once — no
ENABLE=0 frames (the ECU sees a command timeout and brakes hard) and a recording without its
end marker.

A signal can come before the daemon has built anything (systemd stopping a unit that is still
starting, a job killed at once): Python needs about half a second to import leafgate, the
daemon longer to open its buses. The ``leafgate`` command therefore *holds* SIGTERM and SIGHUP
from its first line (:func:`~leafgate.runtime.hold.hold`, a module that imports ``signal``
only), before the heavy imports; the daemon's :func:`signals_set` takes over what was held, and
every other command gets the default actions back (:func:`release`), a signal held meanwhile
delivered then. SIGINT is not held: Ctrl-C while Python loads leafgate ends the process at once
("interrupted", status 130; ``leafgate.__main__``), as does one after the command returned.

What comes before that first line cannot be held from Python: the interpreter's start, its
``site`` and the console script's ``import re``, some 19 ms after exec on an idle machine
(README, "The daemon on the car"). A SIGTERM or SIGHUP then has its default action (status 143
or 129); nothing of leafgate is open yet, so nothing is left half-open.
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from leafgate.runtime.hold import held_handlers, hold_handler, take_held

log = logging.getLogger(__name__)

#: what stops the daemon (and ``sim-ecu``, ``publish-trajectory``) in a controlled way
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def release() -> None:
    """The handlers from before :func:`~leafgate.runtime.hold.hold` back; a signal held
    meanwhile delivered now."""
    pending = take_held()
    for signum in pending:
        signal.raise_signal(signum)  # the default action: the status a kill gives (143, 129)


def reason(signum: int) -> str:
    """The stop's reason, as the state transition and the log name it."""
    return f"{signal.Signals(signum).name} received"


@contextmanager
def interrupt_deferred() -> Iterator[None]:
    """Ctrl-C during the block is noted and raised as KeyboardInterrupt at its end, so that a
    stop in order is not cut short (main thread only; elsewhere a no-op).

    ``sim --realtime`` stops its gateway and ECU threads before it closes the Zenoh session
    they use. A second Ctrl-C once raised KeyboardInterrupt inside the first thread's join: the
    ECU thread was never told to stop, the session closed under it, and the interpreter exited
    while it was inside Zenoh's native code. Python 3.11 ends such a daemon thread with
    ``pthread_exit`` when it takes the GIL back, an unwinding that the Rust frames it passes
    through do not let by: ``FATAL: exception not rethrown`` and SIGABRT (1 in 20 double
    Ctrl-Cs here).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []

    def note(signum: int, _frame: Any) -> None:
        came.append(signum)  # list.append: safe in a handler

    previous = signal.signal(signal.SIGINT, note)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if came:
        raise KeyboardInterrupt


class StopRequest:
    """Why ``stop`` was set: the signal's reason, or "" when something else set it."""

    def __init__(self) -> None:
        self.reason = ""


@contextmanager
def signals_set(stop: threading.Event) -> Iterator[StopRequest]:
    """SIGINT, SIGTERM and SIGHUP set ``stop`` (main thread only; elsewhere a no-op).

    A signal held since the command's first line (:func:`~leafgate.runtime.hold.hold`) is
    handed over at once.
    Yields a :class:`StopRequest` whose ``reason`` names the signal once one came.

    The handler does not set ``stop`` itself. Python runs it on the main thread between two
    bytecodes, and the main thread spends its time in ``stop.wait`` (the loop's sleep to the
    next tick): caught while it holds the event's lock, ``Event.set`` in the handler waits for
    that lock, held by the thread it runs on, for ever (a daemon that ignored Ctrl-C: once in
    about 130 starts here). The handler only puts the signal on a :class:`queue.SimpleQueue`,
    whose ``put`` is safe in a signal handler; a thread takes it from there, logs it and sets
    ``stop``.
    """
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    signals: queue.SimpleQueue[int | None] = queue.SimpleQueue()

    def relay() -> None:
        while (signum := signals.get()) is not None:
            if not request.reason:
                request.reason = reason(signum)
            log.info("%s: disengaging and shutting down", reason(signum))
            stop.set()

    def handler(signum: int, _frame: Any) -> None:
        signals.put(signum)

    thread = threading.Thread(target=relay, name="leafgate-signals", daemon=True)
    thread.start()
    previous: dict[int, Any] = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    for sig, old in held_handlers().items():  # restore what was before the hold, not the hold
        if previous.get(sig) is hold_handler:
            previous[sig] = old
    for signum in take_held():
        signals.put(signum)
    try:
        yield request
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        signals.put(None)
        thread.join()
