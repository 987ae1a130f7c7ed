"""``python -m leafgate`` and the ``leafgate`` command.

The entry point is here, not in :mod:`leafgate.cli`, so that the daemon's stop signals are held
(:func:`leafgate.runtime.hold.hold`) before the half second of imports ``leafgate.cli``
costs: a SIGTERM or SIGHUP then ends ``leafgate run`` cleanly, not with the default kill. Only
``sys``, ``atexit``, ``signal`` and :mod:`leafgate.runtime.hold` (``signal``, and ``os``
that the interpreter has loaded) load before the hold; what runs before this
module (the interpreter, ``site``, the console script) cannot hold anything.

Ctrl-C outside the command proper ends the process at once with status 130 and one line,
never a traceback:

- while ``leafgate.cli`` loads: nothing is open yet, and a ``KeyboardInterrupt`` raised inside
  an extension module's initialisation left it half-loaded (scipy's HiGHS wrapper: "ImportError:
  initialization failed"; numpy: a ``RuntimeError`` on the next import of it) and went on as
  that error's traceback;
- once the command has returned (or ended on a ``KeyboardInterrupt`` of its own): Python's
  shutdown joins threads and runs the ``atexit`` callbacks, where a ``KeyboardInterrupt`` was
  "Exception ignored" with a traceback. A hung join or callback still ends on Ctrl-C;
- after the last ``atexit`` callback Python restores SIGINT's default action before it tears
  the modules down (tens of ms with numpy and scipy loaded), and a Ctrl-C there killed the
  process (status −2, a shell's 130 without the line). SIGINT is ignored from that point:
  nothing there can run a Python handler, so ignoring it is the only way to keep the status.
  A hang in that last, native teardown is ended by SIGTERM or Ctrl-\\ (SIGQUIT), not Ctrl-C.
"""

import atexit
import signal
import sys

from leafgate.runtime.hold import EXIT_INTERRUPTED, hold
from leafgate.runtime.hold import exit_interrupted as _interrupted


def _ignore_interrupts() -> None:
    """The last ``atexit`` callback: SIGINT ignored during the modules' teardown (see above)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def main() -> int:
    """Hold the stop signals, then load and run the command line."""
    hold()
    try:
        previous = signal.signal(signal.SIGINT, _interrupted)
    except ValueError:  # not the main thread (an embedding): Python's own handling
        from leafgate.cli import main as cli_main

        return cli_main()
    atexit.register(_ignore_interrupts)  # registered first, so run last
    from leafgate.cli import main as cli_main

    interrupted = False
    status = EXIT_INTERRUPTED
    try:
        signal.signal(signal.SIGINT, previous)  # the command's own handling (KeyboardInterrupt)
        status = cli_main()
    except KeyboardInterrupt:  # another Ctrl-C while the command was ending on one
        interrupted = True
    while True:  # _interrupted in place, whatever Ctrl-C comes before it is (none after)
        try:
            signal.signal(signal.SIGINT, _interrupted)
            break
        except KeyboardInterrupt:
            interrupted = True
    if interrupted:
        _interrupted(signal.SIGINT, None)
    return status


if __name__ == "__main__":
    sys.exit(main())
