"""python-can buses from the configuration.

On the car
----------
The in-vehicle computer reaches both Leaf buses through SocketCAN (a USB or PCIe CAN
adapter, 500 kbit/s). The kernel interface is brought up outside leafgate, e.g. by a
systemd-networkd ``.network`` file or::

    ip link set can0 type can bitrate 500000 restart-ms 100
    ip link set can0 up

and the config names it::

    can:
      dbw: {interface: socketcan, channel: can0}   # gateway <-> drive-by-wire ECU
      car: {interface: socketcan, channel: can1}   # the Leaf's CAR-CAN, read only

SocketCAN applies the ``can_filters`` in the kernel, so the gateway's socket only wakes up
for the frames it decodes; ``bitrate`` is ignored there (it belongs to ``ip link``).

Without kernel CAN
------------------
``virtual`` connects buses of the same channel name inside one process (filters applied in
software, no rate limiting, no arbitration). ``udp_multicast`` connects processes on one
host or LAN; its channel is a multicast group address (python-can's default is
``ff15:7079:7468:6f6e:6465:6d6f:6d63:6173``). It needs the ``msgpack`` package, and it
delivers a bus's own frames back to it (multicast loopback: the gateway recognises its own
echoes). Any other python-can interface is opened by name with ``kwargs`` passed through.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from types import TracebackType
from typing import Any

import can

from leafgate.config.can import BusConfig, CanConfig
from leafgate.errors import BusError

__all__ = ["Buses", "copy_frame", "discard_queued", "filters_for", "open_bus", "open_buses"]

_STANDARD_MASK = 0x7FF  # all 11 bits of a standard ID must match
# A standard-ID filter on bit 11, which no standard ID has: it delivers nothing.
_NOTHING = {"can_id": 0x800, "can_mask": 0x800, "extended": False}


def copy_frame(msg: can.Message, **changes: Any) -> can.Message:
    """A copy of a frame, every field kept but ``changes`` (the original may be shared)."""
    fields: dict[str, Any] = {
        "timestamp": msg.timestamp,
        "arbitration_id": msg.arbitration_id,
        "is_extended_id": msg.is_extended_id,
        "is_remote_frame": msg.is_remote_frame,
        "is_error_frame": msg.is_error_frame,
        "channel": msg.channel,
        "dlc": msg.dlc,
        "data": msg.data,
        "is_fd": msg.is_fd,
        "is_rx": msg.is_rx,
        "bitrate_switch": msg.bitrate_switch,
        "error_state_indicator": msg.error_state_indicator,
    }
    fields.update(changes)
    return can.Message(**fields)


def filters_for(receive_ids: Iterable[int] | None) -> list[dict[str, int | bool]] | None:
    """python-can ``can_filters`` delivering exactly the given standard IDs.

    :param receive_ids: the standard IDs to deliver; None delivers everything, an empty
        collection nothing (a send-only bus)
    :raises ValueError: for an ID outside 0..0x7FF
    """
    if receive_ids is None:
        return None
    ids = sorted(set(receive_ids))
    if not ids:
        return [dict(_NOTHING)]
    for frame_id in ids:
        if not 0 <= frame_id <= _STANDARD_MASK:
            raise ValueError(f"0x{frame_id:X} is not a standard 11-bit CAN ID")
    return [{"can_id": i, "can_mask": _STANDARD_MASK, "extended": False} for i in ids]


def open_bus(cfg: BusConfig, receive_ids: Iterable[int] | None = None) -> can.BusABC:
    """Open one python-can bus.

    :param cfg: interface, channel, bitrate and extra keyword arguments
    :param receive_ids: standard IDs to deliver (the codec's ``receive_ids(...)``); None
        delivers every frame, an empty collection none. Interfaces without hardware
        filters (``virtual``, ``udp_multicast``) filter in software, in ``recv``.
    :return: the bus; the caller shuts it down (or uses it as a context manager)
    :raises BusError: the interface is unknown or not available here (no kernel CAN, missing
        driver or package), or the channel cannot be opened; one line naming both
    """
    try:
        can_filters = filters_for(receive_ids)
    except ValueError as exc:
        raise BusError(f"{cfg.interface} channel {cfg.channel!r}: {exc}") from None
    try:
        return can.Bus(
            interface=cfg.interface,
            channel=cfg.channel,
            bitrate=cfg.bitrate,
            can_filters=can_filters,
            receive_own_messages=cfg.receive_own_messages,
            **cfg.kwargs,
        )
    except Exception as exc:  # python-can raises CanError, OSError, ValueError, ImportError …
        raise BusError(
            f"cannot open CAN interface {cfg.interface!r} channel {cfg.channel!r}: {_reason(exc)}"
        ) from exc


DISCARD_BUDGET = 0.2  # s, the longest the queued frames are read away (a flooded bus never empties)


def discard_queued(
    bus: can.BusABC, budget: float = DISCARD_BUDGET, clock: Callable[[], float] = time.monotonic
) -> int:
    """Read away the frames queued on ``bus`` since it was opened; return how many.

    Between opening a bus and starting to read it the daemon opens Zenoh and its recording,
    which takes a second on a loaded machine. The socket's queue holds what the ECU sent
    meanwhile, until it overflows and drops frames. Read late, those frames come as a burst
    stamped at the time they were read, with counter skips where the queue dropped some (a
    recorded start under load showed six E2E errors). They are history from before the
    gateway listened, so they are neither acted on nor recorded.

    A bus that fails to read ends the discarding; the receiver meets the same error.
    """
    count = 0
    end = clock() + budget
    while clock() < end:
        try:
            msg = bus.recv(timeout=0.0)
        except (can.CanError, OSError):
            break
        if msg is None:
            break
        count += 1
    return count


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
        if exc.errno == 97:  # EAFNOSUPPORT: the kernel has no AF_CAN
            text += " (this kernel has no SocketCAN support)"
        elif exc.errno == 19:  # ENODEV
            text += " (no such CAN network interface; is it up?)"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())  # one line


class Buses:
    """The dbw and car buses of one process; ``car is dbw`` when they share a bus.

    A context manager: leaving it shuts both down.
    """

    def __init__(self, dbw: can.BusABC, car: can.BusABC) -> None:
        self.dbw = dbw
        self.car = car

    @property
    def shared(self) -> bool:
        """True when CAR-CAN frames travel on the dbw bus."""
        return self.car is self.dbw

    def shutdown(self) -> None:
        """Shut down both buses (once each); safe to call twice."""
        self.dbw.shutdown()
        if self.car is not self.dbw:
            self.car.shutdown()

    def __enter__(self) -> Buses:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.shutdown()


def open_buses(
    cfg: CanConfig,
    dbw_ids: Iterable[int] | None = None,
    car_ids: Iterable[int] | None = None,
) -> Buses:
    """Open the dbw bus and, unless ``cfg.car`` is None, a separate car bus.

    :param cfg: the ``can:`` section
    :param dbw_ids: IDs to receive on the dbw bus (None: all)
    :param car_ids: IDs to receive from CAR-CAN (None: all). When the buses are shared the
        shared bus receives the union (or everything if either is None).
    :raises BusError: if either bus cannot be opened (nothing is left open then)
    """
    if cfg.car is None:
        if dbw_ids is None or car_ids is None:
            shared_ids: frozenset[int] | None = None
        else:
            shared_ids = frozenset(dbw_ids) | frozenset(car_ids)
        bus = open_bus(cfg.dbw, shared_ids)
        return Buses(bus, bus)
    dbw = open_bus(cfg.dbw, dbw_ids)
    try:
        car = open_bus(cfg.car, car_ids)
    except BaseException:
        dbw.shutdown()
        raise
    return Buses(dbw, car)
