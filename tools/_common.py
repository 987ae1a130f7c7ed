"""Helpers shared by the scripts in ``tools/`` (run as ``python tools/X.py``, so importable as
``_common``) and by the tests (``from tools._common import …``, re-exported by
``tests/conftest.py`` where the suite already looks for its helpers)."""

from __future__ import annotations

import socket
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A loopback port the kernel has just handed out (TCP by default, ``SOCK_DGRAM`` for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
