"""Vehicle profiles: which frames a car speaks, and how they map to leafgate's messages.

A profile is a YAML file, data only. It names the DBC files that hold the layouts and maps the
fields of the gateway's commands and the vehicle's reports to DBC messages and signals, with
the unit conversion and scaling at that edge, the counter and checksum scheme of each frame,
the send periods and the capabilities of the interface (lateral, longitudinal, gear, an ECU
that reports its own state). :class:`~leafgate.can.codec.CanCodec` and the simulated ECU work
from it, so a new vehicle needs a DBC and a profile file, not new code.

Four profiles ship with leafgate (``leafgate/data/profiles``):

``leafgate-dbw``
    leafgate's own drive-by-wire protocol (docs/can-protocol.md) with E2E protection on every frame, and
    the 2011–17 Leaf's CAR-CAN feedback.
``leafgate-dbw-auth``
    the same with authenticated command frames (freshness value and truncated HMAC-SHA256,
    :mod:`leafgate.can.secoc`); it needs a key file (``can.auth_key_file``).
``sze-hlc``
    the Széchenyi István University research Leaf's high-level-controller frames. They carry
    **no counter and no checksum**: the gateway's own freshness watchdogs are the only
    protection against a stale or repeated frame.
``leaf-ze1-lkas``
    the 2018+ Leaf's ProPILOT steering frame: lateral only, the driver keeps the pedals.

Signal mappings, in a frame's ``signals``::

    STEER_ANGLE_CMD: steer.angle                      # same unit on both sides (SI)
    TIRE_ANGLE: {field: steer.angle, unit: deg}       # rad inside, deg in the DBC
    DESIRED_ANGLE: {field: steer.angle, unit: deg, scale: steering_ratio}
    AUTONOMOUS: {field: steer.enable, also: [long.enable]}   # one signal, two fields (decode)
    GEAR_SHIFTER: {field: gear.gear, map: {P: 1, R: 2, N: 3, D: [4, 7]}, unknown: NONE}
    MAX_TORQUE: {value: 1}                            # a constant the sender always puts

A frame's protection is ``e2e: NAME`` or, with parameters, ``e2e: {scheme: NAME, ...}``
(:data:`E2E_SCHEMES`; the checksums are computed in :mod:`leafgate.can.e2e`, where a new
scheme is one function and one table entry): ``leafgate`` (alive counter + CRC over the data
ID), ``secoc`` (freshness value + truncated MAC under a key, :mod:`leafgate.can.secoc`),
``nissan-lkas`` (counter + CRC-8 in byte 7), ``nissan-nibble`` (the AZE0's 0x002: counter
and XOR-of-nibbles checksum in byte 4), ``counter-sum`` (the AZE0's 0x284/0x285: 8-bit counter
in byte 6, byte 7 = byte 6 + ``offset``), ``counter`` (a checked counter alone), ``rolling`` (a
counter filled when sending, not checked) or ``none``. ``on_change: true`` marks a frame the
car also sends soon after its payload changes (0x421 after a gear change).

``field`` is ``SOURCE.ATTRIBUTE``. Command frames draw on the sources ``steer``, ``long`` and
``system`` (:class:`~leafgate.messages.SteerCommand` …); report frames on ``steer``, ``long``,
``system`` (the ECU reports), ``steering_wheel``, ``wheels_front``, ``wheels_rear``, ``gear``
and ``motor`` (the car's own sensors). A DBC value is ``convert(field) * scale``; ``scale`` is
a number or the name of a vehicle parameter (``steering_ratio``).

>>> p = load_profile("sze-hlc")
>>> p.name, p.capabilities.longitudinal, p.frame("HLC_AUTONOMOUS").e2e
('sze-hlc', True, 'none')
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final, Literal

from leafgate.config import VehicleConfig, load_yaml, safe_load_yaml
from leafgate.errors import ConfigError
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
    "COMMAND_SOURCES",
    "DEFAULT_PROFILE",
    "PROFILE_NAMES",
    "REPORT_SOURCES",
    "Capabilities",
    "FrameSpec",
    "Profile",
    "SignalMap",
    "SteerRateTable",
    "load_profile",
]

DEFAULT_PROFILE: Final = "leafgate-dbw"
# shipped in the package
PROFILE_NAMES: Final = ("leafgate-dbw", "leafgate-dbw-auth", "sze-hlc", "leaf-ze1-lkas")

Direction = Literal["command", "report"]
E2eScheme = Literal[
    "none", "leafgate", "secoc", "rolling", "counter", "nissan-lkas", "nissan-nibble", "counter-sum"
]
E2E_SCHEMES: Final = (
    "none",
    "leafgate",  # leafgate's own: alive counter + CRC-8 over the data ID (e2e.py)
    "secoc",  # freshness value + truncated HMAC-SHA256 under a key (secoc.py)
    "rolling",  # a counter the sender fills; not checked (its behaviour is not known)
    "counter",  # a counter the sender fills and the receiver checks (+1 per frame)
    "nissan-lkas",  # counter + CRC-8 in byte 7 (the ZE1's 0x169)
    "nissan-nibble",  # counter + XOR-of-nibbles checksum (the AZE0's 0x002)
    "counter-sum",  # 8-bit counter in byte 6, byte 7 = byte 6 + offset (0x284/0x285)
)
# Signals each scheme fills itself (encode) and checks (decode), by default name:
# (counter, checksum).
E2E_SIGNALS: Final[Mapping[str, tuple[str | None, str | None]]] = {
    "none": (None, None),
    "leafgate": ("ALIVE_COUNTER", "CRC"),
    "secoc": ("FRESHNESS", "MAC"),
    "rolling": ("COUNTER", None),
    "counter": ("COUNTER", None),
    "nissan-lkas": ("COUNTER", "CHECKSUM"),
    "nissan-nibble": ("COUNTER", "CHECKSUM"),
    "counter-sum": ("COUNTER", "CHECKSUM"),
}
# Schemes whose signals sit at fixed places of an 8-byte frame (leafgate.can.codec checks them)
# and are filled and checked by the codec itself, not as counter/checksum signals.
FIXED_PLACES: Final = frozenset({"leafgate", "secoc"})
# Schemes whose received counter is checked (leafgate's own one is checked by e2e.py).
COUNTER_CHECKED: Final = frozenset({"counter", "nissan-lkas", "nissan-nibble", "counter-sum"})
# Parameters a scheme takes in ``e2e: {scheme: NAME, PARAM: VALUE}`` (integers).
E2E_PARAMS: Final[Mapping[str, tuple[str, ...]]] = {"counter-sum": ("offset",)}

COMMAND_SOURCES: Final[Mapping[str, type]] = {
    "steer": SteerCommand,
    "long": LongCommand,
    "system": SystemCommand,
}
REPORT_SOURCES: Final[Mapping[str, type]] = {
    "steer": SteerReport,
    "long": LongReport,
    "system": SystemReport,
    "steering_wheel": SteeringWheelAngle,
    "wheels_front": WheelSpeeds,
    "wheels_rear": WheelSpeeds,
    "gear": GearPosition,
    "motor": MotorSpeed,
}
_BUSES: Final = ("dbw", "car")

# Unit conversions at the edge: (SI → DBC unit, DBC unit → SI) as Python operator snippets.
DEG: Final = math.pi / 180.0  # rad/deg
KMH: Final = 3.6  # (km/h)/(m/s)
UNITS: Final[Mapping[str, tuple[str, str]]] = {
    "": ("", ""),
    "deg": (f" / {DEG!r}", f" * {DEG!r}"),
    "deg/s": (f" / {DEG!r}", f" * {DEG!r}"),
    "km/h": (f" * {KMH!r}", f" / {KMH!r}"),
}
_VEHICLE_SCALES: Final = ("steering_ratio",)


@dataclass(frozen=True)
class SignalMap:
    """One DBC signal and the message field(s) it carries."""

    signal: str
    source: str | None = None  # None: a constant
    attr: str | None = None
    also: tuple[tuple[str, str], ...] = ()  # further (source, attr) the decoded value sets
    unit: str = ""
    scale: float = 1.0  # DBC value = convert(field) * scale
    choices: Mapping[str, tuple[int, ...]] | None = None  # enum member name → codes
    unknown: str | None = None  # enum member for codes outside ``choices`` (None: an error)
    constant: float | None = None  # what the sender always puts (``value:``)


@dataclass(frozen=True)
class FrameSpec:
    """One frame of the profile."""

    name: str  # DBC message name
    direction: Direction
    bus: Literal["dbw", "car"]
    period: float  # s, how often the sender sends it
    e2e: E2eScheme
    counter_signal: str | None
    checksum_signal: str | None
    signals: tuple[SignalMap, ...]
    refreshes: tuple[str, ...]  # sources a valid frame stamps fresh; others fields fold in
    e2e_params: Mapping[str, int] = dataclasses.field(default_factory=dict)
    on_change: bool = False  # also sent soon after its payload changes (an event frame)

    @property
    def sources(self) -> tuple[str, ...]:
        """Every source this frame reads or sets, in first-use order."""
        seen: dict[str, None] = {}
        for sig in self.signals:
            for src, _ in ((sig.source, sig.attr), *sig.also):
                if src is not None:
                    seen.setdefault(src)
        return tuple(seen)


@dataclass(frozen=True)
class Capabilities:
    """What the interface lets the gateway do."""

    lateral: bool = True
    longitudinal: bool = True
    gear: bool = True  # the gateway may request gear changes
    ecu_status: bool = True  # an ECU reports enabled/override/fault and its state
    long_modes: tuple[str, ...] = ("acceleration", "speed")


@dataclass(frozen=True)
class SteerRateTable:
    """Road-wheel angle-rate limits by speed (a vehicle's safety model), rad/s."""

    speeds: tuple[float, ...]  # m/s, breakpoints
    windup: tuple[float, ...]  # rad/s, angle moving away from centre
    unwind: tuple[float, ...]  # rad/s, angle moving toward centre


@dataclass(frozen=True)
class Profile:
    """A loaded, checked vehicle profile."""

    name: str
    description: str
    where: str  # the file it came from
    dbc: tuple[str, ...]  # resolved DBC file paths
    protection: str  # one line on what protects the frames (shown at start-up)
    capabilities: Capabilities
    frames: tuple[FrameSpec, ...]
    defaults: Mapping[str, Mapping[str, Mapping[str, Any]]]  # direction → source → attr → value
    steer_rate: SteerRateTable | None = None
    # report source → flags derived from a field: (flag, field, threshold) = |field| > threshold
    derived: Mapping[str, tuple[tuple[str, str, float], ...]] = dataclasses.field(
        default_factory=dict
    )
    # the DBCs a profile *file* names that were not beside it: leafgate's packaged ones are used
    dbc_from_package: tuple[str, ...] = ()

    def frame(self, name: str) -> FrameSpec:
        """The frame spec of a DBC message name.

        :raises KeyError: the profile has no such frame
        """
        for spec in self.frames:
            if spec.name == name:
                return spec
        raise KeyError(name)

    def frames_of(self, direction: Direction) -> tuple[FrameSpec, ...]:
        return tuple(f for f in self.frames if f.direction == direction)

    def report_period(self, source: str) -> float | None:
        """Period of the fastest report frame that refreshes ``source``, s (None: none does)."""
        periods = [f.period for f in self.frames_of("report") if source in f.refreshes]
        return min(periods) if periods else None

    @property
    def authenticated(self) -> bool:
        """Whether frames carry a MAC (``e2e: secoc``): encoding and verifying need a key."""
        return any(f.e2e == "secoc" for f in self.frames)

    @property
    def command_period(self) -> float:
        """The fastest command period, s: the gateway ticks at least this often."""
        return min(f.period for f in self.frames_of("command") if f.sources != ("system",))


# --- loading ----------------------------------------------------------------------------------


class _Reader:
    """Strict reading of one mapping of the file; every error names the file and key path."""

    def __init__(self, where: str) -> None:
        self.where = where

    def fail(self, key: str, text: str) -> ConfigError:
        return ConfigError(f"{self.where}: {key}: {text}")

    def mapping(self, value: Any, key: str) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a mapping, got {type(value).__name__}")
        return value

    def keys(self, value: Mapping[str, Any], key: str, allowed: tuple[str, ...]) -> None:
        for k in value:
            if k not in allowed:
                raise self.fail(f"{key}.{k}" if key else str(k), "unknown key")

    def number(self, value: Any, key: str, *, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, f"expected a number, got {value!r}")
        if not math.isfinite(value) or (positive and value <= 0):
            raise self.fail(key, f"expected a {'positive ' if positive else ''}number, got {value}")
        return float(value)

    def text(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value.strip():
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        return value


def _resolve_profile_path(name_or_path: str) -> tuple[str, Path | None]:
    """The YAML text's location: a packaged profile name, or a file path."""
    if name_or_path in PROFILE_NAMES:
        return f"leafgate/data/profiles/{name_or_path}.yaml", None
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        raise ConfigError(
            f"{name_or_path!r} is neither a packaged profile "
            f"({', '.join(PROFILE_NAMES)}) nor a .yaml file"
        )
    return str(path), path


@functools.cache
def _field_types(cls: type) -> Mapping[str, Any]:
    """The resolved field types of a message class (cached: every codec asks for them)."""
    return MappingProxyType(typing.get_type_hints(cls))


def load_profile(
    name_or_path: str = DEFAULT_PROFILE, vehicle: VehicleConfig | None = None
) -> Profile:
    """Load and check a profile (see :func:`_load_profile`); packaged profiles are loaded once
    per vehicle, so every codec of a process shares their compiled tables."""
    vehicle = vehicle or VehicleConfig()
    if name_or_path in PROFILE_NAMES:
        return _load_packaged(name_or_path, vehicle)
    return _load_profile(name_or_path, vehicle)


@functools.lru_cache(maxsize=16)
def _load_packaged(name: str, vehicle: VehicleConfig) -> Profile:
    return _load_profile(name, vehicle)


def _load_profile(name_or_path: str, vehicle: VehicleConfig) -> Profile:
    """Load and check a profile: a packaged name (``sze-hlc``) or a path to a YAML file.

    DBC files are found next to the profile file, then in the packaged ``dbc`` directory
    (:attr:`Profile.dbc_from_package` names those, for start-up and ``check-config`` to say).
    Every signal and message named must exist in the DBCs; every error names the file and key.

    :param vehicle: the vehicle numbers named scales refer to (``steering_ratio``)
    :raises ConfigError: the file is missing or invalid (one line naming file and key)
    """
    where, path = _resolve_profile_path(name_or_path)
    if path is None:
        resource = resources.files("leafgate") / "data" / "profiles" / f"{name_or_path}.yaml"
        raw = safe_load_yaml(resource.read_text(encoding="utf-8"))
        base_dir = None
    else:
        raw = load_yaml(path)
        base_dir = path.parent
    r = _Reader(where)
    doc = r.mapping(raw, "profile")
    r.keys(
        doc,
        "",
        (
            "name",
            "description",
            "dbc",
            "protection",
            "capabilities",
            "defaults",
            "derived",
            "commands",
            "reports",
            "safety",
        ),
    )
    name = r.text(doc.get("name"), "name")
    dbc_list = doc.get("dbc")
    if not isinstance(dbc_list, list) or not dbc_list:
        raise r.fail("dbc", "expected a list of DBC files")
    dbc = tuple(
        _resolve_dbc(r, str(item), base_dir, f"dbc[{i}]") for i, item in enumerate(dbc_list)
    )
    from_package = tuple(
        str(item)
        for item, found in zip(dbc_list, dbc, strict=True)
        if base_dir is not None and Path(found).parent != base_dir
    )
    caps_raw = r.mapping(doc.get("capabilities", {}), "capabilities")
    r.keys(caps_raw, "capabilities", tuple(f.name for f in dataclasses.fields(Capabilities)))
    caps_kwargs: dict[str, Any] = {}
    for key, value in caps_raw.items():
        if key == "long_modes":
            if not isinstance(value, list) or not all(
                v in ("acceleration", "speed") for v in value
            ):
                raise r.fail("capabilities.long_modes", "expected a list of acceleration, speed")
            caps_kwargs[key] = tuple(value)
        elif not isinstance(value, bool):
            raise r.fail(f"capabilities.{key}", f"expected true or false, got {value!r}")
        else:
            caps_kwargs[key] = value
    caps = Capabilities(**caps_kwargs)

    frames: list[FrameSpec] = []
    for direction, key in (("command", "commands"), ("report", "reports")):
        section = r.mapping(doc.get(key, {}), key)
        for frame_name, spec in section.items():
            frames.append(
                _frame(r, str(frame_name), spec, direction, f"{key}.{frame_name}", vehicle)  # type: ignore[arg-type]
            )
    if not any(f.direction == "command" for f in frames):
        raise r.fail("commands", "a profile needs at least one command frame")
    defaults = _defaults(r, doc.get("defaults", {}))
    derived = _derived(r, doc.get("derived", {}))
    steer_rate = _steer_rate(r, doc.get("safety"), vehicle)
    profile = Profile(
        name=name,
        description=str(doc.get("description", "")).strip(),
        where=where,
        dbc=dbc,
        protection=str(doc.get("protection", "")).strip(),
        capabilities=caps,
        frames=tuple(frames),
        defaults=defaults,
        steer_rate=steer_rate,
        derived=derived,
        dbc_from_package=from_package,
    )
    return profile


def _resolve_dbc(r: _Reader, item: str, base_dir: Path | None, key: str) -> str:
    candidates = []
    if base_dir is not None:
        candidates.append(base_dir / item)
    candidates.append(Path(str(resources.files("leafgate") / "data" / "dbc" / item)))
    for candidate in candidates:
        if candidate.is_file():
            return str(candidate)
    raise r.fail(key, f"DBC file {item!r} not found (looked in {', '.join(map(str, candidates))})")


def _frame(
    r: _Reader,
    name: str,
    spec_raw: Any,
    direction: Direction,
    key: str,
    vehicle: VehicleConfig,
) -> FrameSpec:
    spec = r.mapping(spec_raw, key)
    r.keys(
        spec,
        key,
        ("bus", "period", "e2e", "counter", "checksum", "signals", "refreshes", "on_change"),
    )
    bus = spec.get("bus", "dbw")
    if bus not in _BUSES:
        raise r.fail(f"{key}.bus", f"expected dbw or car, got {bus!r}")
    period = r.number(spec.get("period"), f"{key}.period", positive=True)
    e2e, e2e_params = _e2e(r, spec.get("e2e", "none"), f"{key}.e2e")
    on_change = spec.get("on_change", False)
    if not isinstance(on_change, bool):
        raise r.fail(f"{key}.on_change", f"expected true or false, got {on_change!r}")
    if on_change and e2e != "none":
        raise r.fail(f"{key}.on_change", "an event frame cannot carry a counter")
    defaults = E2E_SIGNALS[e2e]
    fixed = e2e in FIXED_PLACES  # the scheme's own signals, at fixed places (codec checks)
    counter = spec.get("counter", None if fixed else defaults[0])
    checksum = spec.get("checksum", None if fixed else defaults[1])
    sources = COMMAND_SOURCES if direction == "command" else REPORT_SOURCES
    signals_raw = r.mapping(spec.get("signals"), f"{key}.signals")
    signals = tuple(
        _signal(r, str(sig), value, sources, f"{key}.signals.{sig}", vehicle)
        for sig, value in signals_raw.items()
    )
    used: dict[str, None] = {}
    for sig in signals:
        for src, _ in ((sig.source, sig.attr), *sig.also):
            if src is not None:
                used.setdefault(src)
    refreshes_raw = spec.get("refreshes")
    if refreshes_raw is None:
        refreshes = tuple(used)
    else:
        if not isinstance(refreshes_raw, list) or not all(s in used for s in refreshes_raw):
            raise r.fail(
                f"{key}.refreshes",
                f"expected a list of the frame's sources ({', '.join(used)}), got {refreshes_raw!r}",
            )
        refreshes = tuple(refreshes_raw)
    return FrameSpec(
        name=name,
        direction=direction,
        bus=bus,
        period=period,
        e2e=e2e,
        counter_signal=counter,
        checksum_signal=checksum,
        signals=signals,
        refreshes=refreshes,
        e2e_params=e2e_params,
        on_change=on_change,
    )


def _e2e(r: _Reader, raw: Any, key: str) -> tuple[E2eScheme, Mapping[str, int]]:
    """``e2e: NAME`` or ``e2e: {scheme: NAME, PARAM: VALUE}``: the scheme and its parameters."""
    params_raw: Mapping[str, Any] = {}
    if isinstance(raw, Mapping):
        params_raw = {k: v for k, v in raw.items() if k != "scheme"}
        raw = raw.get("scheme")
    if raw not in E2E_SCHEMES:
        raise r.fail(key, f"expected one of {', '.join(E2E_SCHEMES)}, got {raw!r}")
    wanted = E2E_PARAMS.get(raw, ())
    r.keys(params_raw, key, ("scheme", *wanted))
    params: dict[str, int] = {}
    for name in wanted:
        value = params_raw.get(name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise r.fail(f"{key}.{name}", f"expected an integer, got {value!r}")
        params[name] = value
    return raw, params


def _field_ref(r: _Reader, text: Any, sources: Mapping[str, type], key: str) -> tuple[str, str]:
    if not isinstance(text, str) or text.count(".") != 1:
        raise r.fail(key, f"expected SOURCE.FIELD (e.g. steer.angle), got {text!r}")
    source, attr = text.split(".")
    cls = sources.get(source)
    if cls is None:
        raise r.fail(key, f"unknown source {source!r} (known: {', '.join(sources)})")
    if attr not in _field_types(cls):
        raise r.fail(key, f"{cls.__name__} has no field {attr!r}")
    return source, attr


def _signal(
    r: _Reader,
    signal: str,
    value: Any,
    sources: Mapping[str, type],
    key: str,
    vehicle: VehicleConfig,
) -> SignalMap:
    if isinstance(value, str):
        source, attr = _field_ref(r, value, sources, key)
        return SignalMap(signal, source, attr)
    spec = r.mapping(value, key)
    r.keys(spec, key, ("field", "also", "unit", "scale", "map", "unknown", "value"))
    if "value" in spec:
        if set(spec) != {"value"}:
            raise r.fail(key, "a constant (value:) takes no other keys")
        return SignalMap(signal, constant=r.number(spec["value"], f"{key}.value"))
    source, attr = _field_ref(r, spec.get("field"), sources, f"{key}.field")
    also_raw = spec.get("also", [])
    if not isinstance(also_raw, list):
        raise r.fail(f"{key}.also", "expected a list of SOURCE.FIELD")
    also = tuple(_field_ref(r, a, sources, f"{key}.also") for a in also_raw)
    unit = spec.get("unit", "")
    if unit not in UNITS:
        raise r.fail(
            f"{key}.unit", f"expected one of {', '.join(u for u in UNITS if u)}, got {unit!r}"
        )
    scale_raw = spec.get("scale", 1.0)
    if isinstance(scale_raw, str):
        if scale_raw not in _VEHICLE_SCALES:
            raise r.fail(
                f"{key}.scale",
                f"expected a number or {', '.join(_VEHICLE_SCALES)}, got {scale_raw!r}",
            )
        scale = float(getattr(vehicle, scale_raw))
    else:
        scale = r.number(scale_raw, f"{key}.scale")
        if scale == 0.0:
            raise r.fail(f"{key}.scale", "must not be 0")
    choices = None
    unknown = None
    field_type = _field_types(sources[source])[attr]
    if "map" in spec:
        if not (isinstance(field_type, type) and issubclass(field_type, enum.Enum)):
            raise r.fail(f"{key}.map", f"{attr} is not an enumeration")
        raw_map = r.mapping(spec["map"], f"{key}.map")
        built: dict[str, tuple[int, ...]] = {}
        for member, codes in raw_map.items():
            if member not in field_type.__members__:
                raise r.fail(
                    f"{key}.map.{member}",
                    f"not a {field_type.__name__} (known: {', '.join(field_type.__members__)})",
                )
            code_list = codes if isinstance(codes, list) else [codes]
            if not code_list or not all(
                isinstance(c, int) and not isinstance(c, bool) for c in code_list
            ):
                raise r.fail(
                    f"{key}.map.{member}", f"expected an integer code or a list, got {codes!r}"
                )
            built[member] = tuple(code_list)
        choices = built
        unknown = spec.get("unknown")
        if unknown is not None and unknown not in field_type.__members__:
            raise r.fail(f"{key}.unknown", f"not a {field_type.__name__}: {unknown!r}")
    return SignalMap(signal, source, attr, also, unit, scale, choices, unknown)


def _defaults(r: _Reader, raw: Any) -> Mapping[str, Mapping[str, Mapping[str, Any]]]:
    doc = r.mapping(raw, "defaults")
    r.keys(doc, "defaults", ("commands", "reports"))
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for key, direction, sources in (
        ("commands", "command", COMMAND_SOURCES),
        ("reports", "report", REPORT_SOURCES),
    ):
        section = r.mapping(doc.get(key, {}), f"defaults.{key}")
        out[direction] = {}
        for source, fields in section.items():
            cls = sources.get(source)
            if cls is None:
                raise r.fail(f"defaults.{key}.{source}", "unknown source")
            types = _field_types(cls)
            fields_map = r.mapping(fields, f"defaults.{key}.{source}")
            values: dict[str, Any] = {}
            for attr, value in fields_map.items():
                where = f"defaults.{key}.{source}.{attr}"
                if attr not in types:
                    raise r.fail(where, f"{cls.__name__} has no field {attr!r}")
                values[attr] = _coerce(r, types[attr], value, where)
            out[direction][source] = values
    return out


def _derived(r: _Reader, raw: Any) -> Mapping[str, tuple[tuple[str, str, float], ...]]:
    """``derived``: report flags a car does not send, from a field it does.

    ``steer: {override: {field: driver_torque, above: 1.0}}`` sets ``override`` whenever
    ``|driver_torque|`` exceeds 1.0 (as opendbc reads a ZE1 driver steering from 0x185).
    """
    doc = r.mapping(raw, "derived")
    out: dict[str, tuple[tuple[str, str, float], ...]] = {}
    for source, flags in doc.items():
        key = f"derived.{source}"
        cls = REPORT_SOURCES.get(source)
        if cls is None:
            raise r.fail(key, f"unknown report source (known: {', '.join(REPORT_SOURCES)})")
        types = _field_types(cls)
        rules = []
        for flag, rule in r.mapping(flags, key).items():
            where = f"{key}.{flag}"
            if types.get(flag) is not bool:
                raise r.fail(where, f"{cls.__name__}.{flag} is not a flag")
            spec = r.mapping(rule, where)
            r.keys(spec, where, ("field", "above"))
            field = str(spec.get("field"))
            if field not in types or types[field] is bool:
                raise r.fail(f"{where}.field", f"{cls.__name__} has no number field {field!r}")
            rules.append((str(flag), str(field), r.number(spec.get("above"), f"{where}.above")))
        out[str(source)] = tuple(rules)
    return out


def _coerce(r: _Reader, field_type: Any, value: Any, where: str) -> Any:
    if isinstance(field_type, type) and issubclass(field_type, enum.Enum):
        if not isinstance(value, str) or value not in field_type.__members__:
            raise r.fail(
                where, f"expected one of {', '.join(field_type.__members__)}, got {value!r}"
            )
        return field_type[value]
    if field_type is bool:
        if not isinstance(value, bool):
            raise r.fail(where, f"expected true or false, got {value!r}")
        return value
    if field_type is str:
        return r.text(value, where)
    if field_type is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise r.fail(where, f"expected an integer, got {value!r}")
        return value
    return r.number(value, where)


def _steer_rate(r: _Reader, raw: Any, vehicle: VehicleConfig) -> SteerRateTable | None:
    """``safety.steer_angle_rate``: a car's own angle-rate tables, at the steering wheel."""
    if raw is None:
        return None
    doc = r.mapping(raw, "safety")
    r.keys(doc, "safety", ("steer_angle_rate",))
    table = r.mapping(doc.get("steer_angle_rate"), "safety.steer_angle_rate")
    key = "safety.steer_angle_rate"
    r.keys(
        table, key, ("speeds", "windup_deg_per_frame", "unwind_deg_per_frame", "frame_period", "at")
    )
    lists = {}
    for name in ("speeds", "windup_deg_per_frame", "unwind_deg_per_frame"):
        values = table.get(name)
        if not isinstance(values, list) or not values:
            raise r.fail(f"{key}.{name}", "expected a non-empty list of numbers")
        lists[name] = tuple(r.number(v, f"{key}.{name}") for v in values)
    n = len(lists["speeds"])
    if any(len(v) != n for v in lists.values()):
        raise r.fail(key, "speeds and the two tables must have the same length")
    if list(lists["speeds"]) != sorted(lists["speeds"]):
        raise r.fail(f"{key}.speeds", "breakpoints must increase")
    frame_period = r.number(table.get("frame_period"), f"{key}.frame_period", positive=True)
    at = table.get("at", "steering_wheel")
    if at not in ("steering_wheel", "road_wheel"):
        raise r.fail(f"{key}.at", f"expected steering_wheel or road_wheel, got {at!r}")
    # deg per frame at the steering wheel → rad/s at the road wheel
    k = DEG / frame_period / (vehicle.steering_ratio if at == "steering_wheel" else 1.0)
    return SteerRateTable(
        speeds=lists["speeds"],
        windup=tuple(v * k for v in lists["windup_deg_per_frame"]),
        unwind=tuple(v * k for v in lists["unwind_deg_per_frame"]),
    )


def zero_of(field_type: Any) -> Any:
    """The value a field no frame and no default sets takes (0, False, the 0 member)."""
    if isinstance(field_type, type) and issubclass(field_type, enum.Enum):
        return field_type(0)
    if field_type is bool:
        return False
    if field_type is str:
        return ""
    if field_type is int:
        return 0
    return 0.0


def base_values(profile: Profile, direction: Direction, source: str) -> dict[str, Any]:
    """Every field of a source before any frame set it: profile defaults, else zero values."""
    cls = (COMMAND_SOURCES if direction == "command" else REPORT_SOURCES)[source]
    values = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            values[f.name] = f.default
        else:
            values[f.name] = zero_of(_field_types(cls)[f.name])
    if cls is WheelSpeeds:
        values["axle"] = "front" if source == "wheels_front" else "rear"
    values.update(profile.defaults.get(direction, {}).get(source, {}))
    return values
