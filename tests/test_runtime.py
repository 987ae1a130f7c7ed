"""The daemon's runtime: slots, requests, ticks, bus faults as state, shutdown, systemd notify."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from leafgate.can.codec import CanCodec
from leafgate.config import VehicleConfig
from leafgate.config.gateway import GatewayConfig
from leafgate.config.transport import ZenohConfig
from leafgate.gateway.core import Gateway
from leafgate.messages import (
    ControlOutput,
    EcuState,
    GatewayState,
    Gear,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerCommand,
    SteerReport,
    SystemReport,
    Trajectory,
)
from leafgate.runtime.daemon import StablePlan, same_plan, signals_set, tool_view
from leafgate.runtime.loop import RequestBox, Runtime
from leafgate.runtime.receiver import CanReceiver
from leafgate.runtime.systemd import sd_notify

STRAIGHT = Trajectory(
    x=np.arange(0.0, 20.0, 0.5), y=np.zeros(40), heading=np.zeros(40), speed=np.full(40, 1.0)
)


class HoldController:
    """A controller that asks for nothing: straight wheels, no acceleration."""

    period = 0.02

    def reset(self) -> None:
        pass

    def step(self, pose: Pose, steer_angle: float, trajectory: Trajectory) -> ControlOutput:
        return ControlOutput(steer_angle=0.0, accel=0.0, speed=0.0, gear=Gear.D)


class Inputs:
    """Fresh localization and trajectory stamped on the runtime's clock."""

    def __init__(self, clock) -> None:  # type: ignore[no-untyped-def]
        self.clock = clock

    def latest_pose(self) -> Stamped[Pose]:
        return Stamped(Pose(0.0, 0.0, 0.0, 0.0), self.clock())

    def latest_trajectory(self) -> Stamped[Trajectory]:
        return Stamped(STRAIGHT, self.clock())


class FailingBus(can.BusABC):
    """A bus whose every send fails, like a bus-off controller."""

    def __init__(self) -> None:
        super().__init__(channel="failing")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("bus off")

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        return None, False


def feed_reports(receiver: CanReceiver, ecu_codec: CanCodec) -> None:
    """One fresh, valid set of ECU reports through the receiver (as the Notifier would)."""
    for value in (
        SteerReport(0.0, 0.0, 0.0, False, False, False, False),
        LongReport(0.0, 0.0, Gear.D, 0.0, 0.0, False, False, False, False),
        SystemReport(EcuState.READY, False, False, False, False, 0),
    ):
        receiver.on_message_received(ecu_codec.encode(value))


def make_runtime(bus: can.BusABC, clock) -> tuple[Runtime, CanReceiver]:  # type: ignore[no-untyped-def]
    codec = CanCodec(profile="leafgate-dbw")
    receiver = CanReceiver(codec, clock)
    gateway = Gateway(GatewayConfig(), VehicleConfig(), HoldController())
    return Runtime(gateway, codec, bus, receiver, Inputs(clock), 0.02, clock=clock), receiver


def test_receiver_fills_slots_and_counts_good_and_bad_frames() -> None:
    now = [5.0]
    receiver = CanReceiver(CanCodec(profile="leafgate-dbw"), lambda: now[0])
    ecu_codec = CanCodec(profile="leafgate-dbw")
    feed_reports(receiver, ecu_codec)
    steer = receiver.steer.get()
    assert steer is not None and steer.received == 5.0 and steer.valid
    bad = ecu_codec.encode(SteerReport(0.1, 0.0, 0.0, False, False, False, False))
    bad.data[7] ^= 0xFF  # corrupt the CRC
    receiver.on_message_received(bad)
    assert receiver.take_counts() == (3, 1)
    assert receiver.take_counts() == (0, 0)
    assert receiver.steer.get() is steer  # the bad frame did not replace the good report


def _asker(box: RequestBox, request: OperatorRequest, replies: list[dict], timeout: float = 2):
    thread = threading.Thread(target=lambda: replies.append(box.submit(request, timeout=timeout)))
    thread.start()
    return thread


def _wait_pending(box: RequestBox, count: int) -> None:
    for _ in range(400):
        if len(box) >= count:
            return
        time.sleep(0.005)
    raise AssertionError(f"{len(box)} requests pending, expected {count}")


def test_request_box_answers_from_the_control_thread() -> None:
    box = RequestBox()
    replies: list[dict] = []
    asker = _asker(box, OperatorRequest.ENGAGE, replies)
    _wait_pending(box, 1)
    taken = box.take()
    assert taken.request == OperatorRequest.ENGAGE
    taken.answer({"accepted": True, "state": "ENGAGED", "reason": "engaged"}, "ENGAGED")
    asker.join(timeout=2)
    assert replies == [{"accepted": True, "state": "ENGAGED", "reason": "engaged"}]


