"""Bad input (issue 8): every place outside bytes enter leafgate survives them.

Property tests with a modest number of examples each; ``tools/fuzz.py`` runs the same targets
with 100,000+ seeded cases. Each entry point must reject bad input the way it promises — the
CAN codec and the Zenoh subscribers count it and never raise, the file loaders raise only
their :class:`~leafgate.errors.LeafgateError` naming the file and the row, line or key — and
the regression tests at the end pin the bugs the fuzzer found.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from leafgate.can import e2e
from leafgate.can.codec import ERROR_FRAME_KEY, CanCodec, Decoded, FrameStats
from leafgate.config import MAX_YAML_DEPTH
from leafgate.config.transport import ZenohConfig
from leafgate.control.reference import load_trajectory
from leafgate.errors import ConfigError, TrajectoryError
from leafgate.messages import LongReport, Pose, SteerReport, SystemReport, Trajectory
from leafgate.runtime.node import GatewayTransport
from leafgate.runtime.receiver import CanReceiver
from leafgate.settings import load_config
from leafgate.transport.payloads import codecs
from tools._common import StubSession, after_file, names_trajectory_place, stub_sample

ROOT = Path(__file__).resolve().parent.parent
SIM_YAML = ROOT / "config" / "sim.yaml"
FAST = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FILES = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

_ERRORS = {"bad_crc", "bad_counter", "wrong_length", "unknown_id", "decode_error"}
_REFERENCE = CanCodec(profile="leafgate-dbw")
DBW_IDS = sorted(_REFERENCE.receive_ids("commands") | _REFERENCE.receive_ids("reports"))
KNOWN_IDS = sorted(set(DBW_IDS) | _REFERENCE.receive_ids("car"))
REPORT_IDS = sorted(_REFERENCE.receive_ids("reports"))


# --- CAN --------------------------------------------------------------------------------------


@st.composite
def frames(draw: st.DrawFn) -> can.Message:
    """Any frame a bus may deliver: random or known IDs, flags, lengths 0-8 and 64, bytes."""
    extended = draw(st.booleans())
    if draw(st.booleans()):
        frame_id = draw(st.sampled_from(KNOWN_IDS))
    else:
        frame_id = draw(st.integers(0, 0x1FFFFFFF if extended else 0x7FF))
    fd = draw(st.integers(0, 19)) == 0
    remote = draw(st.integers(0, 9)) == 0
    size = 64 if fd else draw(st.integers(0, 8))
    return can.Message(
        arbitration_id=frame_id,
        is_extended_id=extended,
        is_remote_frame=remote,
        is_error_frame=draw(st.integers(0, 9)) == 0,
        is_fd=fd,
        dlc=size,
        data=b"" if remote else draw(st.binary(min_size=size, max_size=size)),
        check=False,
    )


def e2e_frame(frame_id: int, payload: bytes, counter: int) -> can.Message:
    """A DBW frame with a correct CRC and the given alive counter around any payload."""
    return can.Message(
        arbitration_id=frame_id, is_extended_id=False, data=e2e.apply(frame_id, payload, counter)
    )


def assert_consistent(codec: CanCodec, msg: can.Message, out: Decoded) -> None:
    assert isinstance(out, Decoded)
    assert out.valid == (out.error is None)
    assert out.error is None or out.error in _ERRORS
    known = not msg.is_extended_id and codec.name_of(msg.arbitration_id) is not None
    if not known:
        assert out.error == "unknown_id"
    if out.valid:
        assert out.value is not None and out.name == codec.name_of(msg.arbitration_id)


def assert_counts_add_up(codec: CanCodec, fed: int, valid_per_id: dict[int, int]) -> None:
    """Every frame fed is counted once; per known ID, frames - errors = valid decodes."""
    stats = codec.stats
    # unknown_id counts appear only under unknown (or extended, ID | EXTENDED_KEY) keys; error
    # frames have no ID: their own row, not unknown IDs
    in_known = sum(stats[i].frames - stats[i].unknown_id for i in KNOWN_IDS)
    error_frames = stats.get(ERROR_FRAME_KEY, FrameStats())
    assert error_frames.unknown_id == 0
    assert in_known + codec.unknown_id_count + error_frames.frames == fed
    for frame_id in KNOWN_IDS:
        s = stats[frame_id]
        assert s.frames - s.errors == valid_per_id.get(frame_id, 0)


@FAST
@given(st.lists(frames(), max_size=40))
def test_codec_never_raises_and_counts_every_frame(batch: list[can.Message]) -> None:
    codec = CanCodec(profile="leafgate-dbw")
    valid: dict[int, int] = {}
    for msg in batch:
        out = codec.decode(msg)
        assert_consistent(codec, msg, out)
        if out.valid:
            valid[msg.arbitration_id] = valid.get(msg.arbitration_id, 0) + 1
    assert_counts_add_up(codec, len(batch), valid)


@FAST
@given(
    st.sampled_from(DBW_IDS),
    st.integers(0, 15),
    st.lists(st.binary(min_size=8, max_size=8), min_size=1, max_size=20),
)
def test_frames_with_valid_e2e_reach_the_content_decoder(
    frame_id: int, first: int, payloads: list[bytes]
) -> None:
    codec = CanCodec(profile="leafgate-dbw")
    valid = 0
    for k, payload in enumerate(payloads):
        msg = e2e_frame(frame_id, payload, first + k)
        out = codec.decode(msg)
        assert_consistent(codec, msg, out)
        assert out.error in (None, "decode_error")  # CRC and counter pass: content decides
        valid += out.valid
    assert_counts_add_up(codec, len(payloads), {frame_id: valid})
    assert codec.stats[frame_id].decode_error == len(payloads) - valid


@FAST
@given(
    st.lists(
        st.one_of(
            frames(),
            st.builds(
                e2e_frame,
                st.sampled_from(REPORT_IDS),
                st.binary(min_size=8, max_size=8),
                st.integers(0, 15),
            ),
        ),
        max_size=40,
    )
)
def test_gateway_receiver_never_raises_and_keeps_only_valid_reports(
    batch: list[can.Message],
) -> None:
    receiver = CanReceiver(CanCodec(profile="leafgate-dbw"), clock=lambda: 2.0)
    for msg in batch:
        receiver.on_message_received(msg)
        for slot, kind in (
            (receiver.steer, SteerReport),
            (receiver.long, LongReport),
            (receiver.system, SystemReport),
        ):
            sample = slot.get()
            assert sample is None or (sample.valid and isinstance(sample.value, kind))
    good, bad = receiver.take_counts()
    assert good + bad <= len(batch)


# --- Zenoh payloads ---------------------------------------------------------------------------


class Inputs:
    """A transport's two input subscribers, fed samples directly (the daemon's decode path)."""

    def __init__(self, encoding: str) -> None:
        session = StubSession()
        self.transport = GatewayTransport(
            session,  # type: ignore[arg-type]
            ZenohConfig(encoding=encoding),  # type: ignore[arg-type]
            handler=lambda request: {"accepted": False, "state": None, "reason": ""},
            clock=lambda: 7.0,
        )
        self.callbacks = {
            "pose": session.subscribers[self.transport.pose.key],
            "trajectory": session.subscribers[self.transport.trajectory.key],
        }

    def slot(self, key: str) -> Any:
        return self.transport.pose if key == "pose" else self.transport.trajectory

    def feed(self, key: str, payload: bytes) -> bool:
        """Feed one payload; True when it was stored valid. Asserts it was counted once."""
        slot = self.slot(key)
        before = slot.received + slot.errors
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no numpy warnings on Zenoh's thread either
            self.callbacks[key](stub_sample(payload))
        assert slot.received + slot.errors == before + 1
        sample = slot.get()
        if sample is not None and sample.valid:
            value = sample.value
            if key == "pose":
                assert all(math.isfinite(v) for v in (value.x, value.y, value.heading))
            else:
                assert len(value) > 0
                assert all(np.isfinite(a).all() for a in (value.x, value.y, value.heading))
        return sample is not None and sample.valid

    def close(self) -> None:
        self.transport.close()


@pytest.fixture(scope="module")
def cdr_inputs() -> Any:
    inputs = Inputs("cdr")
    yield inputs
    inputs.close()


@pytest.fixture(scope="module")
def json_inputs() -> Any:
    inputs = Inputs("json")
    yield inputs
    inputs.close()


def _trajectory(n: int) -> Trajectory:
    x = np.arange(n, dtype=np.float64) * 0.7
    return Trajectory(x=x, y=np.sin(x), heading=np.cos(x), speed=np.ones(n), stamp=3.0)


VALID_CDR = {
    "pose": codecs("cdr").pose.encode(Pose(1.0, 2.0, 0.3, 1.5, 0.1, stamp=4.0)),
    "trajectory": codecs("cdr").trajectory.encode(_trajectory(6)),
}
VALID_JSON = {
    "pose": codecs("json").pose.encode(Pose(1.0, 2.0, 0.3, 1.5, 0.1, stamp=4.0)),
    "trajectory": codecs("json").trajectory.encode(_trajectory(6)),
}


@st.composite
def mutated(draw: st.DrawFn, valid: bytes) -> bytes:
    """A valid payload truncated, bit-flipped, with bytes inserted or a 32-bit word forged."""
    data = bytearray(valid)
    op = draw(st.sampled_from(["truncate", "flip", "insert", "word"]))
    if op == "truncate":
        return bytes(data[: draw(st.integers(0, len(data)))])
    if op == "flip":
        for i in draw(st.lists(st.integers(0, len(data) - 1), min_size=1, max_size=8)):
            data[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    at = draw(st.integers(0, len(data) - 4))
    if op == "insert":
        return bytes(data[:at]) + draw(st.binary(min_size=1, max_size=16)) + bytes(data[at:])
    word = draw(st.sampled_from([0, 1, 2**31, 2**32 - 1, 1000]))
    return bytes(data[:at]) + word.to_bytes(4, "little") + bytes(data[at + 4 :])


@FAST
@given(st.data(), st.sampled_from(["pose", "trajectory"]))
def test_mutated_cdr_is_stored_or_counted_never_raised(
    cdr_inputs: Inputs, data: st.DataObject, key: str
) -> None:
    payload = data.draw(st.one_of(mutated(VALID_CDR[key]), st.binary(max_size=200)))
    cdr_inputs.feed(key, payload)


_JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=5)
        | st.dictionaries(
            st.sampled_from(["x", "y", "heading", "speed", "stamp", "yaw_rate", "z"]), children
        )
    ),
    max_leaves=20,
)


@FAST
@given(st.data(), st.sampled_from(["pose", "trajectory"]))
def test_random_and_mistyped_json_is_stored_or_counted_never_raised(
    json_inputs: Inputs, data: st.DataObject, key: str
) -> None:
    valid = json.loads(VALID_JSON[key])
    field = data.draw(st.sampled_from(sorted(valid)))
    valid[field] = data.draw(_JSON_VALUES)  # a wrong type, NaN, ±inf, a huge integer …
    payload = data.draw(
        st.one_of(
            st.just(json.dumps(valid).encode()),  # NaN and Infinity as JavaScript literals
            st.builds(lambda v: json.dumps(v).encode(), _JSON_VALUES),
            mutated(VALID_JSON[key]),
            st.binary(max_size=100),
        )
    )
    json_inputs.feed(key, payload)


def test_deep_huge_and_non_utf8_json_is_counted(json_inputs: Inputs) -> None:
    slot = json_inputs.slot("trajectory")
    errors = slot.errors
    for payload in (
        b"[" * 100_000 + b"]" * 100_000,
        b'{"x": [1e999], "y": [0], "heading": [0], "speed": [0]}',
        b'{"x": \xff}',
        json.dumps({"x": [1] * 100_000, "y": [0], "heading": [0], "speed": [0]}).encode(),
    ):
        json_inputs.feed("trajectory", payload)
    # 1e999 is a float (inf): decoded and stored invalid; the others are dropped and counted
    assert slot.errors == errors + 3


def test_a_non_finite_pose_is_stored_invalid_and_counted_as_such() -> None:
    inputs = Inputs("cdr")
    try:
        payload = codecs("cdr").pose.encode(Pose(math.nan, 0.0, 0.0, 0.0))
        assert not inputs.feed("pose", payload)
        assert inputs.transport.pose.invalid == 1
        assert inputs.transport.invalid_samples[inputs.transport.pose.key] == 1
        assert inputs.transport.decode_errors[inputs.transport.pose.key] == 0
    finally:
        inputs.close()


def test_cdr_trajectory_with_overflowing_quaternions_decodes_without_numpy_warnings() -> None:
    x = np.arange(5, dtype=np.float64) * 0.7
    straight = Trajectory(x=x, y=np.zeros(5), heading=np.zeros(5), speed=np.ones(5))
    raw = codecs("cdr").trajectory.encode(straight)
    one, huge = np.float64(1.0).tobytes(), np.float64(1e300).tobytes()
    assert raw.count(one) == 5  # only the quaternions' w of heading 0 hold exactly 1.0
    inputs = Inputs("cdr")
    try:
        # w = 1e300: its square overflows to inf, yet the yaw of (0, 0, 0, w) is still 0
        assert inputs.feed("trajectory", raw.replace(one, huge))  # and no warning escapes
        sample = inputs.transport.latest_trajectory()
        assert sample is not None and (sample.value.heading == 0.0).all()
    finally:
        inputs.close()


# --- trajectory files -------------------------------------------------------------------------


def assert_names_file_and_location(message: str, path: Path) -> None:
    assert names_trajectory_place(after_file(message, path)), message


def _csv_text(t: Trajectory) -> str:
    rows = [
        f"{a!r},{b!r},{c!r},{d!r}" for a, b, c, d in zip(t.x, t.y, t.heading, t.speed, strict=True)
    ]
    return "x,y,heading,speed\n" + "\n".join(rows) + "\n"


_NASTY_CELLS = [
    "",
    "nan",
    "inf",
    "1e400",
    "1" + "0" * 400,
    "x",
    "\x00",
    "🚗",
    "!!int x",
    "2001-13-45",
    "[",
    "{",
    "&a",
    "*a",
    "'",
    "- -",
    ":",
]


@st.composite
def mutated_text(draw: st.DrawFn, text: str) -> bytes:
    """Text with lines dropped, doubled or replaced, a token swapped, truncated, or bad bytes."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["drop", "double", "blank", "token", "nasty_line"]))
        if op == "drop" and len(lines) > 1:
            del lines[i]
        elif op == "double":
            lines.insert(i, lines[i])
        elif op == "blank":
            lines.insert(i, "")
        elif op == "token":
            tokens = re.split(r"([,:\s\[\]-]+)", lines[i])
            j = draw(st.integers(0, len(tokens) - 1))
            tokens[j] = draw(st.sampled_from(_NASTY_CELLS))
            lines[i] = "".join(tokens)
        else:
            lines[i] = draw(st.text(max_size=20))
    data = "\n".join(lines).encode()
    tail = draw(st.sampled_from([b"", b"\xff", b"\xc3", b"\x00"]))
    cut = draw(st.integers(0, len(data)))
    return data[:cut] + tail + data[cut:] if draw(st.booleans()) else data


