"""Session files: one MCAP file holding everything needed to replay and re-run a drive.

Layout (profile ``leafgate``; every JSON record is one object, floats written exactly):

=========================== ========= ==============================================================
topic                       encoding  content
=========================== ========= ==============================================================
``/<ROS topic>``            cdr/json  raw Zenoh input payloads as received, on their ROS topic names
                                      (``/localization/kinematic_state`` …); CDR channels carry their
                                      ``ros2msg`` schema so Foxglove and the ``mcap`` CLI decode them
``/can``                    json      every CAN frame in and out: ``{t, dir, id, ext, data, channel}``
``/leafgate/trajectory``    json      each distinct trajectory once: ``{ref, stamp, x, y, heading,
                                      speed}``, written before the first tick that refers to it
``/leafgate/tick``          json      per control tick the ``GatewayInputs`` exactly as passed to
                                      ``Gateway.step`` (trajectory by ``ref``), the commands sent,
                                      the state, the operator reply, and ``seq``: the tick's number
                                      (0, 1, 2 … as handed to the recorder; absent before it was
                                      written)
``/leafgate/diagnostics``   json      per tick ``Diagnostics.to_dict()`` plus the controller's
                                      predicted path
``/leafgate/lost``          json      ticks or Zenoh inputs the recorder dropped (its queue
                                      overflowed): ``{what: tick|input, count, first, last,
                                      topics}``, times on the gateway clock (s), ``topics`` the
                                      inputs' count per key; logged at the first one's time
=========================== ========= ==============================================================

A tick's ``seq`` goes up by one from tick to tick: a jump is ticks missing from the file, which
:class:`TickContinuity` reports with the times of the ticks on both sides (the CAN frames the
recorder dropped are marked on ``/can``: :func:`~leafgate.record.logs.drop_marker`).

Metadata ``leafgate.config`` holds the configuration as YAML (``{"yaml": …}``) and
``leafgate.session`` the clock, the format version and ``epoch_offset_ns``; both are written
first, so a file cut short by a crash still has them.

Times: MCAP ``log_time`` and ``publish_time`` are Unix-epoch ns on every channel, so a session
lines up with other recordings (rosbag2, Foxglove): the gateway clock (the clock that stamps
``received``) plus ``epoch_offset_ns`` (the wall clock minus the gateway clock at the start;
for a simulated drive, the wall-clock time at which simulated time 0 began). The gateway
clock's exact float seconds live inside the JSON, so a re-run sees bit-identical inputs; a
CAN frame keeps its own bus timestamp in ``t``.

JSON follows :mod:`leafgate.jsonconv` (enums by name, NaN and ±inf as null: a non-finite
input value re-runs as NaN); older files with numeric enums and ``"nan"`` strings still read.
Every JSON channel's schema lists its properties.

Reading is sequential (:class:`SessionReader`), not through the summary at the end: a file
truncated by a crash yields every record up to its last complete chunk (the recorder closes a
chunk at least every second) and reports ``truncated``.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
import os
import time
import types
import typing
import zlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Final, get_type_hints

import can
import numpy as np
import yaml
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.writer import CompressionType, Writer

from leafgate.config import apply_overrides, from_mapping, safe_load_yaml, yaml_error_text
from leafgate.errors import ConfigError, ReplayError
from leafgate.gateway.core import GatewayInputs, StepResult
from leafgate.jsonconv import enum_from_json, float_from_json, json_schema, to_json
from leafgate.messages import (
    Commands,
    FloatArray,
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
from leafgate.settings import LeafgateConfig, apply_profile

__all__ = [
    "FORMAT_VERSION",
    "TOPIC_CAN",
    "TOPIC_DIAGNOSTICS",
    "TOPIC_LOST",
    "TOPIC_TICK",
    "TOPIC_TRAJECTORY",
    "LostItems",
    "SessionDamaged",
    "SessionReader",
    "SessionRecord",
    "SessionWriter",
    "TickContinuity",
    "TickGap",
    "TrajectoryRefs",
    "apply_overrides",
    "config_from_yaml",
    "config_to_yaml",
    "decode_commands",
    "decode_inputs",
    "decode_trajectory",
    "encode_commands",
    "encode_inputs",
    "encode_trajectory",
    "frame_from_record",
    "gateway_mode",
    "to_ns",
]

PROFILE: Final = "leafgate"
FORMAT_VERSION: Final = "2"  # 2: Unix-epoch times, enums by name, NaN as null
TOPIC_CAN: Final = "/can"
TOPIC_TICK: Final = "/leafgate/tick"
TOPIC_TRAJECTORY: Final = "/leafgate/trajectory"
TOPIC_DIAGNOSTICS: Final = "/leafgate/diagnostics"
TOPIC_LOST: Final = "/leafgate/lost"
META_CONFIG: Final = "leafgate.config"
META_SESSION: Final = "leafgate.session"
_CDR_HEADERS: Final = (b"\x00\x00", b"\x00\x01")  # CDR encapsulation: big / little endian
_MAGIC: Final = b"\x89MCAP0\r\n"
_FOOTER_LENGTH: Final = 8 + 8 + 4  # bytes: summary start, summary offset start, summary CRC
_CHUNK_SIZE: Final = 4 * 1024 * 1024  # bytes; chunks are closed by flush() long before this


def to_ns(t: float) -> int:
    """Seconds → MCAP nanoseconds (clamped at 0: MCAP times are unsigned)."""
    return max(0, round(t * 1e9)) if math.isfinite(t) else 0


def epoch_offset(clock: Callable[[], float] | None) -> float:
    """Seconds to add to ``clock`` to get Unix time, measured now; for a simulated drive
    (``clock`` None: simulated time starts at 0) the wall-clock time now."""
    return time.time() - (clock() if clock is not None else 0.0)


def gateway_mode(config: LeafgateConfig) -> LongMode:
    """The longitudinal command mode the gateway runs with for this configuration."""
    return config.long_mode


# --- configuration ------------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    """A config value as plain YAML data: dataclasses → mappings (init fields), tuples → lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def config_to_yaml(config: LeafgateConfig) -> str:
    """The whole configuration as YAML, SI keys, loadable by :func:`config_from_yaml`."""
    return yaml.safe_dump(_plain(config), sort_keys=False)


