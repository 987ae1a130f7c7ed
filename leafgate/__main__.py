"""``python -m leafgate``: the ``leafgate`` command."""

import sys

from leafgate.cli import main

sys.exit(main())
