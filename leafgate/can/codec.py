"""The one CAN codec of leafgate: message dataclasses ⇄ python-can frames.

The gateway and the simulated ECU each own a :class:`CanCodec`; it holds the alive counters
of the frames it sends and the counter state of the frames it receives, so two instances
never share E2E state.

The DBC files are the truth for every layout, and the vehicle profile
(:mod:`leafgate.can.profile`) says which frames and signals carry which message fields: the
codec finds frames and signals by *name* (``DBW_STEER_CMD.STEER_ANGLE_CMD``), reads IDs, bit
positions and scales from the databases, and the units, scales and counter/checksum scheme
from the profile. Units: SI inside leafgate; degrees and km/h exist only in the DBC and are
converted here.

* :meth:`CanCodec.encode` is strict: a value outside the DBC's range, or not finite, raises
  :class:`EncodeError` (clamping is the safety gate's decision, made and counted before).
* :meth:`CanCodec.decode` never raises: unknown IDs, wrong lengths, bad CRCs, counters that
  did not advance and undecodable content become ``Decoded(valid=False, error=...)`` and are
  counted per ID in :attr:`CanCodec.stats`.
* Authenticated frames (``e2e: secoc``, :mod:`leafgate.can.secoc`) are sealed and verified with
  the codec's key on its Unix-time ``clock``: a bad MAC is ``bad_mac``, an old or repeated
  freshness value ``stale_freshness``. Without a key (a tool reading a log) they decode, and
  are counted as ``mac_unverified``: never as verified.

Encoding and decoding run for every frame sent and received (and every frame of a replayed
log), so neither goes through cantools' generic code: at start-up each message is compiled,
from the bit positions, scales and ranges of the cantools database, into one decode function
of shifts and masks and one encode function that range-checks, scales and packs exactly as
cantools' strict ``Message.encode`` does (``tools/bench_can.py`` measures both against
cantools). Tests check them against cantools on random payloads and values for every message,
with values packed around every signal's limits.

>>> from leafgate.messages import SteerCommand
>>> gw, ecu = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
>>> frame = gw.encode(SteerCommand(angle=0.1, enable=True))
>>> hex(frame.arbitration_id), len(frame.data)
('0xa0', 8)
>>> d = ecu.decode(frame)
>>> d.name, d.valid, round(d.value.angle, 4), d.value.enable
('DBW_STEER_CMD', True, 0.1, True)
>>> ecu.decode(frame).error   # the same frame again: the counter did not advance
'bad_counter'
"""

from __future__ import annotations

import dataclasses
import enum
import math
import numbers
import time
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final, Literal, NoReturn

import can
import cantools
import cantools.database
from cantools.database.can import Database, Signal
from cantools.database.can import Message as DbcMessage
from cantools.database.conversion import (
    BaseConversion,
    IdentityConversion,
    LinearIntegerConversion,
)

from leafgate.can import e2e, secoc
from leafgate.can.profile import (
    COMMAND_SOURCES,
    COUNTER_CHECKED,
    REPORT_SOURCES,
    UNITS,
    FrameSpec,
    Profile,
    SignalMap,
    base_values,
    load_profile,
)
from leafgate.errors import CanCodecError, ConfigError
from leafgate.messages import (
    GearPosition,
    LongCommand,
    LongReport,
    MotorSpeed,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    WheelSpeeds,
)

__all__ = [
    "CanCodec",
    "Decoded",
    "Direction",
    "EncodableMessage",
    "EncodeError",
    "FrameStats",
    "LayoutProblem",
]

Direction = Literal["reports", "commands", "car"]
EncodableMessage = (
    SteerCommand
    | LongCommand
    | SystemCommand
    | SteerReport
    | LongReport
    | SystemReport
    | SteeringWheelAngle
    | WheelSpeeds
    | GearPosition
    | MotorSpeed
)

_E2E_SIGNALS: Final = {"ALIVE_COUNTER": (48, 4), "CRC": (56, 8)}  # start bit, length (e2e.py)
_SECOC_SIGNALS: Final = {"FRESHNESS": (32, 8), "MAC": (40, 24)}  # start bit, length (secoc.py)
_FIXED_SIGNALS: Final = {"leafgate": _E2E_SIGNALS, "secoc": _SECOC_SIGNALS}
EXTENDED_KEY: Final = 1 << 31  # added to a 29-bit ID's key in :attr:`CanCodec.stats`
ERROR_FRAME_KEY: Final = 1 << 30  # the key of error frames (no ID) in :attr:`CanCodec.stats`
ERROR_FRAMES_NAME: Final = "error frames"  # what a log's statistics call that key's row
CLASSIC_MAX_DATA: Final = 8  # bytes of a classic CAN frame (more only with CAN FD)


def frame_key(msg: can.Message) -> int:
    """The key of a received frame in :attr:`CanCodec.stats` and in a log's statistics: its ID
    for an 11-bit one, ``ID | EXTENDED_KEY`` for a 29-bit one (apart from the 11-bit ID of the
    same number), ``ERROR_FRAME_KEY`` for an error frame (it has no ID)."""
    if msg.is_error_frame:
        return ERROR_FRAME_KEY
    return msg.arbitration_id | EXTENDED_KEY if msg.is_extended_id else msg.arbitration_id


def stats_label(key: int) -> str:
    """A key of :attr:`CanCodec.stats` as a log shows it: ``284``, a 29-bit ID in 8 digits
    (``12345678``), ``error`` for error frames."""
    if key == ERROR_FRAME_KEY:
        return "error"
    if key & EXTENDED_KEY:
        return f"{key & ~EXTENDED_KEY:08X}"
    return f"{key:03X}"


_MAX_TRACKED_UNKNOWN_IDS: Final = 1024  # beyond this, unknown IDs are only counted globally

ErrorKind = Literal[
    "bad_crc",
    "bad_counter",
    "wrong_length",
    "unknown_id",
    "decode_error",
    "bad_mac",  # an authenticated frame whose MAC does not verify (forged, or another key)
    "stale_freshness",  # … whose freshness is outside the window or not above the last: replay
]


class EncodeError(CanCodecError, cantools.database.EncodeError):
    """A value cannot be encoded: outside the DBC's range, not finite, or of an unknown type.

    Both a :class:`leafgate.errors.CanCodecError` and a cantools ``EncodeError``, so either
    can be caught.
    """


_STATS_FIELDS = (
    "frames",
    "bad_crc",
    "bad_counter",
    "wrong_length",
    "unknown_id",
    "decode_error",
    "bad_mac",
    "stale_freshness",
    "mac_unverified",
)


@dataclass(frozen=True)  # no slots: diagnostics serialise it with vars()
class FrameStats:
    """Receive counters of one CAN ID since the codec was made."""

    frames: int = 0  # frames received with this ID, good or bad
    bad_crc: int = 0
    bad_counter: int = 0  # repeated or skipped alive counter
    wrong_length: int = 0
    unknown_id: int = 0  # frames of an ID no database describes
    decode_error: int = 0  # content that maps to no message value (e.g. gear 6)
    bad_mac: int = 0  # authenticated frames whose MAC did not verify
    stale_freshness: int = 0  # … whose freshness was old or repeated (a replay)
    mac_unverified: int = 0  # … decoded without the key: their MAC was NOT checked (tools only)

    def __add__(self, other: FrameStats) -> FrameStats:
        """Counters summed field by field (e.g. one ID over several channels or logs)."""
        return FrameStats(*(getattr(self, f) + getattr(other, f) for f in _STATS_FIELDS))

    @property
    def errors(self) -> int:
        """All frames of this ID that were not valid."""
        return (
            self.bad_crc
            + self.bad_counter
            + self.wrong_length
            + self.unknown_id
            + self.decode_error
            + self.bad_mac
            + self.stale_freshness
        )


@dataclass(frozen=True, slots=True)
class Decoded:
    """The result of decoding one frame.

    ``value`` is the message dataclass (the first of ``values`` when a frame carries several,
    e.g. steering and speed in one command frame). It is None for unknown IDs, wrong lengths and decode
    errors; for a bad CRC or counter it is still attached (for logging) when the content
    decodes, but ``valid`` is False and the control path must not use it.
    """

    frame_id: int
    name: str | None
    value: object | None
    valid: bool
    error: ErrorKind | None
    values: tuple[object, ...] = ()  # every message the frame refreshes (``value`` is the first)

    @property
    def counts_for_reports(self) -> bool:
        """Whether the frame counts in the gateway's report error counter (docs/watchdogs.md, panda
        style): it refreshed an ECU report, or a frame of a known ID was bad (checksum,
        counter, length, or content outside its value table)."""
        if self.error is not None:
            return self.error != "unknown_id"
        return any(isinstance(v, _ECU_REPORTS) for v in self.values)


