"""Bad-input fuzzing of every place bytes from outside enter leafgate (issue 8, "Bad input").

Targets, each fed seeded random inputs through the real entry point:

* ``can_codec`` — :meth:`CanCodec.decode` on one long-lived codec: random 11- and 29-bit IDs,
  remote and error frames, lengths 0–8 and 64 (FD), random bytes; known IDs with random
  payloads; frames with a *valid* E2E (correct CRC, advancing alive counter) around a random
  payload, so the content decoders run; valid encoded frames with a bit flipped. Never raises;
  at the end the per-ID :attr:`CanCodec.stats` and :attr:`CanCodec.unknown_id_count` must add
  up to the frames fed, and per ID ``frames - errors`` must equal the valid decodes seen.
* ``can_receiver`` — the same frames through the gateway's receive path
  (:class:`leafgate.runtime.loop.CanReceiver`, the Notifier listener): never raises, its
  slots only ever hold valid reports.
* ``zenoh_cdr`` / ``zenoh_json`` — Odometry and Trajectory payloads through the subscriber
  callbacks of a real :class:`~leafgate.runtime.node.GatewayTransport` (declared on a stub
  session, so no network): random bytes, truncated, bit-flipped and spliced valid CDR (both
  byte orders), CDR with a forged sequence length; random, truncated and mistyped JSON, NaN,
  ±Infinity, 1e999, huge integers, huge arrays, deep nesting, non-UTF-8. No exception escapes
  the callback; each payload is either stored (``received``; marked invalid when not finite)
  or counted as dropped (``errors``), and stored valid samples are finite.
* ``engage_request`` — random query payloads and parameters through the engage queryable's
  parsing and answer: never raises, unknown requests refused.
* ``trajectory_csv`` / ``trajectory_yaml`` — mutated valid trajectory files through
  :func:`leafgate.control.reference.load_trajectory`: only :class:`TrajectoryError` escapes,
  its message starts with the file and names the row or line when the problem has one.
* ``config_file`` — mutations of ``config/sim.yaml`` (wrong types, unknown keys, bad values,
  deep nesting, YAML tags, non-UTF-8 bytes) and random YAML trees through
  :func:`leafgate.settings.load_config`: only :class:`ConfigError` escapes, its message starts
  with the file and names the key that was mutated (or a section holding it). Configs that
  load are then put through the rest of ``leafgate check-config`` (codec, controller,
  scenario), where only :class:`LeafgateError` may escape.

Plain ``random.Random`` generation rather than hypothesis: 100,000 cases need a generator that
costs microseconds, runs the same every time for a given ``--seed``, and keeps one long-lived
codec/transport whose counters are checked over the whole run (hypothesis would shrink, but
restarts state per example and spends most of its time in its own engine). The test suite
(``tests/test_fuzz.py``) uses hypothesis on the same targets with a few hundred examples.

Prints one JSON object: per target ``{cases, accepted, rejected, failures, seconds}``, plus
the first failing inputs (repr, capped). Exit status 1 when anything failed.

    .venv/bin/python tools/fuzz.py [--cases 100000] [--seed 1] [--targets can_codec,config_file]
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import math
import random
import re
import sys
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import _common
import can
import numpy as np
import yaml
from _common import StubSession

from leafgate.can import e2e
from leafgate.can.codec import CanCodec, Decoded, EncodableMessage
from leafgate.config.transport import ZenohConfig
from leafgate.control.reference import load_trajectory
from leafgate.errors import ConfigError, LeafgateError, TrajectoryError
from leafgate.gateway.state import EngageReply
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    GearPosition,
    LongCommand,
    LongMode,
    LongReport,
    MotorSpeed,
    OperatorRequest,
    Pose,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    Trajectory,
    WheelSpeeds,
)
from leafgate.runtime.node import GatewayTransport, parse_request
from leafgate.runtime.receiver import CanReceiver
from leafgate.transport import cdr
from leafgate.transport.payloads import codecs, pose_to_odometry, trajectory_to_ros

ROOT = Path(__file__).resolve().parent.parent
SIM_YAML = ROOT / "config" / "sim.yaml"
MAX_FAILURES_SHOWN = 10  # failing inputs printed per target
REPR_CAP = 400  # characters of a failing input's repr
CHECK_MAX_HORIZON = 200  # steps: larger MPC horizons are not built (see KNOWN_LIMITS)

# Findings reported to the owners of files this tool may not change; the fuzzer steers around
# them so that they do not drown everything else, and says so in its output.
KNOWN_LIMITS = {
    "config_file": (
        f"check-config is run only on configs whose MPC horizons are <= {CHECK_MAX_HORIZON}: "
        "MpcConfig has no upper bound on prediction_horizon/control_horizon, and building the "
        "controller for Np = Nc = 20000 needs tens of GB (Np = 2**63 raises OverflowError)"
    ),
}


class Failure(Exception):
    """An input broke a promise of the target (not an exception the target may raise)."""


# --- mutation helpers -------------------------------------------------------------------------


def flip_bits(rng: random.Random, data: bytes, n: int) -> bytes:
    out = bytearray(data)
    for _ in range(n):
        if out:
            out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
    return bytes(out)


def mutate_bytes(rng: random.Random, data: bytes) -> bytes:
    """One random byte-level mutation: truncate, flip, insert, delete, splice or overwrite."""
    op = rng.randrange(7)
    n = len(data)
    if op == 0:  # truncate
        return data[: rng.randrange(n + 1)]
    if op == 1:
        return flip_bits(rng, data, rng.randint(1, 8))
    if op == 2:  # insert random bytes
        i = rng.randrange(n + 1)
        return data[:i] + rng.randbytes(rng.randint(1, 16)) + data[i:]
    if op == 3:  # delete a run
        i = rng.randrange(n + 1)
        return data[:i] + data[i + rng.randint(1, 16) :]
    if op == 4:  # overwrite a 4-byte word (lengths and counts live in them)
        if n < 4:
            return rng.randbytes(4)
        i = rng.randrange(n - 3)
        word = rng.choice([0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000, rng.getrandbits(32)])
        return data[:i] + word.to_bytes(4, "little") + data[i + 4 :]
    if op == 5:  # append garbage
        return data + rng.randbytes(rng.randint(1, 64))
    # splice: the tail of the payload repeated or cut
    i, j = rng.randrange(n + 1), rng.randrange(n + 1)
    return data[:i] + data[j:]


NASTY_NUMBERS: tuple[Any, ...] = (
    0,
    -1,
    1,
    0.0,
    -0.0,
    1e-320,
    1e308,
    -1e308,
    math.nan,
    math.inf,
    -math.inf,
    2**31,
    2**63,
    -(2**63),
    10**400,
    -(10**400),
)
NASTY_TEXT: tuple[str, ...] = (
    "",
    " ",
    "nan",
    "NaN",
    "inf",
    "-Infinity",
    "1e400",
    "1" * 400,
    "0x10",
    "1_000",
    "1,5",
    "\x00",
    "\ufeff1",
    "ünïcode",
    "🚗",
    "true",
    "null",
    "~",
    "- 1",
    "{",
    "[",
    '"',
    "'",
    "\\",
    "%YAML 1.2",
    "!!python/object:os.system",
    "*a",
    "&a 1",
    "2001-13-45",
    "!!int x",
    "!!float x",
    "!!timestamp x",
    "!!binary x",
)


def nasty_value(rng: random.Random, depth: int = 0) -> Any:
    """A value of a random, often wrong, type for a YAML or JSON tree."""
    r = rng.random()
    if r < 0.35:
        return rng.choice(NASTY_NUMBERS)
    if r < 0.55:
        return rng.choice(NASTY_TEXT)
    if r < 0.65:
        return rng.choice([None, True, False])
    if r < 0.75:
        return rng.uniform(-1e3, 1e3)
    if depth > 3 or r < 0.85:
        return [rng.choice(NASTY_NUMBERS) for _ in range(rng.randint(0, 4))]
    if r < 0.93:
        return {str(nasty_value(rng, depth + 1))[:20]: nasty_value(rng, depth + 1)}
    return [nasty_value(rng, depth + 1) for _ in range(rng.randint(0, 3))]


def deep_nesting(rng: random.Random, flow: bool = True) -> str:
    depth = rng.choice([50, 200, 1000, 5000, 50_000])
    if flow:
        return "[" * depth + "]" * depth
    return "".join(f"{'  ' * i}k{i}:\n" for i in range(min(depth, 3000))) + "  " * depth + "v\n"


# --- targets ----------------------------------------------------------------------------------


class Target:
    """One fuzzed entry point: ``generate`` makes an input, ``feed`` runs it.

    ``feed`` returns True when the input was accepted, False when it was rejected the way the
    target promises; it raises :class:`Failure` (or lets any other exception out) when not.
    ``finish`` checks what only holds over the whole run (counters adding up).
    """

    name = ""

    def generate(self, rng: random.Random) -> Any:
        raise NotImplementedError

    def feed(self, case: Any) -> bool:
        raise NotImplementedError

    def finish(self) -> list[str]:
        return []

    def close(self) -> None:
        """Release what the target holds (threads, files)."""

    def show(self, case: Any) -> str:
        return repr(case)


def _random_message(rng: random.Random) -> EncodableMessage:
    """A valid message value of a random kind (for encoding, then mutating)."""
    u = rng.uniform
    kind = rng.randrange(8)
    if kind == 0:
        return SteerCommand(u(-0.5, 0.5), u(0, 1), rng.random() < 0.5, rng.random() < 0.5)
    if kind == 1:
        return LongCommand(
            rng.choice(list(LongMode)),
            u(-3, 1.5),
            u(0, 3),
            rng.choice(list(Gear)),
            rng.random() < 0.5,
            False,
        )
    if kind == 2:
        return SystemCommand(rng.choice(list(GatewayState)), rng.random() < 0.5)
    if kind == 3:
        return SteerReport(u(-0.5, 0.5), u(-1, 1), u(-5, 5), True, False, False, False)
    if kind == 4:
        return LongReport(
            u(-2, 3),
            u(-3, 2),
            rng.choice(list(Gear)),
            u(0, 100),
            u(0, 100),
            True,
            False,
            False,
            False,
        )
    if kind == 5:
        return SystemReport(rng.choice(list(EcuState)), False, False, False, False, 3)
    if kind == 6:
        car: list[EncodableMessage] = [
            SteeringWheelAngle(u(-5, 5)),
            MotorSpeed(u(0, 20)),
            GearPosition(rng.choice([Gear.P, Gear.R, Gear.N, Gear.D])),
        ]
        return rng.choice(car)
    return WheelSpeeds(u(0, 10), u(0, 10), rng.choice(["front", "rear"]))


_DECODED_TYPES = (
    SteerCommand,
    LongCommand,
    SystemCommand,
    SteerReport,
    LongReport,
    SystemReport,
    SteeringWheelAngle,
    MotorSpeed,
    WheelSpeeds,
    GearPosition,
)
_ERRORS = {"bad_crc", "bad_counter", "wrong_length", "unknown_id", "decode_error"}


@dataclass
class CanCase:
    """A frame and what the generator promises about it."""

    frame: can.Message
    kind: str
    e2e_valid: bool = False  # correct CRC and the next alive counter: must not be bad_crc/counter


class CanFrames:
    """Frame generator shared by the CAN targets; tracks the receiver's alive counters."""

    def __init__(self) -> None:
        ref = CanCodec(profile="leafgate-dbw")
        self.dbw_ids = sorted(ref.receive_ids("commands") | ref.receive_ids("reports"))
        self.known_ids = sorted(set(self.dbw_ids) | ref.receive_ids("car"))
        self.sender = CanCodec(profile="leafgate-dbw")
        self.last_counter: dict[int, int] = {}  # what the receiving codec last saw, per ID

    def generate(self, rng: random.Random) -> CanCase:
        r = rng.random()
        if r < 0.25:
            extended = rng.random() < 0.3
            frame_id = rng.getrandbits(29 if extended else 11)
            fd = rng.random() < 0.05
            size = 64 if fd else rng.randint(0, 8)
            remote, error = rng.random() < 0.05, rng.random() < 0.05
            case = CanCase(
                can.Message(
                    arbitration_id=frame_id,
                    is_extended_id=extended,
                    is_remote_frame=remote,
                    is_error_frame=error,
                    is_fd=fd,
                    dlc=size,
                    data=b"" if remote else rng.randbytes(size),
                    check=False,
                ),
                "random",
            )
        elif r < 0.45:
            frame_id = rng.choice(self.known_ids)
            size = 8 if rng.random() < 0.7 else rng.choice([0, 1, 5, 7, 9, 12, 64])
            case = CanCase(
                can.Message(
                    arbitration_id=frame_id,
                    is_extended_id=rng.random() < 0.05,
                    is_fd=size > 8,
                    data=rng.randbytes(size),
                    check=False,
                ),
                "known_id",
            )
        elif r < 0.85:
            frame_id = rng.choice(self.dbw_ids)
            last = self.last_counter.get(frame_id)
            step = 1 if rng.random() < 0.9 else rng.randrange(16)
            counter = rng.randrange(16) if last is None else (last + step) % 16
            data = e2e.apply(frame_id, rng.randbytes(8), counter)
            case = CanCase(
                can.Message(arbitration_id=frame_id, is_extended_id=False, data=data),
                "valid_e2e",
                e2e_valid=last is None or step == 1,
            )
        else:
            frame = self.sender.encode(_random_message(rng))
            if rng.random() < 0.7:
                frame.data = bytearray(flip_bits(rng, bytes(frame.data), rng.randint(1, 3)))
            case = CanCase(frame, "encoded")
        self._track(case.frame)
        return case

    def _track(self, msg: can.Message) -> None:
        """Mirror the codec's counter checker: it remembers every CRC-valid DBW frame's count."""
        data = bytes(msg.data)
        if (
            msg.arbitration_id in self.dbw_ids
            and not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame)
            and e2e.verify(msg.arbitration_id, data)
        ):
            self.last_counter[msg.arbitration_id] = e2e.counter_of(data)

    def __call__(self, rng: random.Random) -> CanCase:
        return self.generate(rng)


