"""One set of names for what the simulators take on the command line.

``leafgate sim`` (one process, simulated clock) and ``leafgate sim-ecu`` (the simulated ECU as a
process) grew their fault names apart; the same fault now has the same name in both, and the
other spelling is an alias either of them accepts. ``--help`` of both lists the same table.
"""

from __future__ import annotations

from collections.abc import Iterable

#: The same fault under its ``sim`` name and its ``sim-ecu`` name.
SAME_INJECTION: tuple[tuple[str, str], ...] = (
    ("localization-dropout", "localization-stop"),
    ("position-jump", "localization-jump"),
    ("override", "override-torque"),
)
TO_SIM = {ecu: sim for sim, ecu in SAME_INJECTION}
TO_SIM_ECU = {sim: ecu for sim, ecu in SAME_INJECTION}


def injection_names(kinds: Iterable[str], aliases: dict[str, str]) -> str:
    """``a, b (= c), …``: the kinds one command runs, each with its other spelling."""
    other = {v: k for k, v in aliases.items()}
    return ", ".join(f"{k} (= {other[k]})" if k in other else k for k in sorted(kinds))


def only_here(kinds: Iterable[str], other: Iterable[str], aliases: dict[str, str]) -> str:
    """The kinds of ``kinds`` the other command does not run, under either spelling (``aliases``
    maps the other command's names to these), comma-separated; ``-`` when there are none."""
    theirs = {aliases.get(k, k) for k in other}
    return ", ".join(sorted(set(kinds) - theirs)) or "-"
