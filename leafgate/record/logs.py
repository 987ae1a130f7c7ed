"""Reading recorded CAN frames: python-can log files and the ``/can`` topic of sessions.

:class:`FrameSource` iterates the frames of a file in recorded order and tells how far it has
got (for a progress bar): python-can's readers for ``.log``, ``.asc``, ``.blf``, ``.trc``,
``.csv``, ``.mf4`` (with asammdf, which leafgate does not install) (and gzip),
:class:`~leafgate.record.session.SessionReader` for ``.mcap``.

A session's frames carry the time they were recorded at on the gateway clock (MCAP log time),
so received and sent frames share one clock; in a simulated session it is the frame's own time.

Files cut short by a crash read up to the cut: a session up to its last complete chunk, a BLF
up to its last complete object (python-can's reader stops there), a text log (``.log``,
``.asc``) up to its last complete line — a line without its newline is dropped, since its
beginning may parse as a different frame (``0A0#0102`` of ``0A0#01020304…``). Either way
:attr:`FrameSource.truncated` tells.

A text log whose content is not of its format (binary content, such as a PNG named ``.asc``,
or text of which no line is a frame, such as a JSON file) is refused naming the file, never
read as an empty log.

A rotated log's parts (the recorder's ``can-…_000.blf``, ``can-…_001.blf`` …) are one log, and
so is a session with the sessions that resume it after a write failure (``session-….mcap``,
``session-….2.mcap`` whose ``leafgate.session`` metadata says ``resumes: session-….mcap`` …):
:func:`group_parts` finds them among the files given, in number order, with the numbers
missing, and :class:`ChainedSource` reads them as one. A part that ends without its
end-of-recording marker and is followed by another was given up by the recorder after a write
failure: :attr:`ChainedSource.losses` holds the stretch of time between the two, which the
recorder lost (it starts the next file with the first item after the outage).

Frames the recorder dropped inside a file, when its queue overflowed (the writer fell behind;
nothing failed), are marked where they were lost: a drop marker (:func:`drop_marker`) at the
first dropped frame's time says how many it dropped and over how long. It is not a frame of
the drive: :class:`FrameSource` never yields it and collects it in :attr:`FrameSource.drops`.
:meth:`ChainedSource.lost_spans` is every stretch the recorder lost, of both kinds: the one
list the tools judge the bus's gaps, silences and counters against.
"""

from __future__ import annotations

import codecs
import functools
import importlib.util
import json
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Final, NamedTuple

import can

from leafgate.can.profile import PROFILE_NAMES, Profile, load_profile
from leafgate.config import safe_load_yaml
from leafgate.errors import ConfigError, ReplayError
from leafgate.record.session import (
    META_SESSION,
    TOPIC_CAN,
    SessionDamaged,
    SessionReader,
    frame_from_record,
)
from leafgate.settings import LeafgateConfig, load_config, with_profile

__all__ = [
    "NEEDS_PACKAGE",
    "READABLE_SUFFIXES",
    "ChainedSource",
    "FrameSource",
    "LogParts",
    "RecorderDrop",
    "RecorderLoss",
    "RecordingContext",
    "drop_marker",
    "group_parts",
    "is_recorder_marker",
    "is_session",
    "part_number",
    "readable_suffixes_text",
    "recording_context",
]

#: File suffixes :class:`FrameSource` reads (python-can's logs and leafgate sessions): the one
#: list behind ``batch check``'s default and every help text that lists them.
READABLE_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4", ".mcap")
#: The suffixes whose python-can reader needs a package leafgate does not install, and which.
#: They stay readable suffixes: ``batch check`` fails such a file, saying what it needs,
#: rather than leave it out of a folder's check without a word.
NEEDS_PACKAGE = {".mf4": "asammdf"}


