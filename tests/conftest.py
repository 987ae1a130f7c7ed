"""Helpers shared by the test suite: one copy each, imported as ``from tests.conftest import …``.

Every cross-process test takes its own free TCP/UDP port and its own multicast group, so parallel
runs (and a daemon on the defaults) never meet.
"""

from __future__ import annotations

import random
import socket

import can


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A loopback port the kernel has just handed out (TCP by default, ``SOCK_DGRAM`` for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def private_group() -> str:
    """An administratively scoped IPv4 group no other test run uses (with a free port)."""
    return f"239.75.{random.randint(1, 250)}.{random.randint(1, 250)}"


def udp_multicast_works() -> bool:
    """python-can's udp_multicast can be opened here (msgpack installed, multicast allowed)."""
    try:
        import msgpack  # noqa: F401  (python-can's udp_multicast needs it)

        bus = can.Bus(interface="udp_multicast", channel=private_group(), port=free_port())
    except Exception:
        return False
    bus.shutdown()
    return True
