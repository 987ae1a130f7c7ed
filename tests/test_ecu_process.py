"""The simulated ECU as its own process (``leafgate sim-ecu``), driven from this process over CAN.

The test process plays the gateway with the codec alone: it sends DBW commands with E2E
protection at 50 Hz, engages with an ENABLE edge, commands a steering angle and watches the
ECU's reports follow it. The ``udp_multicast`` variant runs everywhere; the SocketCAN (vcan)
variant needs a kernel with CAN and skips with a reason where there is none.
"""

from __future__ import annotations

import math
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
import yaml

from leafgate.can.codec import CanCodec
from leafgate.messages import EcuState, LongCommand, SteerCommand, SteerReport, SystemReport
from tests.conftest import free_port

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow


def vcan_available() -> str | None:
    """None when vcan0 can be opened, else the reason it cannot."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as s:
            s.bind(("vcan0",))
    except OSError as exc:
        return f"no usable vcan0 here (kernel CAN missing or vcan0 not up: {exc.strerror})"
    return None


def udp_multicast_available() -> str | None:
    try:
        bus = can.Bus(interface="udp_multicast", channel="239.74.163.251", port=free_port())
    except Exception as exc:
        return f"python-can udp_multicast unavailable: {exc}"
    bus.shutdown()
    return None


def drive_ecu(bus_kwargs: dict, tmp_path: Path) -> None:
    """Start sim-ecu on the given bus, engage it, steer, and check the reports follow."""
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["can"]["dbw"] = {
        "interface": bus_kwargs["interface"],
        "channel": bus_kwargs["channel"],
        "kwargs": {k: v for k, v in bus_kwargs.items() if k not in ("interface", "channel")},
    }
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]  # the ECU only connects there
    config = tmp_path / "sim.yaml"
    config.write_text(yaml.safe_dump(cfg))
    log = (tmp_path / "ecu.log").open("wb")
    ecu = subprocess.Popen(
        [sys.executable, "-m", "leafgate.cli", "sim-ecu", "--config", str(config)],
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=ROOT,
    )
    codec = CanCodec(profile="leafgate-dbw")
    target = math.radians(10.0)  # rad, road-wheel
    steer_seen: list[float] = []
    states: list[EcuState] = []
    try:
        with can.Bus(**bus_kwargs) as bus:
            start = time.monotonic()
            next_tick = start
            while time.monotonic() - start < 8.0:
                t = time.monotonic() - start
                enable = t >= 1.5  # ENABLE 0 first, then the 0→1 edge the ECU needs
                angle = target if t >= 2.5 else 0.0
                bus.send(codec.encode(SteerCommand(angle=angle, enable=enable)))
                bus.send(codec.encode(LongCommand(accel=-1.0, enable=enable)))
                next_tick += 0.02
                while (remaining := next_tick - time.monotonic()) > 0:
                    msg = bus.recv(timeout=remaining)
                    if msg is None:
                        continue
                    decoded = codec.decode(msg)
                    if isinstance(decoded.value, SteerReport) and decoded.valid and t >= 2.5:
                        steer_seen.append(decoded.value.angle)
                    elif isinstance(decoded.value, SystemReport) and decoded.valid:
                        states.append(decoded.value.state)
    finally:
        ecu.send_signal(signal.SIGINT)
        try:
            ecu.wait(timeout=10)
        except subprocess.TimeoutExpired:
            ecu.kill()
        log.close()
    output = (tmp_path / "ecu.log").read_text()
    assert EcuState.ENGAGED in states, f"ECU never engaged; states {set(states)}\n{output[-2000:]}"
    assert steer_seen, "no steering reports after the command"
    # The reported road-wheel angle follows the command (rate-limited, then settled).
    assert abs(steer_seen[-1] - target) < math.radians(0.5)
    assert steer_seen[0] < steer_seen[-1]  # it moved towards the target, not jumped there


def test_sim_ecu_process_follows_steering_over_udp_multicast(tmp_path: Path) -> None:
    reason = udp_multicast_available()
    if reason:
        pytest.skip(reason)
    group = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    drive_ecu({"interface": "udp_multicast", "channel": group, "port": free_port()}, tmp_path)


def test_sim_ecu_process_follows_steering_over_socketcan_vcan(tmp_path: Path) -> None:
    reason = vcan_available()
    if reason:
        pytest.skip(reason)
    drive_ecu({"interface": "socketcan", "channel": "vcan0"}, tmp_path)
