"""The simulated ECU on a hostile bus (issue 17, finding 8).

Before: one malformed ``udp_multicast`` datagram ended ``sim-ecu`` (``CanOperationError``
uncaught, exit 1), and 20,000 frames/s of unrelated IDs made it fall behind and time out,
because python-can's software filter makes ``recv(timeout=0)`` give up at the first unrelated
frame. Here the ECU runs in this process on a private group, a separate process floods the
group with unrelated frames and raw junk datagrams, and a genuine sender commands it every
20 ms: the ECU must stay up, count the junk, and read the command frames sent to it (none left
queued behind the flood), decoding every one it reads as the valid frame it is.

What the ECU cannot help is the kernel: a UDP socket's buffer (rmem_default, 208 KiB) holds a
couple of hundred datagrams, some 40 ms of the flood, and an ECU thread not scheduled for longer
(a loaded two-core CI machine) loses frames, commands among them, before it can read them (CI
lost 2 of about 300 at load average 10). So a command the ECU did not read must be one the
kernel counted as dropped on the ECU's socket (``/proc/net/udp``), and at least half of those
sent under the flood must be read: with the old filtered ``recv`` the ECU read one flood frame
a tick, and the kernel dropped three quarters of the commands behind them. Command timeouts are
reported, not asserted: on a loaded machine the sender thread itself may be late. The suite
floods at 5,000 frames/s: at 20,000 the Python decode of every datagram alone needs a good part
of a core, which a CI machine shared with other jobs does not give the ECU; on an idle machine
the ECU keeps up.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace

from can.interfaces.udp_multicast.utils import pack_message
from harness import PROCESS_TEST, free_port, private_group

from leafgate.can.codec import CanCodec
from leafgate.config.can import BusConfig, CanConfig
from leafgate.config.sim import EcuConfig, SimConfig
from leafgate.messages import EcuState, LongCommand, SteerCommand
from leafgate.settings import LeafgateConfig
from leafgate.sim.ecu import RealtimeStats, SimulatedEcu, run_ecu_realtime

pytestmark = PROCESS_TEST

FLOOD_RATE = 5_000  # frames/s of unrelated IDs (20,000 on an idle machine: see the module note)
DURATION = 3.0  # s of commands under the flood
JUNK_EVERY = 250  # frames of the flood between two junk datagrams
DRAIN_WAIT = 60.0  # s the ECU may take to read what is queued after the flood (a hang: a failure)

FLOODER = """
import socket, struct, sys, time
import can
from can.interfaces.udp_multicast.utils import pack_message
group, port, rate, duration = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
JUNK_EVERY = int(sys.argv[5])
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
frame = pack_message(can.Message(arbitration_id=0x321, data=bytes(8), is_extended_id=False))
junk = [b"", b"\\xff" * 3, b"not a can frame", bytes(range(40))]
t0 = time.perf_counter(); sent = 0
while (elapsed := time.perf_counter() - t0) < duration:
    while sent < elapsed * rate:
        sock.sendto(frame, (group, port)); sent += 1
        if sent % JUNK_EVERY == 0:
            sock.sendto(junk[(sent // JUNK_EVERY) % len(junk)], (group, port))
    time.sleep(0.0005)
print(sent)
"""


def udp_socket(port: int) -> tuple[int, int]:
    """``(bytes queued, datagrams dropped)`` of the IPv4 UDP sockets bound to ``port``, from
    ``/proc/net/udp``: the kernel's count of datagrams that found the socket's buffer full."""
    queued = dropped = 0
    with open("/proc/net/udp", encoding="ascii") as table:
        next(table)
        for line in table:
            fields = line.split()
            if int(fields[1].rsplit(":", 1)[1], 16) == port:
                queued += int(fields[4].split(":")[1], 16)  # tx_queue:rx_queue
                dropped += int(fields[12])
    return queued, dropped


def test_ecu_survives_junk_datagrams_and_reads_its_commands_under_a_flood() -> None:
    group, port = private_group(), free_port()
    dbw = BusConfig(interface="udp_multicast", channel=group, kwargs={"port": port})
    config = LeafgateConfig(can=CanConfig(dbw=dbw), sim=replace(SimConfig(), ecu=EcuConfig()))
    stop = threading.Event()
    result: list[RealtimeStats] = []
    states: list[EcuState] = []
    ecus: list[SimulatedEcu] = []

    def on_tick(_now: float, ecu: SimulatedEcu) -> None:
        if not ecus:
            ecus.append(ecu)
        states.append(ecu.state)

    ecu_thread = threading.Thread(
        target=lambda: result.append(run_ecu_realtime(config, stop, on_tick=on_tick)), daemon=True
    )
    # A plain socket, not a bus: a bus would bind the port too, and /proc/net/udp would mix its
    # (unread, overflowing) queue with the ECU's. The datagrams are the bus's.
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    codec = CanCodec(profile="leafgate-dbw")
    command_ids = codec.receive_ids("commands")
    commands = 0

    def command() -> None:
        nonlocal commands
        for value in (SteerCommand(0.0), LongCommand()):
            sender.sendto(pack_message(codec.encode(value)), (group, port))
            commands += 1

    def read_when_drained() -> int:
        """The command frames the ECU has read, once its socket's queue is empty and a tick
        after that has counted what the tick then under way read. Nothing is sent meanwhile:
        every command sent is then read or dropped."""
        deadline = time.monotonic() + DRAIN_WAIT
        while udp_socket(port)[0] > 0:
            assert ecu_thread.is_alive() and time.monotonic() < deadline, "the ECU stopped reading"
            time.sleep(0.01)
        drained_at = len(states)
        while len(states) < drained_at + 2:
            assert ecu_thread.is_alive() and time.monotonic() < deadline, "the ECU stopped ticking"
            time.sleep(0.01)
        stats = ecus[0].codec.stats
        return sum(stats[i].frames for i in command_ids if i in stats)

    flooder = None
    try:
        ecu_thread.start()
        while not states:  # the ECU's socket is open
            assert ecu_thread.is_alive(), "the ECU loop died before its first tick"
            time.sleep(0.01)
        deadline = time.perf_counter() + 0.5
        while time.perf_counter() < deadline:  # commands before the flood: READY
            command()
            time.sleep(0.02)
        ready_ticks = len(states)
        sent_before, read_before = commands, read_when_drained()
        flooder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                FLOODER,
                group,
                str(port),
                str(FLOOD_RATE),
                str(DURATION),
                str(JUNK_EVERY),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        deadline = time.perf_counter() + DURATION
        while time.perf_counter() < deadline:
            command()
            time.sleep(0.02)
        flooded, _ = flooder.communicate(timeout=30)
        read = read_when_drained()
        _, dropped = udp_socket(port)
        stop.set()
        ecu_thread.join(timeout=10)
    finally:
        stop.set()
        if flooder is not None and flooder.poll() is None:
            flooder.kill()
            flooder.wait()
        sender.close()
    assert not ecu_thread.is_alive()
    assert result, "the ECU loop died"
    (stats,) = result
    counters = stats.counters
    assert flooder.returncode == 0, "the flooder failed"
    assert int(flooded) >= FLOOD_RATE * DURATION * 0.5  # the flood really ran
    assert counters.malformed >= 3  # junk was seen, counted, survived
    assert read == stats.frames_received
    unread = commands - read
    sent_in_flood, read_in_flood = commands - sent_before, read - read_before
    print(
        f"ticks {stats.ticks}, overruns {stats.overruns}, timeouts {counters.timeouts}; "
        f"{read_in_flood} of {sent_in_flood} commands read under the flood, {unread} of "
        f"{commands} unread, {dropped} datagrams dropped by the kernel, "
        f"{counters.bad_counter} counter skips"
    )
    # read, not left behind the flood: the old filtered recv read about a quarter
    assert read_in_flood >= sent_in_flood / 2, (read_in_flood, sent_in_flood)
    # a command not read is one the kernel dropped for a full buffer, never one left queued
    assert unread <= dropped, (unread, dropped)
    # every frame read is decoded as the valid command it is: a counter skip is a lost frame
    assert counters.bad_counter <= unread
    assert counters.rx_errors == counters.bad_counter
    assert ready_ticks < len(states)