_ECU_REPORTS: Final = (SteerReport, LongReport, SystemReport)
_COUNTER_OK: Final = e2e.CounterStatus.OK
_COUNTER_FIRST: Final = e2e.CounterStatus.FIRST

# Indices into the per-ID counter lists (a list is cheaper to bump than a frozen dataclass).
_STATS_LEN: Final = len(_STATS_FIELDS)
_FRAMES, _BAD_CRC, _BAD_COUNTER, _WRONG_LENGTH, _UNKNOWN, _DECODE_ERROR = range(6)
_ERROR_INDEX: Final = {
    "bad_crc": _BAD_CRC,
    "bad_counter": _BAD_COUNTER,
    "bad_mac": _STATS_FIELDS.index("bad_mac"),
    "stale_freshness": _STATS_FIELDS.index("stale_freshness"),
}
_UNVERIFIED: Final = _STATS_FIELDS.index("mac_unverified")
_SECOC_ERRORS: Final[Mapping[str, ErrorKind]] = {"stale": "stale_freshness", "bad_mac": "bad_mac"}

_Decode = Callable[[bytes | bytearray, dict[str, dict[str, Any]]], tuple[object, ...]]
_Getter = Callable[[Mapping[str, object]], tuple[object, ...]]


def _signal_expression(sig: Signal, total_bits: int) -> str:
    """A Python expression for one signal's physical value, reading ``le`` or ``be``.

    ``le``/``be`` are the payload as one little-/big-endian integer. Motorola (big-endian)
    start bits count from the MSB of each byte, so the shift is taken from the MSB end of
    ``be``. Signed values use ``(raw ^ sign) - sign``, a branch-free two's complement.
    """
    mask = (1 << sig.length) - 1
    if sig.byte_order == "little_endian":
        raw = f"((le >> {sig.start}) & {mask})"
    else:
        msb = (sig.start // 8) * 8 + (7 - sig.start % 8)  # bit index counted from the MSB
        raw = f"((be >> {total_bits - (msb + sig.length)}) & {mask})"
    if sig.is_signed:
        sign = 1 << (sig.length - 1)
        raw = f"(({raw} ^ {sign}) - {sign})"
    expr = raw
    if sig.scale != 1:
        expr = f"{expr} * {float(sig.scale)!r}"
    if sig.offset != 0:
        expr = f"{expr} + {float(sig.offset)!r}"
    return expr


def _signals(message: DbcMessage, names: tuple[str, ...]) -> list[Signal]:
    """The named signals of a message, in that order.

    :raises CanCodecError: a named signal is missing, or is float or multiplexed
    """
    signals = []
    for name in names:
        try:
            sig = message.get_signal_by_name(name)
        except KeyError:
            raise CanCodecError(f"{message.name}.{name} is missing from the DBC") from None
        if sig.is_float or sig.multiplexer_ids or sig.is_multiplexer:
            raise CanCodecError(
                f"{message.name}.{name}: float or multiplexed signals are not supported"
            )
        signals.append(sig)
    return signals


def _compile(
    message: DbcMessage, names: tuple[str, ...], build: Callable[..., object]
) -> Callable[[bytes | bytearray], object]:
    """Compile ``payload -> build(*values of the named signals)`` for one message.

    The function is generated from the DBC's bit positions and scales (as
    :func:`collections.namedtuple` generates its class): one shift-and-mask expression per
    signal passed straight to ``build``, with no intermediate dict — about three times faster
    than cantools' generic decoder. Values are in DBC units; the payload must hold at least
    the message's length in bytes (excess bytes are ignored).

    :raises CanCodecError: a named signal is missing, or is float or multiplexed
    """
    total_bits = 8 * message.length
    signals = _signals(message, names)
    lines = ["def decode(data):"]
    if any(sig.byte_order == "little_endian" for sig in signals):
        lines.append("    le = from_bytes(data, 'little')")  # excess bytes only add high bits
    if any(sig.byte_order == "big_endian" for sig in signals):
        lines.append(f"    be = from_bytes(data[:{message.length}], 'big')")
    args = ", ".join(_signal_expression(sig, total_bits) for sig in signals)
    lines.append(f"    return build({args})")
    namespace: dict[str, object] = {"from_bytes": int.from_bytes, "build": build}
    exec(compile("\n".join(lines), f"<dbc {message.name}>", "exec"), namespace)
    return namespace["decode"]  # type: ignore[return-value]


_Encode = Callable[..., bytes]
_EXACT_NUMBERS: Final = frozenset({float, int, bool})  # types the compiled code takes as they are


class _SignalChecks:
    """The slow paths of one compiled encoder: conversions and the errors it raises.

    Only called when a value is not a plain ``float``/``int``/``bool``, or fails its range
    check, so their cost does not count.
    """

    def __init__(self, message: DbcMessage, signals: list[Signal]) -> None:
        self.frame = f"{message.name} (0x{message.frame_id:03X})"
        self.signals = signals

    def number(self, index: int, value: object) -> int | float:
        """``value`` as a plain int or float (numpy scalars, enums, fractions); else raise."""
        if isinstance(value, numbers.Integral):
            return int(value)
        if isinstance(value, numbers.Real):
            return float(value)
        sig = self.signals[index]
        return self._raise(f"{sig.name}: {value!r} is not a number")

    def in_choices(self, index: int, value: float) -> bool:
        """True when ``value`` encodes to a raw code of the signal's value table.

        cantools accepts such a value whatever the range says; so does the codec.
        """
        sig = self.signals[index]
        if not math.isfinite(value) or not sig.conversion.choices:
            return False
        return sig.conversion.numeric_scaled_to_raw(value) in sig.conversion.choices

    def reject(self, index: int, value: float) -> EncodeError:
        """The error for a value that failed the range check: not finite, or outside it."""
        sig = self.signals[index]
        if not math.isfinite(value):
            return EncodeError(f"{self.frame} {sig.name}: value {value!r} is not finite")
        unit = f" {sig.unit}" if sig.unit else ""
        return EncodeError(
            f"{self.frame} {sig.name}: value {value!r} is outside its range "
            f"[{sig.minimum}, {sig.maximum}]{unit}"
        )

    def reject_raw(self, index: int, value: float, raw: int) -> EncodeError:
        """The error for a value the DBC's range admits but the bit field cannot hold."""
        sig = self.signals[index]
        kind = "signed" if sig.is_signed else "unsigned"
        return EncodeError(
            f"{self.frame} {sig.name}: value {value!r} is raw {raw}, which does not fit "
            f"its {sig.length}-bit {kind} field"
        )

    def _raise(self, text: str) -> NoReturn:
        raise EncodeError(f"{self.frame} {text}")


def _field_limits(sig: Signal) -> tuple[int, int]:
    """The raw values a signal's bit field holds."""
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def _raw_lines(sig: Signal, v: str, r: str) -> list[str]:
    """Lines computing the raw value ``r`` of the physical value ``v``, as cantools rounds.

    cantools picks the conversion by the scale and offset (``BaseConversion.factory``): the
    identity rounds the value; integer scale and offset divide exactly when they can;
    otherwise ``round((v - offset) / scale)``. Division, not a multiplication by the inverse
    scale, so that the raw value is the one cantools computes, bit for bit.
    """
    conv = BaseConversion.factory(sig.conversion.scale, sig.conversion.offset, None, False)
    if isinstance(conv, IdentityConversion):
        return [f"    {r} = round({v})"]
    x = f"({v} - {conv.offset!r})" if conv.offset != 0 else v
    if isinstance(conv, LinearIntegerConversion):
        return [
            f"    {r} = {x}",
            f"    q, m = divmod({r}, {conv.scale!r})",
            f"    {r} = round(q if m == 0 else {r} / {conv.scale!r})",
        ]
    return [f"    {r} = round({x} / {conv.scale!r})"]


def _compile_encoder(message: DbcMessage, names: tuple[str, ...]) -> _Encode:
    """Compile ``(*physical values of the named signals) -> payload`` for one message.

    The strict mode of cantools' ``Message.encode``, generated from the DBC like the decoder
    (:func:`_compile`): per signal, a check that the value is a number within the DBC's
    physical range (inclusive, with cantools' tolerance of a millionth of the scale; a code of
    the signal's value table passes too), the raw value rounded as cantools rounds it, and its
    bits shifted into place. Signals left out are 0. Several times faster than cantools,
    which looks signals up by name and packs through dicts and bitstruct on every call.

    :raises CanCodecError: a named signal is missing, float, multiplexed or has scale 0
    :return: a function raising :class:`EncodeError` for a value out of range, not finite or
        not a number, naming the frame, the signal, the value and the range
    """
    total_bits = 8 * message.length
    signals = _signals(message, names)
    for sig in signals:
        if sig.conversion.scale == 0:
            raise CanCodecError(f"{message.name}.{sig.name} has scale 0")
    checks = _SignalChecks(message, signals)
    values = [f"v{i}" for i in range(len(signals))]
    lines = [f"def encode({', '.join(values)}):"]
    le_terms, be_terms = [], []
    for i, (sig, v) in enumerate(zip(signals, values, strict=True)):
        r = f"r{i}"
        lines.append(f"    if {v}.__class__ not in exact:")
        lines.append(f"        {v} = number({i}, {v})")
        # cantools: an error when value < minimum - |scale| * 1e-6 (or > maximum + ...).
        # Without a bound, comparing with ±inf still rejects NaN and infinities.
        tolerance = abs(sig.conversion.scale) * 1e-6
        lowest = None if sig.minimum is None else sig.minimum - tolerance
        highest = None if sig.maximum is None else sig.maximum + tolerance
        low = "-inf <" if lowest is None else f"{lowest!r} <="
        high = "< inf" if highest is None else f"<= {highest!r}"
        accept_code = f" and not in_choices({i}, {v})" if sig.conversion.choices else ""
        lines.append(f"    if not {low} {v} {high}{accept_code}:")
        lines.append(f"        raise reject({i}, {v})")
        lines.extend(_raw_lines(sig, v, r))
        # The range check bounds the raw value; check the field only if the DBC's range (or
        # its value table) reaches beyond what the bits hold.
        field_min, field_max = _field_limits(sig)
        reachable = [int(code) for code in (sig.conversion.choices or {})]
        if lowest is None or highest is None:
            reachable.append(field_max + 1)  # unbounded: always check
        else:  # the conversion is monotonic: the bounds give the extreme raw values
            for bound in (lowest, highest):
                reachable.append(int(sig.conversion.numeric_scaled_to_raw(bound)))
        if not all(field_min <= code <= field_max for code in reachable):
            lines.append(f"    if not {field_min} <= {r} <= {field_max}:")
            lines.append(f"        raise reject_raw({i}, {v}, {r})")
        bits = f"({r} & {(1 << sig.length) - 1})" if sig.is_signed else r  # two's complement
        if sig.byte_order == "little_endian":
            le_terms.append(f"{bits} << {sig.start}" if sig.start else bits)
        else:
            msb = (sig.start // 8) * 8 + (7 - sig.start % 8)  # as in _signal_expression
            shift = total_bits - (msb + sig.length)
            be_terms.append(f"{bits} << {shift}" if shift else bits)
    n = message.length
    le = " | ".join(le_terms) or "0"
    be = " | ".join(be_terms) or "0"
    if not be_terms:
        lines.append(f"    return ({le}).to_bytes({n}, 'little')")
    elif not le_terms:
        lines.append(f"    return ({be}).to_bytes({n}, 'big')")
    else:  # both byte orders in one frame: turn the little-endian part around
        lines.append(f"    le = int.from_bytes(({le}).to_bytes({n}, 'little'), 'big')")
        lines.append(f"    return (le | {be}).to_bytes({n}, 'big')")
    namespace: dict[str, object] = {
        "exact": _EXACT_NUMBERS,
        "inf": math.inf,
        "number": checks.number,
        "in_choices": checks.in_choices,
        "reject": checks.reject,
        "reject_raw": checks.reject_raw,
    }
    exec(compile("\n".join(lines), f"<dbc encode {message.name}>", "exec"), namespace)
    return namespace["encode"]  # type: ignore[return-value]


def _unencodable(reason: str) -> _Encode:
    """An encoder for a message this DBC lets leafgate decode but not encode: it raises."""

    def encode(*values: object) -> bytes:
        raise EncodeError(reason)

    return encode


# --- the profile, compiled ----------------------------------------------------------------------
# A profile maps message fields to DBC signals (leafgate.can.profile). At start-up each frame
# is compiled into one decode function (payload → the message values it carries) and one
# field getter for the encoder (messages → physical signal values), generated as source like
# the bit-level code above, so the per-frame cost stays that of a few shifts and a constructor.


def _to_si(sig: SignalMap, var: str) -> str:
    """Expression converting a signal's DBC value ``var`` to SI (before any type conversion)."""
    expr = var
    if sig.scale != 1.0:
        expr = f"({expr} / {sig.scale!r})"
    suffix = UNITS[sig.unit][1]
    return f"({expr}{suffix})" if suffix else expr


def _typed(field_type: Any, expr: str, conv: str | None) -> str:
    """``expr`` as a value of ``field_type`` (bool, an enumeration, or a number as it is)."""
    if conv is not None:
        return f"{conv}({expr})"
    if field_type is bool:
        return f"({expr} != 0)"
    if isinstance(field_type, type) and issubclass(field_type, enum.Enum):
        return f"{field_type.__name__}({expr})"  # ValueError outside the table → decode_error
    return expr


def _choice_decoder(sig: SignalMap, enum_type: type[enum.Enum]) -> Callable[[float], object]:
    assert sig.choices is not None
    table = {code: enum_type[member] for member, codes in sig.choices.items() for code in codes}
    unknown = None if sig.unknown is None else enum_type[sig.unknown]

    def convert(code: float) -> object:
        member = table.get(int(code), unknown)
        if member is None:
            raise ValueError(f"{sig.signal}: code {code} is not in the profile's map")
        return member

    return convert


def _compile_decoder(
    message: DbcMessage, spec: FrameSpec, profile: Profile, shared: frozenset[str]
) -> _Decode:
    """Compile ``(payload, latest) -> (values this frame refreshes, ...)`` for one frame.

    A source the frame fills completely, and no other frame touches, is built directly; any
    other folds the frame's fields into ``latest[source]`` (a dict of the source's fields,
    kept by the codec) and is built from it when the frame refreshes it.
    """
    sources = COMMAND_SOURCES if spec.direction == "command" else REPORT_SOURCES
    mapped = [sig for sig in spec.signals if sig.source is not None]
    signals = _signals(message, tuple(sig.signal for sig in mapped))
    total_bits = 8 * message.length
    namespace: dict[str, object] = {"from_bytes": int.from_bytes}
    lines = ["def decode(data, latest):"]
    if any(sig.byte_order == "little_endian" for sig in signals):
        lines.append("    le = from_bytes(data, 'little')")  # excess bytes only add high bits
    if any(sig.byte_order == "big_endian" for sig in signals):
        lines.append(f"    be = from_bytes(data[:{message.length}], 'big')")
    # source → attr → expression
    fields: dict[str, dict[str, str]] = {src: {} for src in spec.sources}
    for i, (sig_map, sig) in enumerate(zip(mapped, signals, strict=True)):
        lines.append(f"    s{i} = {_signal_expression(sig, total_bits)}")
        si = _to_si(sig_map, f"s{i}")
        for j, (src, attr) in enumerate(((sig_map.source, sig_map.attr), *sig_map.also)):
            assert src is not None and attr is not None
            field_type = typing.get_type_hints(sources[src])[attr]
            conv = None
            if sig_map.choices is not None:
                conv = f"conv{i}_{j}"
                namespace[conv] = _choice_decoder(sig_map, field_type)
            elif isinstance(field_type, type) and issubclass(field_type, enum.Enum):
                namespace[field_type.__name__] = field_type
            fields[src][attr] = _typed(field_type, si, conv)
    derived = profile.derived if spec.direction == "report" else {}
    out = []
    for src, attrs in fields.items():
        cls = sources[src]
        namespace[cls.__name__] = cls
        all_fields = [f.name for f in dataclasses.fields(cls)]
        complete = set(attrs) == set(all_fields) and src not in shared and src not in derived
        if complete:
            args = ", ".join(f"{a}={attrs[a]}" for a in all_fields)
            if src in spec.refreshes:
                lines.append(f"    v_{src} = {cls.__name__}({args})")
                out.append(f"v_{src}")
            continue
        lines.append(f"    d_{src} = latest[{src!r}]")
        for attr, expr in attrs.items():
            lines.append(f"    d_{src}[{attr!r}] = {expr}")
        if src in spec.refreshes:
            for flag, source_field, above in derived.get(src, ()):  # |field| > threshold
                lines.append(f"    d_{src}[{flag!r}] = abs(d_{src}[{source_field!r}]) > {above!r}")
            lines.append(f"    v_{src} = {cls.__name__}(**d_{src})")
            out.append(f"v_{src}")
    lines.append(f"    return ({', '.join(out)}{',' if out else ''})")
    exec(compile("\n".join(lines), f"<profile {profile.name} {message.name}>", "exec"), namespace)
    return namespace["decode"]  # type: ignore[return-value]


def _compile_getter(spec: FrameSpec, profile: Profile) -> tuple[tuple[str, ...], _Getter]:
    """The signal names the frame's encoder takes, and ``sources -> their physical values``."""
    names: list[str] = []
    exprs: list[str] = []
    namespace: dict[str, object] = {}
    for i, sig in enumerate(spec.signals):
        names.append(sig.signal)
        if sig.source is None:
            exprs.append(repr(sig.constant))
            continue
        expr = f"src[{sig.source!r}].{sig.attr}"
        if sig.choices is not None:
            table = {member: codes[0] for member, codes in sig.choices.items()}
            namespace[f"codes{i}"] = {
                m: table[m.name] for m in _enum_of(spec, sig) if m.name in table
            }
            expr = f"codes{i}[{expr}]"  # KeyError: a member the car has no code for
        else:
            to_dbc = UNITS[sig.unit][0]
            if to_dbc:
                expr = f"{expr}{to_dbc}"
            if sig.scale != 1.0:
                expr = f"{expr} * {sig.scale!r}"
        exprs.append(expr)
    source = f"def values(src):\n    return ({', '.join(exprs)}{',' if exprs else ''})"
    exec(compile(source, f"<profile {profile.name} {spec.name} fields>", "exec"), namespace)
    return tuple(names), namespace["values"]  # type: ignore[return-value]


def _enum_of(spec: FrameSpec, sig: SignalMap) -> type[enum.Enum]:
    sources = COMMAND_SOURCES if spec.direction == "command" else REPORT_SOURCES
    assert sig.source is not None and sig.attr is not None
    enum_type: type[enum.Enum] = typing.get_type_hints(sources[sig.source])[sig.attr]
    return enum_type


def _counter_reader(message: DbcMessage, name: str) -> Callable[[bytes | bytearray], int]:
    """Compile ``payload -> raw value of the counter signal``."""
    sig = _signals(message, (name,))[0]
    expr = _signal_expression(sig, 8 * message.length)
    src = "def counter(data):\n"
    if sig.byte_order == "little_endian":
        src += "    le = from_bytes(data, 'little')\n"
    else:
        src += f"    be = from_bytes(data[:{message.length}], 'big')\n"
    src += f"    return int({expr})"
    namespace: dict[str, object] = {"from_bytes": int.from_bytes}
    exec(compile(src, f"<counter {message.name}>", "exec"), namespace)
    return namespace["counter"]  # type: ignore[return-value]


# --- the codec ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _TxEntry:
    """Everything encode needs for one frame, prepared at start-up."""

    name: str
    frame_id: int
    names: tuple[str, ...]  # signals the encoder takes (the counter, if any, last)
    values: _Getter  # sources -> physical values of ``names`` (without the counter)
    encode: _Encode  # physical values (+ the counter) -> payload, compiled from the DBC
    e2e: str  # the frame's scheme (leafgate.can.profile.E2E_SCHEMES)
    sources: tuple[str, ...]
    modulo: int  # of the frame's counter (0: none); but for leafgate's, the encoder's last value
    params: Mapping[str, int]  # of the checksum scheme
    unencodable: str | None = None  # why no value can ever be encoded (the DBC, the profile)


@dataclass(frozen=True, slots=True)
class _RxEntry:
    """Everything decode needs for one known ID, prepared at start-up."""

    name: str
    length: int  # bytes the DBC defines
    exact: bool  # a protected frame: exactly ``length`` bytes (others: at least)
    e2e: str
    decode: _Decode  # (payload, latest) -> the values it refreshes
    counter: Callable[[bytes | bytearray], int] | None  # reads a checked counter signal
    direction: str
    modulo: int  # of the checked counter
    params: Mapping[str, int]  # of the checksum scheme


def _load_database(path: str | Path) -> tuple[Database, str]:
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CanCodecError(f"{where}: no such DBC file") from None
    except OSError as exc:
        raise CanCodecError(f"{where}: cannot read: {exc.strerror}") from None
    try:
        # Not strict: a DBC often has signals that overlap in frames leafgate never touches
        # (dalathegreat's Leaf DBCs, opendbc's Xterra). The frames the profile uses are checked
        # strictly one by one (_layout_problem); the others are reported, not refused.
        db = cantools.database.load_string(text, database_format="dbc", strict=False)
    except Exception as exc:  # cantools raises several parse error types
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanCodecError(f"{where}: invalid DBC: {first}") from None
    assert isinstance(db, Database)
    return db, where


@dataclass(frozen=True)
class LayoutProblem:
    """A DBC frame whose layout cantools' strict mode refuses: signals that overlap, or a signal
    that does not fit in the frame. A frame the profile uses with such a layout is refused at
    start-up; any other frame is loaded and reported (:attr:`CanCodec.layout_problems`), its
    named signals not to be trusted (their values share bits, so at most one reads them right).
    """

    where: str  # the DBC file
    name: str  # the frame's DBC name
    frame_id: int
    is_extended: bool
    signals: tuple[str, ...]  # the signals at fault, in the DBC's order
    problem: str  # e.g. "signals WHEEL_1 and WHEEL_2 overlap (bit 15)"

    @property
    def frame(self) -> str:
        """The frame as messages name it: ``ABS_1 (0x284)``."""
        return f"{self.name} (0x{self.frame_id:{'08X' if self.is_extended else '03X'}})"

    @property
    def key(self) -> int:
        """The frame's key in :attr:`CanCodec.stats` (see :func:`frame_key`)."""
        return self.frame_id | EXTENDED_KEY if self.is_extended else self.frame_id

    def __str__(self) -> str:
        return f"{self.where}: {self.frame}: {self.problem}"


def _bit_span(bits: frozenset[int]) -> str:
    low, high = min(bits), max(bits)
    return f"bit {low}" if low == high else f"bits {low}..{high}"


def _exclusive(a: Signal, b: Signal) -> bool:
    """Whether two signals are never in one frame: multiplexed by the same multiplexer on
    disjoint multiplexer values."""
    return (
        a.multiplexer_signal is not None
        and a.multiplexer_signal == b.multiplexer_signal
        and bool(a.multiplexer_ids)
        and bool(b.multiplexer_ids)
        and not set(a.multiplexer_ids or ()) & set(b.multiplexer_ids or ())
    )


def _layout_problem(message: DbcMessage, where: str) -> LayoutProblem | None:
    """What cantools' strict mode refuses in ``message`` (the test is cantools' own), with every
    signal at fault named, or None."""
    try:
        message.refresh(strict=True)
    except cantools.database.Error as exc:
        refused = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    else:
        return None
    size = 8 * message.length  # bits
    bits = {sig.name: _bits(message, sig.name) for sig in message.signals}
    named: list[str] = []
    problems: list[str] = []
    for sig in message.signals:
        if max(bits[sig.name]) >= size:
            named.append(sig.name)
            problems.append(
                f"signal {sig.name} does not fit in its {message.length} bytes "
                f"(it reaches bit {max(bits[sig.name])})"
            )
    for i, a in enumerate(message.signals):
        for b in message.signals[i + 1 :]:
            common = bits[a.name] & bits[b.name]
            if common and not _exclusive(a, b):
                named += [n for n in (a.name, b.name) if n not in named]
                problems.append(f"signals {a.name} and {b.name} overlap ({_bit_span(common)})")
    order = [sig.name for sig in message.signals]
    return LayoutProblem(
        where=where,
        name=message.name,
        frame_id=message.frame_id,
        is_extended=message.is_extended_frame,
        signals=tuple(sorted(named, key=order.index)),
        problem="; ".join(problems) or refused,  # cantools' words when ours find nothing
    )


def _layout(message: DbcMessage) -> tuple[Any, ...]:
    """What decodes a frame: its ID, length and every signal's place and scaling."""
    return (
        message.frame_id,
        message.is_extended_frame,
        message.length,
        sorted(
            (s.name, s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset)
            for s in message.signals
        ),
    )


def _hidden_frames(
    profile: Profile,
    loaded: list[tuple[Database, str]],
    used: Mapping[str, tuple[DbcMessage, str]],
) -> tuple[str, ...]:
    """The frames of the profile's DBCs that a frame it uses hides, one line each: a frame of
    another name on a used frame's ID (a received frame of that ID is decoded as the used one;
    a sent one goes out on an ID that DBC gives another frame), or another definition of a
    used frame's name (the first DBC's is used)."""
    roles = {
        spec.name: "sends" if spec.direction == "command" else "reads" for spec in profile.frames
    }
    by_id = {
        message.frame_id: name
        for name, (message, _) in used.items()
        if not message.is_extended_frame
    }
    lines: list[str] = []
    for db, where in loaded:
        for message in db.messages:
            name = message.name
            if name in used and used[name][0] is message:
                continue
            hex_id = f"0x{message.frame_id:{'08X' if message.is_extended_frame else '03X'}}"
            owner = None if message.is_extended_frame else by_id.get(message.frame_id)
            if owner is not None and owner != name:
                lines.append(
                    f"{where}: {name} ({hex_id}) has the ID of {owner}, which profile "
                    f"{profile.name} {roles[owner]} ({used[owner][1]}): frames of {hex_id} are "
                    f"{owner} to leafgate, and {name} is not decoded"
                )
            elif name in used and _layout(message) != _layout(used[name][0]):
                first, first_where = used[name]
                lines.append(
                    f"{where}: {name} ({hex_id}) is also in {first_where} "
                    f"(0x{first.frame_id:03X}), laid out otherwise: profile {profile.name} "
                    f"{roles[name]} that one, and this one is not used"
                )
    return tuple(lines)


def _check_e2e(message: DbcMessage, spec: FrameSpec, where: str) -> None:
    """A protected frame's DBC must place the counter and checksum where the scheme puts them."""
    fixed = _FIXED_SIGNALS.get(spec.e2e)
    if fixed is not None:
        if message.length != e2e.FRAME_LENGTH:
            raise CanCodecError(f"{where}: {message.name} must be {e2e.FRAME_LENGTH} bytes")
        if spec.e2e == "secoc":  # the MAC covers bytes 0-3 only: every signal must lie there
            outside = sorted(
                sig.name
                for sig in message.signals
                if sig.name not in fixed
                and max(_bits(message, sig.name)) >= 8 * secoc.PAYLOAD_BYTES
            )
            if outside:
                raise CanCodecError(
                    f"{where}: {message.name}.{outside[0]} must lie in bytes 0-3, which the MAC "
                    "covers"
                )
        for sig_name, (start, length) in fixed.items():
            try:
                sig = message.get_signal_by_name(sig_name)
            except KeyError:
                raise CanCodecError(f"{where}: {message.name}.{sig_name} is missing") from None
            if (sig.start, sig.length, sig.byte_order) != (start, length, "little_endian"):
                raise CanCodecError(
                    f"{where}: {message.name}.{sig_name} must be {length} bits little-endian at "
                    f"bit {start}, as leafgate.can.{spec.e2e.replace('leafgate', 'e2e')} computes it"
                )
    for role, protection in (("counter", spec.counter_signal), ("checksum", spec.checksum_signal)):
        if protection is not None and protection not in {s.name for s in message.signals}:
            raise CanCodecError(
                f"{where}: {message.name} (0x{message.frame_id:03X}) has no signal {protection}, "
                f"the {role} the profile checks (e2e {spec.e2e})"
            )
    for scheme, place in _SCHEME_PLACES.items():
        if spec.e2e != scheme:
            continue
        for role, signal, bits in (
            ("counter", spec.counter_signal, place[0]),
            ("checksum", spec.checksum_signal, place[1]),
        ):
            assert signal is not None
            if message.length < e2e.SEAL_LENGTH[scheme] or _bits(message, signal) != bits:
                raise CanCodecError(
                    f"{where}: {message.name}.{signal} must be the {role} where {scheme} puts "
                    f"it (bits {min(bits)}..{max(bits)} counted from byte 0 bit 0)"
                )
    if spec.e2e == "nissan-lkas":
        assert spec.checksum_signal is not None
        sig = message.get_signal_by_name(spec.checksum_signal)
        byte7 = (sig.length == 8) and (
            (sig.byte_order == "little_endian" and sig.start == 56)
            or (sig.byte_order == "big_endian" and sig.start == 63)
        )
        if message.length != 8 or not byte7:
            raise CanCodecError(
                f"{where}: {message.name}.{spec.checksum_signal} must be byte 7 of an 8-byte frame"
            )


# Where a checksum scheme expects its counter and checksum: payload bit indices (byte·8 + bit).
_SCHEME_PLACES: Final[Mapping[str, tuple[frozenset[int], frozenset[int]]]] = {
    "nissan-nibble": (frozenset(range(32, 36)), frozenset(range(36, 40))),
    "counter-sum": (frozenset(range(48, 56)), frozenset(range(56, 64))),
}


def _bits(message: DbcMessage, name: str) -> frozenset[int]:
    """The payload bits (byte·8 + bit) a signal occupies."""
    sig = message.get_signal_by_name(name)
    if sig.byte_order == "little_endian":
        return frozenset(range(sig.start, sig.start + sig.length))
    out = set()
    pos = sig.start  # MSB; walk down within the byte, then to the next byte's bit 7
    for _ in range(sig.length):
        out.add(pos)
        pos = pos - 1 if pos % 8 else pos + 15
    return frozenset(out)


_SourceKey = tuple[str, int, int]  # (path, mtime in ns, size in bytes)


def _source_key(path: str | Path) -> _SourceKey:
    """Identify a DBC file for the cache, as it is now."""
    try:
        st = Path(path).stat()
    except OSError:
        return (str(path), -1, -1)  # not cached usefully; _load_database reports the error
    return (str(path), st.st_mtime_ns, st.st_size)


@dataclass(frozen=True)
class _Tables:
    """What a codec needs from its profile and DBCs; immutable, so codecs share it."""

    profile: Profile
    databases: tuple[Database, ...]
    messages: Mapping[str, DbcMessage]  # DBC name → message (the profile's frames)
    encoders: Mapping[str, _TxEntry]  # DBC name → compiled encoder
    rx: Mapping[int, _RxEntry]  # ID → compiled decoder
    ids: Mapping[str, frozenset[int]]  # direction → IDs
    by_type: Mapping[type, tuple[str, str]]  # message type → (frame, source) it alone fills
    shared: Mapping[str, frozenset[str]]  # direction → sources folded from several frames
    layout_problems: tuple[LayoutProblem, ...]  # of frames the profile does not use
    hidden: tuple[str, ...]  # frames a used frame hides (its ID or name), one line each


_TABLES: dict[tuple[int, tuple[_SourceKey, ...]], tuple[Profile, _Tables]] = {}
_TABLES_MAX: Final = 16


def _tables(profile: Profile, keys: tuple[_SourceKey, ...]) -> _Tables:
    """The compiled tables of a profile and its DBCs as they are now; cached, as parsing takes
    tens of milliseconds (profiles are loaded once each, see ``load_profile``)."""
    key = (id(profile), keys)
    hit = _TABLES.get(key)
    if hit is not None and hit[0] is profile:
        return hit[1]
    tables = _compile_tables(profile, keys)
    if len(_TABLES) >= _TABLES_MAX:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = (profile, tables)
    return tables


def _compile_tables(profile: Profile, keys: tuple[_SourceKey, ...]) -> _Tables:
    """Load, check and compile the profile's DBCs."""
    loaded = [_load_database(key[0]) for key in keys]
    found: dict[str, tuple[DbcMessage, str]] = {}
    for db, where in loaded:
        for message in db.messages:
            found.setdefault(message.name, (message, where))
    messages: dict[str, DbcMessage] = {}
    encoders: dict[str, _TxEntry] = {}
    rx: dict[int, _RxEntry] = {}
    ids: dict[str, list[int]] = {"commands": [], "reports": [], "car": []}
    touched: dict[str, dict[str, int]] = {"command": {}, "report": {}}
    for spec in profile.frames:
        for src in spec.sources:
            touched[spec.direction][src] = touched[spec.direction].get(src, 0) + 1
    shared = {d: frozenset(s for s, n in t.items() if n > 1) for d, t in touched.items()}
    by_type: dict[type, tuple[str, str]] = {}
    for spec in profile.frames:
        if spec.name not in found:
            raise CanCodecError(
                f"{profile.where}: frame {spec.name} is in no DBC of the profile "
                f"({', '.join(where for _, where in loaded)})"
            )
        message, where = found[spec.name]
        problem = _layout_problem(message, where)
        if problem is not None:  # the frame is used: a layout cantools' strict mode refuses
            role = "sends" if spec.direction == "command" else "reads"
            raise CanCodecError(
                f"{problem}: profile {profile.name} {role} this frame, so its signals must "
                "fit and must not overlap"
            )
        if message.is_extended_frame:
            raise CanCodecError(f"{where}: {spec.name} must use a standard 11-bit ID")
        if message.frame_id in rx:
            raise CanCodecError(
                f"{spec.name} and {rx[message.frame_id].name} share ID 0x{message.frame_id:03X}"
            )
        try:
            _check_e2e(message, spec, where)
            encoders[spec.name] = _tx_entry(message, spec, profile, where)
            checked = spec.e2e in COUNTER_CHECKED and spec.counter_signal is not None
            rx[message.frame_id] = _RxEntry(
                name=spec.name,
                length=message.length,
                exact=spec.e2e in ("leafgate", "secoc", "nissan-lkas"),
                e2e=spec.e2e,
                decode=_compile_decoder(message, spec, profile, shared[spec.direction]),
                counter=(
                    _counter_reader(message, spec.counter_signal)
                    if checked and spec.counter_signal
                    else None
                ),
                direction=spec.direction,
                modulo=_counter_modulo(message, spec) if checked else 0,
                params=MappingProxyType(dict(spec.e2e_params)),
            )
        except CanCodecError as exc:  # name the profile file as well as the DBC
            text = str(exc)
            raise CanCodecError(
                text if text.startswith(where) else f"{profile.where}: {text} ({where})"
            ) from None
        messages[spec.name] = message
        direction = (
            "commands" if spec.direction == "command" else spec.bus.replace("dbw", "reports")
        )
        ids[direction].append(message.frame_id)
        if len(spec.sources) == 1 and spec.sources[0] not in shared[spec.direction]:
            sources = COMMAND_SOURCES if spec.direction == "command" else REPORT_SOURCES
            cls = sources[spec.sources[0]]
            key_type: type = cls
            if cls is WheelSpeeds:  # two sources of one type: told apart by the axle
                by_type[(WheelSpeeds, spec.sources[0])] = (spec.name, spec.sources[0])  # type: ignore[index]
                continue
            by_type[key_type] = (spec.name, spec.sources[0])
    used = {id(message) for message in messages.values()}
    layout_problems = tuple(
        problem
        for db, where in loaded
        for message in db.messages
        if id(message) not in used and (problem := _layout_problem(message, where)) is not None
    )
    return _Tables(
        profile=profile,
        databases=tuple(db for db, _ in loaded),
        layout_problems=layout_problems,
        hidden=_hidden_frames(profile, loaded, {name: found[name] for name in messages}),
        messages=MappingProxyType(messages),
        encoders=MappingProxyType(encoders),
        rx=MappingProxyType(rx),
        ids=MappingProxyType({d: frozenset(v) for d, v in ids.items()}),
        by_type=MappingProxyType(by_type),
        shared=MappingProxyType(shared),
    )


def _tx_entry(message: DbcMessage, spec: FrameSpec, profile: Profile, where: str) -> _TxEntry:
    """The compiled encoder of a frame (``where``: its DBC file). Strict as cantools: every
    signal of the message must be filled, by the profile or by the frame's E2E scheme;
    otherwise encoding it raises."""
    names, getter = _compile_getter(spec, profile)
    modulo = _counter_modulo(message, spec)
    counter = (spec.counter_signal,) if modulo and spec.e2e != "leafgate" else ()
    filled = set(names) | set(counter)
    filled |= set(_FIXED_SIGNALS.get(spec.e2e, ()))
    if spec.checksum_signal is not None:
        filled.add(spec.checksum_signal)
    unknown = sorted(sig.name for sig in message.signals if sig.name not in filled)
    reason: str | None = None
    if unknown:
        reason = (
            f"{message.name} (0x{message.frame_id:03X}): the profile fills no value for "
            f"signal(s) {', '.join(unknown)} of the DBC {where}"
        )
    else:
        try:
            encode = _compile_encoder(message, names + counter)  # type: ignore[operator]
        except CanCodecError as exc:
            reason = str(exc)
    if reason is not None:
        encode = _unencodable(reason)
    return _TxEntry(
        name=spec.name,
        frame_id=message.frame_id,
        names=names + counter,  # type: ignore[operator]
        values=getter,
        encode=encode,
        e2e=spec.e2e,
        sources=spec.sources,
        modulo=modulo,
        params=MappingProxyType(dict(spec.e2e_params)),
        unencodable=reason,
    )


def _counter_modulo(message: DbcMessage, spec: FrameSpec) -> int:
    """How far the frame's counter signal counts (16 for 4 bits); 0 without a counter."""
    if spec.e2e == "leafgate":
        return e2e.COUNTER_MODULO
    if spec.counter_signal is None or spec.e2e == "none":
        return 0
    return 1 << message.get_signal_by_name(spec.counter_signal).length


class CanCodec:
    """Encode leafgate messages into frames and decode frames into messages, per profile.

    :param dbw_dbc: replaces the profile's first DBC (``leafgate_dbw.dbc`` in the default
        profile); None keeps the profile's
    :param car_dbc: replaces the profile's second DBC (the CAR-CAN one); None keeps it
    :param profile: the vehicle profile (a :class:`~leafgate.can.profile.Profile` or a
        name/path for :func:`~leafgate.can.profile.load_profile`); required, there is no
        default
    :param key: the key of a profile with authenticated frames (``secoc``,
        :mod:`leafgate.can.secoc`): the codec seals the frames it encodes and verifies the
        ones it decodes. Without it such frames cannot be encoded, and are decoded *unverified*
        (counted in ``mac_unverified``; for tools reading a log, never for a sender or an ECU)
    :param clock: the Unix-time clock of the freshness values (s); None takes each received
        frame's own timestamp as the receive time (a recorded log) and the ``timestamp`` given
        to encode as the send time
    :raises CanCodecError: a DBC is unreadable, invalid, or lacks a frame or signal the
        profile maps, or a frame the profile uses has signals that overlap or do not fit (the
        message names the file and the frame); such a frame the profile does not use is only
        reported, in :attr:`layout_problems`
    :raises ConfigError: the profile is missing or invalid

    One instance per sender/receiver: it owns the alive counters of the frames it encodes and
    the counter state of the frames it decodes (and, for profiles that fill one message from
    several frames, the fields seen so far). Decode from one thread; :attr:`stats` may be read
    from another.
    """

    def __init__(
        self,
        dbw_dbc: str | Path | None = None,
        car_dbc: str | Path | None = None,
        profile: Profile | str | None = None,
        *,
        key: bytes | None = None,
        clock: Callable[[], float] | None = time.time,
    ) -> None:
        if profile is None:  # no default: a log of one car read as another's is all unknown
            raise CanCodecError(
                "a CAN codec needs a vehicle profile (a name such as leafgate-dbw, or a file)"
            )
        if not isinstance(profile, Profile):
            profile = load_profile(profile)
        paths = list(profile.dbc)
        for index, override in ((0, dbw_dbc), (1, car_dbc)):
            if override is not None:
                if index >= len(paths):
                    raise CanCodecError(
                        f"{override}: profile {profile.name} has no DBC #{index + 1} to replace"
                    )
                paths[index] = str(override)
        tables = _tables(profile, tuple(_source_key(p) for p in paths))
        self.profile = profile
        self._tables = tables
        self._rx, self._ids = tables.rx, tables.ids
        self._encoders = tables.encoders
        self._tx_counters: dict[int, int] = {}  # next alive counter per sent ID
        self._rx_counters = e2e.CounterChecker()
        self._counts: dict[int, list[int]] = {frame_id: [0] * _STATS_LEN for frame_id in self._rx}
        self._unknown_total = 0
        # fields of each source seen so far, for sources several frames fill (per direction)
        self._latest: dict[str, dict[str, dict[str, Any]]] = {
            direction: {
                src: base_values(profile, direction, src)
                for src in (COMMAND_SOURCES if direction == "command" else REPORT_SOURCES)
            }
            for direction in ("command", "report")
        }
        self.command_frames: tuple[str, ...] = tuple(
            spec.name for spec in profile.frames_of("command")
        )
        self.last_errors: list[str] = []  # why frames were left out of the last encode_commands
        #: the profile authenticates frames (secoc); :attr:`verifies`: with the key to check them
        self.authenticated = profile.authenticated
        self.clock = clock
        self._sealer = secoc.Sealer(key) if key is not None else None
        self._verifier = secoc.Verifier(key) if key is not None else None

    def authenticates(self, frame_id: int) -> bool:
        """Whether frames of ``frame_id`` carry a MAC (``e2e: secoc``)."""
        entry = self._rx.get(frame_id)
        return entry is not None and entry.e2e == "secoc"

    @property
    def verifies(self) -> bool:
        """Whether authenticated frames are sealed and verified (the codec has the key)."""
        return self._verifier is not None

    @classmethod
    def for_config(
        cls, cfg: Any, clock: Callable[[], float] | None = time.time, key: bytes | None = None
    ) -> CanCodec:
        """The codec of a deployment config (a ``LeafgateConfig``): its profile and DBCs, and
        for a profile with authenticated frames the key of ``can.auth_key_file`` (or ``key``,
        a simulation's throwaway one).

        :raises ConfigError: the profile authenticates its frames and no key file is
            configured, or the key file is refused (:func:`leafgate.can.secoc.load_key`)
        """
        profile = cfg.profile
        if profile.authenticated and key is None:
            if cfg.can.auth_key_file is None:
                raise ConfigError(
                    f"profile {profile.name} authenticates its command frames: set "
                    "can.auth_key_file to a key file (make one with `leafgate keygen PATH`)"
                )
            key = secoc.load_key(cfg.can.auth_key_file)
        return cls(cfg.can.dbw_dbc, cfg.can.car_dbc, profile, key=key, clock=clock)

    # --- encode ---------------------------------------------------------------------------

    def cannot_encode(self, name: str) -> str | None:
        """Why frame ``name`` of the profile can never be encoded, whatever the values (its
        DBC message has a signal the profile fills no value for, or a layout leafgate cannot
        encode), or None. The gateway only decodes the reports, so a DBC may carry more
        signals in them than the profile maps; a sender of them (the simulated ECU) cannot.

        :raises EncodeError: the profile has no frame ``name``
        """
        entry = self._encoders.get(name)
        if entry is None:
            raise EncodeError(f"profile {self.profile.name} has no frame {name}")
        return entry.unencodable

    def unsendable_reports(self) -> list[str]:
        """Why each of the profile's report frames that can never be encoded cannot be (see
        :meth:`cannot_encode`): the gateway, which only decodes them, runs with such a DBC;
        the simulated ECU, which sends them, cannot."""
        reports = self.profile.frames_of("report")
        return [why for f in reports if (why := self.cannot_encode(f.name)) is not None]

    @property
    def layout_problems(self) -> tuple[LayoutProblem, ...]:
        """The frames of the DBCs that the profile does not use and whose layout cantools'
        strict mode refuses (signals that overlap or do not fit), in DBC order. They are loaded
        (a used frame with such a layout is refused at start-up), and the signals each names
        are not to be trusted: ``leafgate check-config`` and the daemon warn about each."""
        return self._tables.layout_problems

    def dbc_warnings(self) -> list[str]:
        """What of the profile's DBCs is loaded but not to be trusted, one line each, for
        ``check-config`` and the daemon's start-up to warn with: each :attr:`layout_problems`
        frame, naming the DBC, the frame and its signals; and each frame that a frame the
        profile uses hides, by its ID (a received frame of that ID is decoded as the used one,
        a sent one takes an ID that DBC gives another frame) or by its name (the first DBC's
        definition is used)."""
        return [
            f"{p}: loaded, as profile {self.profile.name} does not use this frame; "
            f"{', '.join(p.signals) or 'its signals'} not to be trusted"
            for p in self._tables.layout_problems
        ] + list(self._tables.hidden)

    def encode_commands(self, commands: Any, timestamp: float = 0.0) -> list[can.Message]:
        """The profile's command frames for one tick's :class:`~leafgate.messages.Commands`.

        A frame drawing on ``system`` is sent only when the tick has a system command (it has
        its own, slower period). A frame that cannot be encoded is left out and its error
        appended to :attr:`last_errors` (the loop counts them; it never raises).
        """
        sources = {"steer": commands.steer, "long": commands.long, "system": commands.system}
        frames = []
        errors = self.last_errors
        errors.clear()
        for name in self.command_frames:
            if commands.system is None and "system" in self._encoders[name].sources:
                continue
            try:
                frames.append(self.encode_frame(name, sources, timestamp))
            except EncodeError as exc:
                errors.append(str(exc))
        return frames

    def encode(self, value: EncodableMessage, timestamp: float = 0.0) -> can.Message:
        """Encode a message dataclass into the one frame that carries it alone.

        Strict like cantools' ``Message.encode(..., strict=True)``, through an encoder
        compiled from the DBC at start-up. A failed encode does not use up an alive counter.
        Frames that carry several messages are encoded with :meth:`encode_frame`.

        :param value: one of the message dataclasses a frame carries
        :param timestamp: s, copied into the frame (the sender's clock)
        :raises EncodeError: a value is outside its DBC range, not finite or not a number
            (the message names the frame, the signal, the value and the range), or no frame
            of the profile carries the type alone
        """
        name, source = self._frame_of(value)
        return self.encode_frame(name, {source: value}, timestamp)

    def _frame_of(self, value: object) -> tuple[str, str]:
        by_type = self._tables.by_type
        key: object = type(value)
        if key is WheelSpeeds:
            axle = getattr(value, "axle", None)
            if axle not in ("front", "rear"):
                raise EncodeError(f"WheelSpeeds.axle must be 'front' or 'rear', got {axle!r}")
            key = (WheelSpeeds, f"wheels_{axle}")
        found = by_type.get(key)  # type: ignore[call-overload]
        if found is None:
            found = next(
                (v for t, v in by_type.items() if isinstance(t, type) and isinstance(value, t)),
                None,
            )
            if found is None:
                raise EncodeError(
                    f"cannot encode a {type(value).__name__}: no frame of profile "
                    f"{self.profile.name} carries it alone"
                )
        return found

    def encode_frame(
        self, name: str, sources: Mapping[str, object], timestamp: float = 0.0
    ) -> can.Message:
        """Encode one frame of the profile from the messages it draws on.

        :param name: the frame's DBC name (e.g. ``HLC_AUTONOMOUS``)
        :param sources: source name → message, e.g. ``{"steer": SteerCommand(...),
            "long": LongCommand(...)}`` (see :mod:`leafgate.can.profile`)
        :raises EncodeError: a source is missing, a value is out of range or not a number
        """
        entry = self._encoders.get(name)
        if entry is None:
            raise EncodeError(f"profile {self.profile.name} has no frame {name}")
        try:
            physical = entry.values(sources)
        except KeyError as exc:
            raise EncodeError(f"{name}: no value for {exc.args[0]!r}") from None
        except (TypeError, AttributeError) as exc:  # a unit conversion met a non-number
            raise EncodeError(f"{name}: a field is not a number ({exc})") from None
        frame_id = entry.frame_id
        scheme = entry.e2e
        counter = self._tx_counters.get(frame_id, 0)
        if scheme == "leafgate":
            data = e2e.apply(frame_id, entry.encode(*physical), counter)
        elif scheme == "secoc":
            if self._sealer is None:
                raise EncodeError(
                    f"{name}: profile {self.profile.name} authenticates it: no key to seal it with"
                )
            now = self.clock() if self.clock is not None else timestamp
            data = self._sealer.seal(frame_id, entry.encode(*physical), now)
        elif entry.modulo:  # the counter is a DBC signal, the encoder's last value
            data = entry.encode(*physical, counter)
            if scheme in e2e.SEALS:
                data = e2e.seal(scheme, frame_id, data, entry.params)
        else:
            data = entry.encode(*physical)
        if entry.modulo:  # only a frame actually produced uses a count
            self._tx_counters[frame_id] = (counter + 1) % entry.modulo
        return can.Message(
            timestamp=timestamp,
            arbitration_id=frame_id,
            is_extended_id=False,
            dlc=len(data),
            data=data,
        )

    def _encode_with_cantools(self, value: EncodableMessage, counter: int = 0) -> bytes:
        """The payload :meth:`encode` makes, computed by cantools' strict ``Message.encode``.

        The reference the compiled encoder is tested and benchmarked against; it does not
        touch the alive counters. An authenticated frame's FRESHNESS and MAC stay 0 (sealing
        is :mod:`leafgate.can.secoc`'s, with the codec's state).

        :raises EncodeError: cantools rejects a value
        """
        name, source = self._frame_of(value)
        message, entry = self._tables.messages[name], self._encoders[name]
        try:
            physical = entry.values({source: value})
        except (KeyError, TypeError, AttributeError) as exc:
            raise EncodeError(f"{name}: {exc}") from None
        signals: dict[str, Any] = dict(zip(entry.names, physical, strict=False))
        counter %= entry.modulo or 1  # the frame's own counter width (8 bits on 0x284)
        if entry.e2e in _FIXED_SIGNALS:  # set below (leafgate), or left to the sealer (secoc)
            signals.update(dict.fromkeys(_FIXED_SIGNALS[entry.e2e], 0))
        elif entry.modulo:
            signals[entry.names[-1]] = counter
        spec = self.profile.frame(name)
        if spec.checksum_signal is not None:
            signals[spec.checksum_signal] = 0
        try:
            data = message.encode(signals, scaling=True, padding=False, strict=True)
        except (cantools.database.EncodeError, TypeError, ValueError, OverflowError) as exc:
            raise EncodeError(f"{name}: {exc}") from None
        if entry.e2e == "leafgate":
            return e2e.apply(entry.frame_id, data, counter)
        return e2e.seal(entry.e2e, entry.frame_id, data, entry.params)

    # --- decode ---------------------------------------------------------------------------

    def decode(self, msg: can.Message) -> Decoded:
        """Decode one received frame; never raises.

        Checks, in order: known standard ID (``unknown_id``; an error frame has none), length
        (``wrong_length``: protected frames exactly their DBC length; others at least it, as
        model years differ in trailing bytes; never over 8 bytes but for a CAN FD frame),
        checksum (``bad_crc``), alive counter (``bad_counter``), content
        (``decode_error``). Every outcome is counted in :attr:`stats`.
        """
        frame_id = msg.arbitration_id
        entry = None if msg.is_extended_id or msg.is_error_frame else self._rx.get(frame_id)
        if entry is None:
            self._count_unknown(frame_key(msg))
            return Decoded(frame_id, None, None, False, "unknown_id")
        counts = self._counts[frame_id]
        counts[_FRAMES] += 1
        try:
            data = msg.data
            size = len(data)
            if (
                msg.is_remote_frame
                or (size > CLASSIC_MAX_DATA and not msg.is_fd)  # no classic frame holds more
                or (size != entry.length if entry.exact else size < entry.length)
            ):
                counts[_WRONG_LENGTH] += 1
                return Decoded(frame_id, entry.name, None, False, "wrong_length")
            error: ErrorKind | None = None
            scheme = entry.e2e
            if scheme == "leafgate":
                if data[e2e.CRC_BYTE] != e2e.e2e_crc(frame_id, data):
                    error = "bad_crc"
                else:
                    status = self._rx_counters.check(frame_id, data[e2e.COUNTER_BYTE] & 0x0F)
                    if status is not _COUNTER_OK and status is not _COUNTER_FIRST:
                        error = "bad_counter"
            elif scheme == "secoc":
                verifier = self._verifier
                if verifier is None:
                    counts[_UNVERIFIED] += 1
                else:
                    now = self.clock() if self.clock is not None else msg.timestamp
                    verdict = verifier.verify(frame_id, data, now)
                    if verdict != "ok":
                        error = _SECOC_ERRORS[verdict]
            elif entry.counter is not None:  # a checked counter, maybe a checksum
                if scheme in e2e.SEALS and not e2e.sealed_ok(scheme, frame_id, data, entry.params):
                    error = "bad_crc"
                else:
                    status = self._rx_counters.check(frame_id, entry.counter(data), entry.modulo)
                    if status is not _COUNTER_OK and status is not _COUNTER_FIRST:
                        error = "bad_counter"
            latest = self._latest[entry.direction]
            if error is not None:  # decoded for the log only: fold nothing into the state
                latest = {src: dict(fields) for src, fields in latest.items()}
            try:
                values = entry.decode(data, latest)
            except (ValueError, KeyError):  # a code outside a value table
                if error is None:
                    counts[_DECODE_ERROR] += 1
                    return Decoded(frame_id, entry.name, None, False, "decode_error")
                values = ()
            value = values[0] if values else None
            if error is None:
                return Decoded(frame_id, entry.name, value, True, None, values)
            counts[_ERROR_INDEX[error]] += 1
            return Decoded(frame_id, entry.name, value, False, error, values)
        except Exception:  # never let a malformed frame escape into the loop
            counts[_DECODE_ERROR] += 1
            return Decoded(frame_id, entry.name, None, False, "decode_error")

    def _count_unknown(self, key: int) -> None:
        """Count a frame of no known ID under its key (:func:`frame_key`). An error frame has
        no ID at all: a frame of its own row, not an unknown ID's."""
        error_frame = key == ERROR_FRAME_KEY
        if not error_frame:
            self._unknown_total += 1
        counts = self._counts.get(key)
        if counts is None:
            if len(self._counts) - len(self._rx) >= _MAX_TRACKED_UNKNOWN_IDS:
                return
            counts = self._counts[key] = [0] * _STATS_LEN
        counts[_FRAMES] += 1
        if not error_frame:
            counts[_UNKNOWN] += 1

    def second_senders(self) -> str:
        """``""``, or which received IDs' alive counters run as two interleaved sequences: a
        second node sends them (another ECU on the bus, a replay), named for a fault reason."""
        ids = self._rx_counters.second_senders()
        if not ids:
            return ""
        names = ", ".join(f"{self.name_of(i) or 'ID'} (0x{i:03X})" for i in ids)
        return f"two interleaved alive-counter sequences on {names}: a second sender on the bus"

    def reset_counters(self, frame_id: int | None = None) -> None:
        """Forget the receive counter state (of one ID, or all): the next frame is accepted.

        For the runtime to call after a receive timeout, when the sender may have restarted.
        """
        self._rx_counters.reset(frame_id)

    # --- introspection --------------------------------------------------------------------

    @property
    def stats(self) -> Mapping[int, FrameStats]:
        """Receive counters per CAN ID (a snapshot). Unknown IDs are listed too, up to 1024
        distinct ones (29-bit IDs as ``ID | EXTENDED_KEY``; :func:`stats_label` shows a key);
        :attr:`unknown_id_count` counts all of them. Error frames have the row
        ``ERROR_FRAME_KEY``, with frames but no ``unknown_id``: they are not frames of an ID."""
        return {frame_id: FrameStats(*counts) for frame_id, counts in list(self._counts.items())}

    @property
    def unknown_id_count(self) -> int:
        """Frames received with an ID no database describes, over all IDs (no error frame)."""
        return self._unknown_total

    def receive_ids(self, direction: Direction) -> frozenset[int]:
        """The IDs one side decodes: ``"reports"`` (the gateway's input on the dbw bus),
        ``"commands"`` (the ECU's input) or ``"car"`` (feedback on the car bus)."""
        try:
            return self._ids[direction]
        except KeyError:
            raise ValueError(
                f"direction must be 'reports', 'commands' or 'car', got {direction!r}"
            ) from None

    def message(self, frame_id: int) -> DbcMessage | None:
        """The cantools message of a known ID (for tools that print signals), else None."""
        entry = self._rx.get(frame_id)
        return None if entry is None else self._tables.messages[entry.name]

    def name_of(self, frame_id: int) -> str | None:
        """The DBC name of a known ID (a key of :attr:`stats`), ``error frames`` for the error
        frames' key, else None."""
        if frame_id == ERROR_FRAME_KEY:
            return ERROR_FRAMES_NAME
        entry = self._rx.get(frame_id)
        return None if entry is None else entry.name

    def frame_id(self, name: str) -> int:
        """The CAN ID of a frame of the profile.

        :raises KeyError: the profile has no such frame
        """
        return self._tables.messages[name].frame_id

    @property
    def databases(self) -> tuple[Database, ...]:
        """The loaded cantools databases, in the profile's order."""
        return self._tables.databases
