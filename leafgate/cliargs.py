"""Command-line options that several commands share (``leafgate`` and ``leafgate batch``).

One definition each, so the same option has the same name, type, default and help everywhere.
"""

from __future__ import annotations

import argparse

PROFILE_HELP = (
    "vehicle profile NAME (leafgate-dbw, leafgate-dbw-auth, sze-hlc, leaf-ze1-lkas) or FILE; "
    "default: the "
    "--config's, or the one a session recorded"
)


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


def add_gap_periods(parser: argparse.ArgumentParser) -> None:
    """``--gap-periods N`` of ``replay check`` and ``batch check``."""
    from leafgate.replay.check import DEFAULT_GAP_PERIODS

    parser.add_argument(
        "--gap-periods",
        type=float,
        default=DEFAULT_GAP_PERIODS,
        help=f"a gap is this many periods of silence (default {DEFAULT_GAP_PERIODS:g})",
    )