def check_decoded(codec: CanCodec, case: CanCase, out: Decoded) -> None:
    msg = case.frame
    if not isinstance(out, Decoded):
        raise Failure(f"decode returned {type(out).__name__}")
    if out.valid != (out.error is None):
        raise Failure(f"valid={out.valid} with error={out.error!r}")
    if out.error is not None and out.error not in _ERRORS:
        raise Failure(f"unknown error kind {out.error!r}")
    known = not msg.is_extended_id and codec.name_of(msg.arbitration_id) is not None
    if not known and out.error != "unknown_id":
        raise Failure(f"an unknown ID decoded as {out.error or 'valid'}")
    if known and out.name != codec.name_of(msg.arbitration_id):
        raise Failure(f"named {out.name!r}")
    if out.valid and not isinstance(out.value, _DECODED_TYPES):
        raise Failure(f"valid frame with value {out.value!r}")
    if out.valid:
        for f in fields(out.value):  # type: ignore[arg-type]
            v = getattr(out.value, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise Failure(f"valid frame with {f.name} = {v}")
    if case.e2e_valid and out.error in ("bad_crc", "bad_counter"):
        raise Failure(f"valid E2E frame rejected as {out.error}")


class CanCodecTarget(Target):
    name = "can_codec"

    def __init__(self) -> None:
        self.frames = CanFrames()
        self.codec = CanCodec(profile="leafgate-dbw")
        self.fed = 0
        self.valid: Counter[int] = Counter()
        self.kinds: Counter[str] = Counter()

    def generate(self, rng: random.Random) -> CanCase:
        return self.frames(rng)

    def feed(self, case: CanCase) -> bool:
        self.fed += 1
        self.kinds[case.kind] += 1
        out = self.codec.decode(case.frame)
        check_decoded(self.codec, case, out)
        if out.valid:
            self.valid[case.frame.arbitration_id] += 1
        return out.valid

    def finish(self) -> list[str]:
        return can_counts_add_up(self.codec, self.fed, self.valid)

    def show(self, case: CanCase) -> str:
        m = case.frame
        return (
            f"{case.kind}: id=0x{m.arbitration_id:X} ext={m.is_extended_id} "
            f"rtr={m.is_remote_frame} err={m.is_error_frame} fd={m.is_fd} "
            f"data={bytes(m.data).hex()}"
        )


def can_counts_add_up(codec: CanCodec, fed: int, valid: Counter[int]) -> list[str]:
    """Every frame fed is in the codec's counters exactly once, and every invalid one as such."""
    problems = []
    stats = codec.stats
    known = set(codec.receive_ids("commands") | codec.receive_ids("reports"))
    known |= codec.receive_ids("car")
    # An unknown (e.g. extended) frame whose number equals a known ID is counted under that ID
    # as unknown_id; all other unknown frames are in unknown_id_count (and, up to 1024 IDs, in
    # their own stats entry).
    in_known = sum(stats[i].frames - stats[i].unknown_id for i in known)
    total = in_known + codec.unknown_id_count
    if total != fed:
        problems.append(f"stats count {total} frames, {fed} were fed")
    tracked_unknown = sum(s.unknown_id for s in stats.values())
    if tracked_unknown > codec.unknown_id_count:
        problems.append(f"{tracked_unknown} unknown frames in stats > unknown_id_count")
    for frame_id in known:
        s = stats[frame_id]
        good = s.frames - s.errors
        if good != valid[frame_id]:
            problems.append(
                f"0x{frame_id:03X}: stats say {good} valid, decode said {valid[frame_id]}"
            )
    return problems


class CanReceiverTarget(CanCodecTarget):
    """The same frames through the gateway's Notifier listener."""

    name = "can_receiver"

    def __init__(self) -> None:
        super().__init__()
        self.receiver = CanReceiver(self.codec, clock=lambda: 1.0)
        self.seen: list[Decoded] = []
        self.receiver.on_frame = lambda _msg, decoded: self.seen.append(decoded)
        self.counted = 0  # frames the receiver should count as good or bad report frames
        # Frames on the gateway's own command IDs are not decoded: they are echoes of what it
        # sent or foreign (another node commanding the ECU), and counted as such.
        self.command_ids: frozenset[int] = getattr(self.receiver, "command_ids", frozenset())
        self.foreign = 0

    def feed(self, case: CanCase) -> bool:
        msg = case.frame
        self.kinds[case.kind] += 1
        self.seen.clear()
        self.receiver.on_message_received(msg)
        if len(self.seen) != 1:
            raise Failure(f"recorder hook called {len(self.seen)} times")
        out = self.seen[0]
        if msg.arbitration_id in self.command_ids and not msg.is_extended_id:
            self.foreign += 1
            if out.valid or out.value is not None:
                raise Failure(f"a foreign command frame reached the recorder as {out!r}")
            if self.receiver.foreign_total != self.foreign:
                raise Failure(f"foreign_total {self.receiver.foreign_total} != {self.foreign}")
            return False
        self.fed += 1  # frames that reach the codec
        check_decoded(self.codec, case, out)
        if out.valid:
            self.valid[case.frame.arbitration_id] += 1
        if isinstance(out.value, (SteerReport, LongReport, SystemReport)) or out.error in (
            "bad_crc",
            "bad_counter",
            "wrong_length",
            "decode_error",  # content outside its value table counts against the ECU too
        ):
            self.counted += 1
        for slot, kind in (
            (self.receiver.steer, SteerReport),
            (self.receiver.long, LongReport),
            (self.receiver.system, SystemReport),
        ):
            sample = slot.get()
            if sample is not None and not (sample.valid and isinstance(sample.value, kind)):
                raise Failure(f"{kind.__name__} slot holds {sample!r}")
        return out.valid

    def finish(self) -> list[str]:
        problems = can_counts_add_up(self.codec, self.fed, self.valid)
        good, bad = self.receiver.take_counts()
        if good + bad != self.counted:
            problems.append(f"receiver counted {good + bad} report frames, expected {self.counted}")
        return problems


# --- Zenoh ------------------------------------------------------------------------------------


def stub_transport(encoding: str) -> tuple[GatewayTransport, StubSession]:
    session = StubSession()
    transport = GatewayTransport(
        session,  # type: ignore[arg-type]
        ZenohConfig(encoding=encoding),  # type: ignore[arg-type]
        handler=lambda request: {"accepted": False, "state": "STANDBY", "reason": "fuzz"},
        clock=lambda: 5.0,
    )
    return transport, session


sample_of = _common.stub_sample


def random_pose(rng: random.Random, finite: bool = True) -> Pose:
    def num() -> float:
        if not finite and rng.random() < 0.2:
            return rng.choice([math.nan, math.inf, -math.inf])
        return rng.uniform(-1e4, 1e4)

    stamp = rng.choice([math.nan, rng.uniform(0, 2e9)])
    return Pose(num(), num(), rng.uniform(-4, 4), num(), num(), stamp=stamp)


def random_trajectory(rng: random.Random, n: int | None = None) -> Trajectory:
    if n is None:
        n = rng.choice([0, 1, 4, rng.randint(2, 60)])
    step = rng.uniform(0.5, 1.0)
    heading = np.cumsum(rng.uniform(-0.2, 0.2) * np.ones(n)) + rng.uniform(-3, 3)
    x = np.cumsum(step * np.cos(heading)) + rng.uniform(-100, 100)
    y = np.cumsum(step * np.sin(heading)) + rng.uniform(-100, 100)
    speed = np.full(n, rng.uniform(-2, 2))
    return Trajectory(x, y, heading, speed, stamp=rng.choice([math.nan, rng.uniform(0, 2e9)]))


@dataclass
class ZenohCase:
    key: str  # "pose" or "trajectory"
    payload: bytes
    kind: str


class ZenohTarget(Target):
    """Payloads for the two input keys through a transport's subscriber callbacks."""

    def __init__(self, encoding: str) -> None:
        self.name = f"zenoh_{encoding}"
        self.encoding = encoding
        self.transport, session = stub_transport(encoding)
        self.callbacks = {
            "pose": session.subscribers[self.transport.pose.key],
            "trajectory": session.subscribers[self.transport.trajectory.key],
        }
        self.codecs = codecs(encoding)
        self.fed: Counter[str] = Counter()
        self.invalid: Counter[str] = Counter()

    def slot(self, key: str) -> Any:
        return self.transport.pose if key == "pose" else self.transport.trajectory

    def generate(self, rng: random.Random) -> ZenohCase:
        key = rng.choice(["pose", "trajectory"])
        if self.encoding == "cdr":
            payload, kind = self._cdr(rng, key)
        else:
            payload, kind = self._json(rng, key)
        return ZenohCase(key, payload, kind)

    def _valid(self, rng: random.Random, key: str) -> bytes:
        if key == "pose":
            finite = self.encoding == "json" or rng.random() < 0.8  # JSON has no ±inf
            return self.codecs.pose.encode(random_pose(rng, finite=finite))
        n = rng.choice([0, 4, rng.randint(0, 50), 2000]) if rng.random() < 0.1 else None
        return self.codecs.trajectory.encode(random_trajectory(rng, n))

    def _cdr(self, rng: random.Random, key: str) -> tuple[bytes, str]:
        r = rng.random()
        if r < 0.1:
            return rng.randbytes(rng.randint(0, 300)), "random"
        if r < 0.15:
            return b"\x00\x01\x00\x00" + rng.randbytes(rng.randint(0, 300)), "random_le_header"
        if r < 0.25:  # big-endian CDR goes through rosbags, not the numpy fast path
            if key == "pose":
                msg, typename = pose_to_odometry(random_pose(rng)), cdr.ODOMETRY
            else:
                msg, typename = trajectory_to_ros(random_trajectory(rng)), cdr.TRAJECTORY
            data = bytes(cdr.store().serialize_cdr(msg, typename, little_endian=False))
            return (mutate_bytes(rng, data) if rng.random() < 0.7 else data), "big_endian"
        valid = self._valid(rng, key)
        if r < 0.35:
            return valid, "valid"
        if r < 0.45 and key == "trajectory" and len(valid) > 24:  # forge the point count
            name_len = int.from_bytes(valid[12:16], "little")
            offset = 12 + name_len  # after stamp and the string, counted from after the header
            at = 4 + offset + (-offset % 4)  # the uint32 sequence length, 4-aligned
            count = rng.choice([1, 2, 1000, 2**20, 2**31, 2**32 - 1, rng.getrandbits(32)])
            return valid[:at] + count.to_bytes(4, "little") + valid[at + 4 :], "forged_count"
        out = valid
        for _ in range(rng.randint(1, 3)):
            out = mutate_bytes(rng, out)
        return out, "mutated"

    def _json(self, rng: random.Random, key: str) -> tuple[bytes, str]:
        r = rng.random()
        if r < 0.08:
            return rng.randbytes(rng.randint(0, 200)), "random"
        if r < 0.13:
            return deep_nesting(rng).encode(), "deep"
        if r < 0.2:
            return json.dumps(nasty_value(rng)).encode(), "random_json"
        valid = self._valid(rng, key)
        if r < 0.3:
            return valid, "valid"
        if r < 0.45:
            return mutate_bytes(rng, valid), "mutated_bytes"
        obj = json.loads(valid)
        for _ in range(rng.randint(1, 3)):
            op = rng.randrange(5)
            names = list(obj)
            if op == 0 and names:
                del obj[rng.choice(names)]
            elif op == 1:
                obj[rng.choice(["z", "X", "extra", "stamp ", ""])] = nasty_value(rng)
            elif op == 2 and names:
                obj[rng.choice(names)] = nasty_value(rng)
            elif op == 3 and key == "trajectory":  # a list element of the wrong kind
                name = rng.choice(["x", "y", "heading", "speed"])
                if isinstance(obj.get(name), list) and obj[name]:
                    obj[name][rng.randrange(len(obj[name]))] = nasty_value(rng)
            elif op == 4 and key == "trajectory":  # huge or mismatched arrays
                size = rng.choice([0, 1, 3, 100_000])
                obj[rng.choice(["x", "y", "heading", "speed"])] = [
                    rng.choice([0.0, 1.0, math.nan]) for _ in range(size)
                ]
        text = json.dumps(obj)  # NaN and ±Infinity come out as their JavaScript literals
        if rng.random() < 0.1:
            text = text.replace("1.0", "1e999", 1)
        return text.encode(), "mutated_tree"

    def feed(self, case: ZenohCase) -> bool:
        slot = self.slot(case.key)
        before = (slot.received, slot.errors)
        self.fed[case.key] += 1
        self.callbacks[case.key](sample_of(case.payload))
        after = (slot.received, slot.errors)
        if after[0] + after[1] != before[0] + before[1] + 1:
            raise Failure(f"counters went from {before} to {after}")
        if after[1] > before[1]:
            return False  # dropped and counted
        sample = slot.get()
        value: Any = None if sample is None else sample.value
        kind = Pose if case.key == "pose" else Trajectory
        # a pose's receive time goes back by its stamp's age (issue 17), never forward
        if not isinstance(value, kind) or not sample.received <= 5.0:
            raise Failure(f"stored {sample!r}")
        if kind is Trajectory and sample.received != 5.0:
            raise Failure(f"stored {sample!r}")
        if sample.valid:
            values: list[float] = []
            if isinstance(value, Pose):
                values = [value.x, value.y, value.heading, value.speed]
            else:
                if len(value) == 0:
                    raise Failure("an empty trajectory stored as valid")
                values = [
                    float(np.sum(np.abs(a))) for a in (value.x, value.y, value.heading, value.speed)
                ]
            if not all(math.isfinite(v) for v in values):
                raise Failure(f"a non-finite {case.key} stored as valid")
            return True
        self.invalid[case.key] += 1
        return False

    def finish(self) -> list[str]:
        problems = []
        for key in ("pose", "trajectory"):
            slot = self.slot(key)
            if slot.received + slot.errors != self.fed[key]:
                problems.append(
                    f"{key}: received {slot.received} + dropped {slot.errors} != fed {self.fed[key]}"
                )
            invalid = getattr(slot, "invalid", None)
            if invalid is not None and invalid != self.invalid[key]:
                problems.append(f"{key}: slot counts {invalid} invalid, saw {self.invalid[key]}")
        return problems

    def close(self) -> None:
        self.transport.close()

    def show(self, case: ZenohCase) -> str:
        return f"{case.key} {case.kind}: {case.payload!r}"


#: every engage reply's fields (docs/state-machine.md), as the gateway's reply type has them
REPLY_FIELDS = {f.name for f in fields(EngageReply)}


class EngageRequestTarget(Target):
    """Query payloads and ``request=`` parameters through the engage queryable's answer."""

    name = "engage_request"

    def __init__(self) -> None:
        self.transport, _ = stub_transport("cdr")

    def generate(self, rng: random.Random) -> tuple[bytes | None, str | None]:
        words = [r.value for r in OperatorRequest]
        payload: bytes | None
        r = rng.random()
        if r < 0.3:
            payload = rng.randbytes(rng.randint(0, 64))
        elif r < 0.6:
            payload = (rng.choice(words) + rng.choice(["", " ", "\n", "\x00", "!"])).encode()
            if rng.random() < 0.3:
                payload = payload.upper()
        elif r < 0.8:
            payload = rng.choice(NASTY_TEXT).encode()
        else:
            payload = None
        parameter = rng.choice([None, rng.choice(words), rng.choice(NASTY_TEXT)])
        return payload, parameter

    def feed(self, case: tuple[bytes | None, str | None]) -> bool:
        request = parse_request(*case)
        reply = self.transport.answer(request)
        if set(reply) != REPLY_FIELDS:
            raise Failure(f"reply {reply!r}")
        json.dumps(reply, allow_nan=False)  # the reply goes out as JSON
        if not isinstance(request, OperatorRequest):
            if reply["accepted"] or "unknown request" not in reply["reason"]:
                raise Failure(f"unknown request answered {reply!r}")
            return False
        return True

    def close(self) -> None:
        self.transport.close()


# --- files ------------------------------------------------------------------------------------


class FileTarget(Target):
    """Inputs are file contents, written to one scratch file and loaded by path."""

    suffix = ".txt"

    def __init__(self, directory: Path) -> None:
        self.path = directory / f"{self.name}{self.suffix}"

    def write(self, data: bytes) -> Path:
        self.path.write_bytes(data)
        return self.path

    def show(self, case: Any) -> str:
        return repr(case)


def text_mutation(rng: random.Random, text: str, cells: bool = True) -> str:
    """One line- or token-level mutation of a text file."""
    lines = text.split("\n")
    op = rng.randrange(10)
    i = rng.randrange(len(lines))
    if op == 0:
        del lines[i]
    elif op == 1:
        lines.insert(i, lines[i])
    elif op == 2:
        lines.insert(i, rng.choice(["", "   ", "#", ",,,", rng.choice(NASTY_TEXT)]))
    elif op == 3 and cells:  # replace one token (a number or a name) with something nasty
        tokens = re.split(r"([,:\[\]{}\s-]+)", lines[i])
        spots = [k for k, t in enumerate(tokens) if t and not re.fullmatch(r"[,:\[\]{}\s-]+", t)]
        if spots:
            tokens[rng.choice(spots)] = rng.choice((*NASTY_TEXT, "1e400", "1" + "0" * 400))
            lines[i] = "".join(tokens)
    elif op == 4:
        return text[: rng.randrange(len(text) + 1)]
    elif op == 5:
        lines[i] = lines[i] + rng.choice([",1", ", x", "  # c", "\t", ": 1", " ]"])
    elif op == 6:
        return text.replace("\n", "\r\n")
    elif op == 7:
        return "\ufeff" + text
    elif op == 8:
        lines[i] = rng.choice(["\t", "  ", " "]) + lines[i]
    else:
        rng.shuffle(lines)
    return "\n".join(lines)


def file_bytes_mutation(rng: random.Random, text: str) -> bytes:
    """Text with, sometimes, a byte-level change: non-UTF-8 bytes, NUL, a huge field."""
    data = text.encode("utf-8")
    r = rng.random()
    if r < 0.05:
        i = rng.randrange(len(data) + 1)
        return data[:i] + rng.choice([b"\xff", b"\xc3", b"\x80\x81", b"\xed\xa0\x80"]) + data[i:]
    if r < 0.08:
        return flip_bits(rng, data, rng.randint(1, 4))
    if r < 0.09:
        i = rng.randrange(len(data) + 1)
        return data[:i] + b"a" * rng.choice([1000, 200_000]) + data[i:]
    if r < 0.1:
        return data.replace(b",", b"\x00", 1).replace(b":", b"\x00", 1)
    return data


class TrajectoryFileTarget(FileTarget):
    def __init__(self, directory: Path, fmt: str) -> None:
        self.name = f"trajectory_{fmt}"
        self.suffix = f".{fmt}"
        self.fmt = fmt
        super().__init__(directory)

    def generate(self, rng: random.Random) -> bytes:
        t = random_trajectory(rng, rng.choice([0, 2, 4, rng.randint(3, 30)]))
        columns = {"x": t.x, "y": t.y, "heading": t.heading, "speed": t.speed}
        if self.fmt == "csv":
            header = list(columns)
            if rng.random() < 0.3:
                rng.shuffle(header)
            rows = [",".join(header)]
            rows += [",".join(repr(float(columns[h][i])) for h in header) for i in range(len(t))]
            text = "\n".join(rows) + "\n"
        elif rng.random() < 0.5:
            text = yaml.safe_dump(
                [{k: float(v[i]) for k, v in columns.items()} for i in range(len(t))]
            )
        else:
            text = yaml.safe_dump({k: [float(x) for x in v] for k, v in columns.items()})
        if self.fmt == "yaml" and rng.random() < 0.05:
            text = rng.choice([deep_nesting(rng), deep_nesting(rng, flow=False), "x: &a [*a]\n"])
        for _ in range(rng.choice([0, 1, 1, 2, 3])):
            text = text_mutation(rng, text)
        return file_bytes_mutation(rng, text)

    def feed(self, case: bytes) -> bool:
        path = self.write(case)
        try:
            traj = load_trajectory(path)
        except TrajectoryError as exc:
            check_file_message(str(exc), path)
            return False
        if len(traj) < 4 or not all(
            np.isfinite(a).all() for a in (traj.x, traj.y, traj.heading, traj.speed)
        ):
            raise Failure(f"accepted a trajectory of {len(traj)} points with non-finite values")
        return True


def after_file(message: str, path: Path) -> str:
    """What a file error says after ``"{path}: "``; a Failure unless it is one such line."""
    try:
        return _common.after_file(message, path)
    except ValueError as exc:
        raise Failure(str(exc)) from None


def check_file_message(message: str, path: Path) -> None:
    """A trajectory file error: one line, starts with the file, names the row/line if any."""
    if not _common.names_trajectory_place(after_file(message, path)):
        raise Failure(f"message names no location: {message!r}")


# --- config files -----------------------------------------------------------------------------


def _paths(tree: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any, Any]]:
    """(dotted path, container, key, value) of every node below ``tree``."""
    if isinstance(tree, dict):
        for k, v in list(tree.items()):
            path = f"{prefix}.{k}" if prefix else str(k)
            yield path, tree, k, v
            yield from _paths(v, path)
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            path = f"{prefix}[{i}]"
            yield path, tree, i, v
            yield from _paths(v, path)


