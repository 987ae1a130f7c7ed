"""CAN section of the configuration (``can:``).

.. code-block:: yaml

    can:
      dbw: {interface: socketcan, channel: can0}
      car: {interface: socketcan, channel: can1}   # null: CAR-CAN frames arrive on dbw

A vehicle profile that authenticates its command frames (``leafgate-dbw-auth``) needs a key
file, ``auth_key_file``; a relative path is taken from the config file's directory::

      auth_key_file: leafgate.key    # hex text, mode 0600, owned by the service user

On a machine without kernel CAN, two processes share a bus with python-can's
``udp_multicast`` interface, whose channel is a multicast group address::

      dbw: {interface: udp_multicast, channel: "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"}
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import Any

# python-can's default udp_multicast group (IPv6, link-local scope 5 = site).
UDP_MULTICAST_DEFAULT_GROUP = "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"


@dataclass(frozen=True)
class BusConfig:
    """One python-can bus: the interface by name and its keyword arguments passed through.

    ``interface`` is any python-can interface name (``socketcan``, ``virtual``,
    ``udp_multicast``, ``pcan``, ``kvaser`` …); ``kwargs`` go to ``can.Bus`` unchanged
    (e.g. ``{port: 43113}`` for udp_multicast, ``{fd: true}``).
    """

    interface: str = "virtual"
    channel: str = "leafgate"
    bitrate: int = 500_000  # bit/s; socketcan ignores it (set it with `ip link`)
    receive_own_messages: bool = False  # deliver frames this bus sent back to it
    kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.interface.strip():
            raise ValueError("interface must name a python-can interface")
        if not self.channel.strip():
            raise ValueError("channel must not be empty")
        if self.bitrate <= 0:
            raise ValueError(f"bitrate must be a positive number of bit/s, got {self.bitrate}")
        reserved = {"interface", "channel", "bitrate", "can_filters", "receive_own_messages"}
        clash = sorted(reserved & set(self.kwargs))
        if clash:
            raise ValueError(f"kwargs must not repeat {', '.join(clash)}: set them as keys")
        if self.interface == "udp_multicast":
            try:
                group = ipaddress.ip_address(self.channel)
            except ValueError:
                group = None
            if group is None or not group.is_multicast:
                raise ValueError(
                    "udp_multicast needs a multicast group address as channel "
                    f"(e.g. {UDP_MULTICAST_DEFAULT_GROUP}), got {self.channel!r}"
                )


@dataclass(frozen=True)
class CanConfig:
    """The two channels of the research Leaf; ``car: null`` means CAR-CAN shares the dbw bus.

    ``dbw_dbc`` / ``car_dbc`` name other DBC files than the packaged ones (None: packaged;
    relative to the config file's directory).
    ``auth_key_file``: the key of a profile with authenticated frames
    (:func:`leafgate.can.secoc.load_key`; relative to the config file's directory).
    """

    dbw: BusConfig = field(default_factory=BusConfig)
    car: BusConfig | None = None
    dbw_dbc: str | None = None
    car_dbc: str | None = None
    auth_key_file: str | None = None
