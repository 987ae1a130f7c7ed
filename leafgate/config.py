"""YAML configuration → typed, frozen dataclasses.

Each part of leafgate owns its section's dataclass (``ControllerConfig`` in
``leafgate.control.config``, ``CanConfig`` in ``leafgate.can.bus`` …); this module composes them
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
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

from leafgate.errors import ConfigError

T = TypeVar("T")

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
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")


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
        dotted = f"{where}.{key}" if where else key
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
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{source}: {where or '<top level>'}: {exc}") from None


def _scale(value: Any, factor: float, source: str, dotted: str) -> Any:
    if isinstance(value, float):
        return value * factor
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return tuple(v * factor for v in value)
    raise ConfigError(f"{source}: {dotted}: a unit suffix needs a number or a list of numbers")


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
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
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
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: invalid YAML{at}: {problem}") from None


# The top-level config is assembled in leafgate.settings to keep this module free of imports
# from the parts (which import from here).