def _related(a: str, b: str) -> bool:
    """True when one dotted key is the other or holds it (``gateway`` holds ``gateway.x[1]``)."""
    if a == "<top level>" or b == "<top level>":
        return True
    short, long = sorted((a, b), key=len)
    return long == short or long.startswith((short + ".", short + "["))


@dataclass
class ConfigCase:
    data: bytes
    mutated: list[str] = field(default_factory=list)  # dotted keys changed in the tree
    text_mutated: bool = False  # the text was changed after dumping: any key may be named


class ConfigFileTarget(FileTarget):
    name = "config_file"
    suffix = ".yaml"

    def __init__(self, directory: Path) -> None:
        super().__init__(directory)
        self.base = yaml.safe_load(SIM_YAML.read_text())
        self.checked = 0  # configs that loaded and went through the rest of check-config
        self.skipped_checks = 0
        self.check_rejected = 0
        sections = {k: list(v) for k, v in self.base.items() if isinstance(v, dict)}
        self.known_keys = sorted({k for keys in sections.values() for k in keys})

    def generate(self, rng: random.Random) -> ConfigCase:
        if rng.random() < 0.05:
            text = rng.choice(
                [
                    yaml.safe_dump(nasty_value(rng)),
                    deep_nesting(rng),
                    "vehicle:\n" + deep_nesting(rng, flow=False),
                    "vehicle: " + deep_nesting(rng) + "\n",
                    "a: &a [*a]\nvehicle: &v {wheelbase: *v}\n",
                    rng.choice(NASTY_TEXT) + "\n",
                ]
            )
            return ConfigCase(file_bytes_mutation(rng, text), ["<top level>"], True)
        tree = json.loads(json.dumps(self.base))  # a deep copy
        mutated = []
        for _ in range(rng.randint(1, 3)):
            nodes = list(_paths(tree))
            path, container, key, _value = rng.choice(nodes)
            op = rng.randrange(6)
            if op == 0:  # a wrong or bad value
                container[key] = nasty_value(rng)
            elif op == 1 and isinstance(container, dict):  # an unknown key next to it
                new = rng.choice(
                    [
                        "x",
                        "wheelbase_deg",
                        "max_steer_angle_kmh",
                        f"{key}_degps",
                        f"{key}_deg",
                        str(key).upper(),
                        rng.choice(self.known_keys),
                    ]
                )
                if new in container:
                    continue
                container[new] = nasty_value(rng)
                parent = path.rsplit(".", 1)[0] if "." in path else ""
                path = f"{parent}.{new}" if parent else new
            elif op == 2 and isinstance(container, dict):
                del container[key]
                path = path.rsplit(".", 1)[0] if "." in path else "<top level>"
            elif op == 3:  # a number of the right type but any size
                container[key] = rng.choice(
                    [rng.uniform(-10, 10), rng.randint(-5, 500), 10 ** rng.randint(3, 30)]
                )
            elif op == 4:  # a list where a number was, or a mapping
                container[key] = rng.choice([[1.0, 2.0], {"a": 1}, [], {}])
            else:  # swap in a known key's value from elsewhere
                container[key] = copy.deepcopy(rng.choice(nodes)[3])  # never itself
            mutated.append(path)
        text = yaml.safe_dump(tree, allow_unicode=rng.random() < 0.5, sort_keys=False)
        text_mutated = rng.random() < 0.2
        if text_mutated:
            text = text_mutation(rng, text)
        data = file_bytes_mutation(rng, text)
        return ConfigCase(data, mutated, text_mutated or data != text.encode("utf-8"))

    def feed(self, case: ConfigCase) -> bool:
        from leafgate.settings import load_config

        path = self.write(case.data)
        try:
            cfg = load_config(path)
        except ConfigError as exc:
            self._check_message(str(exc), path, case)
            return False
        mpc = cfg.controller.mpc
        if max(mpc.prediction_horizon, mpc.control_horizon) > CHECK_MAX_HORIZON:
            self.skipped_checks += 1
            return True
        self.checked += 1
        try:
            check_config_rest(path)
        except LeafgateError as exc:
            if "\n" in str(exc):
                raise Failure(f"multi-line check-config message: {exc}") from None
            self.check_rejected += 1
            return False
        return True

    def _check_message(self, message: str, path: Path, case: ConfigCase) -> None:
        rest = after_file(message, path)
        if re.match(r"(invalid YAML|not UTF-8|cannot read)", rest):
            if not _common.LOCATION.search(rest) and "line" not in rest:
                raise Failure(f"YAML error without a line: {message!r}")
            return
        named = rest.split(": ", 1)[0]
        if case.text_mutated:
            if not named.strip():
                raise Failure(f"message names no key: {message!r}")
            return
        if not any(_related(named, m) for m in case.mutated):
            raise Failure(f"message names {named!r}, the mutated keys were {case.mutated}")

    def finish(self) -> list[str]:
        return []

    def show(self, case: ConfigCase) -> str:
        return f"mutated {case.mutated}: {case.data!r}"


