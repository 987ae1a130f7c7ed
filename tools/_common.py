"""Helpers shared by the scripts in ``tools/`` (run as ``python tools/X.py``, so importable as
``_common``) and by the tests (``from tools._common import …``, re-exported by
``tests/conftest.py`` where the suite already looks for its helpers)."""

from __future__ import annotations

import re
import socket
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A loopback port the kernel has just handed out (TCP by default, ``SOCK_DGRAM`` for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stub_sample(payload: bytes) -> Any:
    """What a Zenoh subscriber callback receives from a publisher that sends no identity: a real
    ``ZBytes`` payload, no attachment, no source info."""
    import zenoh

    return SimpleNamespace(payload=zenoh.ZBytes(payload), attachment=None, source_info=None)


class StubEntity:
    """A declared Zenoh subscriber, queryable, publisher or token that does nothing."""

    def undeclare(self) -> None:
        pass

    def put(self, payload: bytes) -> None:
        pass


class StubSession:
    """Enough of ``zenoh.Session`` for :class:`~leafgate.runtime.node.GatewayTransport` to
    declare itself on.

    Keeps the subscriber callbacks so that samples can be fed to them directly: the decode
    path is exactly the daemon's, without a network between.
    """

    def __init__(self) -> None:
        self.subscribers: dict[str, Callable[[Any], None]] = {}

    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> StubEntity:
        self.subscribers[key] = callback
        return StubEntity()

    def declare_queryable(self, key: str, callback: Any, **kwargs: Any) -> StubEntity:
        return StubEntity()

    def zid(self) -> str:
        return "0123456789abcdef0123456789abcdef"  # a Zenoh session id, for the ROS tokens

    def declare_publisher(self, key: str, **kwargs: Any) -> StubEntity:
        return StubEntity()

    def liveliness(self) -> StubSession:
        return self

    @property
    def info(self) -> Any:
        """The session's identity (the gateway names its liveliness token after it)."""
        return SimpleNamespace(zid=lambda: "0")

    def declare_token(self, key: str) -> StubEntity:
        return StubEntity()

    def close(self) -> None:
        pass


# --- file error messages ----------------------------------------------------------------------

#: a file error's place in the file
LOCATION = re.compile(r"\b(row \d+|line \d+)\b")
#: whole-file problems of a trajectory file: the file is named, no row or line applies
TRAJECTORY_FILE_LEVEL = (
    "empty file",
    "no header",
    "missing column",
    "unknown column",
    "a column is given twice",
    "waypoint(s), at least",
    "the lists differ in length",
    "expected a list of waypoints",
    ": expected a list of numbers",
    "unknown trajectory format",
)


def after_file(message: str, path: Path) -> str:
    """What a file error says after ``"{path}: "``.

    :raises ValueError: the message is not one line starting with the file, saying why
    """
    if "\n" in message:
        raise ValueError(f"multi-line message: {message!r}")
    prefix = f"{path}: "
    if not message.startswith(prefix):
        raise ValueError(f"message does not start with the file: {message!r}")
    return message[len(prefix) :]


def names_trajectory_place(rest: str) -> bool:
    """A trajectory file error (after the file name) names its row or line, or is about the
    whole file, or about one key of the YAML mapping."""
    return bool(
        LOCATION.search(rest)
        or any(text in rest for text in TRAJECTORY_FILE_LEVEL)
        or re.match(r"(x|y|heading|speed): expected a list", rest)
    )
