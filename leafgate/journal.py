"""Log lines the systemd journal understands, written off the control thread.

- Every line carries a syslog priority (RFC 5424: 2 crit, 3 err, 4 warning, 5 notice, 6 info,
  7 debug). JSON lines have it as ``"priority"``; under systemd (stdout connected to the
  journal, ``JOURNAL_STREAM``) every line starts with ``<N>``, which journald strips and files
  as the line's priority (``SyslogLevelPrefix=yes``, the default).
- A record may carry its own priority (``extra={"priority": NOTICE}``), e.g. a state transition
  that is worth more than info but is no warning.
- The stream handler sits behind a queue (:class:`logging.handlers.QueueHandler`): the control
  loop only enqueues, and a slow or blocked stdout never delays a tick.
- A reader that closes stdout (``leafgate … | head``) silences the log instead of printing a
  logging traceback for every later line.
"""

from __future__ import annotations

import atexit
import json
import logging
import logging.handlers
import os
import queue
import sys
from typing import Any, TextIO

__all__ = [
    "CRIT",
    "DEBUG",
    "ERR",
    "INFO",
    "NOTICE",
    "WARNING",
    "JsonFormatter",
    "TextFormatter",
    "priority_of",
    "setup_logging",
    "under_journal",
]

CRIT, ERR, WARNING, NOTICE, INFO, DEBUG = 2, 3, 4, 5, 6, 7


def priority_of(record: logging.LogRecord) -> int:
    """The record's syslog priority: its own ``priority`` attribute, else from its level."""
    own = getattr(record, "priority", None)
    if isinstance(own, int):
        return own
    if record.levelno >= logging.CRITICAL:
        return CRIT
    if record.levelno >= logging.ERROR:
        return ERR
    if record.levelno >= logging.WARNING:
        return WARNING
    if record.levelno >= logging.INFO:
        return INFO
    return DEBUG


def under_journal(stream: TextIO | None = None) -> bool:
    """Whether ``stream`` (stdout) is the journal's stream, as systemd says in JOURNAL_STREAM."""
    expected = os.environ.get("JOURNAL_STREAM")
    if not expected:
        return False
    try:
        st = os.fstat((stream or sys.stdout).fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return expected == f"{st.st_dev}:{st.st_ino}"


class TextFormatter(logging.Formatter):
    """``WARNING leafgate.runtime.daemon: message``, with ``<N>`` in front for the journal."""

    def __init__(self, journal: bool = False) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"<{priority_of(record)}>{text}" if self.journal else text


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ``t``, ``level``, ``priority``, ``logger``, ``msg`` and any
    ``fields`` the record carries (``extra={"fields": {...}}``)."""

    def __init__(self, journal: bool = False) -> None:
        super().__init__()
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        priority = priority_of(record)
        data: dict[str, Any] = {
            "t": record.created,
            "level": record.levelname,
            "priority": priority,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        fields = getattr(record, "fields", None)
        if isinstance(fields, dict):
            data.update(fields)
        if record.exc_info:
            data["exc"] = self.formatException(record.exc_info)
        text = json.dumps(data, default=str)
        return f"<{priority}>{text}" if self.journal else text


class _StdoutHandler(logging.StreamHandler):  # type: ignore[type-arg,unused-ignore]
    """A stream handler that goes quiet when its reader has gone (closed pipe)."""

    def handleError(self, record: logging.LogRecord) -> None:
        if isinstance(sys.exc_info()[1], (BrokenPipeError, ValueError)):
            # not setStream(): it flushes the old stream, which fails the same way
            self.stream = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115
            return
        super().handleError(record)


_listener: logging.handlers.QueueListener | None = None


def _stop_listener() -> None:
    """Write what is still queued and stop the listener (at exit, and before a new set-up).

    A Ctrl-C meanwhile (the daemon's second or third, once it has stopped) drops the lines
    still queued instead of ending in "Exception ignored in atexit callback" and a traceback:
    the exit status is decided by then.
    """
    global _listener
    try:
        if _listener is not None:
            _listener.stop()  # writes what is still queued
    except KeyboardInterrupt:
        pass
    finally:
        _listener = None


def setup_logging(
    fmt: str = "text",
    verbose: bool = False,
    *,
    stream: TextIO | None = None,
    journal: bool | None = None,
    queued: bool = True,
) -> logging.Handler:
    """Send the root logger to ``stream`` (stdout) in ``fmt`` ("text" or "json").

    :param journal: prefix ``<N>`` priorities (None: when stdout is the journal's stream)
    :param queued: write from a listener thread, so a caller never waits for the stream
    :returns: the handler installed on the root logger
    """
    global _listener
    _stop_listener()
    stream = stream or sys.stdout
    journal = under_journal(stream) if journal is None else journal
    handler = _StdoutHandler(stream)
    handler.setFormatter(JsonFormatter(journal) if fmt == "json" else TextFormatter(journal))
    root = logging.getLogger()
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not queued:
        root.handlers[:] = [handler]
        return handler
    q: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    front = logging.handlers.QueueHandler(q)
    _listener = logging.handlers.QueueListener(q, handler, respect_handler_level=True)
    _listener.start()
    atexit.register(_stop_listener)
    root.handlers[:] = [front]
    return front