def readable_suffixes_text() -> str:
    """The readable suffixes as help texts list them: ``.log .asc … .mcap; .mf4 needs asammdf``."""
    plain = " ".join(s for s in READABLE_SUFFIXES if s not in NEEDS_PACKAGE)
    needs = "; ".join(f"{s} needs {package}" for s, package in NEEDS_PACKAGE.items())
    return f"{plain}; {needs}" if needs else plain


def _missing_package(path: Path) -> str | None:
    """The package ``path``'s reader needs and this installation lacks, or None."""
    package = NEEDS_PACKAGE.get(path.suffix.lower())
    if package is None or importlib.util.find_spec(package) is not None:
        return None
    return package


# ASC stores times relative to a start written with ms resolution; absolute times keep the
# formats comparable (to ±1 ms for ASC).
_TEXT_READERS: dict[str, Any] = {
    ".log": can.CanutilsLogReader,
    ".asc": functools.partial(can.ASCReader, relative_timestamp=False),
}


# The text formats: what each is called in an error, and how a file of it may begin without a
# frame (a header); a file with text but neither a frame nor such a start is not of the format.
_TEXT_FORMATS: dict[str, tuple[str, tuple[str, ...]]] = {
    ".log": ("candump -L", ()),  # candump's log format; its screen output does not read
    ".asc": ("ASC", ("date ", "base ", "internal events", "begin triggerblock", "//")),
    ".csv": ("CSV", ("timestamp,",)),
    ".trc": ("TRC", (";",)),
}
_SNIFF_BYTES: Final = 8192


def _binary(path: Path) -> bool:
    """Whether the file's beginning is not UTF-8 text (a NUL byte, or invalid UTF-8)."""
    with path.open("rb") as file:
        head = file.read(_SNIFF_BYTES)
    if b"\x00" in head:
        return True
    try:  # not final: a character cut at the end of the sample is not an error
        codecs.getincrementaldecoder("utf-8")().decode(head, final=False)
    except UnicodeDecodeError:
        return True
    return False


def _first_text_line(path: Path) -> str | None:
    """The first non-blank line of a text file, stripped (None: the file has none)."""
    with path.open("r", encoding="utf-8", errors="replace") as file:
        for line in file:
            if line.strip():
                return line.strip()
    return None


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


# The end-of-recording marker: the last frame of every CAN log file and session that was
# closed properly. `replay check` reports a log without it as incomplete, with where it stops.
END_MARKER_ID: Final = 0x1FFFFFFF  # extended ID, outside every DBC
END_MARKER_DATA: Final = b"LGEND\x00\x00\x00"
# A rotated log's part closed properly, the recording going on in the next part: so a check of
# the parts given can tell that the last of them is not the recording's end.
PART_MARKER_DATA: Final = b"LGNXT\x00\x00\x00"


def end_marker(timestamp: float, channel: Any = None, continues: bool = False) -> can.Message:
    """The end-of-recording marker frame (``continues``: of a part, the next part follows)."""
    return can.Message(
        timestamp=timestamp,
        arbitration_id=END_MARKER_ID,
        is_extended_id=True,
        data=PART_MARKER_DATA if continues else END_MARKER_DATA,
        channel=channel,
        is_rx=False,
    )


def is_end_marker(msg: can.Message) -> bool:
    """Whether ``msg`` is an end-of-recording marker: the file was closed properly (the
    recording's end, or a part's before the next one)."""
    return (
        msg.is_extended_id
        and msg.arbitration_id == END_MARKER_ID
        and bytes(msg.data) in (END_MARKER_DATA, PART_MARKER_DATA)
    )


# The drop marker: frames the recorder dropped when its queue overflowed, on the marker's ID:
# ``LGL``, how many (3 bytes), over how many ms from the marker's time (2 bytes), big-endian.
DROP_MARKER_MAGIC: Final = b"LGL"
DROP_MAX_FRAMES: Final = 0xFFFFFF  # a marker counts at most this many frames …
DROP_MAX_SPAN: Final = 0xFFFF / 1000  # … dropped within this many s (the recorder splits)


