"""``leafgate replay rerun SESSION.mcap``: re-run a recorded drive through ``Gateway.step``.

The session holds, per tick, the :class:`~leafgate.gateway.core.GatewayInputs` exactly as the
gateway got them, the commands it sent, and the configuration it ran with. The re-run rebuilds
the controller and the gateway from that configuration (with optional dotted-key overrides,
``controller.mpc.weight_lateral=10``), feeds every recorded tick on the recorded clock, and
compares the commands per signal: largest and RMS difference, how many ticks differ and the
first time they do. The gateway and the controllers are deterministic, so identical code and
configuration reproduce every command bit for bit; a changed weight shows where the drive
would have gone differently (open loop: the recorded vehicle does not react to the new
commands, so differences after the first divergence are indicative only).

Only the ``vehicle``, ``controller`` and ``gateway`` sections build what a re-run runs (the
vehicle profile, the controller, the gateway and its longitudinal mode); the other sections
(``can``, ``zenoh``, ``sim``, ``recording``) concern the bus, the middleware, the simulator and
the recorder, whose effects are already in the recorded inputs. An override of such a key is
refused (:func:`check_rerun_overrides`): an IDENTICAL verdict would say nothing about it.

A session that resumes another after a recording failure (``session-….2.mcap``, metadata
``resumes``) starts mid-drive: its first tick's gateway state, controller memory and previous
commands are not in it, so a fresh gateway would differ from its first engaged tick on, a
divergence of the recording, not of the code. It is refused (an error naming the session it
resumes), never reported as IDENTICAL or DIVERGED; the session it resumes re-runs up to its
cut.

Ticks missing from the session — the recorder dropped them when its queue overflowed (its
``/leafgate/lost`` records say so), or lost them otherwise: the ticks' numbers (``seq``) jump —
end the re-run there. The gateway's state after the gap (the controller's memory, the rate
limits' last commands, the watchdogs' clocks) is not in the recording, so no fresh gateway can
take up the drive after it: the ticks before the gap are compared, those after are counted and
not re-run, and the verdict is INCOMPLETE (exit 1) with where the gap is (the ticks' numbers and
times), never IDENTICAL over a span it did not check; DIVERGED before the gap stays DIVERGED,
with the gap named. Zenoh inputs the recorder dropped do not stop a re-run (the ticks hold the
inputs the gateway used); they are named. A session recorded before ticks were numbered is
re-run whole, and its IDENTICAL says that its continuity was not checked.

Exit status: 0 when every command is identical, 1 when any signal diverges, ticks are missing
or the session cannot be re-run, 2 for an override a re-run cannot honour (or a configuration
that does not load).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TextIO

from leafgate.config import parse_overrides
from leafgate.control import make_controller
from leafgate.errors import ReplayError, UsageError
from leafgate.gateway.core import Gateway
from leafgate.messages import Commands, GatewayState, Trajectory
from leafgate.record.session import (
    META_SESSION,
    TOPIC_LOST,
    TOPIC_TICK,
    TOPIC_TRAJECTORY,
    LostItems,
    SessionReader,
    TickContinuity,
    TickGap,
    decode_commands,
    decode_inputs,
    decode_trajectory,
    encode_commands,
    gateway_mode,
)
from leafgate.replay.report import write_report
from leafgate.text import plural

__all__ = [
    "RERUN_SECTIONS",
    "RerunReport",
    "SignalDiff",
    "check_rerun_overrides",
    "main_rerun",
    "parse_overrides",
    "rerun_session",
]

#: The configuration sections a re-run builds from (:func:`rerun_session`): the vehicle (its
#: profile adjusts the gateway), the controller (and the longitudinal mode of its MPC), the
#: gateway. Everything else acts before the recorded inputs and cannot change a re-run.
RERUN_SECTIONS: Final = ("vehicle", "controller", "gateway")


def check_rerun_overrides(overrides: Mapping[str, Any] | None) -> None:
    """Refuse overrides of keys a re-run does not use.

    :raises ConfigError: naming the first such key and the sections a re-run uses
    """
    for key in overrides or {}:
        section = key.split(".", 1)[0]
        if section not in RERUN_SECTIONS:
            raise UsageError(
                f"--set {key}: a re-run feeds the recorded gateway inputs to a controller and "
                f"gateway built from the {', '.join(RERUN_SECTIONS)} sections only; "
                f"{section}.* cannot change its commands (override one of those sections)"
            )


#: The compared signals, in report order.
SIGNALS: Final = (
    "steer.angle",
    "steer.rate_limit",
    "steer.enable",
    "steer.clear_override",
    "long.mode",
    "long.accel",
    "long.speed",
    "long.gear",
    "long.enable",
    "long.clear_override",
    "system.sent",
    "system.state",
    "system.clear_faults",
    "state",
)


def command_signals(commands: Commands, state: GatewayState | str) -> tuple[float, ...]:
    """The compared signals of one tick as numbers (flags 0/1, enums by code, NaN if absent)."""
    s, lc, sys_cmd = commands.steer, commands.long, commands.system
    state_code = GatewayState[state] if isinstance(state, str) else state
    return (
        s.angle,
        s.rate_limit,
        float(s.enable),
        float(s.clear_override),
        float(lc.mode),
        lc.accel,
        lc.speed,
        float(lc.gear),
        float(lc.enable),
        float(lc.clear_override),
        float(sys_cmd is not None),
        math.nan if sys_cmd is None else float(sys_cmd.state),
        math.nan if sys_cmd is None else float(sys_cmd.clear_faults),
        float(state_code),
    )


@dataclass
class SignalDiff:
    """Recorded vs re-run values of one signal over the session."""

    name: str
    max_abs: float = 0.0  # in the signal's unit (rad, m/s², m/s, code)
    sum_sq: float = 0.0
    ticks: int = 0  # ticks compared
    differing: int = 0  # ticks whose values are not identical
    first_divergence: float | None = None  # s, gateway clock of the first differing tick

    @property
    def rms(self) -> float:
        return math.sqrt(self.sum_sq / self.ticks) if self.ticks else 0.0

    def add(self, t: float, recorded: float, rerun: float) -> None:
        self.ticks += 1
        if recorded == rerun or (math.isnan(recorded) and math.isnan(rerun)):
            return
        diff = abs(recorded - rerun)
        if math.isnan(diff):  # present on one side only
            diff = math.inf
        self.differing += 1
        self.max_abs = max(self.max_abs, diff)
        self.sum_sq += diff * diff if math.isfinite(diff) else 0.0
        if self.first_divergence is None:
            self.first_divergence = t

    def to_dict(self) -> dict[str, Any]:
        return {
            "signal": self.name,
            "max_abs_diff": self.max_abs if math.isfinite(self.max_abs) else None,
            "rms_diff": self.rms,
            "differing_ticks": self.differing,
            "first_divergence_s": self.first_divergence,
        }


@dataclass
class RerunReport:
    """The comparison of a re-run with the recording."""

    path: str
    overrides: dict[str, Any] = field(default_factory=dict)
    ticks: int = 0
    signals: list[SignalDiff] = field(default_factory=lambda: [SignalDiff(n) for n in SIGNALS])
    truncated: bool = False  # the session ended before its footer (a crash): re-run up to there
    gap: TickGap | None = None  # the first ticks missing: the re-run ended there
    not_rerun: int = 0  # ticks after the gap, not re-run
    lost_inputs: list[LostItems] = field(default_factory=list)  # Zenoh inputs the recorder lost
    numbered: bool = True  # the session's ticks are numbered: their continuity was checked

    @property
    def diverged(self) -> bool:
        """A command of the ticks re-run differs."""
        return any(s.differing for s in self.signals)

    @property
    def identical(self) -> bool:
        """Every command reproduced bit for bit, and no tick of the session left out."""
        return not self.diverged and self.gap is None

    @property
    def first_divergence(self) -> float | None:
        times = [s.first_divergence for s in self.signals if s.first_divergence is not None]
        return min(times) if times else None

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "overrides": self.overrides,
            "ticks": self.ticks,
            "identical": self.identical,
            "first_divergence_s": self.first_divergence,
            "truncated": self.truncated,
            "ticks_numbered": self.numbered,
            "gap": None
            if self.gap is None
            else {
                "missing_ticks": self.gap.missing,
                "seq": self.gap.seq,
                "before_s": self.gap.before,
                "after_s": self.gap.after,
                "dropped_by_recorder": self.gap.dropped,
                "text": self.gap.text(),
            },
            "ticks_not_rerun": self.not_rerun,
            "lost_inputs": [
                {
                    "count": lost.count,
                    "first_s": lost.first,
                    "last_s": lost.last,
                    "topics": dict(lost.topics),
                }
                for lost in self.lost_inputs
            ],
            "signals": [s.to_dict() for s in self.signals],
        }

    def format(self) -> list[str]:
        lines = [
            f"{self.path}: {plural(self.ticks, 'tick')} re-run"
            + (
                f" with {', '.join(f'{k}={v}' for k, v in self.overrides.items())}"
                if self.overrides
                else ""
            )
            + (" (truncated session)" if self.truncated else "")
            + (f"; not the {plural(self.not_rerun, 'tick')} after a gap" if self.gap else ""),
            f"{'signal':<22} {'max |diff|':>12} {'RMS diff':>12} {'ticks':>7} {'first [s]':>11}",
        ]
        for s in self.signals:
            first = "-" if s.first_divergence is None else f"{s.first_divergence:.3f}"
            lines.append(
                f"{s.name:<22} {s.max_abs:>12.6g} {s.rms:>12.6g} {s.differing:>7} {first:>11}"
            )
        for lost in self.lost_inputs:
            lines.append(
                f"note: {lost.text()} (the recorder's queue overflowed): missing from the "
                "session's input topics; the ticks hold the inputs the gateway used"
            )
        after = (
            ""
            if self.gap is None
            else f"; the {plural(self.not_rerun, 'tick')} after it not re-run (the gateway's "
            "state after a gap is not in the recording)"
        )
        if self.diverged:
            lines.append(
                f"DIVERGED: first at {self.first_divergence:.3f} s"
                + ("" if self.gap is None else f"; then {self.gap.text()}{after}")
            )
        elif self.gap is not None:
            before = (
                f"the {plural(self.ticks, 'tick')} before it reproduced bit for bit"
                if self.ticks
                else "no tick before it"
            )
            lines.append(f"INCOMPLETE: {self.gap.text()}; {before}{after}")
        elif self.truncated:
            lines.append(
                f"IDENTICAL up to the cut: the {plural(self.ticks, 'tick')} the truncated session holds "
                "reproduced bit for bit; the drive after the cut was not recorded, not re-run"
            )
        elif self.numbered:
            lines.append("IDENTICAL: every command reproduced bit for bit")
        else:
            lines.append(
                "IDENTICAL: every recorded command reproduced bit for bit; the session's ticks "
                "are not numbered (recorded before leafgate numbered them), so ticks the "
                "recorder may have lost were not looked for"
            )
        return lines


def rerun_session(path: str | Path, overrides: Mapping[str, Any] | None = None) -> RerunReport:
    """Re-run a session through a fresh gateway and compare the commands.

    :raises ReplayError: not a session, one without configuration or ticks, or one that
        resumes another (it starts mid-drive)
    :raises ConfigError: an override outside :data:`RERUN_SECTIONS`, or the recorded
        configuration (with the overrides) does not load
    """
    check_rerun_overrides(overrides)
    path = Path(path)
    report = RerunReport(str(path), dict(overrides or {}))
    with SessionReader(path) as reader:
        resumed = reader.read_metadata().get(META_SESSION, {}).get("resumes")
        if resumed:
            raise ReplayError(
                f"{path}: not re-run: it resumes {resumed} after a recording failure, so it "
                "starts mid-drive (the gateway's state and the controller's memory at its first "
                f"tick are not in it) and cannot be re-run from its first tick; re-run {resumed}"
            )
        config = reader.config(overrides)
        controller = make_controller(config.controller, config.vehicle, config.gateway.period)
        gateway = Gateway(config.gateway, config.vehicle, controller, gateway_mode(config))
        contents: dict[int, Mapping[str, Any]] = {}
        current: tuple[int, Trajectory] | None = None  # (obj, the object handed to the gateway)

        def trajectory(ref: int, obj: int) -> Trajectory:
            nonlocal current
            if current is None or current[0] != obj:
                try:
                    current = (obj, decode_trajectory(contents[ref]))
                except KeyError:
                    raise ReplayError(
                        f"{path}: a tick refers to trajectory {ref}, never recorded"
                    ) from None
            return current[1]

        continuity = TickContinuity(first_seq=0)
        for record in reader.records(frozenset({TOPIC_TICK, TOPIC_TRAJECTORY, TOPIC_LOST})):
            data = record.json()
            if record.topic == TOPIC_TRAJECTORY:
                contents[int(data["ref"])] = data
                continue
            if record.topic == TOPIC_LOST:
                continuity.take_lost(data)
                continue
            if report.gap is not None:  # past a gap: no gateway state to go on from
                report.not_rerun += 1
                continue
            report.gap = continuity.take_tick(data)
            if report.gap is not None:
                report.not_rerun += 1
                continue
            now = float(data["now"])
            inputs = decode_inputs(data["inputs"], trajectory)
            result = gateway.step(now, inputs)
            recorded = command_signals(decode_commands(data["commands"]), data["state"])
            # Through the session's JSON form, as the recorded side went: ±inf reads back as
            # NaN there (leafgate.jsonconv), so the re-run's commands must take the same path.
            rerun_commands = decode_commands(encode_commands(result.commands))
            rerun = command_signals(rerun_commands, result.diagnostics.state)
            for diff, a, b in zip(report.signals, recorded, rerun, strict=True):
                diff.add(now, a, b)
            report.ticks += 1
        report.truncated = reader.truncated
        report.gap = continuity.gaps[0] if continuity.gaps else None  # with late lost records
        report.lost_inputs = continuity.lost_inputs
        report.numbered = continuity.numbered is not False
    if report.ticks == 0 and report.gap is None:
        raise ReplayError(f"{path}: the session holds no control ticks")
    return report


def main_rerun(
    session: str | Path,
    *,
    overrides: Sequence[str] = (),
    as_json: bool = False,
    out: TextIO | None = None,
) -> int:
    """``leafgate replay rerun SESSION.mcap [--set KEY=VALUE …] [--json]``.

    :return: 0 when every command is reproduced exactly, 1 when any diverges or ticks are
        missing (the re-run ends at the first gap)
    :raises LeafgateError: unreadable session or configuration, or an override a re-run does
        not use (a :class:`ConfigError`; the CLI prints it, exit 2)
    """
    out = out or sys.stdout
    report = rerun_session(session, parse_overrides(overrides))
    write_report(report, as_json, out)
    return 0 if report.identical else 1