def test_request_box_times_out_with_a_refusal() -> None:
    reply = RequestBox().submit(OperatorRequest.ENGAGE, timeout=0.01)
    assert reply["accepted"] is False and "did not answer" in reply["reason"]


def test_abandoned_engage_is_never_executed_later() -> None:
    # issue 17 finding 1: an engage whose client gave up ran when the loop got to it
    box = RequestBox()
    reply = box.submit(OperatorRequest.ENGAGE, timeout=0.01)
    assert "withdrawn" in reply["reason"]
    assert box.take().request is None


def test_disengage_overtakes_and_supersedes_a_queued_engage() -> None:
    # issue 17 finding 1: a stale engage re-engaged the car after the disengage had run
    box = RequestBox()
    replies: list[dict] = []
    engages = [_asker(box, OperatorRequest.ENGAGE, replies) for _ in range(3)]
    _wait_pending(box, 3)
    stop = _asker(box, OperatorRequest.DISENGAGE, replies)
    _wait_pending(box, 4)
    taken = box.take()  # one control tick
    assert taken.request == OperatorRequest.DISENGAGE
    taken.answer({"accepted": True, "state": "STANDBY", "reason": "disengaged"}, "STANDBY")
    for thread in (*engages, stop):
        thread.join(timeout=2)
    assert len(replies) == 4
    assert sum(r["accepted"] for r in replies) == 1
    assert all("superseded by a disengage" in r["reason"] for r in replies if not r["accepted"])
    assert box.take().request is None  # nothing left to run after it


def test_request_box_is_bounded() -> None:
    box = RequestBox(length=2)
    replies: list[dict] = []
    threads = [_asker(box, OperatorRequest.ENGAGE, replies, timeout=0.5) for _ in range(2)]
    _wait_pending(box, 2)
    reply = box.submit(OperatorRequest.RESET, timeout=0.5)
    assert reply["accepted"] is False and reply["reason"].startswith("busy")
    for thread in threads:
        thread.join(timeout=2)


def test_tick_sends_steer_long_and_periodic_system_frames() -> None:
    now = [0.0]
    with (
        can.Bus(interface="virtual", channel="rt-tick") as bus,
        can.Bus(interface="virtual", channel="rt-tick") as listener,
    ):
        runtime, receiver = make_runtime(bus, lambda: now[0])
        ids = []
        for k in range(10):
            now[0] = k * 0.02
            feed_reports(receiver, CanCodec(profile="leafgate-dbw"))
            runtime.tick(now[0])
            while (msg := listener.recv(timeout=0)) is not None:
                ids.append(msg.arbitration_id)
    assert ids.count(0x0A0) == 10 and ids.count(0x0A1) == 10
    assert 1 <= ids.count(0x0A2) <= 3  # DBW_SYSTEM_CMD every 100 ms
    assert runtime.stats.ticks == 10 and runtime.stats.send_errors == 0


def test_bus_send_errors_become_a_fault_not_an_exception() -> None:
    now = [0.0]
    runtime, receiver = make_runtime(FailingBus(), lambda: now[0])
    for k in range(5):
        now[0] = k * 0.02
        feed_reports(receiver, CanCodec(profile="leafgate-dbw"))
        runtime.tick(now[0])  # must not raise
    assert runtime.stats.send_errors >= 2
    assert runtime.gateway.state == GatewayState.FAULT


def test_encode_error_is_counted_and_faults() -> None:
    now = [0.0]
    with can.Bus(interface="virtual", channel="rt-encode") as bus:
        runtime, receiver = make_runtime(bus, lambda: now[0])
        real = runtime.gateway.step

        def bad_step(t, inputs):  # type: ignore[no-untyped-def]
            result = real(t, inputs)
            object.__setattr__(
                result.commands, "steer", SteerCommand(angle=50.0)
            )  # out of DBC range
            return result

        runtime.gateway.step = bad_step  # type: ignore[method-assign]
        for k in range(3):
            now[0] = k * 0.02
            feed_reports(receiver, CanCodec(profile="leafgate-dbw"))
            runtime.tick(now[0])
        runtime.gateway.step = real  # type: ignore[method-assign]
        runtime.tick(0.06)
    assert runtime.stats.encode_errors >= 1
    assert runtime.gateway.state == GatewayState.FAULT


