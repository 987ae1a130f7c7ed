"""``python -m leafgate`` and the ``leafgate`` command.

The entry point is here, not in :mod:`leafgate.cli`, so that the daemon's stop signals are held
(:func:`leafgate.runtime.signals.hold`) before the half second of imports ``leafgate.cli``
costs: a SIGTERM or SIGHUP then ends ``leafgate run`` cleanly, not with the default kill.
"""

import sys

from leafgate.runtime.signals import hold


def main() -> int:
    """Hold the stop signals, then load and run the command line."""
    hold()
    from leafgate.cli import main as cli_main

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