def check_config_rest(path: Path) -> None:
    """What ``leafgate check-config`` does after loading (its stdout discarded)."""
    from leafgate.cli import cmd_check_config

    with contextlib.redirect_stdout(io.StringIO()):
        cmd_check_config(argparse.Namespace(file=str(path)))


# --- driver -----------------------------------------------------------------------------------


@dataclass
class Result:
    cases: int = 0
    accepted: int = 0
    rejected: int = 0
    failures: int = 0
    seconds: float = 0.0
    slowest_case_s: float = 0.0  # s, the longest single accepted or rejected input
    failing_inputs: list[dict[str, str]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k not in ("failing_inputs", "extra")}
        out["seconds"] = round(self.seconds, 3)
        out["slowest_case_s"] = round(self.slowest_case_s, 4)
        out.update(self.extra)
        if self.failing_inputs:
            out["failing_inputs"] = self.failing_inputs
        return out


def make_targets(directory: Path) -> dict[str, Callable[[], Target]]:
    return {
        "can_codec": CanCodecTarget,
        "can_receiver": CanReceiverTarget,
        "zenoh_cdr": lambda: ZenohTarget("cdr"),
        "zenoh_json": lambda: ZenohTarget("json"),
        "engage_request": EngageRequestTarget,
        "trajectory_csv": lambda: TrajectoryFileTarget(directory, "csv"),
        "trajectory_yaml": lambda: TrajectoryFileTarget(directory, "yaml"),
        "config_file": lambda: ConfigFileTarget(directory),
    }


