"""The import contract of the package layout (issue 14, "Folders that show the architecture").

Walks every module's imports with :mod:`ast` (no import is executed, so a test of the layout
cannot be fooled by import order) and checks the arrows between the layers.
"""

from __future__ import annotations

import subprocess
import sys


def test_loading_the_config_imports_no_controller() -> None:
    """``import leafgate.settings`` (and each section config) loads no algorithm module."""
    code = (
        "import sys, leafgate.settings\n"
        "bad = sorted(m for m in sys.modules if m.startswith('leafgate.control.')"
        " and m not in ('leafgate.control.config', 'leafgate.control.base'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "", f"loading the config imported {out.stdout.strip()}"
