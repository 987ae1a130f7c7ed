"""ROS 2 names on Zenoh against published values: rmw_zenoh's design document, REP-2011 hashes
published for Jazzy, zenoh-plugin-ros2dds's token format."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest
import ros2_peer
import xxhash
import yaml

from leafgate.config import from_mapping
from leafgate.config.transport import ZenohConfig
from leafgate.errors import TransportError
from leafgate.settings import load_config
from leafgate.transport import cdr, ros2
from leafgate.transport.session import build_config

# RIHS01 hashes for Jazzy as published: std_msgs/String and example_interfaces/AddTwoInts in
# ros2/rmw_zenoh docs/design.md; Odometry and the Autoware messages in public repositories that
# pin them from `ros2 topic info -v` on a Jazzy system.
PUBLISHED = {
    "std_msgs/msg/String": "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "nav_msgs/msg/Odometry": "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    cdr.VELOCITY_REPORT: "9052adda949c32f4a98500abc1fb5bd23f2560e321eebdfbb25318d6108d4ce4",
    cdr.STEERING_REPORT: "aa3acc9ca95ebc4daf9dec0ecf87911ad9c196392857c3026bfead589db65a94",
    cdr.GEAR_REPORT: "4d14bc3f186c1a6af6a732bb5ebd540cdd742a56770012f4c3cb9e762de8f391",
    cdr.CONTROL_MODE_REPORT: "968feaa6441be3c3b161f2eb65972a4b15394d0a7ddc4664318551280d1ff222",
    cdr.TURN_INDICATORS_REPORT: "c05a54cd244f1c9d683613b11c87a5b3ef816eed7a5f207368301221731a0964",
    cdr.HAZARD_LIGHTS_REPORT: "01ce3b4293a5c2799fd7483b2d62a790e26fe8f2b5d60e48149163475685f28a",
    cdr.CONTROL: "7818be59aa790ebb777db06e55a2c15e3756de4cc35c80b1e8271afc5bab2e9d",
}
ADD_TWO_INTS = "example_interfaces/srv/AddTwoInts"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


@pytest.mark.parametrize("typename", sorted(PUBLISHED))
def test_message_hashes_match_the_published_jazzy_values(typename: str) -> None:
    assert ros2.type_hash(typename, "jazzy") == "RIHS01_" + PUBLISHED[typename]


def test_service_hash_matches_the_design_document() -> None:
    # The service hash covers Request, Response and the Event type with ServiceEventInfo, whose
    # char[16] client_gid is uint8[16] in the type description: the step that is easy to miss.
    ros2.register_service("jazzy", ADD_TWO_INTS, "int64 a\nint64 b\n", "int64 sum\n")
    assert ros2.type_hash(ADD_TWO_INTS) == ADD_TWO_INTS_HASH


@pytest.mark.parametrize(
    "typename",
    # Control is pinned by its published hash above (the test peer does not carry its .msg).
    [t for t in cdr.KEY_TYPES if t != cdr.CONTROL]
    + [cdr.TRAJECTORY_POINT, cdr.CONTROL_MODE_COMMAND],
)
def test_every_hash_agrees_with_an_independent_rep2011_implementation(typename: str) -> None:
    assert ros2.type_hash(typename) == ros2_peer.rihs01(typename)


def test_humble_has_no_type_hashes_and_unknown_distros_are_refused() -> None:
    assert ros2.type_hash(cdr.ODOMETRY, "humble") == "TypeHashNotSupported"
    with pytest.raises(TransportError, match="unknown ROS 2 distribution 'foxy'"):
        ros2.type_hash(cdr.ODOMETRY, "foxy")


def test_keys_follow_the_design_document_examples() -> None:
    string_hash = "RIHS01_" + PUBLISHED["std_msgs/msg/String"]
    assert (
        ros2.topic_key(0, "/chatter", "std_msgs/msg/String", string_hash)
        == f"0/chatter/std_msgs::msg::dds_::String_/{string_hash}"
    )
    assert (
        ros2.topic_key(0, "/robot1/chatter", "std_msgs/msg/String", string_hash)
        == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{string_hash}"
    )
    assert (
        ros2.topic_key(2, "/add_two_ints", ADD_TWO_INTS, ADD_TWO_INTS_HASH)
        == f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"
    )


def test_liveliness_tokens_follow_the_design_document_examples() -> None:
    string_hash = "RIHS01_" + PUBLISHED["std_msgs/msg/String"]
    listener = ros2.Node(2, "aac3178e146ba6f1fc6e6a4085e77f21", name="listener")
    assert (
        listener.node_token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    )
    assert listener.entity_token(
        10, "MS", "/chatter", "std_msgs/msg/String", string_hash, ros2.Qos(depth=10)
    ) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{string_hash}/::,10:,:,:,,"
    )
    talker = ros2.Node(2, "8b20917502ee955ac4476e0266340d5c", name="talker")
    assert talker.entity_token(
        10, "MP", "/chatter", "std_msgs/msg/String", string_hash, ros2.Qos(depth=7)
    ).endswith(
        "/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/" + string_hash + "/::,7:,:,:,,"
    )
    server = ros2.Node(2, "f9980ee0495eaafb3e38f0d19e2eae12", name="add_two_ints_server")
    assert server.entity_token(
        10, "SS", "/add_two_ints", ADD_TWO_INTS, ADD_TWO_INTS_HASH, ros2.SERVICE_QOS
    ) == (
        "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
        f"%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,"
    )
    # A namespace is mangled like every name; non-default QoS values are written out.
    ns = ros2.Node(0, "ab", namespace="/leaf", name="leafgate")
    assert ns.node_token() == "@ros2_lv/0/ab/0/0/NN/%/%leaf/leafgate"
    qos = ros2.Qos(reliability=ros2.BEST_EFFORT, durability=ros2.TRANSIENT_LOCAL, depth=42)
    assert qos.rmw_zenoh_keyexpr() == "2:1:,:,:,:,,"


def test_attachment_layout_is_seq_stamp_gid_length_gid() -> None:
    gid = bytes(range(16))
    data = ros2.attachment(5, 1_700_000_000_123_456_789, gid)
    assert data == (
        (5).to_bytes(8, "little")
        + (1_700_000_000_123_456_789).to_bytes(8, "little")
        + b"\x10"
        + gid
    )
    assert ros2.parse_attachment(data) == (5, 1_700_000_000_123_456_789, gid)
    assert ros2_peer.read_attachment(data) == (5, 1_700_000_000_123_456_789, gid)
    with pytest.raises(TransportError, match="not an rmw_zenoh attachment"):
        ros2.parse_attachment(data[:-1])


def test_gid_is_rmw_zenohs_xxh3_128_of_the_token_low_half_first() -> None:
    """rmw_zenoh (liveliness_utils.cpp, ``Entity::Entity``) copies the token's XXH3-128 into
    the GID as ``low64`` then ``high64``, each little-endian. Old code: blake2b of the token,
    so the GID in leafgate's attachments was not the one ``ros2 topic info -v`` lists."""
    # XXH3-128 of no bytes (xxHash's test vector): high64 99aa06d3014798d8, low64 6001c324468d497f
    assert ros2.gid_of("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    token = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter/std_msgs"
    canonical = xxhash.xxh3_128_digest(token.encode())  # high64, low64, each big-endian
    assert ros2.gid_of(token) == canonical[8:][::-1] + canonical[:8][::-1]


def test_bridge_tokens_follow_zenoh_plugin_ros2dds() -> None:
    qos = ros2.Qos(depth=1)
    token = ros2.bridge_token(
        "1f2e", "MP", "leaf/vehicle/status/steering_status", cdr.STEERING_REPORT, qos
    )
    assert token == (
        "@/1f2e/@ros2_lv/MP/leaf§vehicle§status§steering_status/"
        "autoware_vehicle_msgs§msg§SteeringReport/:1:0:0,1"
    )
    hashed = ros2.bridge_token("1f2e", "MS", "leaf/x", cdr.ODOMETRY, qos, "RIHS01_ab")
    assert hashed.endswith("/MS/leaf§x/nav_msgs§msg§Odometry/:1:0:0,1:typehash=RIHS01_ab;")
    assert (
        ros2.bridge_token(
            "1f2e", "SS", "leaf/control/control_mode_request", cdr.CONTROL_MODE_COMMAND
        )
        == "@/1f2e/@ros2_lv/SS/leaf§control§control_mode_request/"
        "autoware_vehicle_msgs§srv§ControlModeCommand"
    )


def test_topics_default_to_autowares_absolute_names() -> None:
    cfg = ZenohConfig(node_namespace="/vehicle_a")
    assert cfg.topic("trajectory") == "/planning/scenario_planning/trajectory"
    assert cfg.topic("steering_status") == "/vehicle/status/steering_status"
    assert cfg.topic("control_mode_request") == "/control/control_mode_request"
    assert cfg.topic("command_echo") == ""  # off: /control/command/control_cmd is Autoware's
    relative = ZenohConfig(node_namespace="/vehicle_a", topics={"command_echo": "echo"})
    assert relative.topic("command_echo") == "/vehicle_a/echo"
    assert ZenohConfig().ros_namespace == "/leaf"  # what zenoh-bridge-ros2dds -n takes


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"topics": {"trajectroy": "/x"}}, "unknown role"),
        ({"ros": "rmw_zenoh", "encoding": "json"}, "CDR only"),
        ({"domain_id": 300}, "not a ROS domain"),
        ({"node_namespace": "leaf"}, "must start with '/'"),
        ({"node_name": "leaf-gate"}, "letters, digits"),
    ],
)
def test_bad_ros_settings_are_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ZenohConfig(**kwargs)