def test_run_ticks_in_real_time_and_disengages_on_stop() -> None:
    with (
        can.Bus(interface="virtual", channel="rt-run") as bus,
        can.Bus(interface="virtual", channel="rt-run") as listener,
    ):
        runtime, receiver = make_runtime(bus, time.perf_counter)
        stop = threading.Event()
        ready = threading.Event()
        ecu_codec = CanCodec(profile="leafgate-dbw")
        feeder_stop = threading.Event()

        def feeder() -> None:
            while not feeder_stop.is_set():
                feed_reports(receiver, ecu_codec)
                time.sleep(0.005)

        threads = [
            threading.Thread(target=feeder, daemon=True),
            threading.Thread(
                target=runtime.run, args=(stop,), kwargs={"on_ready": ready.set}, daemon=True
            ),
        ]
        for t in threads:
            t.start()
        assert ready.wait(2.0)
        time.sleep(0.3)
        reply = runtime.requests.submit(OperatorRequest.ENGAGE, timeout=2.0)
        stop.set()
        threads[1].join(timeout=5.0)
        feeder_stop.set()
        frames = []
        while (msg := listener.recv(timeout=0)) is not None:
            frames.append(msg)
    assert reply["state"] in ("ENGAGED", "STANDBY")  # answered by the control thread
    assert runtime.stats.ticks > 10
    last_steer = [
        CanCodec(profile="leafgate-dbw").decode(m).value
        for m in frames
        if m.arbitration_id == 0x0A0
    ][-1]
    assert isinstance(last_steer, SteerCommand) and last_steer.enable is False  # disengaged on stop


def test_sd_notify_sends_ready_to_the_notify_socket(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(str(path))
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        assert sd_notify("READY=1")
        assert server.recv(64) == b"READY=1"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not sd_notify("READY=1")  # outside systemd: a no-op


def test_stable_plan_keeps_one_object_for_a_republished_plan() -> None:
    copy = Trajectory(
        x=STRAIGHT.x.copy(), y=STRAIGHT.y.copy(), heading=STRAIGHT.heading, speed=STRAIGHT.speed
    )
    other = Trajectory(
        x=STRAIGHT.x + 1.0, y=STRAIGHT.y, heading=STRAIGHT.heading, speed=STRAIGHT.speed
    )
    samples = iter([Stamped(STRAIGHT, 1.0), Stamped(copy, 2.0), Stamped(other, 3.0)])

    class Source:
        def latest_pose(self) -> None:
            return None

        def latest_trajectory(self) -> Stamped[Trajectory]:
            return next(samples)

    plan = StablePlan(Source())
    first = plan.latest_trajectory()
    second = plan.latest_trajectory()
    third = plan.latest_trajectory()
    assert first is not None and second is not None and third is not None
    assert second.value is STRAIGHT and second.received == 2.0
    assert third.value is other
    assert same_plan(STRAIGHT, copy) and not same_plan(STRAIGHT, other)


def test_tools_connect_to_the_daemons_endpoint_instead_of_listening() -> None:
    cfg = ZenohConfig(listen=("tcp/127.0.0.1:7447",), connect=("tcp/10.0.0.2:7447",))
    tool = tool_view(cfg)
    assert tool.connect == ("tcp/127.0.0.1:7447", "tcp/10.0.0.2:7447")
    # It listens on a port the system picks, on the daemon's interface, so that tools can
    # reach each other directly (the daemon's gossip names them), never on the daemon's port.
    assert tool.listen == ("tcp/127.0.0.1:0",) and tool.mode == "peer"


if os.name != "posix":  # AF_UNIX datagram sockets
    pytest.skip("POSIX only", allow_module_level=True)


def test_report_age_counts_from_the_frames_receive_timestamp() -> None:
    # issue 17, finding 7: a starved receive thread made the ECU's reports look 31-54 ms old
    codec = CanCodec(profile="leafgate-dbw")
    receiver = CanReceiver(
        CanCodec(profile="leafgate-dbw"), lambda: 100.0, wall_clock=lambda: 5000.0
    )
    msg = codec.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False))
    msg.timestamp = 5000.0 - 0.045  # arrived 45 ms before the Notifier thread got to it
    receiver.on_message_received(msg)
    steer = receiver.steer.get()
    assert steer is not None and steer.received == pytest.approx(100.0 - 0.045)
    for stamp in (0.0, 5000.5, 5000.0 - 60.0):  # unset, in the future, implausibly old
        msg = codec.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False))
        msg.timestamp = stamp
        receiver.on_message_received(msg)
        steer = receiver.steer.get()
        assert steer is not None and steer.received == 100.0


def test_late_echo_after_a_stall_is_still_our_own() -> None:
    # issue 17, finding 5: after a 4 s stall the gateway's own echoes counted as foreign
    now, wall = [10.0], [1000.0]
    codec = CanCodec(profile="leafgate-dbw")
    receiver = CanReceiver(codec, lambda: now[0], wall_clock=lambda: wall[0])
    frame = codec.encode(SteerCommand(0.0))
    receiver.sent.add(frame, now[0])
    echo = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
    echo.timestamp = wall[0] + 0.001  # arrived at once …
    now[0] += 4.5  # … but the Notifier thread only gets to it 4.5 s later
    wall[0] += 4.5
    receiver.on_message_received(echo)
    assert receiver.own_echoes == 1 and receiver.foreign_total == 0


