"""YAML configuration → typed, frozen dataclasses.

Each part of leafgate owns its section's dataclass (``ControllerConfig`` in
``leafgate.config.control``, ``CanConfig`` in ``leafgate.can.bus`` …); this module composes them
into :class:`LeafgateConfig` and loads YAML into it strictly: an unknown key, a value of the
wrong type or a value outside its range is a :class:`~leafgate.errors.ConfigError` naming the
file and the dotted key.

Values are SI. Angles may be written in degrees at this edge by suffixing the key with
``_deg`` (``max_steer_angle_deg: 31``); likewise ``_degps`` (deg/s → rad/s) and ``_kmh``
(km/h → m/s). The dataclass field is always the SI one without the suffix.

>>> cfg = from_mapping(VehicleConfig, {"max_steer_angle_deg": 30.0}, "example.yaml")
>>> round(cfg.max_steer_angle, 4)
0.5236
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

from leafgate.errors import ConfigError

T = TypeVar("T")

_PLAIN_KEY = re.compile(r"[\w\-]+")  # keys shown as they are in messages; others as repr
# A number YAML 1.1 leaves a string: `1e-3` (no dot before the exponent), `+1e9`. Only digits,
# sign, dot and exponent: "nan", "inf" and "1_000" stay strings.
_NUMBER_TEXT = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")

_UNIT_SUFFIXES: dict[str, float] = {
    "_deg": math.pi / 180.0,  # deg → rad
    "_degps": math.pi / 180.0,  # deg/s → rad/s
    "_kmh": 1.0 / 3.6,  # km/h → m/s
}


@dataclasses.dataclass(frozen=True)
class VehicleConfig:
    """Leaf numbers (research vehicle, public sources)."""

    wheelbase: float = 2.70  # m
    max_steer_angle: float = math.radians(31.0)  # rad, road-wheel angle limit
    steering_ratio: float = 18.25  # steering-wheel angle / road-wheel angle
    max_accel: float = 3.0  # m/s²
    min_accel: float = -6.0  # m/s²
    mass: float = 1580.0  # kg, Leaf AZE0 with two occupants
    yaw_inertia: float = 2400.0  # kg·m²
    cg_to_front: float = 1.20  # m, centre of gravity to front axle
    cornering_stiffness_front: float = 60000.0  # N/rad, per axle
    cornering_stiffness_rear: float = 70000.0  # N/rad, per axle
    # The CAN interface: a packaged profile (leafgate-dbw, leafgate-dbw-auth, sze-hlc,
    # leaf-ze1-lkas) or the path of a profile YAML file (leafgate.can.profile).
    profile: str = "leafgate-dbw"

    def __post_init__(self) -> None:
        _positive(self, "wheelbase", "max_steer_angle", "steering_ratio", "max_accel", "mass")
        if self.min_accel >= 0.0:
            raise ValueError("min_accel must be negative")
        if not 0.0 < self.max_steer_angle < math.pi / 2:
            raise ValueError("max_steer_angle must lie in (0, 90°)")
        if not 0.0 < self.cg_to_front < self.wheelbase:
            raise ValueError("cg_to_front must lie inside the wheelbase")


def _positive(obj: object, *names: str) -> None:
    """Raise ValueError naming the first field that is not a finite positive number."""
    for name in names:
        value = getattr(obj, name)
        # an int is finite however large (math.isfinite would overflow converting it)
        if not (value > 0 and (isinstance(value, int) or math.isfinite(value))):
            raise ValueError(f"{name} must be a positive number, got {_show(value)}")


def positive(obj: object, *names: str) -> None:
    """Check, in a section's ``__post_init__``, that the named fields are finite and > 0."""
    _positive(obj, *names)


