"""Session records: gateway inputs and commands survive JSON exactly; the config round-trips."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

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
from leafgate.replay.session import (
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
    overrun=st.booleans(),
    bus_errors=st.integers(0, 10),
)


def same(a: object, b: object) -> bool:
    """Equality with NaN equal to NaN, through dataclasses."""
    if dataclasses.is_dataclass(a) and dataclasses.is_dataclass(b):
        return type(a) is type(b) and all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    return a == b and type(a) is type(b)


@given(inputs)
def test_gateway_inputs_survive_json_exactly(value: GatewayInputs) -> None:
    text = json.dumps(encode_inputs(value, None), allow_nan=False)
    assert same(
        decode_inputs(json.loads(text), lambda ref, obj: pytest.fail("no trajectory")), value
    )


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