def drop_marker(first: float, last: float, frames: int, channel: Any = None) -> can.Message:
    """The marker of ``frames`` frames the recorder dropped, the first at ``first`` (s, the
    marker's time), the last at ``last``; the span is rounded up to the ms, so it covers them."""
    span = max(0, math.ceil(round((last - first) * 1000, 6)))
    if not 0 < frames <= DROP_MAX_FRAMES or span > 0xFFFF:
        raise ValueError(f"no drop marker holds {frames} frames over {span} ms")
    return can.Message(
        timestamp=first,
        arbitration_id=END_MARKER_ID,
        is_extended_id=True,
        data=DROP_MARKER_MAGIC + frames.to_bytes(3, "big") + span.to_bytes(2, "big"),
        channel=channel,
        is_rx=False,
    )


def _drop(msg: can.Message) -> tuple[int, float] | None:
    """(frames dropped, span in s) of a drop marker (the caller checked its ID), else None."""
    data = bytes(msg.data)
    if len(data) != 8 or not data.startswith(DROP_MARKER_MAGIC):
        return None
    return int.from_bytes(data[3:6], "big"), int.from_bytes(data[6:8], "big") / 1000


def is_recorder_marker(msg: can.Message) -> bool:
    """Whether ``msg`` is one of the recorder's markers (end of recording, of a part, frames
    dropped): none is a frame of the drive."""
    return (
        msg.is_extended_id
        and msg.arbitration_id == END_MARKER_ID
        and (is_end_marker(msg) or _drop(msg) is not None)
    )


class RecorderDrop(NamedTuple):
    """Frames the recorder dropped inside ``path`` (its queue overflowed): ``frames`` of them,
    from ``start`` to ``end`` (s)."""

    path: Path
    start: float
    end: float
    frames: int


def is_session(path: str | Path) -> bool:
    """True for an MCAP session file (by suffix)."""
    return _session_suffix(Path(path).suffix)


def _session_suffix(suffix: str) -> bool:
    return suffix.lower() == ".mcap"