def from_mapping(cls: type[T], data: Any, source: str, where: str = "") -> T:
    """Build the dataclass ``cls`` from a mapping, strictly.

    :param cls: a (frozen) dataclass type whose fields have type annotations
    :param data: the parsed YAML mapping (or None for all defaults)
    :param source: file name used in error messages
    :param where: dotted key prefix of this section, for error messages
    :raises ConfigError: on unknown keys, wrong types, or values the dataclass rejects
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: {where or '<top level>'}: expected a mapping, got {_show(data)}"
        )
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for raw_key, raw_value in data.items():
        key = str(raw_key)
        name, scale = key, None
        if name not in fields:
            for suffix, factor in _UNIT_SUFFIXES.items():
                if key.endswith(suffix) and key[: -len(suffix)] in fields:
                    name, scale = key[: -len(suffix)], factor
                    break
        shown = key if _PLAIN_KEY.fullmatch(key) else repr(key)  # "" or "a: b" stay readable
        dotted = f"{where}.{shown}" if where else shown
        if name not in fields or not fields[name].init:
            known = ", ".join(sorted(f for f in fields if fields[f].init))
            raise ConfigError(f"{source}: {dotted}: unknown key (known here: {known})")
        if name in kwargs:
            raise ConfigError(f"{source}: {dotted}: given twice (with and without a unit suffix)")
        value = _convert(hints[name], raw_value, source, dotted)
        if scale is not None:
            value = _scale(value, scale, source, dotted)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(f"{source}: {where or '<top level>'}: {exc}") from None


def _scale(value: Any, factor: float, source: str, dotted: str) -> Any:
    if isinstance(value, float):
        return value * factor
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return tuple(v * factor for v in value)
    raise ConfigError(f"{source}: {dotted}: a unit suffix needs a number or a list of numbers")


def _int_as_float(value: int) -> float:
    """``value`` as a float; inf when it is too large for one (YAML integers are unbounded)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _convert(tp: Any, value: Any, source: str, dotted: str) -> Any:
    origin = get_origin(tp)
    args = get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        errors = []
        for option in non_none:
            try:
                return _convert(option, value, source, dotted)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(
            errors[0] if len(errors) == 1 else f"{source}: {dotted}: bad value {_show(value)}"
        )
    if origin is Literal:
        if value in args:
            return value
        allowed = ", ".join(repr(a) for a in args)
        raise ConfigError(f"{source}: {dotted}: {_show(value)} is not one of {allowed}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{source}: {dotted}: expected true or false, got {_show(value)}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{source}: {dotted}: expected an integer, got {_show(value)}")
    if tp is float:
        if isinstance(value, str) and _NUMBER_TEXT.fullmatch(value.strip()):
            value = float(value)  # `latency: 1e-3`: a number YAML 1.1 reads as a string
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value if isinstance(value, float) else _int_as_float(value)):
                raise ConfigError(
                    f"{source}: {dotted}: expected a finite number, got {_show(value)}"
                )
            return float(value)
        raise ConfigError(f"{source}: {dotted}: expected a number, got {_show(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{source}: {dotted}: expected a string, got {_show(value)}")
    if tp is Any:
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {dotted}: expected a list, got {_show(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(
                _convert(args[0], v, source, f"{dotted}[{i}]") for i, v in enumerate(value)
            )
        if len(value) != len(args):
            raise ConfigError(
                f"{source}: {dotted}: expected a list of {len(args)}, got {len(value)}"
            )
        return tuple(
            _convert(a, v, source, f"{dotted}[{i}]")
            for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {dotted}: expected a mapping, got {_show(value)}")
        key_t, val_t = args if args else (str, Any)
        return {
            _convert(key_t, k, source, f"{dotted}.{k}"): _convert(val_t, v, source, f"{dotted}.{k}")
            for k, v in value.items()
        }
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return from_mapping(tp, value, source, dotted)
    raise ConfigError(f"{source}: {dotted}: unsupported field type {tp!r}")  # a bug, not user input


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file, turning I/O and syntax errors into one-line ConfigErrors."""
    path = Path(path)
    text = read_text(path, ConfigError)
    try:
        return safe_load_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: {yaml_error_text(exc, text)}") from None


# --- dotted-key overrides (`leafgate sim --set`, `leafgate replay rerun --set`) ---------------


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings (values in YAML: ``10``, ``true``, ``[1, 2]``) → a mapping.

    :raises ConfigError: an item without ``=``
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(
                f"--set {item!r}: expected KEY=VALUE, e.g. controller.mpc.weight_lateral=10"
            )
        try:
            out[key.strip()] = safe_load_yaml(text)
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML") from None
    return out


def apply_overrides(data: dict[str, Any], overrides: Mapping[str, Any], source: str) -> None:
    """Set dotted keys (``controller.mpc.weight_lateral``) in a config mapping, in place.

    A key with a unit suffix (``gateway.safety.max_steer_angle_deg``) replaces its SI twin.

    :raises ConfigError: when a dotted key runs through a value that is not a mapping
    """
    for dotted, value in overrides.items():
        parts = dotted.split(".")
        node = data
        for i, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                where = ".".join(parts[: i + 1])
                raise ConfigError(f"{source}: {dotted}: {where} is not a section")
            node = child
        key = parts[-1]
        for suffix in _UNIT_SUFFIXES:
            if key.endswith(suffix):
                node.pop(key[: -len(suffix)], None)
                break
        node[key] = value


# --- reading YAML and text files safely (shared with the trajectory loader) ---------------------

MAX_YAML_DEPTH = 100  # nesting levels; deeper input is refused before PyYAML recurses that deep


class _SafeLoader(yaml.SafeLoader):
    """PyYAML's safe loader with every failure a ``MarkedYAMLError`` carrying a line.

    PyYAML lets some bad scalars out as plain ``ValueError``/``AttributeError`` (``!!int x``,
    a timestamp ``2001-13-45``) and recurses once per nesting level (``[[[[…`` ends in
    ``RecursionError``); here both become YAML errors at the node where they happen.
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def fetch_flow_collection_start(self, token_class: Any) -> None:
        # Refused while scanning: PyYAML's scanner is quadratic in the flow nesting depth
        # (seconds for a 100 kB line of "["), long before the composer would see the depth.
        if self.flow_level >= MAX_YAML_DEPTH:
            raise yaml.scanner.ScannerError(
                None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", self.get_mark()
            )
        super().fetch_flow_collection_start(token_class)

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark
                raise yaml.composer.ComposerError(
                    None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", mark
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        # A key given twice is refused (PyYAML keeps the last one silently: a second
        # `controller:` section would replace the first without a word). Keys a merge (`<<`)
        # brings in may be overridden, as YAML intends; only the mapping's own keys count.
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:  # an unhashable key: PyYAML's own error follows
                    continue
                if first is not key_node:
                    raise yaml.constructor.ConstructorError(
                        None,
                        None,
                        f"duplicate key {_show(key)} (first at line {first.start_mark.line + 1})",
                        key_node.start_mark,
                    )
        return super().construct_mapping(node, deep)

    def construct_object(self, node: Any, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except yaml.YAMLError:
            raise
        except (ValueError, TypeError, AttributeError, OverflowError) as exc:
            raise yaml.constructor.ConstructorError(
                None, None, f"bad {node.tag} value {_show(node.value)}: {exc}", node.start_mark
            ) from None


def safe_load_yaml(text: str) -> Any:
    """``yaml.safe_load`` that raises only ``yaml.YAMLError`` (see :func:`yaml_error_text`)."""
    loader = _SafeLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def yaml_error_text(exc: yaml.YAMLError, text: str) -> str:
    """``"invalid YAML at line L, column C: problem"`` for an error of :func:`safe_load_yaml`."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    if mark is not None:
        line, column = mark.line + 1, mark.column + 1
    elif isinstance(exc, yaml.reader.ReaderError):  # a character YAML does not allow
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - (text.rfind("\n", 0, exc.position) + 1) + 1
    else:
        return f"invalid YAML: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
    if isinstance(exc, yaml.reader.ReaderError):
        code = exc.character if isinstance(exc.character, int) else ord(exc.character)
        problem = f"character U+{code:04X} is not allowed"
    else:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return f"invalid YAML at line {line}, column {column}: {problem}"


def read_text(path: Path, error: type[Exception]) -> str:
    """A user's file as text (UTF-8, a leading BOM dropped).

    :raises error: one line naming the file: missing, unreadable, or not UTF-8 (and where)
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return utf8_text(data)
    except ValueError as exc:
        raise error(f"{path}: {exc}") from None


def utf8_text(data: bytes) -> str:
    """Decode a file's bytes as UTF-8 (a leading BOM is dropped).

    :raises ValueError: ``"not UTF-8 at line L, column C (byte 0xNN)"``, counted in bytes
    """
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ValueError(
            f"not UTF-8 at line {line}, column {column} (byte 0x{data[exc.start]:02x})"
        ) from None


# The top-level config is assembled in leafgate.settings to keep this module free of imports
# from the parts (which import from here).
