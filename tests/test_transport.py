"""Zenoh transport on loopback: sessions from config, the gateway's node, the operator client.

Every test opens its own sessions on a free port with explicit ``tcp/127.0.0.1`` endpoints and
multicast scouting off, so tests never see each other or the network.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import zenoh

from leafgate.config import from_mapping
from leafgate.config.transport import ZenohConfig
from leafgate.errors import ConfigError, TransportError
from leafgate.messages import (
    Commands,
    EcuState,
    GatewayState,
    Gear,
    LongCommand,
    LongMode,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerCommand,
    SteerReport,
    Trajectory,
)
from leafgate.runtime.node import GatewayTransport
from leafgate.transport import client, keys
from leafgate.transport.payloads import (
    ControlMode,
    HazardLights,
    SteeringStatus,
    TurnIndicators,
    codecs,
)
from leafgate.transport.session import build_config, open_session
from tests.conftest import free_port, wait_for

ZENOH_FILES = Path(__file__).resolve().parents[1] / "config" / "zenoh"
WAIT = 5.0  # s, upper bound for loopback delivery; tests poll and never assert on speed


def wait_until(condition: Callable[[], bool], timeout: float = WAIT) -> bool:
    """:func:`tests.conftest.wait_for` with this module's loopback bound."""
    return wait_for(condition, timeout)


class FakeClock:
    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Handler:
    """Records engage requests and answers like the gateway would."""

    def __init__(self) -> None:
        self.requests: list[OperatorRequest] = []
        self.fail = False

    def __call__(self, request: OperatorRequest) -> dict[str, Any]:
        self.requests.append(request)
        if self.fail:
            raise RuntimeError("state machine is broken")
        refused = request == OperatorRequest.RESET
        return {
            "accepted": not refused,
            "state": GatewayState.ENGAGED if request == OperatorRequest.ENGAGE else "STANDBY",
            "reason": "nothing to reset" if refused else "",
        }


@pytest.fixture
def configs() -> tuple[ZenohConfig, ZenohConfig]:
    """(gateway, tool) configs: the gateway listens, the tool connects."""
    port = free_port()
    return (
        ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)),
        ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)),
    )


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(42.0)


@pytest.fixture
def handler() -> Handler:
    return Handler()


@pytest.fixture
def gateway(
    configs: tuple[ZenohConfig, ZenohConfig], handler: Handler, clock: FakeClock
) -> Iterator[GatewayTransport]:
    with GatewayTransport.open(
        configs[0], handler, clock=clock, stamp_clock=lambda: 1_700_000_000.5
    ) as transport:
        yield transport


@pytest.fixture
def tool(configs: tuple[ZenohConfig, ZenohConfig]) -> Iterator[zenoh.Session]:
    session = open_session(configs[1])
    yield session
    session.close()


def straight(n: int = 5) -> Trajectory:
    x = np.arange(n) * 0.5
    return Trajectory(x=x, y=np.zeros(n), heading=np.zeros(n), speed=np.full(n, 1.0), stamp=9.0)


# --- inputs ------------------------------------------------------------------------------------


def test_localization_fills_the_slot_with_its_receive_time(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, clock: FakeClock
) -> None:
    assert gateway.latest_pose() is None
    with client.OdometryPublisher(tool, configs[1]) as publisher:
        assert publisher.wait_for_subscriber(WAIT)
        clock.now = 123.25
        stamp = 1_700_000_000.5 - 0.01  # within max_clock_offset of the gateway's wall clock
        publisher.publish(Pose(x=3.0, y=-1.0, heading=0.4, speed=-0.5, yaw_rate=0.1), stamp=stamp)
        assert wait_until(lambda: gateway.latest_pose() is not None)
    sample = gateway.latest_pose()
    assert sample is not None and sample.valid
    assert sample.received == 123.25  # from the injected clock, not the sender's stamp
    pose = sample.value
    assert (pose.x, pose.y, pose.speed, pose.yaw_rate, pose.stamp) == (3.0, -1.0, -0.5, 0.1, stamp)
    assert pose.heading == pytest.approx(0.4, abs=1e-12)
    assert gateway.pose.received == 1