class FrameSource:
    """The CAN frames of a recording, in file order.

    The recorder's end-of-recording marker is not a frame of the drive: it is not yielded
    (unless ``markers``), and :attr:`ended` tells whether the recording's last frame was one.

    :param path: a python-can log or a ``.mcap`` session
    :param markers: yield the end-of-recording markers too (``replay check``)
    :raises ReplayError: (on iteration) the file is missing, of an unknown format or unreadable
    """

    def __init__(self, path: str | Path, markers: bool = False) -> None:
        self.path = Path(path)
        self.markers = markers
        self.ended = False  # the last frame read was an end-of-recording marker
        self.continues = False  # … one saying the recording goes on in the next part
        if not self.path.is_file():
            raise ReplayError(f"{self.path}: no such file")
        self.size = self.path.stat().st_size
        self.frames = 0
        self.drops: list[RecorderDrop] = []  # the recorder's drop markers read so far
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
        package = _missing_package(self.path)
        if package is not None:
            raise ReplayError(
                f"{self.path}: unreadable: a {self.path.suffix} log needs the {package} package, "
                f"which is not installed (pip install {package})"
            )
        text_format = _TEXT_FORMATS.get(self.path.suffix.lower())
        if text_format is not None and _binary(self.path):
            raise ReplayError(
                f"{self.path}: unreadable: not a{'n' if text_format[0][0] in 'AEIOU' else ''} "
                f"{text_format[0]} log: binary content"
            )
        try:
            for msg in self._frames():
                if msg.arbitration_id == END_MARKER_ID and msg.is_extended_id:
                    drop = _drop(msg)
                    if drop is not None:  # not a frame of the drive, nor an end
                        frames, span = drop
                        self.drops.append(
                            RecorderDrop(self.path, msg.timestamp, msg.timestamp + span, frames)
                        )
                        self.ended = self.continues = False
                        continue
                self.ended = is_end_marker(msg)
                self.continues = self.ended and bytes(msg.data) == PART_MARKER_DATA
                if self.markers or not self.ended:
                    yield msg
        except SessionDamaged as exc:
            raise ReplayError(
                f"{self.path}: unreadable after {self.frames} frames: {exc.reason}"
            ) from None
        except ReplayError:
            raise
        except Exception as exc:  # each reader has its own errors (ValueError, BLFParseError …)
            reason = " ".join((str(exc) or type(exc).__name__).split())
            if self.frames == 0 and "unknown log format" in reason:
                raise ReplayError(
                    f"{self.path}: {reason} (readable: {readable_suffixes_text()})"
                ) from None
            if self.frames == 0 and text_format is not None:
                raise ReplayError(
                    f"{self.path}: unreadable: not a{'n' if text_format[0][0] in 'AEIOU' else ''} "
                    f"{text_format[0]} log: its first line does not parse ({reason})"
                ) from None
            raise ReplayError(
                f"{self.path}: unreadable after {self.frames} frames: {reason}"
            ) from None
        if self.frames == 0 and text_format is not None:
            # python-can's text readers skip what they do not recognise: text of another kind
            # reads as no frames. Only an empty file, or one that begins as the format does (a
            # header without frames), is an empty log.
            first = _first_text_line(self.path)
            name, starts = text_format
            if first is not None and not first.lower().startswith(starts or ("\x00",)):
                raise ReplayError(
                    f"{self.path}: unreadable: not a{'n' if name[0] in 'AEIOU' else ''} {name} log: "
                    f"no line of it is a frame (it begins {first[:40]!r})"
                )

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
                msg = frame_from_record(json.loads(record.data))
                # One clock for frames in and out: the record's log time (the gateway clock).
                # A frame's own time is the kernel's for a received frame, the gateway's for
                # a sent one: two clocks on one bus would make silences out of nothing.
                msg.timestamp = record.log_time * 1e-9
                yield msg
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


_PART_STEM = re.compile(r"^(?P<base>.+)_(?P<number>\d{3,})$")  # a rotated log's part
_RESUMED_STEM = re.compile(r"^(?P<base>.+)\.(?P<number>[1-9]\d*)$")  # a resumed session


@dataclass(frozen=True)
class LogParts:
    """One log as given: a single file, or the parts of one recording in number order (a
    rotated log's, or a session and the sessions resuming it).

    ``missing`` names the parts absent from the numbering (from the first, ``_000`` or the
    session itself, to the last given): deleted, lost, or, for several parts given, not among
    them.
    """

    paths: tuple[Path, ...]
    missing: tuple[Path, ...] = ()

    @property
    def name(self) -> str:
        """The file, or the first part and how many more."""
        if len(self.paths) == 1:
            return str(self.paths[0])
        return f"{self.paths[0]} … {self.paths[-1].name} ({len(self.paths)} parts)"


_Key = tuple[Path, str, str]  # one recording's parts: folder, base stem, suffix


def _first_number(key: _Key) -> int:
    """A rotated log's first part is ``_000``; a session is the first of its resumptions."""
    return 1 if _session_suffix(key[2]) else 0


def _part_name(key: _Key, number: int, width: int = 3) -> Path:
    """The file of part ``number``: ``STEM_NNN.SUFFIX`` of a log; ``STEM.mcap`` (1), then
    ``STEM.N.mcap`` of a session."""
    folder, base, suffix = key
    if not _session_suffix(suffix):
        return folder / f"{base}_{number:0{width}d}{suffix}"
    return folder / (f"{base}{suffix}" if number == 1 else f"{base}.{number}{suffix}")


def _width(path: Path, key: _Key) -> int:
    """The digits of a rotated log's part numbers (3, or more as the recorder went on)."""
    return max(3, len(path.stem) - len(key[1]) - 1)


