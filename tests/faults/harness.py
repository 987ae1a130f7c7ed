"""The multi-process fault-injection harness: the stack as separate processes, a bus sniffer.

One :class:`FaultRun` is one maneuver with one fault: ``leafgate sim-ecu`` (with ``--inject``
faults armed at the ECU's first engagement), ``leafgate run`` (recording to the test's
directory) and ``leafgate publish-trajectory`` as subprocesses, on a private ``udp_multicast``
group and a free loopback Zenoh port. The test process itself

- sniffs the bus (:class:`Sniffer`): every frame with its receive time, the gateway state from
  DBW_SYSTEM_CMD, the vehicle speed and the ECU's flags from its reports;
- engages through Zenoh, and reads the final state with ``leafgate status --json``;
- after the run, reads the ECU's trace (plant states with ``time.perf_counter`` stamps and the
  injection events), the gateway's recorded session (state transitions, stamped with the same
  monotonic clock) and its CAN log, and works out the reaction time, the time to the safe state
  and the command frames on the bus missing from the recording (:meth:`FaultRun.outcome`).

Times compare across processes because ``time.perf_counter`` is CLOCK_MONOTONIC on Linux, in
every process of the machine.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml

from leafgate.can.codec import CanCodec
from leafgate.messages import (
    GatewayState,
    LongReport,
    SteerReport,
    SystemCommand,
    SystemReport,
)
from tests.conftest import RELAXED_WATCHDOG, free_port, private_group, udp_multicast_works

ROOT = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-m", "leafgate.cli"]
COMMAND_IDS = frozenset({0x0A0, 0x0A1, 0x0A2})  # DBW_STEER_CMD, DBW_LONG_CMD, DBW_SYSTEM_CMD
REST_SPEED = 0.01  # m/s, below this the vehicle counts as at rest
# DBW_STEER_RPT periods without a report before FAULT in every run here (docs/watchdogs.md: 3):
# write_config's docstring says why
REPORT_TIMEOUT_PERIODS = 20.0
REPORT_ENV = "LEAFGATE_FAULT_REPORT"  # JSON lines of outcomes are appended there when set


def write_config(
    path: Path,
    recording_dir: Path,
    *,
    localization_design_thresholds: bool = False,
    overrun_design_threshold: bool = False,
    watchdog: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """config/sim.yaml on a private group and port, recording into ``recording_dir``.

    Four Python processes share two cores here (with a 1 kHz simulated ECU): a scheduling stall
    of 100 ms is no localization failure, nor one of 40 ms an ECU report failure, nor three late
    ticks in a row a loop failure, worth ending a run before its fault is injected (other test
    sessions share the machine, too). The thresholds a test is not about are therefore relaxed
    (as in test_daemon_processes.py); a test about one keeps docs/watchdogs.md's, except the ECU
    report timeout: its 30 ms is within such a stall (109 ms was seen beside other test sessions),
    so every run here has REPORT_TIMEOUT_PERIODS (200 ms), and
    test_watchdog.py holds the gateway to the 30 ms in one process.
    """
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    cfg["can"]["dbw"]["channel"] = private_group()
    cfg["can"]["dbw"]["kwargs"] = {"port": free_port()}
    wd = cfg["gateway"]["watchdog"]
    if localization_design_thresholds:
        wd.update({"localization_stop_age": 0.1, "localization_fault_age": 0.5})
    else:
        wd.update(
            {k: RELAXED_WATCHDOG[k] for k in ("localization_stop_age", "localization_fault_age")}
        )
    wd["report_timeout_periods"] = REPORT_TIMEOUT_PERIODS
    if not overrun_design_threshold:
        wd["max_overruns"] = 25  # late ticks in a row: 0.5 s instead of the default 3
        wd["max_stall_periods"] = 25.0  # one tick 0.5 s late instead of 100 ms
        wd["max_receive_lag"] = 1.0  # the receive thread 1 s behind instead of 0.2 s
    wd.update(watchdog or {})
    cfg["recording"] = {
        "enabled": True,
        "directory": str(recording_dir),
        "can_log": "can.blf",
        "session": "session.mcap",
        "flush_period": 1.0,
    }
    path.write_text(yaml.safe_dump(cfg))
    return cfg


# --- the sniffer --------------------------------------------------------------------------------


class Sniffer(threading.Thread):
    """Every frame on the bus, and what the test needs to know from them, as they arrive.

    python-can's ``udp_multicast`` stamps frames with the kernel's receive time (epoch); the
    sniffer keeps its own ``time.perf_counter`` stamp, the clock of the other processes' logs.
    """

    def __init__(self, channel: str, port: int) -> None:
        super().__init__(name="fault-sniffer", daemon=True)
        self.bus = can.Bus(interface="udp_multicast", channel=channel, port=port)
        self.codec = CanCodec(profile="leafgate-dbw")
        self.frames: list[tuple[float, can.Message]] = []
        self.gateway_state: GatewayState | None = None
        self.states: list[tuple[float, GatewayState]] = []  # changes seen on DBW_SYSTEM_CMD
        self.speed: float | None = None  # m/s, last DBW_LONG_RPT
        self.moving_at = -np.inf  # s, last report with |speed| >= REST_SPEED
        self.engaged_at: float | None = None  # s, first DBW_STEER_RPT with ENABLED
        self.cmd_timeouts: list[float] = []  # s, each report raising CMD_TIMEOUT after none had
        self.overrides: list[float] = []  # s, each report raising OVERRIDE after none had
        self._flag_state = {"cmd_timeout": False, "override": False}
        self.system: SystemReport | None = None
        self._lock = threading.Lock()
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                msg = self.bus.recv(timeout=0.1)
            except can.CanError:
                continue
            if msg is None:
                continue
            now = time.perf_counter()
            with self._lock:
                self.frames.append((now, msg))
            self._note(now, msg)

    def _note(self, now: float, msg: can.Message) -> None:
        value = self.codec.decode(msg).value  # attached even with a bad counter (rogue runs)
        if isinstance(value, SystemCommand) and msg.arbitration_id == 0x0A2:
            if value.state != self.gateway_state:
                self.states.append((now, value.state))
            self.gateway_state = value.state
        elif isinstance(value, LongReport):
            self.speed = value.speed
            if abs(value.speed) >= REST_SPEED:
                self.moving_at = now
            self._flags(now, value)
        elif isinstance(value, SteerReport):
            if value.enabled and self.engaged_at is None:
                self.engaged_at = now
            self._flags(now, value)
        elif isinstance(value, SystemReport):
            self.system = value

    def _flags(self, now: float, value: SteerReport | LongReport) -> None:
        # A flag counts as raised by the first report (of either kind) that carries it.
        for name, times in (("cmd_timeout", self.cmd_timeouts), ("override", self.overrides)):
            flag = bool(getattr(value, name))
            if flag and not self._flag_state[name]:
                times.append(now)
            if isinstance(value, SteerReport):  # the faster report sets the current state
                self._flag_state[name] = flag

    @staticmethod
    def first_after(times: Sequence[float], t: float) -> float | None:
        """The first of ``times`` at or after ``t``."""
        return next((x for x in times if x >= t), None)

    def at_rest(self, hold: float) -> bool:
        """The vehicle reported |v| < REST_SPEED for the last ``hold`` seconds."""
        return self.speed is not None and time.perf_counter() - self.moving_at >= hold

    def snapshot(self) -> list[tuple[float, can.Message]]:
        with self._lock:
            return list(self.frames)

    def close(self) -> None:
        self._halt.set()
        self.join(timeout=2.0)
        self.bus.shutdown()


# --- the run ------------------------------------------------------------------------------------


@dataclass
class Outcome:
    """What one fault run showed (one line of the results table)."""

    fault: str
    detected: bool
    state: str | None
    reason: str
    reaction_s: float | None  # s from the injection to the gateway's (or ECU's) first reaction
    safe_state_s: float | None  # s from the injection to the vehicle at rest
    frames_missing: int | None  # gateway command frames on the bus missing from the CAN log
    frames_missing_session: int | None = None  # … missing from the session's /can topic
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out = {
            "fault": self.fault,
            "detected": self.detected,
            "state": self.state,
            "reason": self.reason,
            "reaction_s": _round(self.reaction_s),
            "safe_state_s": _round(self.safe_state_s),
            "frames_missing": self.frames_missing,
            "frames_missing_session": self.frames_missing_session,
        }
        out.update(self.extra)
        return out

    def report(self) -> None:
        """Append to ``$LEAFGATE_FAULT_REPORT`` (JSON lines) when it is set."""
        path = os.environ.get(REPORT_ENV)
        if path:
            with open(path, "a", encoding="utf-8") as f:
                f.write(json.dumps(self.to_json()) + "\n")


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


def read_trace(path: Path) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """The ECU trace's rows (t, x, y, heading, speed, steer_angle, mono) and footer records."""
    rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    footer = [
        json.loads(line[2:])
        for line in path.read_text(encoding="utf-8").splitlines()
        if line.startswith("# ")
    ]
    return rows, footer


