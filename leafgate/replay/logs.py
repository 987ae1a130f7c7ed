"""Reading recorded CAN frames: python-can log files and the ``/can`` topic of sessions.

:class:`FrameSource` iterates the frames of a file in recorded order and tells how far it has
got (for a progress bar): python-can's readers for ``.log``, ``.asc``, ``.blf``, ``.trc``,
``.csv``, ``.mf4`` (and gzip), :class:`~leafgate.replay.session.SessionReader` for ``.mcap``.

Files cut short by a crash read up to the cut: a session up to its last complete chunk, a BLF
up to its last complete object (python-can's reader stops there), a text log (``.log``,
``.asc``) up to its last complete line — a line without its newline is dropped, since its
beginning may parse as a different frame (``0A0#0102`` of ``0A0#01020304…``). Either way
:attr:`FrameSource.truncated` tells.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import can

from leafgate.errors import ReplayError
from leafgate.replay.session import TOPIC_CAN, SessionReader, frame_from_record

__all__ = ["READABLE_SUFFIXES", "FrameSource", "is_session"]

#: File suffixes :class:`FrameSource` reads (python-can's logs and leafgate sessions).
READABLE_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4", ".mcap")

# ASC stores times relative to a start written with ms resolution; absolute times keep the
# formats comparable (to ±1 ms for ASC).
_TEXT_READERS: dict[str, Any] = {
    ".log": can.CanutilsLogReader,
    ".asc": functools.partial(can.ASCReader, relative_timestamp=False),
}


class _CompleteLines:
    """A text file's lines, without a last line that lacks its newline (a cut write).

    One iterator, as a file is: python-can's ASC reader reads the header, then goes on.
    """

    def __init__(self, file: IO[str]) -> None:
        self.file = file
        self.cut = False  # the last line was dropped

    def __iter__(self) -> _CompleteLines:
        return self

    def __next__(self) -> str:
        line = self.file.readline()
        if not line:
            raise StopIteration
        if not line.endswith("\n"):
            self.cut = True
            raise StopIteration
        return line

    def close(self) -> None:
        self.file.close()


def is_session(path: str | Path) -> bool:
    """True for an MCAP session file (by suffix)."""
    return Path(path).suffix.lower() == ".mcap"


class FrameSource:
    """The CAN frames of a recording, in file order.

    :param path: a python-can log or a ``.mcap`` session
    :raises ReplayError: (on iteration) the file is missing, of an unknown format or unreadable
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise ReplayError(f"{self.path}: no such file")
        self.size = self.path.stat().st_size
        self.frames = 0
        self.truncated = False  # a session without its footer, a text log with a cut last line
        self._position: Any = None  # callable giving the bytes consumed, when known
        self.session: SessionReader | None = None

    def fraction(self) -> float | None:
        """How much of the file has been read, 0–1 (None when the reader cannot tell)."""
        if self._position is None or self.size <= 0:
            return None
        try:
            return min(1.0, self._position() / self.size)
        except (OSError, ValueError):
            return None

    def __iter__(self) -> Iterator[can.Message]:
        try:
            yield from self._frames()
        except ReplayError:
            raise
        except Exception as exc:  # each reader has its own errors (ValueError, BLFParseError …)
            reason = " ".join((str(exc) or type(exc).__name__).split())
            if self.frames == 0 and "unknown log format" in reason:
                raise ReplayError(
                    f"{self.path}: {reason} (readable: {', '.join(READABLE_SUFFIXES)})"
                ) from None
            raise ReplayError(
                f"{self.path}: unreadable after {self.frames} frames: {reason}"
            ) from None

    def _frames(self) -> Iterator[can.Message]:
        if self.path.suffix.lower() == ".mcap":
            yield from self._session_frames()
        else:
            yield from self._log_frames()

    def _session_frames(self) -> Iterator[can.Message]:
        with SessionReader(self.path) as session:
            self.session = session
            self._position = session.position
            for record in session.records(frozenset({TOPIC_CAN})):
                self.frames += 1
                yield frame_from_record(json.loads(record.data))
            self.truncated = session.truncated

    def _log_frames(self) -> Iterator[can.Message]:
        suffix = self.path.suffix.lower()
        file: Any = None
        reader: Any
        lines: _CompleteLines | None = None
        if suffix in _TEXT_READERS:
            file = self.path.open("r", encoding="utf-8", errors="replace")
            self._position = file.buffer.tell  # the text layer hides tell() while iterating
            lines = _CompleteLines(file)
            reader = _TEXT_READERS[suffix](lines)
        elif suffix == ".blf":
            file = self.path.open("rb")
            self._position = file.tell
            reader = can.BLFReader(file)
        else:
            reader = can.LogReader(self.path)
        try:
            for msg in reader:
                self.frames += 1
                yield msg
            if lines is not None and lines.cut:
                self.truncated = True
        finally:
            reader.stop()
            if file is not None:
                file.close()