def _part(path: Path) -> tuple[_Key, int] | None:
    """(the recording this file is a part of, its number) by the file's name alone, or None
    for a file that is no part (a log not named ``STEM_NNN.SUFFIX``). A session is part 1 of
    itself; ``STEM.N.mcap`` (N ≥ 2) is named as its part N."""
    if is_session(path):
        match = _RESUMED_STEM.match(path.stem)
        if match is not None and int(match["number"]) >= 2:
            return (path.parent, match["base"], path.suffix), int(match["number"])
        return (path.parent, path.stem, path.suffix), 1
    match = _PART_STEM.match(path.stem)
    if match is None:
        return None
    return (path.parent, match["base"], path.suffix), int(match["number"])


def part_number(path: Path) -> int | None:
    """The number of a recording's part by its name (see :func:`group_parts`), or None."""
    part = _part(path)
    return None if part is None else part[1]


def resumes(path: Path) -> str | None:
    """The file a session resumes after a write failure (its ``leafgate.session`` metadata),
    None when it resumes none or does not read (a check of it says why)."""
    try:
        with SessionReader(path) as reader:
            value = reader.read_metadata().get(META_SESSION, {}).get("resumes")
    except Exception:  # a damaged file is reported when it is checked, not here
        return None
    return value or None


def _grouped_part(path: Path) -> tuple[_Key, int] | None:
    """:func:`_part`, with a session named as a resumption (``STEM.N.mcap``) a part only when
    its metadata says it resumes the part before (``lap.2.mcap`` may be a drive of its own)."""
    part = _part(path)
    if part is None or not is_session(path) or part[1] == 1:
        return part
    key, number = part
    if resumes(path) != _part_name(key, number - 1).name:
        return None
    return part


def next_part(path: Path) -> Path | None:
    """The rotated log's part after ``path`` (None: ``path`` is not named as a part)."""
    part = _part(path)
    if part is None:
        return None
    key, number = part
    return _part_name(key, number + 1, _width(path, key))


def unread_next_part(parts: LogParts, continues: bool) -> Path | None:
    """The part a rotated log goes on in after the last one given, when it was not given and
    is not left out on purpose (a single part given, the next on disk: as :func:`group_parts`
    counts missing parts)."""
    nxt = next_part(parts.paths[-1]) if continues else None
    if nxt is None or (len(parts.paths) == 1 and nxt.is_file()):
        return None
    return nxt


def group_parts(paths: Sequence[str | Path]) -> list[LogParts]:
    """The files as logs, in the order given: the parts of one recording together and in
    number order — a rotated log's (the recorder's ``STEM_000.SUFFIX``, ``STEM_001.SUFFIX`` … in
    one folder), a session's (``STEM.mcap``, then ``STEM.2.mcap`` … each of whose metadata says
    it ``resumes`` the one before) — and every other file alone. A file given twice is read
    once. This is the one place that decides which files are one recording.

    A number between the first part and the last part given that is not given is ``missing`` —
    unless a single part was given and the others are on disk (one part, checked on purpose).
    """
    groups: dict[_Key, dict[int, Path]] = {}
    for raw in paths:
        path = Path(raw)
        part = _grouped_part(path)
        key = (path, "", "") if part is None else part[0]  # a file alone: itself
        number = -1 if part is None else part[1]
        groups.setdefault(key, {}).setdefault(number, path)
    out = []
    for key, parts in groups.items():
        numbers = sorted(parts)
        ordered = tuple(parts[n] for n in numbers)
        missing: list[Path] = []
        if numbers[0] >= 0:
            width = _width(parts[numbers[0]], key)
            for n in range(_first_number(key), numbers[-1]):
                if n in parts:
                    continue
                name = _part_name(key, n, width)
                if len(parts) == 1 and name.is_file():
                    continue
                missing.append(name)
        out.append(LogParts(ordered, tuple(missing)))
    return out


