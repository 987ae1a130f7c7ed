"""Session records: gateway inputs and commands survive JSON exactly; the config round-trips."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from leafgate.errors import ConfigError
from leafgate.gateway.core import GatewayInputs
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
    SystemCommand,
    SystemReport,
    Trajectory,
)
from leafgate.record.recorder import Recording, SessionRecorder
from leafgate.record.session import (
    TrajectoryRefs,
    config_from_yaml,
    config_to_yaml,
    decode_commands,
    decode_inputs,
    decode_trajectory,
    encode_commands,
    encode_inputs,
    encode_trajectory,
)
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario
from leafgate.transport import cdr
from leafgate.transport.payloads import pose_to_odometry

anyfloat = st.floats(allow_nan=True, allow_infinity=True)


def stamped(value: st.SearchStrategy[Any]) -> st.SearchStrategy[Stamped[Any] | None]:
    return st.none() | st.builds(Stamped, value, anyfloat, st.booleans())


inputs = st.builds(
    GatewayInputs,
    pose=stamped(st.builds(Pose, anyfloat, anyfloat, anyfloat, anyfloat, anyfloat, anyfloat)),
    trajectory=st.none(),
    steer_report=stamped(
        st.builds(
            SteerReport,
            anyfloat,
            anyfloat,
            anyfloat,
            st.booleans(),
            st.booleans(),
            st.booleans(),
            st.booleans(),
        )
    ),
    long_report=stamped(
        st.builds(
            LongReport,
            anyfloat,
            anyfloat,
            st.sampled_from(Gear),
            anyfloat,
            anyfloat,
            st.booleans(),
            st.booleans(),
            st.booleans(),
            st.booleans(),
        )
    ),
    system_report=stamped(
        st.builds(
            SystemReport,
            st.sampled_from(EcuState),
            st.booleans(),
            st.booleans(),
            st.booleans(),
            st.booleans(),
            st.integers(0, 255),
        )
    ),
    good_report_frames=st.integers(0, 1000),
    bad_report_frames=st.integers(0, 1000),
    request=st.none() | st.sampled_from(OperatorRequest),
    request_reason=st.text(max_size=20),
    overrun=st.booleans(),
    # a stall FAULT is decided on it: old sessions lost it, and a re-run diverged from the
    # recorded FAULT (outside audit)
    lateness=st.floats(0.0, 10.0),
    bus_errors=st.integers(0, 10),
)


def same(a: object, b: object) -> bool:
    """Equality through dataclasses, with the session's JSON convention for non-finite floats:
    NaN and ±inf are written as null and read back as NaN (leafgate.jsonconv)."""
    if dataclasses.is_dataclass(a) and dataclasses.is_dataclass(b):
        return type(a) is type(b) and all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, float) and isinstance(b, float):
        if not math.isfinite(b):
            return math.isnan(a)
        return a == b
    return a == b and type(a) is type(b)


@given(inputs)
def test_gateway_inputs_survive_json_exactly(value: GatewayInputs) -> None:
    text = json.dumps(encode_inputs(value, None), allow_nan=False)
    assert same(
        decode_inputs(json.loads(text), lambda ref, obj: pytest.fail("no trajectory")), value
    )
    assert "NaN" not in text and "Infinity" not in text and '"nan"' not in text


@given(
    st.builds(SteerCommand, anyfloat, anyfloat, st.booleans(), st.booleans()),
    st.builds(
        LongCommand,
        st.sampled_from(LongMode),
        anyfloat,
        anyfloat,
        st.sampled_from(Gear),
        st.booleans(),
        st.booleans(),
    ),
    st.none() | st.builds(SystemCommand, st.sampled_from(GatewayState), st.booleans()),
)
def test_commands_survive_json_exactly(
    steer: SteerCommand, long: LongCommand, system: SystemCommand | None
) -> None:
    commands = Commands(steer, long, system)
    text = json.dumps(encode_commands(commands), allow_nan=False)
    assert same(decode_commands(json.loads(text)), commands)


def test_trajectory_is_stored_once_but_every_new_object_is_marked() -> None:
    a = Trajectory(x=[0.0, 1.0], y=[0.0, 0.1], heading=[0.0, 0.1], speed=[1.0, 1.0], stamp=3.0)
    b = Trajectory(x=a.x, y=a.y, heading=a.heading, speed=a.speed, stamp=3.0)  # same content
    refs = TrajectoryRefs()
    assert refs.refer(a) == (1, 1, True)
    assert refs.refer(a) == (1, 1, False)
    assert refs.refer(b) == (1, 2, False)  # a new object: the controller restarts its search
    back = decode_trajectory(json.loads(json.dumps(encode_trajectory(1, a))))
    assert all((getattr(back, k) == getattr(a, k)).all() for k in ("x", "y", "heading", "speed"))


def test_config_round_trips_through_yaml_exactly() -> None:
    config = LeafgateConfig()
    config = dataclasses.replace(
        config,
        controller=dataclasses.replace(
            config.controller,
            mpc=dataclasses.replace(config.controller.mpc, weight_lateral=0.1 + 0.2),
        ),
    )
    assert config_from_yaml(config_to_yaml(config), "test") == config


def test_overrides_replace_recorded_values_and_name_bad_keys() -> None:
    text = config_to_yaml(LeafgateConfig())
    cfg = config_from_yaml(text, "s.mcap", {"gateway.safety.max_steer_angle_deg": 20})
    assert cfg.gateway.safety.max_steer_angle == pytest.approx(math.radians(20))
    with pytest.raises(ConfigError, match=r"controller\.mpc\.nope"):
        config_from_yaml(text, "s.mcap", {"controller.mpc.nope": 1})


# --- a whole session as other tools read it ------------------------------------------------------


def test_a_recorded_session_lines_up_and_decodes_with_the_mcap_readers(tmp_path: Path) -> None:
    """Unix-epoch times on every channel, schemas with properties, CDR channels that
    mcap-ros2-support decodes, enums by name and no "nan" strings."""
    config = LeafgateConfig()
    path = tmp_path / "session.mcap"
    odometry = cdr.serialize(pose_to_odometry(Pose(1.5, -2.0, 0.3, 1.0, stamp=12.0)), cdr.ODOMETRY)
    before = time.time()
    session = SessionRecorder(path, config)
    with Recording([session]) as recording:
        session.on_zenoh_input("leaf/localization/kinematic_state", odometry, 0.25, cdr.ODOMETRY)
        run(config, get_scenario("s-curve"), recorder=recording)
    assert recording.fault == ""
    last_tick = 0.0

    with path.open("rb") as f:
        reader = make_reader(f)
        ros2 = DecoderFactory()
        summary = reader.get_summary()
        assert summary is not None
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        offset_ns = int(meta["leafgate.session"]["epoch_offset_ns"])
        # A simulated drive starts its simulated clock at the wall-clock time of its start.
        assert before <= offset_ns / 1e9 <= time.time()
        times: dict[str, list[int]] = {}
        schemas = {s.id: s for s in summary.schemas.values()}
        for channel in summary.channels.values():
            schema = schemas.get(channel.schema_id)
            if channel.message_encoding == "json":
                assert schema is not None and schema.encoding == "jsonschema"
                assert json.loads(schema.data)["properties"], channel.topic
        decoded_pose = None
        for schema, channel, message in reader.iter_messages():
            assert message.publish_time == message.log_time
            times.setdefault(channel.topic, []).append(message.log_time)
            if channel.message_encoding == "cdr":
                decode = ros2.decoder_for(channel.message_encoding, schema)
                assert decode is not None  # mcap-ros2-support reads the ros2msg schema
                decoded_pose = decode(message.data).pose.pose.position
            else:
                assert b'"nan"' not in message.data and b"NaN" not in message.data
                record = json.loads(message.data)
                assert set(record) <= set(json.loads(schema.data)["properties"]), channel.topic
                if channel.topic == "/leafgate/tick":
                    # log_time is the tick's gateway time, moved to the Unix epoch
                    assert message.log_time == offset_ns + round(record["now"] * 1e9)
                    last_tick = max(last_tick, record["now"])
                    if record["inputs"]["long_report"]:
                        gear = record["inputs"]["long_report"]["value"]["gear"]
                        assert gear in Gear.__members__  # enums by name
    assert decoded_pose is not None and (decoded_pose.x, decoded_pose.y) == (1.5, -2.0)
    assert times["/leaf/localization/kinematic_state"] == [offset_ns + 250_000_000]
    for topic in ("/can", "/leafgate/tick", "/leafgate/diagnostics"):
        first, last = min(times[topic]), max(times[topic])
        assert offset_ns <= first and last <= offset_ns + round((last_tick + 1.0) * 1e9), topic
    assert last_tick > 10.0  # the whole drive was recorded


def test_sessions_of_format_1_still_decode() -> None:
    """Before the one JSON convention, sessions wrote enums by number and NaN as "nan"."""
    old = {
        "steer": {"angle": "nan", "rate_limit": "inf", "enable": True, "clear_override": False},
        "long": {
            "mode": 1,
            "accel": 0.0,
            "speed": "-inf",
            "gear": 2,
            "enable": True,
            "clear_override": False,
        },
        "system": None,
        "extra": {"k": "nan"},
    }
    commands = decode_commands(old)
    assert math.isnan(commands.steer.angle) and commands.steer.rate_limit == math.inf
    assert commands.long.mode == LongMode(1) and commands.long.gear == Gear(2)
    assert commands.long.speed == -math.inf and math.isnan(commands.extra["k"])
    new = json.loads(json.dumps(encode_commands(commands), allow_nan=False))
    assert new["long"]["mode"] == LongMode(1).name and new["steer"]["angle"] is None