def config_from_yaml(
    text: str, source: str, overrides: Mapping[str, Any] | None = None
) -> LeafgateConfig:
    """Rebuild the recorded configuration, with optional dotted-key overrides.

    :raises ConfigError: the YAML is invalid or a key/value is rejected (named)
    """
    try:
        data = safe_load_yaml(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: {yaml_error_text(exc, text)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the recorded configuration is not a mapping")
    # Sections this version does not know (a newer recorder) are dropped, not fatal: a re-run
    # only needs the sections that build the gateway.
    known = {f.name for f in dataclasses.fields(LeafgateConfig)}
    data = {k: v for k, v in data.items() if k in known}
    if overrides:
        apply_overrides(data, overrides, "override")
    return apply_profile(from_mapping(LeafgateConfig, data, source), source)


# --- values ⇄ JSON ------------------------------------------------------------------------------


_float_out = to_json  # floats exact, non-finite as null
_float_in = float_from_json


def encode_flat(value: Any) -> dict[str, Any]:
    """A flat message dataclass → JSON object (:mod:`leafgate.jsonconv`: enums by name)."""
    out: dict[str, Any] = to_json(value)
    return out


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    """Field name → type of a message dataclass (cached: get_type_hints is slow)."""
    hints = _HINTS.get(cls)
    if hints is None:
        all_hints = get_type_hints(cls)
        fields = dataclasses.fields(cls)
        hints = _HINTS[cls] = {f.name: all_hints[f.name] for f in fields if f.init}
    return hints


def _convert(tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
    if tp is float:
        return _float_in(value)
    if tp is bool:
        return bool(value)
    if tp is int:
        return int(value)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return enum_from_json(tp, value)
    return value


T = typing.TypeVar("T")


def decode_flat(cls: type[T], data: Mapping[str, Any]) -> T:
    """The inverse of :func:`encode_flat` (missing fields take their defaults)."""
    hints = _hints(cls)
    kwargs = {name: _convert(tp, data[name]) for name, tp in hints.items() if name in data}
    return cls(**kwargs)


def _stamped(s: Stamped[Any] | None) -> dict[str, Any] | None:
    if s is None:
        return None
    out = {"value": encode_flat(s.value), "received": _float_out(s.received), "valid": s.valid}
    if s.sources:  # the publishers heard (a second one faults): a rerun must see them too
        out["sources"] = list(s.sources)
    return out


def _unstamped(cls: type[T], d: Mapping[str, Any] | None) -> Stamped[T] | None:
    if d is None:
        return None
    sources = tuple(str(x) for x in d.get("sources") or ())
    return Stamped(
        decode_flat(cls, d["value"]), _float_in(d["received"]), bool(d["valid"]), sources
    )


def encode_trajectory(ref: int, trajectory: Trajectory) -> dict[str, Any]:
    """A trajectory record (``ref`` is how ticks refer to it)."""
    return {
        "ref": ref,
        "stamp": _float_out(trajectory.stamp),
        **{k: [_float_out(float(v)) for v in getattr(trajectory, k)] for k in _TRAJ_ARRAYS},
    }


_TRAJ_ARRAYS: Final = ("x", "y", "heading", "speed")


def decode_trajectory(d: Mapping[str, Any]) -> Trajectory:
    """A new :class:`Trajectory` object from its record."""
    arrays = {k: np.array([_float_in(v) for v in d[k]], dtype=np.float64) for k in _TRAJ_ARRAYS}
    return Trajectory(stamp=_float_in(d["stamp"]), **arrays)


class TrajectoryRefs:
    """Numbers trajectories for the session: each distinct content is stored once.

    Two numbers per tick: ``ref`` names the content, ``obj`` changes whenever the gateway was
    handed a *different object* (the controller restarts its search on a new object, even with
    the same content, so a re-run must hand over a new object at the same tick).
    """

    def __init__(self) -> None:
        self._last: Trajectory | None = None  # kept alive so identity comparisons stay valid
        self._last_ref = 0
        self._obj = 0
        self._by_content: dict[bytes, int] = {}

    def refer(self, trajectory: Trajectory) -> tuple[int, int, bool]:
        """``(ref, obj, new_content)`` for the trajectory of this tick."""
        if trajectory is self._last:
            return self._last_ref, self._obj, False
        digest = hashlib.blake2b(digest_size=16)
        for name in _TRAJ_ARRAYS:
            digest.update(np.ascontiguousarray(getattr(trajectory, name)).tobytes())
            digest.update(b"|")
        digest.update(repr(trajectory.stamp).encode())
        key = digest.digest()
        new = key not in self._by_content
        if new:
            self._by_content[key] = len(self._by_content) + 1
        self._last, self._last_ref = trajectory, self._by_content[key]
        self._obj += 1
        return self._last_ref, self._obj, new


def encode_inputs(inputs: GatewayInputs, trajectory: tuple[int, int] | None) -> dict[str, Any]:
    """The inputs of one tick; the trajectory by ``(ref, obj)`` from :class:`TrajectoryRefs`."""
    traj: dict[str, Any] | None = None
    if inputs.trajectory is not None:
        assert trajectory is not None
        traj = {
            "ref": trajectory[0],
            "obj": trajectory[1],
            "received": _float_out(inputs.trajectory.received),
            "valid": inputs.trajectory.valid,
        }
    return {
        "pose": _stamped(inputs.pose),
        "trajectory": traj,
        "steer_report": _stamped(inputs.steer_report),
        "long_report": _stamped(inputs.long_report),
        "system_report": _stamped(inputs.system_report),
        "good_report_frames": inputs.good_report_frames,
        "bad_report_frames": inputs.bad_report_frames,
        "request": None if inputs.request is None else inputs.request.name,
        "request_reason": inputs.request_reason,
        "overrun": inputs.overrun,
        "lateness": inputs.lateness,
        "bus_errors": inputs.bus_errors,
        "foreign_command_frames": inputs.foreign_command_frames,
        "foreign_command_names": list(inputs.foreign_command_names),
    }


def decode_inputs(
    d: Mapping[str, Any], trajectory: Callable[[int, int], Trajectory]
) -> GatewayInputs:
    """The inverse of :func:`encode_inputs`; ``trajectory(ref, obj)`` supplies the object.

    :raises KeyError: a field is missing or the trajectory ref is unknown
    """
    traj = d["trajectory"]
    return GatewayInputs(
        pose=_unstamped(Pose, d["pose"]),
        trajectory=None
        if traj is None
        else Stamped(
            trajectory(int(traj["ref"]), int(traj["obj"])),
            _float_in(traj["received"]),
            bool(traj["valid"]),
        ),
        steer_report=_unstamped(SteerReport, d["steer_report"]),
        long_report=_unstamped(LongReport, d["long_report"]),
        system_report=_unstamped(SystemReport, d["system_report"]),
        good_report_frames=int(d["good_report_frames"]),
        bad_report_frames=int(d["bad_report_frames"]),
        request=None if d["request"] is None else enum_from_json(OperatorRequest, d["request"]),
        # absent in sessions recorded before a signal's stop named itself
        request_reason=str(d.get("request_reason", "")),
        overrun=bool(d["overrun"]),
        # absent in sessions recorded before the loop's stall was an input: a stall FAULT of
        # such a session is not reproduced (a re-run reports the divergence)
        lateness=float(d.get("lateness", 0.0)),
        bus_errors=int(d["bus_errors"]),
        # absent in sessions recorded before the gateway watched its command IDs
        foreign_command_frames=int(d.get("foreign_command_frames", 0)),
        foreign_command_names=tuple(str(n) for n in d.get("foreign_command_names", ())),
    )


def encode_commands(commands: Commands) -> dict[str, Any]:
    return {
        "steer": encode_flat(commands.steer),
        "long": encode_flat(commands.long),
        "system": None if commands.system is None else encode_flat(commands.system),
        "extra": {k: _float_out(float(v)) for k, v in commands.extra.items()},
    }


def decode_commands(d: Mapping[str, Any]) -> Commands:
    return Commands(
        steer=decode_flat(SteerCommand, d["steer"]),
        long=decode_flat(LongCommand, d["long"]),
        system=None if d["system"] is None else decode_flat(SystemCommand, d["system"]),
        extra={k: _float_in(v) for k, v in d.get("extra", {}).items()},
    )


def _channel_text(channel: object) -> str | int | None:
    return channel if isinstance(channel, (str, int)) or channel is None else str(channel)


def frame_record(t: float, msg: can.Message, rx: bool) -> dict[str, Any]:
    return {
        "t": _float_out(t),
        "dir": "rx" if rx else "tx",
        "id": msg.arbitration_id,
        "ext": msg.is_extended_id,
        "data": bytes(msg.data).hex(),
        "channel": _channel_text(msg.channel),
        "error": msg.is_error_frame,
        "remote": msg.is_remote_frame,
    }


def frame_from_record(d: Mapping[str, Any]) -> can.Message:
    """A python-can frame from a ``/can`` record."""
    data = bytes.fromhex(d["data"])
    return can.Message(
        timestamp=_float_in(d["t"]),
        arbitration_id=int(d["id"]),
        is_extended_id=bool(d["ext"]),
        is_rx=d["dir"] == "rx",
        is_error_frame=bool(d.get("error", False)),
        is_remote_frame=bool(d.get("remote", False)),
        channel=d.get("channel"),
        dlc=len(data),
        data=data,
    )


def _dumps(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


# --- writing ------------------------------------------------------------------------------------

_NUMBER: Final = {"type": ["number", "null"]}  # null: NaN or ±inf (leafgate.jsonconv)
_NUMBERS: Final = {"type": "array", "items": _NUMBER}


def _obj(**properties: Any) -> dict[str, Any]:
    return {"type": "object", "properties": properties}


def _nullable(schema: dict[str, Any]) -> dict[str, Any]:
    return {"anyOf": [schema, {"type": "null"}]}


def _stamped_schema(cls: type) -> dict[str, Any]:
    return _nullable(_obj(value=json_schema(cls), received=_NUMBER, valid={"type": "boolean"}))


def _json_schemas() -> dict[str, tuple[str, dict[str, Any]]]:
    """Topic → (schema name, JSON Schema with the properties), for Foxglove's field names."""
    integer, string, boolean = {"type": "integer"}, {"type": "string"}, {"type": "boolean"}
    commands = _obj(
        steer=json_schema(SteerCommand),
        long=json_schema(LongCommand),
        system=_nullable(json_schema(SystemCommand)),
        extra={"type": "object", "additionalProperties": _NUMBER},
    )
    inputs = _obj(
        pose=_stamped_schema(Pose),
        trajectory=_nullable(_obj(ref=integer, obj=integer, received=_NUMBER, valid=boolean)),
        steer_report=_stamped_schema(SteerReport),
        long_report=_stamped_schema(LongReport),
        system_report=_stamped_schema(SystemReport),
        good_report_frames=integer,
        bad_report_frames=integer,
        request=_nullable(json_schema(OperatorRequest)),
        request_reason=string,
        overrun=boolean,
        lateness=_NUMBER,
        bus_errors=integer,
        foreign_command_frames=integer,
        foreign_command_names={"type": "array", "items": string},
    )
    return {
        TOPIC_CAN: (
            "leafgate.CanFrame",
            _obj(
                t=_NUMBER,
                dir={"type": "string", "enum": ["rx", "tx"]},
                id=integer,
                ext=boolean,
                data=string,
                channel={"type": ["string", "integer", "null"]},
                error=boolean,
                remote=boolean,
            ),
        ),
        TOPIC_TICK: (
            "leafgate.Tick",
            _obj(
                seq=integer,
                now=_NUMBER,
                inputs=inputs,
                commands=commands,
                state=string,
                reply=_nullable(_obj(accepted=boolean, state=string, reason=string)),
            ),
        ),
        TOPIC_LOST: (
            "leafgate.Lost",
            _obj(
                what={"type": "string", "enum": ["tick", "input"]},
                count=integer,
                first=_NUMBER,
                last=_NUMBER,
                topics={"type": "object", "additionalProperties": integer},
            ),
        ),
        TOPIC_TRAJECTORY: (
            "leafgate.Trajectory",
            _obj(
                ref=integer, stamp=_NUMBER, x=_NUMBERS, y=_NUMBERS, heading=_NUMBERS, speed=_NUMBERS
            ),
        ),
        TOPIC_DIAGNOSTICS: (
            "leafgate.Diagnostics",
            _obj(
                time=_NUMBER,
                state=string,
                reason=string,
                fault=string,
                fault_causes={"type": "array", "items": string},
                engage_phase=string,
                watchdogs={"type": "object"},
                error_counter=integer,
                overruns_in_row=integer,
                ecu_state=_nullable(string),
                controller=_nullable({"type": "object"}),
                gear_change=boolean,
                clamps={"type": "object", "additionalProperties": integer},
                clamped={"type": "array", "items": string},
                transitions={"type": "array", "items": {"type": "object"}},
                predicted_xy={"type": "array", "items": _NUMBERS},
            ),
        ),
    }


_COMPRESSION: Final = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class SessionWriter:
    """Writes one session file. Not thread-safe: one thread (the recorder's) calls it.

    :param stream: a binary stream opened for writing (the caller closes it after
        :meth:`finish`)
    :param config: the configuration the gateway runs with (written first, as metadata)
    :param compression: MCAP chunk compression: ``zstd``, ``lz4`` or ``none``
    :param session: extra ``leafgate.session`` metadata (clock name, start time …)
    :raises OSError: when the stream cannot be written
    """

    def __init__(
        self,
        stream: IO[bytes],
        config: LeafgateConfig,
        compression: str = "zstd",
        session: Mapping[str, str] | None = None,
        epoch_offset: float = 0.0,
    ) -> None:
        # the data-section CRC (checked at the end of a finished file) also covers the message
        # indexes between the chunks, which no chunk CRC does: one flipped byte anywhere in a
        # finished session is found
        self._writer = Writer(
            stream,
            chunk_size=_CHUNK_SIZE,
            compression=_COMPRESSION[compression],
            enable_data_crcs=True,
        )
        self._writer.start(profile=PROFILE, library="leafgate")
        self._writer.add_metadata(META_CONFIG, {"yaml": config_to_yaml(config)})
        self._offset_ns = round(epoch_offset * 1e9)
        self._writer.add_metadata(
            META_SESSION,
            {
                "format_version": FORMAT_VERSION,
                "epoch_offset_ns": str(self._offset_ns),
                "log_time": "unix epoch ns = gateway clock + epoch_offset_ns",
                **dict(session or {}),
            },
        )
        self._channels: dict[str, int] = {}
        self._zenoh: dict[tuple[str, str], int] = {}
        self._trajectories = TrajectoryRefs()
        self._sequence = 0
        for topic, (name, body) in _json_schemas().items():
            schema = json.dumps({"title": name, **body}).encode()
            schema_id = self._writer.register_schema(name, "jsonschema", schema)
            self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)

    def _add(self, channel_id: int, t: int, data: bytes) -> None:
        """One message at gateway-clock time ``t`` (ns), stamped in Unix-epoch ns."""
        self._sequence += 1
        stamp = max(0, t + self._offset_ns)
        self._writer.add_message(
            channel_id,
            log_time=stamp,
            data=data,
            publish_time=stamp,
            sequence=self._sequence & 0xFFFFFFFF,
        )

    def can_frame(self, log_time: float, msg: can.Message, rx: bool) -> None:
        """One CAN frame (``log_time`` on the gateway clock; the frame keeps its bus time)."""
        self._add(
            self._channels[TOPIC_CAN], to_ns(log_time), _dumps(frame_record(msg.timestamp, msg, rx))
        )

    def zenoh_input(
        self,
        key: str,
        payload: bytes,
        received: float,
        typename: str | None,
        log_time: float | None = None,
    ) -> None:
        """A raw Zenoh payload as received on topic ``key`` (the ROS name the gateway passes,
        e.g. ``/localization/kinematic_state``); CDR payloads get a ``ros2msg`` schema channel.

        :param log_time: s, the time it is logged at when not ``received`` (a recorder keeping
            the file in time order logs a late sample at the last time written)
        """
        cdr = typename is not None and payload[:2] in _CDR_HEADERS
        encoding = "cdr" if cdr else "json"
        channel_id = self._zenoh.get((key, encoding))
        if channel_id is None:
            schema_id = 0
            if cdr:
                from leafgate.transport.cdr import msg_definition

                assert typename is not None
                schema_id = self._writer.register_schema(
                    typename, "ros2msg", msg_definition(typename).encode()
                )
            topic = "/" + key.lstrip("/")
            if encoding == "json":
                topic += "/json" if (key, "cdr") in self._zenoh else ""
            channel_id = self._writer.register_channel(
                topic, encoding, schema_id, {"zenoh_key": key, "type": typename or ""}
            )
            self._zenoh[(key, encoding)] = channel_id
        self._add(channel_id, to_ns(received if log_time is None else log_time), bytes(payload))

    def tick(
        self,
        now: float,
        inputs: GatewayInputs,
        result: StepResult,
        predicted_xy: FloatArray | None = None,
        diagnostics: bool = True,
        log_time: float | None = None,
        seq: int | None = None,
    ) -> None:
        """One control tick: inputs, commands, state, and (optionally) the diagnostics.

        :param predicted_xy: the controller's predicted positions of this tick, (Np, 2) m,
            when a :class:`~leafgate.record.recorder.ControllerTap` caught them
        :param log_time: s, the MCAP log time when not ``now`` (``now`` in the record stays
            exact; see :meth:`zenoh_input`)
        :param seq: the tick's number, one more than the tick before it (None: not written)
        """
        t = to_ns(now if log_time is None else log_time)
        ref: tuple[int, int] | None = None
        if inputs.trajectory is not None:
            r, obj, new = self._trajectories.refer(inputs.trajectory.value)
            if new:
                self._add(
                    self._channels[TOPIC_TRAJECTORY],
                    t,
                    _dumps(encode_trajectory(r, inputs.trajectory.value)),
                )
            ref = (r, obj)
        record: dict[str, Any] = {} if seq is None else {"seq": seq}
        record |= {
            "now": _float_out(now),
            "inputs": encode_inputs(inputs, ref),
            "commands": encode_commands(result.commands),
            "state": result.diagnostics.state.name,
            "reply": None if result.reply is None else result.reply.to_dict(),
        }
        self._add(self._channels[TOPIC_TICK], t, _dumps(record))
        if diagnostics:
            diag = result.diagnostics.to_dict()
            if predicted_xy is not None:
                xy = np.asarray(predicted_xy, dtype=np.float64).reshape(-1, 2)
                diag["predicted_xy"] = [[_float_out(float(a)), _float_out(float(b))] for a, b in xy]
            self._add(self._channels[TOPIC_DIAGNOSTICS], t, _dumps(diag))

    def lost(
        self,
        log_time: float,
        what: str,
        count: int,
        first: float,
        last: float,
        topics: Mapping[str, int] | None = None,
    ) -> None:
        """``count`` ticks (``what`` ``"tick"``) or Zenoh inputs (``"input"``) the recorder
        dropped, the first at ``first``, the last at ``last`` (s, gateway clock).

        :param log_time: s, where the record is logged (the first one's time, or later)
        :param topics: for inputs, how many of each key
        """
        record = {
            "what": what,
            "count": count,
            "first": _float_out(first),
            "last": _float_out(last),
            "topics": dict(topics or {}),
        }
        self._add(self._channels[TOPIC_LOST], to_ns(log_time), _dumps(record))

    def flush(self) -> None:
        """Close the chunk in progress and push it to the stream (a crash keeps it)."""
        self._writer.flush()

    def finish(self) -> None:
        """Write the summary and footer: a complete, indexed MCAP file."""
        self._writer.finish()


# --- reading ------------------------------------------------------------------------------------


class SessionDamaged(ReplayError):
    """A session file that cannot be read on: damaged, not cut short by a crash.

    :param offset: where the record that does not read begins, in bytes from the file's start
    :param messages: messages read before it
    """

    def __init__(self, path: Path, offset: int, messages: int, reason: str) -> None:
        self.path = path
        self.offset = offset
        self.messages = messages
        where = "" if f"offset {offset}" in reason else f" at offset {offset}"
        self.reason = f"{reason}{where}"
        super().__init__(f"{path}: unreadable after {messages} messages: {self.reason}")


def _ends_with_footer(file: IO[bytes], size: int) -> bool:
    """The file's last bytes are an MCAP footer record and the closing magic: it was finished,
    so a record that cannot be read in it is damage, not a crash's cut."""
    tail = 1 + 8 + _FOOTER_LENGTH + len(_MAGIC)
    if size < tail + len(_MAGIC):
        return False
    here = file.tell()
    try:
        file.seek(size - tail)
        data = file.read(tail)
    finally:
        file.seek(here)
    return (
        data[0] == Opcode.FOOTER
        and int.from_bytes(data[1:9], "little") == _FOOTER_LENGTH
        and data.endswith(_MAGIC)
    )


def _summary_damage(file: IO[bytes], footer: Footer) -> str:
    """Why the summary section (read just before ``footer``) is damaged, "" when it is not.

    The stream reader checks chunk and data-section CRCs but not the summary's, which the
    footer carries: the bytes from the summary's start through the footer's second field.
    """
    if footer.summary_crc == 0 or footer.summary_start == 0:
        return ""  # written without a summary CRC
    here = file.tell()  # just after the footer record
    covered = here - 4 - footer.summary_start  # up to, not including, the CRC field
    if covered <= 0:
        return f"the footer's summary start {footer.summary_start} is past the footer"
    try:
        file.seek(footer.summary_start)
        data = file.read(covered)
    finally:
        file.seek(here)
    if zlib.crc32(data) != footer.summary_crc:
        return "the summary section's CRC does not match (indexes, statistics)"
    return ""


@dataclass(frozen=True, slots=True)
class SessionRecord:
    """One message of a session file."""

    topic: str
    log_time: int  # ns, Unix epoch (format 2; the gateway clock in format 1)
    publish_time: int  # ns, Unix epoch
    data: bytes
    encoding: str  # "json", "cdr"
    schema: str  # schema name ("" when none)

    def json(self) -> Any:
        return json.loads(self.data)


@dataclass(frozen=True, slots=True)
class LostItems:
    """Ticks or Zenoh inputs the recorder dropped when its queue overflowed (a
    ``/leafgate/lost`` record): ``count`` of them from ``first`` to ``last`` (s, gateway clock),
    for inputs how many of each key in ``topics``."""

    what: str  # "tick" or "input"
    count: int
    first: float
    last: float
    topics: Mapping[str, int] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_record(cls, d: Mapping[str, Any]) -> LostItems:
        """From a ``/leafgate/lost`` record's JSON.

        :raises KeyError: a field is missing
        """
        topics = {str(k): int(v) for k, v in (d.get("topics") or {}).items()}
        return cls(
            str(d["what"]), int(d["count"]), _float_in(d["first"]), _float_in(d["last"]), topics
        )

    def text(self) -> str:
        """``"3 Zenoh inputs (/a 2, /b 1) lost between 8.010 s and 8.090 s"``."""
        what = "tick" if self.what == "tick" else "Zenoh input"
        which = ", ".join(f"{k} {n}" for k, n in sorted(self.topics.items()))
        return (
            f"{self.count} {what}{'' if self.count == 1 else 's'}"
            + (f" ({which})" if which else "")
            + f" lost between {self.first:.3f} s and {self.last:.3f} s"
        )


@dataclass(frozen=True, slots=True)
class TickGap:
    """Ticks missing from a session between two it holds (or before its first)."""

    missing: int  # ticks (negative: the numbers go backwards)
    seq: int | None  # the number of the tick after the gap (None: the ticks are not numbered)
    before: float | None  # s, gateway clock: the tick before the gap (None: none, at the start)
    after: float  # s: the tick after the gap
    dropped: int = 0  # of them, the ticks the recorder's /leafgate/lost records say it dropped

    def text(self) -> str:
        """``"50 ticks missing (#812–#861) between the ticks at 8.110 s and 8.610 s: the
        recorder dropped them (its queue overflowed)"``."""
        if self.missing < 0 and self.seq is not None:
            return (
                f"tick #{self.seq} at {self.after:.3f} s comes after tick #{self.seq - self.missing - 1}"
                ": the ticks' numbers go backwards"
            )
        numbers = ""
        if self.seq is not None:
            first = self.seq - self.missing
            last = self.seq - 1
            numbers = f" (#{first})" if first == last else f" (#{first}–#{last})"
        where = (
            f"before the first tick, at {self.after:.3f} s"
            if self.before is None
            else f"between the ticks at {self.before:.3f} s and {self.after:.3f} s"
        )
        why = (
            "the recorder dropped them (its queue overflowed)"
            if self.dropped >= self.missing
            else "the recorder lost them"
        )
        s = "" if self.missing == 1 else "s"
        return f"{self.missing} tick{s} missing{numbers} {where}: {why}"


class TickContinuity:
    """Follows a session's ticks and ``/leafgate/lost`` records in file order: which ticks the
    file lacks. Ticks are numbered (``seq``) as the recorder was handed them, so a jump is ticks
    missing whatever lost them; a session recorded before they were numbered tells only
    through its lost records (:attr:`numbered` False: a jump of the clock is not judged).

    :param first_seq: the number the first tick should have (0 for a session from its start;
        None when not known: a session that resumes another after a recording failure)
    """

    def __init__(self, first_seq: int | None = 0) -> None:
        self.numbered: bool | None = None  # whether the ticks carry numbers (None: no tick yet)
        self.gaps: list[TickGap] = []
        self.lost: list[LostItems] = []  # every lost record read, ticks and inputs
        self._last_seq: int | None = None if first_seq is None else first_seq - 1
        self._last_now: float | None = None
        self._dropped = 0  # ticks the lost records since the last tick say were dropped

    def take_lost(self, data: Mapping[str, Any]) -> LostItems:
        """A ``/leafgate/lost`` record's JSON."""
        lost = LostItems.from_record(data)
        self.lost.append(lost)
        if lost.what != "tick":
            return lost
        gap = self.gaps[-1] if self.gaps else None
        if (
            gap is not None
            and gap.before is not None
            and gap.before < lost.first <= lost.last < gap.after
        ):
            # logged late (the recorder orders its writes within a window): after the tick that
            # ends the gap it accounts for
            self.gaps[-1] = dataclasses.replace(gap, dropped=gap.dropped + lost.count)
        else:
            self._dropped += lost.count
        return lost

    def take_tick(self, data: Mapping[str, Any]) -> TickGap | None:
        """A ``/leafgate/tick`` record's JSON: the gap before it, None when it follows on."""
        now = _float_in(data["now"])
        seq = data.get("seq")
        self.numbered = seq is not None if self.numbered is None else self.numbered
        gap = None
        if self.numbered and seq is not None:
            seq = int(seq)
            if self._last_seq is not None and seq != self._last_seq + 1:
                gap = TickGap(seq - self._last_seq - 1, seq, self._last_now, now, self._dropped)
            self._last_seq = seq
        elif self._dropped:  # ticks not numbered: the lost records say it
            gap = TickGap(self._dropped, None, self._last_now, now, self._dropped)
        self._last_now = now
        self._dropped = 0
        if gap is not None:
            self.gaps.append(gap)
        return gap

    @property
    def lost_inputs(self) -> list[LostItems]:
        """The lost records of Zenoh inputs."""
        return [lost for lost in self.lost if lost.what != "tick"]


class SessionReader:
    """Reads a session file record by record, tolerating a truncated end.

    >>> # with SessionReader(path) as reader:
    >>> #     for record in reader.records(): ...
    >>> #     reader.truncated, reader.config_yaml

    :param path: the ``.mcap`` file
    :raises ReplayError: the file is missing or not an MCAP file
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file = self.path.open("rb")
        except FileNotFoundError:
            raise ReplayError(f"{self.path}: no such file") from None
        except OSError as exc:
            raise ReplayError(f"{self.path}: cannot read: {exc.strerror}") from None
        if self._file.read(8) != _MAGIC:
            self._file.close()
            raise ReplayError(f"{self.path}: not an MCAP file")
        self._file.seek(0)
        self.metadata: dict[str, dict[str, str]] = {}
        self.truncated = False  # the file ends before its footer (a crash)
        self.error = ""  # what stopped the reading early, if anything
        self.messages = 0  # messages read so far (every topic)

    @property
    def config_yaml(self) -> str | None:
        """The recorded configuration (YAML), once the metadata has been read."""
        return self.metadata.get(META_CONFIG, {}).get("yaml")

    def config(self, overrides: Mapping[str, Any] | None = None) -> LeafgateConfig:
        """The recorded configuration (with overrides).

        :raises ReplayError: the session holds no configuration
        :raises ConfigError: it does not load (names the key)
        """
        text = self.config_yaml
        if text is None:
            raise ReplayError(f"{self.path}: the session holds no {META_CONFIG} metadata")
        return config_from_yaml(text, f"{self.path}:{META_CONFIG}", overrides)

    def position(self) -> int:
        """Bytes of the file consumed so far (for progress bars)."""
        return self._file.tell()

    def read_metadata(self) -> dict[str, dict[str, str]]:
        """Read up to the first message: the recorder writes every metadata record before it."""
        for _ in self.records():
            break
        self._file.seek(0)
        return self.metadata

    def records(self, topics: frozenset[str] | None = None) -> Iterator[SessionRecord]:
        """Messages in file order (metadata is collected on the way).

        A file that stops before its footer is a crash's truncation: the records up to there,
        then :attr:`truncated`. Anything else that stops the reading — a CRC or parse error, a
        record reaching past the end of a file that does end with a footer, bytes after the
        footer (two sessions concatenated) — is damage, and a silent "truncated" or "empty"
        would hide it: :class:`SessionDamaged` says where.

        :param topics: only these topics (None: all)
        :raises SessionDamaged: the file is damaged (names the offset and the reason)
        """
        self.truncated = False
        self.error = ""
        self.messages = 0
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str, str]] = {}
        # no record of a file can be longer than the file: a damaged length field is a
        # clear error rather than a read of gigabytes
        size = os.fstat(self._file.fileno()).st_size
        reader = StreamReader(self._file, validate_crcs=True, record_size_limit=size)
        stream = iter(reader.records)
        footer = False
        while True:
            # where the record being read begins (chunks are read whole; the opening magic was
            # checked on opening)
            start = max(self._file.tell(), len(_MAGIC))
            try:
                record = next(stream)
            except StopIteration:
                break
            except Exception as exc:  # EndOfFile, CRC, zstd, struct, UnicodeDecodeError …
                reason = " ".join((str(exc) or type(exc).__name__).split())
                # the read ran into the end of the file (a short read fails in struct), or a
                # record is longer than what is left of it
                cut = isinstance(exc, (EndOfFile, RecordLengthLimitExceeded))
                cut = cut or self._file.tell() >= size
                if cut and not _ends_with_footer(self._file, size):
                    self.truncated = True  # a crash: the file stops inside a record
                    self.error = reason or "cut record"
                    return
                if cut:
                    reason = "a record reaches past the end of the file"
                elif isinstance(exc, CRCValidationError) and isinstance(exc.record, DataEnd):
                    reason = f"the data section's CRC does not match: damaged before offset {start}"
                elif isinstance(exc, CRCValidationError):
                    reason = (
                        f"a {type(exc.record).__name__.lower()}'s CRC does not match its content"
                    )
                raise SessionDamaged(self.path, start, self.messages, reason) from None
            if isinstance(record, Message):
                self.messages += 1
                topic, encoding, schema = channels.get(record.channel_id, ("?", "", ""))
                if topics is not None and topic not in topics:
                    continue
                yield SessionRecord(
                    topic, record.log_time, record.publish_time, record.data, encoding, schema
                )
            elif isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (
                    record.topic,
                    record.message_encoding,
                    schemas.get(record.schema_id, ""),
                )
            elif isinstance(record, Metadata):
                self.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Footer):
                footer = True  # the stream reader reads the closing magic and stops
                summary = _summary_damage(self._file, record)
                if summary:
                    raise SessionDamaged(self.path, record.summary_start, self.messages, summary)
        if not footer:
            self.truncated = True  # ended between records, without a footer
            self.error = "no footer"
            return
        end = self._file.tell()
        if end < size:
            raise SessionDamaged(
                self.path,
                end,
                self.messages,
                f"{size - end} bytes after the session's end at offset {end}: not read",
            )

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