class RecorderLoss(NamedTuple):
    """A stretch the recorder lost: the part ``before`` ends without its end-of-recording
    marker (given up after a write failure) and the recording goes on in ``after``."""

    before: Path
    after: Path
    start: float  # s, the last frame of ``before``
    end: float  # s, the first frame of ``after``


class ChainedSource:
    """The frames of a rotated log's parts, one after the other (see :class:`FrameSource`).

    :attr:`spans` holds each part read: (its path, first and last timestamp, whether its last
    frame was an end-of-recording marker). What the recorder lost (:attr:`losses`,
    :attr:`drops`, :meth:`lost_spans`) is known up to the frame just yielded: a tool that goes
    frame by frame (``decode``) can tell a frame after a loss as it comes.
    """

    def __init__(self, paths: Sequence[str | Path], markers: bool = False) -> None:
        self.sources = [FrameSource(path, markers=markers) for path in paths]
        self.size = sum(s.size for s in self.sources)
        self.spans: list[tuple[Path, float, float, bool]] = []
        self.losses: list[RecorderLoss] = []  # the stretches between parts the recorder lost
        self._current = 0

    @property
    def frames(self) -> int:
        return sum(s.frames for s in self.sources)

    @property
    def truncated(self) -> bool:
        return any(s.truncated for s in self.sources)

    @property
    def truncated_parts(self) -> list[Path]:
        """The parts read that were cut short (a session without its footer, a text log with a
        cut last line)."""
        return [s.path for s in self.sources if s.truncated]

    def truncation(self) -> str:
        """Which parts were cut short, in words for a report's first line ("" when none): a
        single file is a ``truncated session`` or a log ``cut short``; of a recording's parts,
        the part is named, and a part the recorder gave up after a write failure is said to be
        that (it leaves the file as it is: its cut is the loss reported between it and the
        next, not a crash)."""
        cut = self.truncated_parts
        if not cut:
            return ""
        if len(self.sources) == 1:
            return "truncated session" if is_session(cut[0]) else "cut short"
        given_up = {loss.before for loss in self.losses}
        words = []
        for path in cut:
            if path in given_up:
                words.append(f"part {path.name} cut where the recorder gave it up")
            elif path == self.sources[-1].path:
                what = "a truncated session" if is_session(path) else "cut short"
                words.append(f"the last part, {path.name}, is {what}")
            else:
                words.append(f"part {path.name} is cut short")
        return "; ".join(words)

    @property
    def ended(self) -> bool:
        return self.sources[-1].ended

    @property
    def continues(self) -> bool:
        """The last part read says the recording goes on in a next part."""
        return self.sources[-1].continues

    @property
    def session(self) -> SessionReader | None:
        return self.sources[-1].session

    @property
    def drops(self) -> list[RecorderDrop]:
        """The frames the recorder dropped inside the parts read (its queue overflowed)."""
        return [d for s in self.sources for d in s.drops]

    def lost_spans(self) -> list[tuple[float, float]]:
        """Every stretch (start, end; s) in which the recorder lost frames, of both kinds: the
        hole between a part given up and the next, and the frames dropped inside a part."""
        spans = [(loss.start, loss.end) for loss in self.losses]
        spans += [(d.start, d.end) for d in self.drops]
        return sorted(spans)

    def fraction(self) -> float | None:
        """How much of the parts has been read, 0–1 (None when a reader cannot tell)."""
        if self.size <= 0:
            return None
        done = sum(s.size for s in self.sources[: self._current])
        if self._current < len(self.sources):
            part = self.sources[self._current].fraction()
            if part is None:
                return None
            done += int(part * self.sources[self._current].size)
        return min(1.0, done / self.size)

    def __iter__(self) -> Iterator[can.Message]:
        for index, source in enumerate(self.sources):
            self._current = index
            first = last = float("nan")
            for msg in source:
                if first != first:
                    first = msg.timestamp
                    self._loss_before(source.path, first)
                last = msg.timestamp
                yield msg
            self.spans.append((source.path, first, last, source.ended))
        self._current = len(self.sources)

    def _loss_before(self, path: Path, first: float) -> None:
        """A part whose first frame is at ``first``, after one that ends without its
        end-of-recording marker: the recorder gave that one up (see the module)."""
        if not self.spans:
            return
        before, _, last, ended = self.spans[-1]
        if not ended and math.isfinite(last) and math.isfinite(first):
            self.losses.append(RecorderLoss(before, path, last, first))


