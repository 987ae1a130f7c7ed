"""leafgate's one JSON convention, for every JSON it writes: Zenoh JSON payloads, diagnostics,
MCAP sessions and reports.

- enums by **name** (``"ENGAGED"``, ``"R"``); read back by name, or by value for files written
  before this convention;
- floats as JSON numbers, exactly (Python's shortest repr round-trips every finite float);
  **NaN and ±inf as null** (JSON has neither), read back as NaN; the strings ``"nan"``,
  ``"inf"``, ``"-inf"`` of older session files are still read;
- numpy scalars and arrays as numbers and lists, dataclasses and named tuples as objects,
  tuples and sets as lists; anything else as its ``str``, so writing never fails.

:func:`json_schema` gives the JSON Schema of a dataclass in the same convention (MCAP channels
carry it, so Foxglove shows the field names).

>>> import enum, math
>>> class Mode(enum.IntEnum):
...     OFF = 0
...     ON = 1
>>> to_json({"mode": Mode.ON, "speed": math.nan, "x": (1.5, 2)})
{'mode': 'ON', 'speed': None, 'x': [1.5, 2]}
>>> (float_from_json(None), enum_from_json(Mode, "ON"), enum_from_json(Mode, 0))
(nan, <Mode.ON: 1>, <Mode.OFF: 0>)
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

import numpy as np

E = TypeVar("E", bound=enum.Enum)

_LEGACY_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def to_json(value: Any) -> Any:
    """``value`` as JSON-able Python data in leafgate's convention (see the module)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [to_json(v) for v in value.tolist()]
    if isinstance(value, Mapping):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # a NamedTuple
        return {k: to_json(getattr(value, k)) for k in value._fields}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_json(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return str(value)


def dumps(value: Any, *, compact: bool = True) -> str:
    """JSON text of ``value`` in the convention (compact separators unless told otherwise)."""
    separators = (",", ":") if compact else None
    return json.dumps(to_json(value), separators=separators, allow_nan=False)


def float_from_json(value: Any) -> float:
    """A float written by :func:`to_json` (null → NaN; legacy "nan"/"inf"/"-inf" accepted).

    :raises ValueError: when ``value`` is not a number, null or a legacy string
    """
    if value is None:
        return math.nan
    if isinstance(value, str):
        if value in _LEGACY_FLOATS:
            return _LEGACY_FLOATS[value]
        raise ValueError(f"expected a number or null, got {value!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"expected a number or null, got {value!r}")
    return float(value)


def enum_from_json(kind: type[E], value: Any) -> E:
    """An enum written by :func:`to_json` (by name; by value in older files).

    :raises ValueError: when ``value`` names no member of ``kind``
    """
    if isinstance(value, str) and value in kind.__members__:
        return kind[value]
    try:
        return kind(value)
    except ValueError:
        names = ", ".join(kind.__members__)
        raise ValueError(f"{value!r} is not a {kind.__name__} ({names})") from None


# --- JSON Schema ---------------------------------------------------------------------------------

NUMBER: dict[str, Any] = {"type": ["number", "null"]}  # null: NaN or ±inf


def json_schema(tp: Any, title: str | None = None) -> dict[str, Any]:
    """The JSON Schema of values of type ``tp`` (a dataclass, enum, builtin, Optional, tuple)
    as :func:`to_json` writes them."""
    schema = _schema(tp)
    if title is not None:
        schema = {"title": title, **schema}
    return schema


def _schema(tp: Any) -> dict[str, Any]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        inner = _schema(args[0]) if len(args) == 1 else {"anyOf": [_schema(a) for a in args]}
        return {"anyOf": [inner, {"type": "null"}]}
    if origin in (tuple, list, set, frozenset) or tp in (tuple, list):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return {"type": "array", "items": _schema(args[0])} if args else {"type": "array"}
    if origin in (dict, Mapping) or tp is dict:
        return {"type": "object"}
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return {"type": "string", "enum": list(tp.__members__)}
    if tp is bool:
        return {"type": "boolean"}
    if tp is int:
        return {"type": "integer"}
    if tp is float:
        return dict(NUMBER)
    if tp is str:
        return {"type": "string"}
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        hints = typing.get_type_hints(tp)
        return {
            "type": "object",
            "properties": {
                f.name: _schema(hints[f.name]) for f in dataclasses.fields(tp) if f.init
            },
        }
    return {}