def rest_time(rows: np.ndarray, after: float) -> float | None:
    """Monotonic time from which the plant stays at rest to the end of the trace (after ``after``)."""
    mono, speed = rows[:, 6], rows[:, 4]
    later = mono >= after
    if not later.any():
        return None
    moving = np.nonzero(later & (np.abs(speed) >= REST_SPEED))[0]
    if len(moving) == 0:
        return float(mono[later][0])
    last = int(moving[-1])
    return float(mono[last + 1]) if last + 1 < len(mono) else None


TRUE_STATE_WINDOW = 0.06  # s back from a command frame in which the plant's state may be taken
# slack on every bound: a few quantisation steps of the command signals
LIMIT_TOLERANCE = {"angle": 1e-3, "long": 1e-2}  # rad; m/s² and m/s


@dataclass
class TrueStateJudgement:
    """The gateway's command frames on the bus judged against the plant's true state."""

    checked: int = 0  # ENABLE=1 command frames judged
    outside: int = 0  # … outside the safety limits at every true state of their window
    examples: list[str] = field(default_factory=list)  # the first few, described


def judge_commands_on_true_state(
    frames: Sequence[tuple[float, can.Message]],
    excluded: Counter[tuple[int, bytes]],
    rows: np.ndarray,
    config: Path,
) -> TrueStateJudgement:
    """Every ENABLE=1 command frame the gateway sent, against the safety gate's limits at the
    plant's TRUE speed and road-wheel angle (the ECU's trace), not at the reports' values.

    The gate limits each command against the one before (rates, jerk) and the measured speed
    (speed-dependent steering rate, lateral acceleration, direction); an ENABLE=1 steering
    command after ENABLE=0 is judged from the true wheel angle (a forged angle report must not
    seed it). Reports lag the plant by up to a report period, so a frame counts as outside only
    when it breaks a limit at every trace sample within ``TRUE_STATE_WINDOW`` before it (and at
    the state interpolated at its time). Frames the test sent itself (``excluded``) are skipped.
    """
    from leafgate.gateway.safety import Measured, SafetyLimits, check
    from leafgate.messages import Gear, LongCommand, SteerCommand
    from leafgate.replay.check import LONG_KINDS, STEER_KINDS
    from leafgate.settings import load_config

    cfg = load_config(str(config))
    limits = SafetyLimits.from_config(cfg.gateway.safety, cfg.vehicle, cfg.gateway.period)
    codec = CanCodec.for_config(cfg)
    mono, speed, angle = rows[:, 6], rows[:, 4], rows[:, 5]
    skip = Counter(excluded)
    out = TrueStateJudgement()
    last_steer, last_long = SteerCommand(angle=0.0), LongCommand()
    last_time: dict[int, float] = {}
    gear = Gear.NONE
    for t, msg in frames:
        key = frame_key(msg)
        if skip[key] > 0:
            skip[key] -= 1
            continue
        decoded = codec.decode(msg)
        if isinstance(decoded.value, LongReport):
            gear = decoded.value.gear
        if msg.arbitration_id not in COMMAND_IDS:
            continue
        elapsed = t - last_time.get(msg.arbitration_id, -math.inf)
        last_time[msg.arbitration_id] = t
        for value in decoded.values:
            if not isinstance(value, (SteerCommand, LongCommand)):
                continue
            previous = last_steer if isinstance(value, SteerCommand) else last_long
            if isinstance(value, SteerCommand):
                last_steer = value
            else:
                last_long = value
            if not value.enable:
                continue
            inside = (mono >= t - TRUE_STATE_WINDOW) & (mono <= t)
            if not inside.any() or t > mono[-1]:
                continue  # no plant state known for this frame
            at = float(np.interp(t, mono, speed)), float(np.interp(t, mono, angle))
            states = [at, *zip(speed[inside].tolist(), angle[inside].tolist(), strict=True)]
            lim = limits if not elapsed > 1.5 * limits.period else replace(limits, period=elapsed)
            steer = isinstance(value, SteerCommand)
            kinds = STEER_KINDS if steer else LONG_KINDS
            found: list[str] = []
            for v, a in states:
                if steer:
                    last = previous if previous.enable else SteerCommand(angle=a)
                    args = (value, last_long, last, last_long)
                else:
                    args = (last_steer, value, last_steer, previous)
                tol = LIMIT_TOLERANCE["angle" if steer else "long"]
                broken = [x for x in check(*args, Measured(v, gear), lim, tol) if x.kind in kinds]
                if not broken:
                    break
                found = [f"{x.kind} {x.value:.4f} beyond {x.bound:.4f}" for x in broken]
            else:
                out.outside += 1
                if len(out.examples) < 5:
                    out.examples.append(f"t={t:.3f} 0x{msg.arbitration_id:03X}: {'; '.join(found)}")
            out.checked += 1
    return out