class RecordingContext:
    """What a tool needs to read a recording's frames: the configuration and vehicle profile."""

    def __init__(self, config: LeafgateConfig) -> None:
        self.config = config

    @property
    def profile(self) -> Profile:
        return self.config.profile


def recording_context(
    path: str | Path,
    *,
    config: str | Path | LeafgateConfig | None = None,
    profile: str | None = None,
) -> RecordingContext:
    """The configuration and profile to read a recording with; the codec has no default.

    In order: ``profile`` (``--profile NAME|FILE``) over the configuration's; the
    configuration ``config`` (``--config FILE``); a session's recorded configuration. A
    python-can log carries no profile, so without ``--profile`` or ``--config`` it is an error.

    :raises ReplayError: no source names a profile
    :raises ConfigError: the configuration or profile does not load (names the file)
    """
    cfg: LeafgateConfig | None
    if isinstance(config, LeafgateConfig):
        cfg = config
    elif config is not None:
        cfg = load_config(config)
    else:
        cfg = None
        if is_session(path) and Path(path).is_file():
            with SessionReader(path) as reader:
                reader.read_metadata()
                if reader.config_yaml is not None:
                    cfg = reader.config()
    if profile is not None:
        try:
            load_profile(profile)  # a clear error before the configuration is refitted
        except ConfigError as exc:
            raise ConfigError(f"--profile: {exc}") from None
        cfg = with_profile(cfg or LeafgateConfig(), profile)
    if cfg is None:
        if not Path(path).exists():  # not a recording without a profile: no recording at all
            raise ReplayError(f"{path}: no such file")
        raise ReplayError(
            f"{path}: the recording names no vehicle profile; give --profile NAME|FILE "
            f"({', '.join(PROFILE_NAMES)}) or --config FILE{_profiles_beside(Path(path))}"
        )
    return RecordingContext(cfg)


_BESIDE_MAX: Final = 20  # sessions read for the hint of a log that names no profile


def _profiles_beside(path: Path) -> str:
    """A hint for a CAN log that names no profile: the profiles the sessions in its folder were
    recorded with (the daemon records both side by side). Only a hint: nothing tells which
    drive a log is of, so no profile is taken from them."""
    if is_session(path):
        return ""
    found: dict[str, list[str]] = {}
    for session in sorted(path.parent.glob("*.mcap"))[:_BESIDE_MAX]:
        try:
            with SessionReader(session) as reader:
                reader.read_metadata()
                text = reader.config_yaml
            name = safe_load_yaml(text or "")["vehicle"]["profile"]
        except Exception:  # a session that does not tell: no hint from it
            continue
        if isinstance(name, str):
            found.setdefault(name, []).append(session.name)
    if len(found) == 1:
        ((name, sessions),) = found.items()
        which = (
            f"the session beside it, {sessions[0]}, was"
            if len(sessions) == 1
            else f"the {len(sessions)} sessions beside it were"
        )
        hint = f"--profile {name} if the log is of the same drive"
        return f" ({which} recorded with profile {name}: {hint})"
    if found:
        listed = "; ".join(f"{name}: {', '.join(s)}" for name, s in found.items())
        return f" (the sessions beside it were recorded with several profiles: {listed})"
    return ""
