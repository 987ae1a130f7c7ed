"""``python -m leafgate`` and the ``leafgate`` command.

The entry point is here, not in :mod:`leafgate.cli`, so that the daemon's stop signals are held
(:func:`leafgate.runtime.hold.hold`) before the half second of imports ``leafgate.cli``
costs: a SIGTERM or SIGHUP then ends ``leafgate run`` cleanly, not with the default kill. Only
``sys`` and :mod:`leafgate.runtime.hold` (``signal`` only) load before the hold; what runs before
this module (the interpreter, ``site``, the console script) cannot hold anything.
"""

import sys

from leafgate.runtime.hold import hold


def main() -> int:
    """Hold the stop signals, then load and run the command line."""
    hold()
    from leafgate.cli import main as cli_main

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
