"""Buses from config: filters deliver only decoded IDs; failures are one-line BusErrors."""

from __future__ import annotations

import importlib.util
import random
import socket
import uuid

import can
import pytest

from leafgate.can.bus import Buses, filters_for, open_bus, open_buses
from leafgate.can.codec import CanCodec
from leafgate.config import from_mapping
from leafgate.config.can import UDP_MULTICAST_DEFAULT_GROUP, BusConfig, CanConfig
from leafgate.errors import BusError, ConfigError
from leafgate.messages import SteerCommand, SteerReport


def virtual(channel: str) -> BusConfig:
    return BusConfig(interface="virtual", channel=channel)


def frame(frame_id: int) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=bytes(8), is_extended_id=False)


def drain(bus: can.BusABC, timeout: float = 0.05) -> list[int]:
    ids = []
    while (msg := bus.recv(timeout)) is not None:
        ids.append(msg.arbitration_id)
    return ids


def test_virtual_round_trip_delivers_only_the_decoded_ids() -> None:
    channel = f"leafgate-test-{uuid.uuid4().hex}"
    codec = CanCodec(profile="leafgate-dbw")
    with (
        open_bus(virtual(channel), codec.receive_ids("reports")) as gateway,
        open_bus(virtual(channel), codec.receive_ids("commands")) as ecu,
    ):
        gateway.send(CanCodec(profile="leafgate-dbw").encode(SteerCommand(0.1, enable=True)))
        ecu.send(frame(0x123))  # decoded by nobody
        ecu.send(
            CanCodec(profile="leafgate-dbw").encode(
                SteerReport(0.1, 0.0, 0.0, True, False, False, False)
            )
        )
        assert drain(gateway) == [0x0B0]
        assert drain(ecu) == [0x0A0]


def test_receive_ids_none_delivers_everything_and_empty_delivers_nothing() -> None:
    channel = f"leafgate-test-{uuid.uuid4().hex}"
    with (
        open_bus(virtual(channel), None) as everything,
        open_bus(virtual(channel), frozenset()) as nothing,
        open_bus(virtual(channel), None) as sender,
    ):
        for frame_id in (0x000, 0x0A0, 0x7FF):
            sender.send(frame(frame_id))
        sender.send(can.Message(arbitration_id=0x800, data=bytes(8), is_extended_id=True))
        assert drain(everything) == [0x000, 0x0A0, 0x7FF, 0x800]
        assert drain(nothing) == []


def test_filters_reject_ids_outside_11_bits() -> None:
    with pytest.raises(ValueError, match="standard 11-bit"):
        filters_for([0x800])
    with pytest.raises(BusError, match="virtual channel 'x'"):
        open_bus(virtual("x"), [0x800])


def test_unknown_interface_is_a_one_line_bus_error_naming_interface_and_channel() -> None:
    with pytest.raises(BusError) as info:
        open_bus(BusConfig(interface="no_such_interface", channel="can7"))
    text = str(info.value)
    assert "'no_such_interface'" in text and "'can7'" in text
    assert "\n" not in text


def test_shared_buses_are_one_object_receiving_the_union() -> None:
    channel = f"leafgate-test-{uuid.uuid4().hex}"
    with (
        open_buses(CanConfig(dbw=virtual(channel)), [0x0B0], [0x002]) as buses,
        open_bus(virtual(channel)) as sender,
    ):
        assert buses.shared and buses.car is buses.dbw
        for frame_id in (0x0B0, 0x002, 0x0B1):
            sender.send(frame(frame_id))
        assert drain(buses.dbw) == [0x0B0, 0x002]


def test_separate_buses_filter_separately_and_shut_down_together() -> None:
    dbw_channel, car_channel = (f"leafgate-test-{uuid.uuid4().hex}" for _ in range(2))
    cfg = CanConfig(dbw=virtual(dbw_channel), car=virtual(car_channel))
    buses = open_buses(cfg, [0x0B0], [0x284])
    assert isinstance(buses, Buses) and not buses.shared
    with open_bus(virtual(car_channel)) as car_sender:
        car_sender.send(frame(0x284))
        car_sender.send(frame(0x0B0))
        assert drain(buses.car) == [0x284]
        assert drain(buses.dbw) == []
    buses.shutdown()
    buses.shutdown()  # twice is harmless


def test_failing_car_bus_leaves_the_dbw_bus_closed(monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[can.BusABC] = []
    real = can.Bus

    def recording_bus(*args: object, **kwargs: object) -> can.BusABC:
        bus = real(*args, **kwargs)  # type: ignore[arg-type]
        opened.append(bus)
        return bus

    monkeypatch.setattr(can, "Bus", recording_bus)
    cfg = CanConfig(dbw=virtual("a"), car=BusConfig(interface="no_such_interface"))
    with pytest.raises(BusError, match="no_such_interface"):
        open_buses(cfg)
    assert len(opened) == 1 and opened[0]._is_shutdown


def kernel_can_available() -> tuple[bool, str]:
    if not hasattr(socket, "AF_CAN"):
        return False, "this Python has no socket.AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return False, f"the kernel has no SocketCAN support ({exc.strerror})"
    if not any(name == "vcan0" for _, name in socket.if_nameindex()):
        return (
            False,
            "no vcan0 interface (modprobe vcan; ip link add vcan0 type vcan; ip link set vcan0 up)",
        )
    return True, ""


def test_socketcan_round_trip_with_kernel_filters() -> None:
    available, reason = kernel_can_available()
    if not available:
        pytest.skip(reason)
    cfg = BusConfig(interface="socketcan", channel="vcan0")
    with open_bus(cfg, [0x0B0]) as receiver, open_bus(cfg, frozenset()) as sender:
        sender.send(frame(0x123))
        sender.send(frame(0x0B0))
        assert drain(receiver, 0.2) == [0x0B0]


def test_socketcan_without_kernel_support_is_a_bus_error() -> None:
    if kernel_can_available()[0] or not hasattr(socket, "AF_CAN"):
        pytest.skip("needs a Linux kernel without SocketCAN")
    with pytest.raises(BusError, match=r"'socketcan' channel 'vcan0'.*SocketCAN"):
        open_bus(BusConfig(interface="socketcan", channel="vcan0"))


@pytest.mark.skipif(
    importlib.util.find_spec("msgpack") is None, reason="udp_multicast needs msgpack"
)
def test_udp_multicast_round_trip_with_filters() -> None:
    port = random.randint(20000, 60000)  # private port: no cross-talk with other tests
    cfg = BusConfig(
        interface="udp_multicast", channel=UDP_MULTICAST_DEFAULT_GROUP, kwargs={"port": port}
    )
    with open_bus(cfg, [0x0A0]) as receiver, open_bus(cfg, frozenset()) as sender:
        sender.send(frame(0x123))
        sender.send(frame(0x0A0))
        assert drain(receiver, 0.5) == [0x0A0]


def test_udp_multicast_channel_must_be_a_multicast_group() -> None:
    with pytest.raises(ValueError, match="multicast group"):
        BusConfig(interface="udp_multicast", channel="leafgate")
    with pytest.raises(ConfigError, match=r"can\.dbw.*multicast group"):
        from_mapping(
            CanConfig,
            {"dbw": {"interface": "udp_multicast", "channel": "10.0.0.1"}},
            "x.yaml",
            "can",
        )


def test_bus_config_rejects_kwargs_that_repeat_fields() -> None:
    with pytest.raises(ValueError, match="can_filters"):
        BusConfig(kwargs={"can_filters": []})
