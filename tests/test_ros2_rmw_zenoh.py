"""leafgate as a ROS 2 node on rmw_zenoh, seen by a peer written from the rmw_zenoh design
document (``tests/ros2_peer.py``): discovery, statuses, inputs and the ControlModeCommand
service, through a Zenoh router standing in for ``rmw_zenohd``; and the bridge mode's
announcements and CDR service for ``zenoh-bridge-ros2dds``.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import ros2_peer
import zenoh
from test_transport import wait_until

from leafgate.config.transport import ZenohConfig
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    LongReport,
    OperatorRequest,
    Pose,
    Stamped,
    SteerReport,
    Trajectory,
)
from leafgate.runtime.node import GatewayTransport
from leafgate.transport.payloads import codecs

WAIT = 10.0  # s, upper bound for discovery and delivery on a loaded machine; never a speed goal
SRV = "autoware_vehicle_msgs/srv/ControlModeCommand"
STATUSES = {
    "/vehicle/status/steering_status": "autoware_vehicle_msgs/msg/SteeringReport",
    "/vehicle/status/velocity_status": "autoware_vehicle_msgs/msg/VelocityReport",
    "/vehicle/status/gear_status": "autoware_vehicle_msgs/msg/GearReport",
    "/vehicle/status/control_mode": "autoware_vehicle_msgs/msg/ControlModeReport",
    "/vehicle/status/turn_indicators_status": "autoware_vehicle_msgs/msg/TurnIndicatorsReport",
    "/vehicle/status/hazard_lights_status": "autoware_vehicle_msgs/msg/HazardLightsReport",
}
INPUTS = {
    "/localization/kinematic_state": "nav_msgs/msg/Odometry",
    "/planning/scenario_planning/trajectory": "autoware_planning_msgs/msg/Trajectory",
}


class Handler:
    def __init__(self) -> None:
        self.requests: list[OperatorRequest] = []

    def __call__(self, request: OperatorRequest) -> dict[str, Any]:
        self.requests.append(request)
        return {"accepted": True, "state": GatewayState.ENGAGED, "reason": ""}


@pytest.fixture
def handler() -> Handler:
    return Handler()


@pytest.fixture
def gateway(router: str, handler: Handler) -> Iterator[GatewayTransport]:
    cfg = ZenohConfig(ros="rmw_zenoh", connect=(router,))
    with GatewayTransport.open(cfg, handler) as transport:
        yield transport


@pytest.fixture
def peer(router: str) -> Iterator[ros2_peer.Peer]:
    node = ros2_peer.Peer(router)
    yield node
    node.close()


def drive_step(gateway: GatewayTransport) -> None:
    result = SimpleNamespace(
        commands=None,
        diagnostics=SimpleNamespace(state=GatewayState.ENGAGED, ecu_state=EcuState.ENGAGED),
    )
    reports = {
        "steer": Stamped(SteerReport(0.125, 0.0, 0.0, True, False, False, False), 1.0),
        "long": Stamped(LongReport(2.5, 0.0, Gear.D, 0.0, 0.0, True, False, False, False), 1.0),
    }
    gateway.publish_step(0.0, result, reports)


def test_discovery_lists_the_node_and_every_topic_with_its_type(
    gateway: GatewayTransport, peer: ros2_peer.Peer
) -> None:
    expected = {
        ("MP", topic, ros2_peer.dds_name(typ), ros2_peer.rihs01(typ))
        for topic, typ in STATUSES.items()
    }
    expected |= {
        ("MS", topic, ros2_peer.dds_name(typ), ros2_peer.rihs01(typ))
        for topic, typ in INPUTS.items()
    }
    expected.add(
        ("SS", "/control/control_mode_request", ros2_peer.dds_name(SRV), ros2_peer.rihs01(SRV))
    )
    tokens: list[list[str]] = []

    def complete() -> bool:
        # The graph fills in as the tokens propagate: ask until everything is there.
        nonlocal tokens
        tokens = [t for t in peer.graph() if t[8:9] == ["leafgate"]]
        return len(tokens) >= len(expected) + 1

    assert wait_until(complete, WAIT), tokens
    # @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<ns>/<node>[/<topic>/…]
    assert [t[5:9] for t in tokens if t[5] == "NN"] == [["NN", "%", "%", "leafgate"]]
    entities = {(t[5], t[9].replace("%", "/"), t[10], t[11]) for t in tokens if t[5] != "NN"}
    assert entities == expected
    # Every entity of the node has its own id; all share the session's id.
    assert len({t[4] for t in tokens}) == len(tokens)
    assert {t[2] for t in tokens} == {str(gateway.ros.node.session_id)}


def test_peer_receives_the_statuses_with_attachments(
    gateway: GatewayTransport, peer: ros2_peer.Peer
) -> None:
    received: dict[str, list[tuple[bytes, tuple[int, int, bytes]]]] = {t: [] for t in STATUSES}
    lock = threading.Lock()
    for topic, typ in STATUSES.items():

        def on_message(payload: bytes, meta: tuple[int, int, bytes], topic: str = topic) -> None:
            with lock:
                received[topic].append((payload, meta))

        peer.subscribe(topic, typ, on_message)

    def everything_flows() -> bool:
        drive_step(gateway)
        time.sleep(0.02)
        with lock:
            return all(received.values())

    assert wait_until(everything_flows, WAIT)
    for _ in range(50):  # a second more: the peers' direct link replaces the router's path
        drive_step(gateway)
        time.sleep(0.02)
    with lock:
        first = {topic: msgs[-1][1][0] for topic, msgs in received.items()}
    sent = 200
    for _ in range(sent):  # 50 Hz, the statuses' rate on the car
        drive_step(gateway)
        time.sleep(0.02)
    time.sleep(0.5)
    with lock:
        for topic, msgs in received.items():
            later = {m[1][0] for m in msgs if m[1][0] > first[topic]}
            missing = sorted(set(range(first[topic] + 1, first[topic] + sent + 1)) - later)
            assert len(later) >= 0.99 * sent, (topic, len(later), first[topic], missing)
            seqs = [m[1][0] for m in msgs if m[1][0] > first[topic]]
            assert seqs == sorted(seqs)  # sequence numbers count up per publisher
            assert len({m[1][2] for m in msgs}) == 1  # one GID per publisher
            stamp_ns = msgs[-1][1][1]
            assert abs(stamp_ns / 1e9 - time.time()) < 60  # Unix-epoch source time stamps
    c = codecs("cdr")
    steering = received["/vehicle/status/steering_status"][-1][0]
    assert c.steering.decode(steering).angle == 0.125
    velocity = received["/vehicle/status/velocity_status"][-1][0]
    assert c.velocity.decode(velocity).speed == 2.5
    hazard = received["/vehicle/status/hazard_lights_status"][-1][0]
    assert hazard[4:] == struct.pack("<iIB", *struct.unpack_from("<iI", hazard, 4), 1)  # DISABLE


def test_peer_inputs_reach_the_gateway(gateway: GatewayTransport, peer: ros2_peer.Peer) -> None:
    c = codecs("cdr")
    tapped: set[tuple[str, str | None]] = set()
    # The session recorder's tap names the ROS topic, not the rmw_zenoh key with its hash.
    gateway.on_raw = lambda name, payload, received, typename: tapped.add((name, typename))
    odometry = peer.publisher(
        "/localization/kinematic_state", INPUTS["/localization/kinematic_state"]
    )
    trajectory = peer.publisher(
        "/planning/scenario_planning/trajectory", INPUTS["/planning/scenario_planning/trajectory"]
    )
    pose = Pose(x=3.0, y=-1.0, heading=0.4, speed=1.5, stamp=1_700_000_000.0)
    path = Trajectory(
        x=np.arange(5) * 0.5, y=np.zeros(5), heading=np.zeros(5), speed=np.ones(5), stamp=1.0
    )

    def arrived() -> bool:
        odometry(c.pose.encode(pose))
        trajectory(c.trajectory.encode(path))
        time.sleep(0.02)
        return gateway.latest_pose() is not None and gateway.latest_trajectory() is not None

    assert wait_until(arrived, WAIT)
    got = gateway.latest_pose()
    assert got is not None and got.valid and got.value.x == 3.0
    traj = gateway.latest_trajectory()
    assert traj is not None and traj.valid
    np.testing.assert_array_equal(traj.value.x, path.x)
    assert tapped == set(INPUTS.items())


def control_mode_request(mode: int) -> bytes:
    """ControlModeCommand_Request in little-endian CDR, built by hand: Time stamp, uint8 mode."""
    return b"\x00\x01\x00\x00" + struct.pack("<iIB", 1_700_000_000, 5, mode)


@pytest.mark.parametrize(
    ("mode", "success", "expected"),
    [
        (1, True, OperatorRequest.ENGAGE),  # AUTONOMOUS
        (4, True, OperatorRequest.DISENGAGE),  # MANUAL
        (2, False, None),  # AUTONOMOUS_STEER_ONLY: the ECU engages both axes together
        (0, True, None),  # NO_COMMAND: nothing to do
    ],
)
def test_control_mode_command_is_engage_and_disengage(
    gateway: GatewayTransport,
    peer: ros2_peer.Peer,
    handler: Handler,
    mode: int,
    success: bool,
    expected: OperatorRequest | None,
) -> None:
    answer: tuple[bytes, Any] | None = None

    def answered() -> bool:
        nonlocal answer
        answer = peer.call("/control/control_mode_request", SRV, control_mode_request(mode), 2.0)
        return answer is not None

    assert wait_until(answered, WAIT)
    assert answer is not None
    payload, (_, stamp_ns, _) = answer
    assert payload == b"\x00\x01\x00\x00" + bytes([success])  # bool success in CDR
    assert abs(stamp_ns / 1e9 - time.time()) < 60
    assert handler.requests[-1:] == ([expected] if expected else [])


def test_a_garbled_service_request_gets_a_refusal(
    gateway: GatewayTransport, peer: ros2_peer.Peer, handler: Handler
) -> None:
    answer = None

    def answered() -> bool:
        nonlocal answer
        answer = peer.call("/control/control_mode_request", SRV, b"\x00\x01", 2.0)
        return answer is not None

    assert wait_until(answered, WAIT)
    assert answer is not None and answer[0] == b"\x00\x01\x00\x00\x00"
    assert handler.requests == []


# --- bridge mode ------------------------------------------------------------------------------


def test_bridge_mode_announces_topics_and_answers_cdr_service_calls(
    router: str, handler: Handler
) -> None:
    """What zenoh-bridge-ros2dds -n /leaf needs: announcement tokens in its format under the
    gateway's Zenoh id, keys ``leaf/<ROS name>``, a queryable answering CDR with CDR."""
    cfg = ZenohConfig(connect=(router,))
    tool_cfg = zenoh.Config()
    tool_cfg.insert_json5("connect/endpoints", json.dumps([router]))
    tool_cfg.insert_json5("scouting/multicast/enabled", "false")
    with GatewayTransport.open(cfg, handler) as gateway, zenoh.open(tool_cfg) as tool:
        zid = str(gateway.ros.node.session_id)

        announced: set[tuple[str, ...]] = set()  # (kind, key with '§', type with '§')

        def complete() -> bool:  # ask until every token has propagated
            nonlocal announced
            replies = tool.liveliness().get(f"@/{zid}/@ros2_lv/**", timeout=2.0)
            keys = {str(r.ok.key_expr) for r in replies if r.ok is not None}
            announced = {tuple(k.split("/")[3:6]) for k in keys}
            return len(announced) >= len(STATUSES) + len(INPUTS) + 1

        assert wait_until(complete, WAIT), announced
        for topic, typ in STATUSES.items():
            key = ("leaf" + topic).replace("/", "§")
            assert ("MP", key, typ.replace("/", "§")) in announced
        assert (
            "MS",
            "leaf§planning§scenario_planning§trajectory",
            "autoware_planning_msgs§msg§Trajectory",
        ) in announced
        assert ("SS", "leaf§control§control_mode_request", SRV.replace("/", "§")) in announced

        replies = list(
            tool.get(
                "leaf/control/control_mode_request",
                payload=control_mode_request(1),
                # the bridge strips the DDS request id (client GUID + sequence number, 16
                # bytes) from the request and sends it as the attachment
                attachment=bytes(range(16)),
                target=zenoh.QueryTarget.ALL_COMPLETE,
                timeout=WAIT,
            )
        )
        oks = [r.ok for r in replies if r.ok is not None]
        assert len(oks) == 1  # the bridge forwards one reply per request
        assert oks[0].payload.to_bytes() == b"\x00\x01\x00\x00\x01"  # CDR: bool success
        assert handler.requests == [OperatorRequest.ENGAGE]
