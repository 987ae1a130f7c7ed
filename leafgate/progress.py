"""Progress of long work on a terminal: one line rewritten in place on stderr.

Quiet when stderr is not a terminal (a pipe, a log file, CI), so scripted output stays clean.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """``compare: 12/60 drives, 14 s`` on stderr, rewritten at most every ``interval`` s.

    :param label: what is being done
    :param total: the number of steps (None: unknown; only the count is shown)
    :param unit: the steps' name
    :param stream: where to write (default stderr); nothing is written unless it is a TTY
    """

    def __init__(
        self,
        label: str,
        total: float | None = None,
        unit: str = "",
        *,
        stream: TextIO | None = None,
        interval: float = 0.2,
        force: bool = False,
    ) -> None:
        self.label, self.total, self.unit = label, total, unit
        self.stream = stream or sys.stderr
        self.interval = interval
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = force or bool(isatty and isatty())
        self._t0 = time.monotonic()
        self._last = -float("inf")
        self._shown = False

    def update(self, done: float, note: str = "") -> None:
        """Show ``done`` steps (rate-limited)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < self.interval and not (self.total and done >= self.total):
            return
        self._last = now
        count = f"{done:g}" if self.total is None else f"{done:g}/{self.total:g}"
        text = f"{self.label}: {count}{' ' + self.unit if self.unit else ''}"
        text += f", {now - self._t0:.0f} s" + (f" {note}" if note else "")
        try:
            self.stream.write(f"\r\x1b[K{text}")
            self.stream.flush()
        except (OSError, ValueError):
            self.enabled = False
            return
        self._shown = True

    def close(self) -> None:
        """Clear the line, so what follows starts on a clean one."""
        if self._shown:
            try:
                self.stream.write("\r\x1b[K")
                self.stream.flush()
            except (OSError, ValueError):
                pass
            self._shown = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
