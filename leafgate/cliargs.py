"""Command-line options that several commands share (``leafgate`` and ``leafgate batch``).

One definition each, so the same option has the same name, type, default and help everywhere.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

PROFILE_HELP = (
    "vehicle profile NAME (leafgate-dbw, leafgate-dbw-auth, sze-hlc, leaf-ze1-lkas) or FILE; "
    "default: the "
    "--config's, or the one a session recorded"
)


def _number(text: str, kind: type[int] | type[float]) -> float:
    """``text`` as a finite ``kind``; an ``ArgumentTypeError`` argparse reports with the option."""
    try:
        value = kind(text)
    except ValueError:
        what = "a whole number" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"must be {what}, not {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, not {text!r}")
    return value


def _bounded(
    kind: type[int] | type[float], low: float, strict: bool, what: str, high: float = math.inf
) -> Any:
    """An argparse type: a finite ``kind`` above ``low`` (``strict``) or at least ``low``, and
    at most ``high``; ``what`` names what it must be in the error, e.g.
    ``"a number of seconds > 0"``."""

    def check(text: str) -> float:
        value = _number(text, kind)
        if value < low or (strict and value == low) or value > high:
            raise argparse.ArgumentTypeError(f"must be {what}, not {text!r}")
        return kind(value)

    return check


#: argparse types, one object each (an option shared by commands has the same type everywhere)
positive_seconds = _bounded(float, 0.0, True, "a number of seconds > 0")  # timeout, period
non_negative_seconds = _bounded(float, 0.0, False, "a number of seconds >= 0")  # 0: no wait
positive_number = _bounded(float, 0.0, True, "a number > 0")  # metres, a factor
non_negative_number = _bounded(float, 0.0, False, "a number >= 0")
positive_int = _bounded(int, 1, False, "a whole number >= 1")  # worker processes
non_negative_int = _bounded(int, 0, False, "a whole number >= 0")  # a count, 0: no limit


def whole_number_between(low: int, high: int, what: str) -> Any:
    """An argparse type: a whole number ``low``–``high``, ``what`` it is named in the error."""
    return _bounded(int, low, False, f"{what} {low}-{high}", high=high)


def add_overrides(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable): dotted config overrides, for ``parse_overrides``."""
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. controller.mpc.weight_lateral=10 (repeatable)",
    )


def add_profile_options(parser: argparse.ArgumentParser, config_help: str) -> None:
    """``--config FILE`` and ``--profile NAME|FILE``: what a tool that reads frames decodes with."""
    parser.add_argument("--config", help=config_help)
    parser.add_argument("--profile", metavar="NAME|FILE", help=PROFILE_HELP)
