"""``leafgate run`` whose dbw bus cannot send while a trigger file exists.

The fault suite's bus-send-error case: python-can's ``udp_multicast`` bus is wrapped here, in
this test-only launcher, so no chaos code lives in the package::

    python tests/faults/send_error_daemon.py TRIGGER_FILE run --config sim.yaml

While ``TRIGGER_FILE`` exists every ``send`` raises :class:`can.CanOperationError`, as a bus
whose controller went bus-off or whose socket buffer is full does.
"""

from __future__ import annotations

import sys
from pathlib import Path

import can
from can.interfaces.udp_multicast import UdpMulticastBus


def main(argv: list[str]) -> int:
    trigger = Path(argv[0])
    real_send = UdpMulticastBus.send

    def send(self: UdpMulticastBus, msg: can.Message, timeout: float | None = None) -> None:
        if trigger.exists():
            raise can.CanOperationError(f"injected send failure ({trigger} exists)")
        real_send(self, msg, timeout)

    UdpMulticastBus.send = send  # type: ignore[method-assign]
    from leafgate.cli import main as leafgate

    return leafgate(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