def test_frames_waiting_sees_unread_data_in_a_bus_socket() -> None:
    # issue 17, finding 7: ages count only up to what the receive thread has read
    from leafgate.runtime.loop import frames_waiting

    class SocketBus:
        def __init__(self, sock: socket.socket) -> None:
            self.sock = sock

        def fileno(self) -> int:
            return self.sock.fileno()

    class NoFileno:
        def fileno(self) -> int:
            raise NotImplementedError

    a, b = socket.socketpair()
    with a, b:
        assert not frames_waiting([SocketBus(b), NoFileno()])  # type: ignore[list-item]
        a.send(b"frame")
        assert frames_waiting([SocketBus(b), NoFileno()])  # type: ignore[list-item]
        b.recv(16)
        assert not frames_waiting([SocketBus(b)])  # type: ignore[list-item]
    assert not frames_waiting([NoFileno()])  # type: ignore[list-item]


@pytest.mark.timeout(20)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_a_signal_that_lands_while_the_loop_sleeps_on_stop_still_stops_it(
    sig: signal.Signals,
) -> None:
    """The control loop sleeps in ``stop.wait``; a signal handled while that call holds the
    event's lock once made ``Event.set`` in the handler wait for the lock its own thread held:
    the daemon ignored Ctrl-C for good (CI: "run × sigint: still running"). SIGHUP (a closed
    terminal) stops it as SIGTERM does; it killed the daemon while ENGAGED."""
    stop = threading.Event()
    before = signal.getsignal(sig)
    with signals_set(stop) as request:
        with stop._cond:  # type: ignore[attr-defined]  # the lock stop.wait holds at times
            os.kill(os.getpid(), sig)
            time.sleep(0.1)  # the handler runs here, on this thread, inside the lock
        assert stop.wait(timeout=10.0)
        assert request.reason == f"{sig.name} received"
    assert signal.getsignal(sig) == before  # the handler is restored


@pytest.mark.timeout(20)
def test_a_stop_signal_held_from_the_commands_first_line_reaches_the_daemon() -> None:
    """``leafgate`` holds SIGTERM and SIGHUP before its imports; the daemon's handlers take
    over what came meanwhile, and leave the handlers from before the hold."""
    from leafgate.runtime import hold, signals

    before = signal.getsignal(signal.SIGTERM)
    hold.hold()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        stop = threading.Event()
        with signals_set(stop) as request:
            assert stop.wait(timeout=10.0)
            assert request.reason == "SIGTERM received"
    finally:
        signals.release()
    assert signal.getsignal(signal.SIGTERM) == before


REPLY_FIELDS = {"accepted", "state", "reason", "changed", "already"}


def test_engage_vetoed_by_the_shell_replies_in_the_format_and_after_the_fault() -> None:
    """A failing required recording refuses engage in STANDBY with the reply format's five
    fields; in FAULT the core's ``fault latched (…); reset first`` comes first (it was the
    recording's reason, without ``changed``/``already``)."""
    veto = "recording is required but failing: disk full"
    now = [0.0]
    ecu = CanCodec(profile="leafgate-dbw")
    with can.Bus(interface="virtual", channel="rt-veto") as bus:
        runtime, receiver = make_runtime(bus, lambda: now[0])
        runtime.engage_veto = lambda: veto
        for k in range(5):
            now[0] = k * 0.02
            feed_reports(receiver, ecu)
            runtime.tick(now[0])
        replies: list[dict] = []
        asker = _asker(runtime.requests, OperatorRequest.ENGAGE, replies)
        _wait_pending(runtime.requests, 1)
        feed_reports(receiver, ecu)
        runtime.tick(0.1)
        asker.join(timeout=2)
    assert replies[0] == {
        "accepted": False,
        "state": "STANDBY",
        "reason": veto,
        "changed": False,
        "already": False,
    }
    assert runtime.gateway.state.name == "STANDBY"

    failing = FailingBus()
    runtime, receiver = make_runtime(failing, lambda: now[0])
    runtime.engage_veto = lambda: veto
    for k in range(5):
        now[0] = k * 0.02
        feed_reports(receiver, ecu)
        runtime.tick(now[0])
    assert runtime.gateway.state.name == "FAULT"
    replies.clear()
    asker = _asker(runtime.requests, OperatorRequest.ENGAGE, replies)
    _wait_pending(runtime.requests, 1)
    runtime.tick(0.1)
    asker.join(timeout=2)
    failing.shutdown()
    assert set(replies[0]) == REPLY_FIELDS
    assert (
        replies[0]["reason"].startswith("fault latched (") and "reset first" in replies[0]["reason"]
    )