@FILES
@given(st.data(), st.sampled_from(["csv", "list", "mapping"]))
def test_trajectory_files_load_or_name_file_and_row(
    tmp_path: Path, data: st.DataObject, layout: str
) -> None:
    t = _trajectory(data.draw(st.integers(0, 8)))
    if layout == "csv":
        text, path = _csv_text(t), tmp_path / "t.csv"
    elif layout == "list":
        rows = [
            {"x": float(a), "y": float(b), "heading": float(c), "speed": float(d)}
            for a, b, c, d in zip(t.x, t.y, t.heading, t.speed, strict=True)
        ]
        text, path = yaml.safe_dump(rows), tmp_path / "t.yaml"
    else:
        columns = {k: [float(v) for v in getattr(t, k)] for k in ("x", "y", "heading", "speed")}
        text, path = yaml.safe_dump(columns), tmp_path / "t.yaml"
    path.write_bytes(data.draw(mutated_text(text)))
    try:
        loaded = load_trajectory(path)
    except TrajectoryError as exc:
        assert_names_file_and_location(str(exc), path)
    else:
        assert len(loaded) >= 4
        assert all(np.isfinite(getattr(loaded, k)).all() for k in ("x", "y", "heading", "speed"))


# --- config files -----------------------------------------------------------------------------

