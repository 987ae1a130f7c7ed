"""SIGTERM and SIGHUP held from the ``leafgate`` command's first line.

:func:`hold` is the first thing ``leafgate.__main__`` runs (and ``python -m leafgate.cli``):
this module imports ``signal`` only, so that the hold is in place a millisecond after Python
reaches leafgate, not after the imports of :mod:`leafgate.runtime.signals` (logging, threads,
queues: some 12 ms). A signal held is only noted; :mod:`leafgate.runtime.signals` decides what
it means (the daemon's controlled stop, or the default action for every other command).
"""

from __future__ import annotations

import os
import signal
import sys

#: held from the command's first line (SIGINT has its KeyboardInterrupt meanwhile)
HELD_SIGNALS = (signal.SIGTERM, signal.SIGHUP)

_held: list[int] = []  # signals received while held, in order
_original: dict[int, signal._HANDLER] = {}  # the handlers before hold(); empty: nothing held


def hold_handler(signum: int, _frame: object) -> None:
    """The handler while held: the signal noted, nothing done."""
    _held.append(signum)  # list.append: safe in a handler (main thread, between bytecodes)


def hold() -> None:
    """Hold SIGTERM and SIGHUP until the command decides what they mean (main thread only:
    elsewhere, where Python refuses a handler, nothing is held)."""
    if _original:
        return
    try:
        for sig in HELD_SIGNALS:
            _original[sig] = signal.signal(sig, hold_handler)
    except ValueError:  # not the main thread
        return


def held_handlers() -> dict[int, signal._HANDLER]:
    """The handlers :func:`hold` replaced (empty when nothing is held)."""
    return dict(_original)


def take_held() -> list[int]:
    """The signals held so far, in order, and the handlers from before :func:`hold` back."""
    for sig, old in _original.items():
        if signal.getsignal(sig) is hold_handler:
            signal.signal(sig, old)
    _original.clear()
    pending = list(_held)
    _held.clear()
    return pending


EXIT_INTERRUPTED = 130  # 128 + SIGINT


def exit_interrupted(_signum: int = signal.SIGINT, _frame: object = None) -> None:
    """A SIGINT handler where nothing is left to close in order (or a second Ctrl-C asks not
    to wait for it): what was printed is flushed, one line, and the process exits at once with
    status 130. No exception unwinds, so nothing is cut half-way through Python code, and no
    thread is ended inside native code (see :func:`leafgate.runtime.signals.interrupt_deferred`).
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except Exception:  # a reentrant flush, a closed pipe: exit anyway
            pass
    try:  # noqa: SIM105 (contextlib is not loaded yet when the command starts)
        os.write(2, b"leafgate: interrupted\n")  # not through sys.stderr: it may be mid-write
    except OSError:
        pass
    os._exit(EXIT_INTERRUPTED)


def interrupt_once(_signum: int, _frame: object) -> None:
    """A SIGINT handler: the first Ctrl-C raises KeyboardInterrupt (the command closes what it
    opened on its way out), any further one exits at once (:func:`exit_interrupted`) instead of
    raising again inside that closing (a Zenoh session left half-closed)."""
    signal.signal(signal.SIGINT, exit_interrupted)
    raise KeyboardInterrupt
