"""Helpers shared by the test suite: one copy each, imported as ``from tests.conftest import …``.

Every cross-process test takes its own free TCP/UDP port and its own multicast group, so parallel
runs (and a daemon on the defaults) never meet.
"""

from __future__ import annotations

import random

import can

from tools._common import free_port  # one copy for the tests and the tools


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