BASE_CONFIG = yaml.safe_load(SIM_YAML.read_text())


def _leaves(tree: Any, prefix: str = "") -> list[str]:
    out = []
    for k, v in tree.items():
        path = f"{prefix}.{k}" if prefix else k
        out.append(path)
        if isinstance(v, dict):
            out.extend(_leaves(v, path))
    return out


CONFIG_KEYS = _leaves(BASE_CONFIG)
_BAD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=10),
    st.lists(st.floats(allow_nan=True), max_size=3),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
)


def _related(named: str, mutated: str) -> bool:
    short, long = sorted((named, mutated), key=len)
    return long == short or long.startswith((short + ".", short + "["))


@FILES
@given(
    st.sampled_from(CONFIG_KEYS),
    _BAD_VALUES,
    st.sampled_from(["replace", "unknown"]),
)
def test_config_mutations_load_or_name_file_and_key(
    tmp_path: Path, key: str, value: Any, how: str
) -> None:
    tree = json.loads(json.dumps(BASE_CONFIG))
    *parents, last = key.split(".")
    node = tree
    for name in parents:
        node = node[name]
    if how == "unknown":
        last = f"{last}_typo"
        key = ".".join([*parents, last])
    node[last] = value
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(tree))
    try:
        load_config(path)
    except ConfigError as exc:
        message = str(exc)
        assert "\n" not in message
        assert message.startswith(f"{path}: "), message
        named = message[len(f"{path}: ") :].split(": ", 1)[0]
        assert _related(named, key), (named, key)
    else:
        # an unknown key is never accepted, except in the pass-through mappings (bus kwargs)
        assert how == "replace" or ".kwargs." in key


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (b"vehicle: {wheelbase: \xff}\n", "not UTF-8 at line 1, column 22"),
        (b"vehicle:\n  wheelbase: " + b"1" + b"0" * 400 + b"\n", "vehicle.wheelbase"),
        (b"controller:\n  mpc:\n    control_horizon: 1" + b"0" * 400 + b"\n", "control_horizon"),
        (b"vehicle:\n  wheelbase: 2001-13-45\n", "invalid YAML at line 2"),
        (b"vehicle:\n  wheelbase: !!float x\n", "invalid YAML at line 2"),
        (b"vehicle:\n  mass: !!int x\n", "invalid YAML at line 2"),
        (b"vehicle:\n  mass: !!timestamp x\n", "invalid YAML at line 2"),
        (b"vehicle:\n  mass: 1\x00\n", "invalid YAML at line 2, column 10"),
        (b"vehicle: " + b"[" * 50_000 + b"]" * 50_000, f"nested deeper than {MAX_YAML_DEPTH}"),
        (b"'': 1\n", "'': unknown key"),
    ],
)
def test_config_file_errors_are_config_errors_naming_file_and_place(
    tmp_path: Path, text: bytes, expected: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_bytes(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message


@pytest.mark.parametrize(
    ("name", "text", "expected"),
    [
        (
            "t.yaml",
            b"{x: [1" + b"0" * 400 + b", 1, 2, 3], y: [0, 1, 2, 3], heading: [0, 0, 0, 0], "
            b"speed: [1, 1, 1, 1]}\n",
            "row 1: x is out",
        ),
        ("t.yaml", b"- {x: !!int x, y: 0, heading: 0, speed: 1}\n", "invalid YAML at line 1"),
        ("t.yaml", b"x: [2001-13-45]\n", "invalid YAML at line 1"),
        ("t.yaml", b"x: " + b"[" * 50_000, f"nested deeper than {MAX_YAML_DEPTH}"),
        ("t.csv", b"x,y,heading,speed\n0,0,0,1\n1,\xff,0,1\n", "not UTF-8 at line 3, column 3"),
        ("t.csv", b'x,y,heading,speed\n0,0,0,1\n"' + b"a" * 200_000 + b'",0,0,1\n', "row 2"),
        ("t.csv", b"x,y," + b"a" * 200_000 + b"\n0,0,0,1\n", "line 1 (the header)"),
        # a blank line keeps its number: the bad waypoint is on row 5 of the file
        ("t.csv", b"x,y,heading,speed\n0,0,0,1\n\n1,0,0,1\n2,0,0,1\n3,0,inf,1\n", "row 5: heading"),
        ("t.csv", b"x,y,heading,speed\n0,0,0,1\n\n1,0,0,1\n2,nan,0,1\n3,0,0,1\n", "row 4: y is"),
    ],
)
def test_trajectory_file_errors_name_file_and_place(
    tmp_path: Path, name: str, text: bytes, expected: str
) -> None:
    path = tmp_path / name
    path.write_bytes(text)
    with pytest.raises(TrajectoryError) as info:
        load_trajectory(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and expected in message and "\n" not in message


@pytest.mark.parametrize(
    "text",
    [
        b"vehicle: {wheelbase: \xff}\n",
        b"vehicle:\n  mass: !!int x\n",
        b"gateway:\n  safety:\n    rate_up: [1" + b"0" * 400 + b"]\n",
        b"vehicle: " + b"[" * 5000,
    ],
)
def test_check_config_cli_prints_one_line_and_no_traceback(tmp_path: Path, text: bytes) -> None:
    path = tmp_path / "bad.yaml"
    path.write_bytes(text)
    proc = subprocess.run(
        [sys.executable, "-m", "leafgate.cli", "check-config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"leafgate: error: {path}: "), proc.stderr
    assert "Traceback" not in proc.stderr


def test_fuzz_tool_runs_clean_on_a_small_budget() -> None:
    proc = subprocess.run(
        [sys.executable, "tools/fuzz.py", "--cases", "400", "--seed", "7"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    report = json.loads(proc.stdout)
    assert report["total"]["cases"] == 400
    assert report["total"]["failures"] == 0, json.dumps(report, indent=1)[:2000]
    assert proc.returncode == 0