# --- shipped configs and the README's commands --------------------------------------------------

ROOT = Path(__file__).resolve().parent.parent
ROS_PORTS = {7447}  # zenoh-bridge-ros2dds (router mode) and rmw_zenohd listen there


@pytest.mark.parametrize("name", ["leafgate.yaml", "sim.yaml"])
def test_shipped_configs_leave_the_bridge_and_rmw_zenohd_their_port(name: str) -> None:
    cfg = load_config(str(ROOT / "config" / name)).zenoh
    ports = {int(e.rsplit(":", 1)[1]) for e in cfg.listen}
    assert ports and not ports & ROS_PORTS
    assert cfg.mode == "router"  # routes for clients (the bridge), gossips for the tools
    assert cfg.ros_namespace == "/leaf"  # what the README gives zenoh-bridge-ros2dds -n


def test_the_readme_rmw_zenoh_section_connects_to_rmw_zenohd() -> None:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```yaml\n(zenoh:\n  ros: rmw_zenoh\n.*?)```", text, re.DOTALL)
    assert block is not None
    cfg = from_mapping(ZenohConfig, yaml.safe_load(block.group(1))["zenoh"], "README")
    assert cfg.ros == "rmw_zenoh" and cfg.ros_distro == "jazzy"
    config = build_config(dataclasses.replace(cfg, connect=()))  # the default endpoint
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("mode")) == "peer"
    assert "zenoh-bridge-ros2dds -n /leaf -e tcp/127.0.0.1:7450" in text
