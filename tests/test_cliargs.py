"""Options several commands share are one definition (leafgate/cliargs.py): the same name,
type, default, metavar and help in ``leafgate …`` and ``leafgate batch …``."""

from __future__ import annotations

import argparse

import pytest

from leafgate.cli import build_parser


def _command(parser: argparse.ArgumentParser, *path: str) -> argparse.ArgumentParser:
    for name in path:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return parser


def _option(parser: argparse.ArgumentParser, flag: str) -> tuple[object, ...]:
    action = next(a for a in parser._actions if flag in a.option_strings)
    return (
        action.dest,
        action.type,
        repr(action.default),
        action.metavar,
        action.help,
        action.nargs,
    )


@pytest.mark.parametrize(
    ("flag", "commands"),
    [
        ("--set", [("sim",), ("replay", "rerun"), ("batch", "rerun")]),
        ("--profile", [("replay", "check"), ("replay", "plot"), ("decode",), ("batch", "check")]),
        ("--gap-periods", [("replay", "check"), ("batch", "check")]),
    ],
)
def test_a_shared_option_is_the_same_in_every_command(
    flag: str, commands: list[tuple[str, ...]]
) -> None:
    parser = build_parser()
    seen = {path: _option(_command(parser, *path), flag) for path in commands}
    assert len(set(seen.values())) == 1, seen


def test_gap_periods_default_is_the_checkers() -> None:
    from leafgate.replay.check import DEFAULT_GAP_PERIODS

    args = build_parser().parse_args(["batch", "check", "logs/"])
    assert args.gap_periods == DEFAULT_GAP_PERIODS