def transitions(session: Path) -> list[dict[str, Any]]:
    """Every state transition recorded in the session (times on the gateway's clock)."""
    from leafgate.record.session import TOPIC_DIAGNOSTICS, SessionReader

    out: list[dict[str, Any]] = []
    with SessionReader(session) as reader:
        for record in reader.records(frozenset({TOPIC_DIAGNOSTICS})):
            out.extend(record.json().get("transitions", ()))
    return out


def frame_key(msg: can.Message) -> tuple[int, bytes]:
    return (msg.arbitration_id, bytes(msg.data))


def recorded_commands(paths: Iterable[Path]) -> Counter[tuple[int, bytes]]:
    """The gateway's sent command frames in recordings (CAN logs or a session's /can topic)."""
    from leafgate.record.logs import FrameSource

    out: Counter[tuple[int, bytes]] = Counter()
    for path in paths:
        for msg in FrameSource(path):
            if msg.arbitration_id in COMMAND_IDS and not msg.is_rx:
                out[frame_key(msg)] += 1
    return out


class FaultRun:
    """One maneuver with faults; a context manager that always ends every process it started.

    :param tmp_path: the test's directory (config, logs, trace, recordings)
    :param fault: the name of the fault in the results table
    :param injections: ``sim-ecu --inject`` arguments (T after the ECU's first engagement)
    :param daemon: the daemon's command line after ``python``; default ``-m leafgate.cli run``
    """

    def __init__(
        self,
        tmp_path: Path,
        fault: str,
        *,
        scenario: str = "s-curve",
        injections: Sequence[str] = (),
        localization_design_thresholds: bool = False,
        overrun_design_threshold: bool = False,
        watchdog: dict[str, Any] | None = None,
        daemon: Sequence[str] | None = None,
    ) -> None:
        self.dir = tmp_path
        self.fault = fault
        self.scenario = scenario
        self.injections = tuple(injections)
        self.config = tmp_path / "sim.yaml"
        self.recordings = tmp_path / "rec"
        self.cfg = write_config(
            self.config,
            self.recordings,
            localization_design_thresholds=localization_design_thresholds,
            overrun_design_threshold=overrun_design_threshold,
            watchdog=watchdog,
        )
        self.trace = tmp_path / "trace.csv"
        self.daemon_cmd = list(daemon) if daemon is not None else [*CLI[1:], "run"]
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.sniffer: Sniffer | None = None
        self.excluded: Counter[tuple[int, bytes]] = Counter()  # frames the test itself sent
        self.startup_resets: list[str] = []  # faults reset before the maneuver (see engage)
        self._session: Any = None
        self.zcfg: Any = None  # the Zenoh section as a tool sees it (set by zenoh())

    # -- processes --

    def _start(self, name: str, argv: Sequence[str]) -> subprocess.Popen[bytes]:
        log = (self.dir / f"{name}.log").open("wb")
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        log.close()
        self.procs[name] = proc
        return proc

    def start(self, planner: bool = True) -> FaultRun:
        dbw = self.cfg["can"]["dbw"]
        self.sniffer = Sniffer(dbw["channel"], dbw["kwargs"]["port"])
        self.sniffer.start()
        inject = [arg for text in self.injections for arg in ("--inject", text)]
        self._start(
            "ecu",
            [
                *CLI,
                "sim-ecu",
                "--config",
                str(self.config),
                "--scenario",
                self.scenario,
                "--trace",
                str(self.trace),
                *inject,
            ],
        )
        # One start at a time: three Python start-ups at once on two cores stall the daemon's
        # first ticks (an overrun fault before the test has even begun).
        self.wait_for("the ECU loop", lambda: "simulated ECU on" in self.log("ecu"), 30)
        self._start("gateway", [sys.executable, *self.daemon_cmd, "--config", str(self.config)])
        self.wait_for("the control loop", lambda: "control loop running" in self.log("gateway"), 30)
        if planner:
            self.start_planner()
        return self

    def start_planner(self) -> None:
        self._start(
            "planner",
            [
                *CLI,
                "publish-trajectory",
                "--scenario",
                self.scenario,
                "--config",
                str(self.config),
            ],
        )

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int | None:
        proc = self.procs.get(name)
        if proc is None:
            return None
        if proc.poll() is None:
            proc.send_signal(sig)
        try:
            return proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait(timeout=5)

    def log(self, name: str) -> str:
        path = self.dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def logs_tail(self, chars: int = 1500) -> str:
        return "\n".join(f"--- {n}.log ---\n{self.log(n)[-chars:]}" for n in self.procs)

    def __enter__(self) -> FaultRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End every process (planner, daemon, ECU), the Zenoh session and the sniffer."""
        for name in ("planner", "gateway", "ecu", *self.procs):
            proc = self.procs.get(name)
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
        if self._session is not None:
            with contextlib.suppress(Exception):
                self._session.close()
            self._session = None
        if self.sniffer is not None and self.sniffer.is_alive():
            self.sniffer.close()

    # -- Zenoh --

    def zenoh(self) -> Any:
        """The test's own Zenoh session (a tool's view of the daemon's endpoints)."""
        if self._session is None:
            from leafgate.runtime.daemon import tool_view
            from leafgate.settings import load_config
            from leafgate.transport.session import open_session

            self.zcfg = tool_view(load_config(str(self.config)).zenoh)
            self._session = open_session(self.zcfg)
        return self._session

    def request(self, command: str, timeout: float = 2.0) -> dict[str, Any]:
        from leafgate.errors import LeafgateError
        from leafgate.transport.client import request

        session = self.zenoh()
        try:
            return dict(request(self.zcfg, command, timeout=timeout, session=session))
        except LeafgateError as exc:
            return {"accepted": False, "reason": str(exc)}

    def engage(self, timeout: float = 30.0) -> dict[str, Any]:
        """Ask until the gateway accepts (it refuses until every input is fresh).

        A fault latched before the maneuver (start-up stalls on a loaded machine can overrun
        the loop) is reset, as an operator would, and counted in :attr:`startup_resets`.
        """
        reply: dict[str, Any] = {}
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check_alive()
            reply = self.request("engage")
            # "already engaged" (accepted: false since issue 19) after a reply that was lost
            if reply.get("accepted") or reply.get("state") == "ENGAGED":
                return reply
            if reply.get("state") == "FAULT":
                self.startup_resets.append(str(reply.get("reason")))
                self.request("reset")
            time.sleep(0.3)
        raise AssertionError(f"engage refused: {reply}\n{self.logs_tail()}")

    def status(self) -> dict[str, Any]:
        """``leafgate status --json``: the daemon's latest diagnostics."""
        result = subprocess.run(
            [*CLI, "status", "--config", str(self.config), "--duration", "0.5", "--json"],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=ROOT,
        )
        lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
        return json.loads(lines[-1]) if lines else {}

    # -- waiting --

    @staticmethod
    def sniffer_time() -> float:
        """Now on the clock of the sniffer, the logs and the gateway (perf_counter)."""
        return time.perf_counter()

    def check_alive(self, *names: str) -> None:
        for name in names or ("ecu", "gateway"):
            proc = self.procs.get(name)
            if proc is not None and proc.poll() is not None:
                raise AssertionError(f"{name} exited ({proc.returncode})\n{self.logs_tail()}")

    def wait_for(
        self, what: str, predicate: Callable[[], bool], timeout: float, alive: Sequence[str] = ()
    ) -> float:
        """Poll ``predicate`` until true; returns the time it became true (perf_counter)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return time.perf_counter()
            self.check_alive(*alive)
            time.sleep(0.02)
        raise AssertionError(
            f"timed out after {timeout:g} s waiting for {what}\n{self.logs_tail()}"
        )

    def wait_engaged(self, timeout: float = 10.0) -> float:
        """When the ECU first reported ENABLED (perf_counter)."""
        sniffer = self.sniffer
        assert sniffer is not None
        self.wait_for("the ECU to report ENABLED", lambda: sniffer.engaged_at is not None, timeout)
        assert sniffer.engaged_at is not None
        return sniffer.engaged_at

    def wait_at_rest(
        self,
        states: Iterable[GatewayState] | None = None,
        timeout: float = 20.0,
        hold: float = 0.5,
        alive: Sequence[str] = (),
    ) -> None:
        """Until the vehicle stands (and the gateway's DBW_SYSTEM_CMD shows one of ``states``)."""
        sniffer = self.sniffer
        assert sniffer is not None
        wanted = None if states is None else frozenset(states)

        def done() -> bool:
            state_ok = wanted is None or sniffer.gateway_state in wanted
            return state_ok and sniffer.at_rest(hold)

        names = "/".join(s.name for s in wanted) if wanted else "any state"
        self.wait_for(f"the vehicle at rest ({names})", done, timeout, alive)

    def injection_started(self, kind: str) -> float | None:
        """The ECU log's monotonic time of the start of injection ``kind`` (while running)."""
        m = re.search(
            rf"injection {re.escape(kind)} started .*?monotonic ([0-9.]+)", self.log("ecu")
        )
        return float(m.group(1)) if m else None

    # -- after the run --

    def shutdown(self, keep: Sequence[str] = ()) -> None:
        """SIGTERM planner, daemon and ECU in that order (the daemon closes its recording)."""
        for name in ("planner", "gateway", "ecu"):
            if name not in keep:
                self.stop(name)
        if self.sniffer is not None:
            time.sleep(0.2)  # the last frames in flight on loopback
            self.sniffer.close()

    def recording_files(self) -> tuple[list[Path], Path]:
        logs = sorted(self.recordings.glob("can_*.blf"))
        return logs, self.recordings / "session.mcap"

    def gateway_frames_on_bus(self) -> Counter[tuple[int, bytes]]:
        """The command frames the sniffer saw, less those the test itself sent."""
        assert self.sniffer is not None
        seen = Counter(
            frame_key(m) for _, m in self.sniffer.snapshot() if m.arbitration_id in COMMAND_IDS
        )
        return seen - self.excluded

    def outcome(
        self,
        injected_at: float | None,
        *,
        status: dict[str, Any] | None,
        reaction_kinds: Iterable[str] = ("STOPPING", "FAULT", "STANDBY"),
        ecu_reaction_at: float | None = None,
        extra: dict[str, Any] | None = None,
    ) -> Outcome:
        """Times and losses of this run (call after :meth:`shutdown`).

        :param injected_at: perf_counter time the fault began (the ECU log's, or the test's)
        :param status: the daemon's last diagnostics (``status --json``), None if it is gone
        :param ecu_reaction_at: the reaction time when the ECU, not the gateway, reacts
        """
        rows, _footer = read_trace(self.trace)
        logs, session = self.recording_files()
        changes = transitions(session) if session.exists() else []
        if injected_at is not None:
            # A fault of its own before the injection would make this run measure the wrong thing.
            engaged = [t["time"] for t in changes if t["to"] == "ENGAGED"]
            early = [t for t in changes if engaged and engaged[-1] < t["time"] < injected_at - 0.05]
            assert not early, f"the maneuver ended before the fault was injected: {early}"
        reaction = None
        if injected_at is not None:
            if ecu_reaction_at is not None:
                reaction = ecu_reaction_at - injected_at
            elif session.exists():
                targets = frozenset(reaction_kinds)
                times = [
                    t["time"]
                    for t in changes
                    if t["to"] in targets and t["time"] >= injected_at - 0.05
                ]
                reaction = min(times) - injected_at if times else None
        rest = rest_time(rows, injected_at) if injected_at is not None else None
        on_bus = self.gateway_frames_on_bus()
        missing = sum((on_bus - recorded_commands(logs)).values()) if logs else None
        missing_session = (
            sum((on_bus - recorded_commands([session])).values()) if session.exists() else None
        )
        judged = (
            judge_commands_on_true_state(self.sniffer.snapshot(), self.excluded, rows, self.config)
            if self.sniffer is not None
            else None
        )
        state = status.get("state") if status else None
        reason = (status or {}).get("reason", "")
        detected = reaction is not None
        return Outcome(
            fault=self.fault,
            detected=detected,
            state=state,
            reason=reason,
            reaction_s=reaction,
            safe_state_s=None if rest is None or injected_at is None else rest - injected_at,
            frames_missing=missing,
            frames_missing_session=missing_session,
            extra={
                **({"startup_resets": self.startup_resets} if self.startup_resets else {}),
                **(
                    {
                        "commands_checked": judged.checked,
                        "commands_outside_limits": judged.outside,
                        **({"outside_examples": judged.examples} if judged.examples else {}),
                    }
                    if judged is not None
                    else {}
                ),
                **(extra or {}),
            },
        )


@contextlib.contextmanager
def cpu_hogs(count: int = 2) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``count`` busy-loop processes, ended on the way out."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield procs
    finally:
        for proc in procs:
            proc.kill()
        for proc in procs:
            proc.wait(timeout=5)


class RogueNode:
    """A node on the bus sending frames on the gateway's command IDs (its own codec, counters)."""

    def __init__(self, channel: str, port: int, excluded: Counter[tuple[int, bytes]]) -> None:
        self.bus = can.Bus(interface="udp_multicast", channel=channel, port=port)
        self.codec = CanCodec(profile="leafgate-dbw")
        self.excluded = excluded
        self.sent = 0

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)
        self.excluded[frame_key(msg)] += 1
        self.sent += 1

    def send_value(self, value: Any) -> None:
        """A well-formed frame: valid CRC, this node's own alive counter."""
        self.send(self.codec.encode(value))

    def send_garbage(self, frame_id: int, rng: random.Random) -> None:
        """Random bytes on ``frame_id`` (a CRC that almost never matches)."""
        data = bytes(rng.getrandbits(8) for _ in range(8))
        self.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    def close(self) -> None:
        self.bus.shutdown()


#: ``pytestmark`` of every multi-process module here.
PROCESS_TEST = [
    pytest.mark.slow,
    pytest.mark.skipif(not udp_multicast_works(), reason="python-can udp_multicast unavailable"),
    pytest.mark.skipif(
        bool(os.environ.get("LEAFGATE_NO_SUBPROCESS")), reason="subprocess tests disabled"
    ),
]
