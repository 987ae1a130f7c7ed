"""Stop signals: SIGINT, SIGTERM and SIGHUP ask for the daemon's controlled stop.

SIGHUP is one of them because README section 2 runs the daemon as a shell job: a closed
terminal or ssh session sends SIGHUP, whose default action kills the process at once — no
ENABLE=0 frames (the ECU sees a command timeout and brakes hard) and a recording without its
end marker.

A signal can come before the daemon has built anything (systemd stopping a unit that is still
starting, a job killed at once): Python needs about half a second to import leafgate, the
daemon longer to open its buses. The ``leafgate`` command therefore *holds* SIGTERM and SIGHUP
from its first line (:func:`hold`), stdlib only, before the heavy imports; the daemon's
:func:`signals_set` takes over what was held, and every other command gets the default actions
back (:func:`release`), a signal held meanwhile delivered then. SIGINT is not held: Ctrl-C
while Python loads leafgate is ``KeyboardInterrupt`` ("interrupted", status 130), as before.
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

log = logging.getLogger(__name__)

#: what stops the daemon (and ``sim-ecu``) in a controlled way
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: held from the command's first line (SIGINT has its KeyboardInterrupt meanwhile)
HELD_SIGNALS = (signal.SIGTERM, signal.SIGHUP)

_held: list[int] = []  # signals received while held, in order
_original: dict[int, Any] = {}  # the handlers before hold(); empty when nothing is held


def _hold_handler(signum: int, _frame: Any) -> None:
    _held.append(signum)  # list.append: safe in a handler (main thread, between bytecodes)


def hold() -> None:
    """Hold SIGTERM and SIGHUP until the command decides what they mean (main thread only)."""
    if _original or threading.current_thread() is not threading.main_thread():
        return
    for sig in HELD_SIGNALS:
        _original[sig] = signal.signal(sig, _hold_handler)


def release() -> None:
    """The handlers from before :func:`hold` back; a signal held meanwhile delivered now."""
    pending = _take()
    for signum in pending:
        signal.raise_signal(signum)  # the default action: the status a kill gives (143, 129)


def _take() -> list[int]:
    """The held signals, and the handlers from before :func:`hold` back in place."""
    for sig, old in _original.items():
        if signal.getsignal(sig) is _hold_handler:
            signal.signal(sig, old)
    _original.clear()
    pending = list(_held)
    _held.clear()
    return pending


def reason(signum: int) -> str:
    """The stop's reason, as the state transition and the log name it."""
    return f"{signal.Signals(signum).name} received"


class StopRequest:
    """Why ``stop`` was set: the signal's reason, or "" when something else set it."""

    def __init__(self) -> None:
        self.reason = ""


@contextmanager
def signals_set(stop: threading.Event) -> Iterator[StopRequest]:
    """SIGINT, SIGTERM and SIGHUP set ``stop`` (main thread only; elsewhere a no-op).

    A signal held since the command's first line (:func:`hold`) is handed over at once.
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
    for sig, old in _original.items():  # restore what was there before the hold, not the hold
        if previous.get(sig) is _hold_handler:
            previous[sig] = old
    for signum in _take():
        signals.put(signum)
    try:
        yield request
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        signals.put(None)
        thread.join()