def _cap(text: str) -> str:
    return text if len(text) <= REPR_CAP else text[: REPR_CAP - 3] + "..."


def run_target(target: Target, cases: int, seed: int) -> Result:
    rng = random.Random(f"{seed}:{target.name}")  # str seeds are stable across runs
    result = Result()
    slowest: Any = None
    start = time.perf_counter()
    try:
        for _ in range(cases):
            case = target.generate(rng)
            result.cases += 1
            began = time.perf_counter()
            try:
                accepted = target.feed(case)
            except Failure as exc:
                problem = str(exc)
            except BaseException as exc:  # anything else escaping is what we look for
                if isinstance(exc, KeyboardInterrupt):
                    raise
                last = traceback.extract_tb(exc.__traceback__)[-1]
                problem = f"{type(exc).__name__}: {exc} (at {last.filename}:{last.lineno})"
            else:
                if accepted:
                    result.accepted += 1
                else:
                    result.rejected += 1
                took = time.perf_counter() - began
                if took > result.slowest_case_s:
                    result.slowest_case_s, slowest = took, case
                continue
            result.failures += 1
            if len(result.failing_inputs) < MAX_FAILURES_SHOWN:
                result.failing_inputs.append(
                    {"input": _cap(target.show(case)), "problem": _cap(problem)}
                )
        for problem in target.finish():
            result.failures += 1
            result.failing_inputs.append({"input": "(whole run)", "problem": _cap(problem)})
    finally:
        target.close()
    result.seconds = time.perf_counter() - start
    if slowest is not None:
        result.extra["slowest_case"] = _cap(target.show(slowest))[:160]
    if isinstance(target, CanCodecTarget):
        result.extra["frame_kinds"] = dict(target.kinds)
    if isinstance(target, ConfigFileTarget):
        result.extra.update(
            check_config_run=target.checked,
            check_config_rejected=target.check_rejected,
            check_config_skipped=target.skipped_checks,
        )
    if target.name in KNOWN_LIMITS:
        result.extra["note"] = KNOWN_LIMITS[target.name]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=100_000, help="total, split across targets")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--targets", help="comma-separated subset (default: all)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="leafgate-fuzz-") as tmp:
        factories = make_targets(Path(tmp))
        names = args.targets.split(",") if args.targets else list(factories)
        unknown = [n for n in names if n not in factories]
        if unknown:
            parser.error(f"unknown target(s) {', '.join(unknown)}; known: {', '.join(factories)}")
        per_target, extra = divmod(args.cases, len(names))
        results: dict[str, Any] = {}
        start = time.perf_counter()
        for i, name in enumerate(names):
            cases = per_target + (1 if i < extra else 0)
            results[name] = run_target(factories[name](), cases, args.seed).to_dict()
        total = {
            k: sum(r[k] for r in results.values())
            for k in ("cases", "accepted", "rejected", "failures")
        }
        total["seconds"] = round(time.perf_counter() - start, 3)
    print(json.dumps({"seed": args.seed, "total": total, "targets": results}, indent=2))
    return 1 if total["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