def test_published_trajectory_reaches_the_gateway(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    client.publish_trajectory(configs[1], straight(7), session=tool)
    assert wait_until(lambda: gateway.latest_trajectory() is not None)
    sample = gateway.latest_trajectory()
    assert sample is not None and sample.valid and sample.received == 42.0
    np.testing.assert_array_equal(sample.value.x, straight(7).x)
    assert sample.value.stamp == 9.0


def test_non_finite_pose_is_stored_but_marked_invalid(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    with client.OdometryPublisher(tool, configs[1]) as publisher:
        assert publisher.wait_for_subscriber(WAIT)
        publisher.publish(Pose(x=math.nan, y=0.0, heading=0.0, speed=0.0))
        assert wait_until(lambda: gateway.latest_pose() is not None)
    sample = gateway.latest_pose()
    assert sample is not None and not sample.valid


@pytest.mark.parametrize(
    "bad",
    [b"", b"garbage that is not CDR", "truncated"],
)
def test_undecodable_payloads_are_counted_and_the_last_good_sample_kept(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, bad: bytes | str
) -> None:
    key = configs[1].key(keys.KINEMATIC_STATE)
    good = codecs("cdr").pose.encode(Pose(x=1.0, y=2.0, heading=0.0, speed=1.0, stamp=5.0))
    payload = good[: len(good) // 2] if bad == "truncated" else bad
    with client.OdometryPublisher(tool, configs[1]) as publisher:
        assert publisher.wait_for_subscriber(WAIT)
        publisher.publish(Pose(x=1.0, y=2.0, heading=0.0, speed=1.0, stamp=5.0))
        assert wait_until(lambda: gateway.latest_pose() is not None)
        before = gateway.latest_pose()
        tool.put(key, payload)
        tool.put(key, payload)
        assert wait_until(lambda: gateway.decode_errors[key] == 2)
    assert gateway.latest_pose() is before  # the good sample stays, untouched
    assert gateway.pose.received == 1
    assert gateway.pose.last_error
    assert gateway.decode_errors[configs[1].key(keys.TRAJECTORY)] == 0


def test_undecodable_trajectory_is_counted_and_the_last_good_kept(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    key = configs[1].key(keys.TRAJECTORY)
    client.publish_trajectory(configs[1], straight(4), session=tool)
    assert wait_until(lambda: gateway.latest_trajectory() is not None)
    before = gateway.latest_trajectory()
    good = codecs("cdr").trajectory.encode(straight(4))
    tool.put(key, good[:-9])  # cut inside the last point
    assert wait_until(lambda: gateway.decode_errors[key] == 1)
    assert gateway.latest_trajectory() is before


def test_oversized_plan_and_payload_are_refused_with_their_reason(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    # issue 17, finding 5: a 10⁶-point plan stalled a tick 4.36 s, a 15 MB payload 140-180 ms
    key = configs[1].key(keys.TRAJECTORY)
    client.publish_trajectory(configs[1], straight(4), session=tool)
    assert wait_until(lambda: gateway.latest_trajectory() is not None)
    before = gateway.latest_trajectory()
    limit = configs[0].max_plan_points
    tool.put(key, codecs("cdr").trajectory.encode(straight(limit + 1)))
    assert wait_until(lambda: gateway.decode_errors[key] == 1)
    assert f"plan of {limit + 1} points > {limit}" in gateway.last_errors[key]
    tool.put(key, bytes(configs[0].max_payload_bytes + 1))
    assert wait_until(lambda: gateway.decode_errors[key] == 2)
    assert "max_payload_bytes" in gateway.last_errors[key]
    assert gateway.latest_trajectory() is before


# --- engage queryable -----------------------------------------------------------------------


def test_engage_query_calls_the_handler_and_replies_json(
    gateway: GatewayTransport, configs: Any, handler: Handler
) -> None:
    # the CLI path: the client opens and closes its own session
    reply = client.request(configs[1], "engage", timeout=WAIT)
    # the handler's three fields, and the two it left out (docs/state-machine.md's format)
    assert reply == {
        "accepted": True,
        "state": "ENGAGED",
        "reason": "",
        "changed": False,
        "already": False,
    }
    assert handler.requests == [OperatorRequest.ENGAGE]


def test_refusal_and_disengage_come_back_as_replies(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    reset = client.request(configs[1], OperatorRequest.RESET, WAIT, session=tool)
    assert reset == {
        "accepted": False,
        "state": "STANDBY",
        "reason": "nothing to reset",
        "changed": False,
        "already": False,
    }
    disengage = client.request(configs[1], "disengage", WAIT, session=tool)
    assert disengage["accepted"] is True
    assert handler.requests == [OperatorRequest.RESET, OperatorRequest.DISENGAGE]


def test_unknown_request_is_refused_without_calling_the_handler(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    reply = client.request(configs[1], "launch", WAIT, session=tool)
    assert reply["accepted"] is False
    assert "launch" in reply["reason"] and "engage" in reply["reason"]
    assert set(reply) == {"accepted", "state", "reason", "changed", "already"}
    assert handler.requests == []


def test_request_in_the_selector_parameters_is_understood(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    client.request(configs[1], "engage", WAIT, session=tool)  # the queryable is known now
    replies = list(tool.get(configs[1].key(keys.ENGAGE) + "?request=disengage", timeout=WAIT))
    assert len(replies) == 1 and replies[0].ok is not None
    assert json.loads(replies[0].ok.payload.to_bytes())["accepted"] is True
    assert handler.requests[-1] == OperatorRequest.DISENGAGE


def test_failing_handler_gives_a_refusal_not_a_dead_queryable(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    handler.fail = True
    reply = client.request(configs[1], "engage", WAIT, session=tool)
    assert reply["accepted"] is False and "state machine is broken" in reply["reason"]
    assert gateway.handler_errors == 1
    handler.fail = False
    assert client.request(configs[1], "engage", WAIT, session=tool)["accepted"] is True


def test_slow_engage_handler_does_not_hold_up_localization(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    release = threading.Event()
    answered: list[dict[str, Any]] = []
    original = handler.__call__

    def slow(request: OperatorRequest) -> dict[str, Any]:
        release.wait(WAIT)  # as if waiting for the control thread's decision
        return original(request)

    gateway._handler = slow  # the handler the runtime would pass, made slow
    asker = threading.Thread(
        target=lambda: answered.append(client.request(configs[1], "engage", WAIT, session=tool))
    )
    asker.start()
    try:
        with client.OdometryPublisher(tool, configs[1]) as publisher:
            assert publisher.wait_for_subscriber(WAIT)
            publisher.publish(Pose(x=1.0, y=0.0, heading=0.0, speed=0.0))
            # the pose arrives over the same link while the handler is still busy
            assert wait_until(lambda: gateway.latest_pose() is not None)
            assert not answered
    finally:
        release.set()
        asker.join()
    assert answered == [
        {"accepted": True, "state": "ENGAGED", "reason": "", "changed": False, "already": False}
    ]


def test_request_without_a_gateway_raises_transport_error(configs: Any) -> None:
    # the time rounded: a remaining wait printed as "within 1.99744 s" said more than it knew
    match = r"no gateway answered on leaf/gateway/engage within 0\.2 s$"
    with pytest.raises(TransportError, match=match):
        client.request(configs[1], "engage", timeout=0.2345)


# --- liveliness -------------------------------------------------------------------------------


def _alive(session: zenoh.Session, cfg: ZenohConfig) -> bool:
    replies = session.liveliness().get(cfg.key(keys.ALIVE), timeout=1.0)
    return any(r.ok is not None for r in replies)


def test_liveliness_token_is_visible_while_open_and_gone_after_close(
    configs: Any, handler: Handler, tool: zenoh.Session
) -> None:
    transport = GatewayTransport.open(configs[0], handler)
    try:
        assert wait_until(lambda: _alive(tool, configs[1]))
    finally:
        transport.close()
    assert transport.closed
    assert wait_until(lambda: not _alive(tool, configs[1]))
    transport.close()  # idempotent


# --- outputs ----------------------------------------------------------------------------------


def test_publish_step_sends_decodable_autoware_statuses(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    received: dict[str, bytes] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received[str(sample.key_expr)] = sample.payload.to_bytes()

    subscribers = [tool.declare_subscriber(configs[1].key("**"), on_sample)]
    result = SimpleNamespace(
        commands=Commands(
            steer=SteerCommand(angle=0.25, rate_limit=0.0, enable=True),
            long=LongCommand(mode=LongMode.SPEED, speed=1.5, gear=Gear.NONE, enable=True),
        ),
        diagnostics=SimpleNamespace(state=GatewayState.ENGAGED, ecu_state=EcuState.ENGAGED),
    )
    reports = {
        "steer": Stamped(SteerReport(0.125, 0.0, 0.0, True, False, False, False), 1.0),
        "long": Stamped(LongReport(-1.25, 0.0, Gear.R, 0.0, 0.0, True, False, False, False), 1.0),
        "system": None,
    }
    wanted = {
        configs[1].key(k)
        for k in (
            keys.STEERING_STATUS,
            keys.VELOCITY_STATUS,
            keys.GEAR_STATUS,
            keys.CONTROL_MODE,
            keys.TURN_INDICATORS_STATUS,
            keys.HAZARD_LIGHTS_STATUS,
        )
    }

    def all_arrived() -> bool:
        gateway.publish_step(10.0, result, reports)  # until the subscriptions are known
        with lock:
            return wanted <= set(received)

    try:
        assert wait_until(all_arrived)
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
    c = codecs("cdr")
    steering = c.steering.decode(received[configs[1].key(keys.STEERING_STATUS)])
    assert steering.angle == 0.125 and steering.stamp == pytest.approx(1_700_000_000.5)
    assert c.velocity.decode(received[configs[1].key(keys.VELOCITY_STATUS)]).speed == -1.25
    assert c.gear.decode(received[configs[1].key(keys.GEAR_STATUS)]).gear == Gear.R
    mode = c.control_mode.decode(received[configs[1].key(keys.CONTROL_MODE)])
    assert mode.mode == ControlMode.AUTONOMOUS
    lamps = c.turn_indicators.decode(received[configs[1].key(keys.TURN_INDICATORS_STATUS)])
    assert lamps.report == TurnIndicators.DISABLE  # no profile commands the indicators
    hazard = c.hazard_lights.decode(received[configs[1].key(keys.HAZARD_LIGHTS_STATUS)])
    assert hazard.report == HazardLights.DISABLE
    # The command echo is off by default: Autoware's /control/command/control_cmd belongs to
    # its vehicle_cmd_gate, and leafgate once published there.
    assert not any("control/command" in key for key in received)
    assert gateway.publish_errors == {}


def test_command_echo_goes_to_its_configured_topic(configs: Any, tool: zenoh.Session) -> None:
    cfg = ZenohConfig(listen=configs[0].listen, topics={"command_echo": "/leafgate/control_cmd"})
    received: list[bytes] = []
    subscriber = tool.declare_subscriber(
        "leaf/leafgate/control_cmd", lambda s: received.append(s.payload.to_bytes())
    )
    result = SimpleNamespace(
        commands=Commands(
            steer=SteerCommand(angle=0.25, rate_limit=0.0, enable=True),
            long=LongCommand(mode=LongMode.SPEED, speed=1.5, gear=Gear.NONE, enable=True),
        ),
        diagnostics=None,
    )
    reverse = {
        "long": Stamped(LongReport(-1.25, 0.0, Gear.R, 0.0, 0.0, True, False, False, False), 1.0)
    }

    def arrived() -> bool:
        gateway.publish_step(10.0, result, reverse)
        return bool(received)

    try:
        with GatewayTransport.open(cfg, Handler(), stamp_clock=lambda: 5.0) as gateway:
            assert wait_until(arrived)
    finally:
        subscriber.undeclare()
    command = codecs("cdr").command.decode(received[0])
    assert command.steer_angle == 0.25
    assert command.speed == -1.5  # reversing: the engaged gear is R
    assert command.accel_defined is False


def test_unencodable_status_is_counted_not_raised(gateway: GatewayTransport) -> None:
    gateway.publish_steering(SteeringStatus(0.0, stamp=1e12))  # does not fit a ROS time
    gateway.publish_diagnostics({"bad": math.inf, "fine": 1.0})  # inf becomes null: sent
    assert gateway.publish_errors == {"steering_status": 1}


def test_publishing_after_close_is_silent(gateway: GatewayTransport) -> None:
    gateway.close()
    gateway.publish_steering(SteeringStatus(0.1, 1.0))
    gateway.publish_diagnostics({"state": "STANDBY"})
    assert gateway.closed


def test_diagnostics_arrive_as_json_objects(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    got: list[dict[str, Any]] = []
    stop = threading.Event()

    def publish() -> None:
        while not stop.is_set():
            gateway.publish_diagnostics(
                {"state": GatewayState.STOPPING, "age": math.nan, "xy": np.array([1.0, 2.0])}
            )
            time.sleep(0.01)

    thread = threading.Thread(target=publish)
    thread.start()
    try:
        count = client.watch_diagnostics(configs[1], got.append, duration=0.5, session=tool)
    finally:
        stop.set()
        thread.join()
    assert count == len(got) > 0
    assert got[0] == {"state": "STOPPING", "age": None, "xy": [1.0, 2.0]}


def test_a_record_delivered_as_the_watch_ends_is_counted(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any
) -> None:
    # The callback is still running when the watch's time is up: the count returned must
    # include it, and nothing may be delivered after it.
    got: list[dict[str, Any]] = []
    stop = threading.Event()

    def slow(data: dict[str, Any]) -> None:
        time.sleep(0.6)
        got.append(data)

    def publish() -> None:
        while not stop.is_set():
            gateway.publish_diagnostics({"state": GatewayState.STOPPING})
            time.sleep(0.01)

    thread = threading.Thread(target=publish)
    thread.start()
    try:
        count = client.watch_diagnostics(configs[1], slow, duration=0.5, session=tool)
        delivered = len(got)
        time.sleep(0.7)  # a callback let through late would append by now
    finally:
        stop.set()
        thread.join()
    assert count == delivered == len(got) > 0


def test_json_encoding_end_to_end(handler: Handler) -> None:
    port = free_port()
    gw_cfg = ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), encoding="json")
    tool_cfg = ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",), encoding="json")
    with GatewayTransport.open(gw_cfg, handler) as gateway, open_session(tool_cfg) as tool:
        client.publish_trajectory(tool_cfg, straight(3), session=tool)
        assert wait_until(lambda: gateway.latest_trajectory() is not None)
        sample = gateway.latest_trajectory()
        assert sample is not None and len(sample.value) == 3
        # a script can write the flat JSON by hand
        tool.put(
            tool_cfg.key(keys.KINEMATIC_STATE),
            json.dumps({"x": 1, "y": 2, "heading": 0, "speed": 0.5}),
        )
        assert wait_until(lambda: gateway.latest_pose() is not None)
        pose = gateway.latest_pose()
        assert pose is not None and pose.value.speed == 0.5 and math.isnan(pose.value.stamp)


# --- sessions from config ---------------------------------------------------------------------


def _one_line(exc: pytest.ExceptionInfo[TransportError]) -> str:
    text = str(exc.value)
    assert "\n" not in text and ".rs:" not in text
    return text


def test_unreadable_json5_raises_one_line_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.json5"
    path.write_text("{ mode: 'peer',\n  listen: { endpoints: ['tcp/127.0.0.1:0'] },\n  ")
    with pytest.raises(TransportError) as exc:
        open_session(ZenohConfig(config_file=str(path)))
    assert str(path) in _one_line(exc)


def test_missing_json5_file_raises_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "absent.json5"
    with pytest.raises(TransportError) as exc:
        open_session(ZenohConfig(config_file=str(path)))
    assert str(path) in _one_line(exc) and "not found" in str(exc.value)


def test_json5_with_an_unknown_setting_raises_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "typo.json5"
    path.write_text("{ mode: 'peer', scouting: { multicast: { enabeld: false } } }")
    with pytest.raises(TransportError) as exc:
        open_session(ZenohConfig(config_file=str(path)))
    assert "enabeld" in _one_line(exc)


@pytest.mark.parametrize("endpoint", ["127.0.0.1:7447", "tcp", "tcp/127.0.0.1:notaport"])
def test_bad_endpoint_raises_one_line_naming_it(endpoint: str) -> None:
    with pytest.raises(TransportError) as exc:
        open_session(ZenohConfig(listen=(endpoint,)))
    assert endpoint in _one_line(exc)


def test_port_in_use_raises_naming_the_endpoint() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        endpoint = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        with pytest.raises(TransportError) as exc:
            open_session(ZenohConfig(listen=(endpoint,)))
    assert endpoint in _one_line(exc)


def test_bad_extra_setting_raises_naming_the_key() -> None:
    with pytest.raises(TransportError) as exc:
        open_session(ZenohConfig(extra={"scouting/multicast/nonsense": "true"}))
    assert "zenoh.extra.scouting/multicast/nonsense" in _one_line(exc)


@pytest.mark.parametrize("name", ["peer.json5", "router.json5", "secure.json5"])
def test_example_zenoh_files_are_valid_zenoh_configs(name: str) -> None:
    config = build_config(ZenohConfig(config_file=str(ZENOH_FILES / name)))
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def test_router_file_serves_clients_on_the_configured_endpoint(handler: Handler) -> None:
    port = free_port()
    router_cfg = ZenohConfig(
        config_file=str(ZENOH_FILES / "router.json5"), listen=(f"tcp/127.0.0.1:{port}",)
    )
    assert json.loads(build_config(router_cfg).get_json("mode")) == "router"
    client_cfg = ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
    with GatewayTransport.open(router_cfg, handler):
        assert client.request(client_cfg, "engage", WAIT)["accepted"] is True


def test_prefix_must_be_a_plain_key_expression() -> None:
    with pytest.raises(ConfigError, match=r"leafgate.yaml: zenoh: prefix 'leaf/\*'"):
        from_mapping(ZenohConfig, {"prefix": "leaf/*"}, "leafgate.yaml", "zenoh")
    assert ZenohConfig(prefix="car/leaf").key(keys.ENGAGE) == "car/leaf/gateway/engage"


# --- hostile operator requests (issue 17, findings 1 and 9) -------------------------------------


def _raw_get(session: zenoh.Session, selector: str, payload: bytes | None) -> list[dict[str, Any]]:
    replies = session.get(
        selector, payload=payload, timeout=WAIT, consolidation=zenoh.ConsolidationMode.NONE
    )
    return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]


@pytest.mark.parametrize(
    "payload", [b"ENGAGE", b"  eNgAgE \n\t", "\u00a0engage".encode(), b"engage\n", b"engage!"]
)
def test_requests_are_one_exact_word(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler, payload: bytes
) -> None:
    client.request(configs[1], "disengage", WAIT, session=tool)  # the queryable is known now
    (reply,) = _raw_get(tool, configs[1].key(keys.ENGAGE), payload)
    assert reply["accepted"] is False and "unknown request" in reply["reason"]
    assert handler.requests == [OperatorRequest.DISENGAGE]
    # the reply format of every other reply (docs/state-machine.md), and the text as sent
    assert reply == {
        "accepted": False,
        "state": "UNKNOWN",  # this gateway published no state yet
        "reason": reply["reason"],
        "changed": False,
        "already": False,
    }
    assert f"'{payload.decode(errors='replace')}'" in reply["reason"]


def test_wildcard_query_never_resets_or_engages(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    client.request(configs[1], "disengage", WAIT, session=tool)
    for payload in (b"reset", b"engage"):
        (reply,) = _raw_get(tool, "leaf/**", payload)
        assert reply["accepted"] is False and "exactly" in reply["reason"]
    assert handler.requests == [OperatorRequest.DISENGAGE]


def test_large_request_is_refused_without_echoing_it(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    client.request(configs[1], "disengage", WAIT, session=tool)
    (reply,) = _raw_get(tool, configs[1].key(keys.ENGAGE), b"engage" * 200_000)
    assert reply["accepted"] is False and "1200000 bytes" in reply["reason"]
    assert len(json.dumps(reply)) < 300
    assert handler.requests == [OperatorRequest.DISENGAGE]


def test_disengage_overtakes_a_flood_of_engages(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, handler: Handler
) -> None:
    release = threading.Event()
    original = handler.__call__

    def slow(request: OperatorRequest) -> dict[str, Any]:
        if request is OperatorRequest.ENGAGE:
            release.wait(WAIT)  # the control thread has not decided yet
        return original(request)

    gateway._handler = slow
    client.request(configs[1], "disengage", WAIT, session=tool)
    flood = [
        tool.get(configs[1].key(keys.ENGAGE), payload=b"engage", timeout=WAIT) for _ in range(50)
    ]
    try:
        reply = client.request(configs[1], "disengage", WAIT, session=tool)
        assert reply["accepted"] is True  # answered while the engage lane is still stuck
    finally:
        release.set()
    answers = [json.loads(r.ok.payload.to_bytes()) for f in flood for r in f if r.ok is not None]
    assert len(answers) == 50
    # the one engage already with the handler ran; the queued ones were superseded or refused
    assert sum(a["accepted"] for a in answers) <= 1
    assert handler.requests.count(OperatorRequest.ENGAGE) <= 1
    assert any("superseded by a disengage" in a["reason"] for a in answers)


@pytest.fixture
def impostor_and_tool(configs: Any) -> Iterator[tuple[zenoh.Session, zenoh.Session, ZenohConfig]]:
    """A second session listening on its own port, and a tool connected to it and the gateway."""
    port = free_port()
    impostor = open_session(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    cfg = ZenohConfig(connect=(*configs[1].connect, f"tcp/127.0.0.1:{port}"))
    tool = open_session(cfg)
    yield impostor, tool, cfg
    tool.close()
    impostor.close()


def test_tool_ignores_a_reply_from_a_session_without_the_gateway_token(
    gateway: GatewayTransport, impostor_and_tool: Any
) -> None:
    impostor, tool, cfg = impostor_and_tool
    key = cfg.key(keys.ENGAGE)
    fake = impostor.declare_queryable(
        key, lambda q: q.reply(key, b'{"accepted": true, "state": "ENGAGED", "reason": "fake"}')
    )
    assert wait_until(lambda: len(_raw_get(tool, key, b"disengage")) == 2)  # both answer
    reply = client.request(cfg, "disengage", WAIT, session=tool)
    assert reply["state"] == "STANDBY" and reply["reason"] == ""  # the gateway's own answer
    assert [r["reply"]["reason"] for r in reply["ignored_replies"]] == ["fake"]
    assert client.gateway_ids(cfg, tool, WAIT) == {str(gateway._session.info.zid())}
    fake.undeclare()


def test_tool_reports_a_second_session_claiming_to_be_the_gateway(
    gateway: GatewayTransport, impostor_and_tool: Any, handler: Handler
) -> None:
    impostor, tool, cfg = impostor_and_tool
    with GatewayTransport(impostor, cfg, handler):
        assert wait_until(lambda: len(client.gateway_ids(cfg, tool, 1.0)) == 2)
        reply = client.request(cfg, "disengage", WAIT, session=tool)
        assert len(reply["conflicting_replies"]) == 1


def test_old_header_stamp_ages_the_pose_and_a_future_one_invalidates_it(
    gateway: GatewayTransport, tool: zenoh.Session, configs: Any, clock: FakeClock
) -> None:
    # issue 17, finding 3: poses 400 ms old by their stamps were taken as fresh
    wall = 1_700_000_000.5  # the fixture's stamp clock
    offset = configs[0].max_clock_offset
    clock.now = 50.0
    with client.OdometryPublisher(tool, configs[1]) as publisher:
        assert publisher.wait_for_subscriber(WAIT)
        publisher.publish(Pose(x=1.0, y=0.0, heading=0.0, speed=0.0), stamp=wall - 0.4)
        assert wait_until(lambda: gateway.latest_pose() is not None)
        sample = gateway.latest_pose()
        assert sample is not None and sample.valid
        assert sample.received == pytest.approx(50.0 - (0.4 - offset))
        publisher.publish(Pose(x=1.0, y=0.0, heading=0.0, speed=0.0), stamp=wall + 0.5)
        assert wait_until(lambda: gateway.pose.received == 2)
    sample = gateway.latest_pose()
    assert sample is not None and not sample.valid


def test_a_peer_whose_connect_endpoints_do_not_answer_is_named(
    configs: tuple[ZenohConfig, ZenohConfig],
) -> None:
    """A peer opens whether or not its ``connect`` endpoints answer (the README said start-up
    stops on a refused endpoint; only client mode does): start-up names the silent ones."""
    from leafgate.transport.session import unanswered_connect

    nobody = ZenohConfig(
        connect=(f"tcp/127.0.0.1:{free_port()}",), listen=(f"tcp/127.0.0.1:{free_port()}",)
    )
    lonely = open_session(nobody)
    try:
        assert unanswered_connect(lonely, nobody, wait=0.3) == nobody.connect
    finally:
        lonely.close()
    listener = open_session(configs[0])
    try:
        peer = open_session(configs[1])
        try:  # a connect endpoint that answers: nothing to say
            assert unanswered_connect(peer, configs[1], wait=WAIT) == ()
        finally:
            peer.close()
    finally:
        listener.close()
    # no connect endpoints, or a client (whose open fails instead): nothing judged
    assert unanswered_connect(SimpleNamespace(), configs[0]) == ()  # type: ignore[arg-type]
    client_cfg = ZenohConfig(mode="client", connect=nobody.connect)
    assert unanswered_connect(SimpleNamespace(), client_cfg) == ()  # type: ignore[arg-type]


def test_closing_a_session_whose_peer_never_answers_the_handshake_is_prompt() -> None:
    """A ``connect`` endpoint that accepts the connection and then says nothing (another
    service on the port, a hung process): closing the session waited for the pending Zenoh
    handshake, 10 s by default, so every tool took ~10 s to exit (``status --duration 1``: 11 s)
    and a Ctrl-C waited with it. The handshake is now bounded (OPEN_TIMEOUT_MS)."""
    from leafgate.transport.session import OPEN_TIMEOUT_MS

    mute = socket.socket()
    mute.bind(("127.0.0.1", 0))
    mute.listen(8)  # the kernel accepts the connections; nobody ever reads or writes them
    endpoint = f"tcp/127.0.0.1:{mute.getsockname()[1]}"
    try:
        session = open_session(ZenohConfig(connect=(endpoint,)))
        time.sleep(0.2)  # the handshake has begun
        start = time.monotonic()
        session.close()
        took = time.monotonic() - start
    finally:
        mute.close()
    # Zenoh's default held it ~9.8 s; the bound leaves room for a loaded machine
    assert took < OPEN_TIMEOUT_MS / 1000 + 4.0, f"close waited {took:.1f} s for the handshake"
