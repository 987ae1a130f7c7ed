"""Soak: the hardware-free stack as separate processes for a long time; prints JSON.

``leafgate sim-ecu`` and ``leafgate run`` run as subprocesses on a copy of ``config/sim.yaml``
with a private Zenoh port and CAN multicast group (parallel runs do not meet). This process is
the planner and the operator: it drives maneuvers one after another — when one ends (the
gateway back in STANDBY with "trajectory end"), the next scenario of ``--scenarios`` is moved to
start at the vehicle's current pose and heading, published (re-published every 0.5 s, as a
planner does) and engaged. It is also the observer:

- the gateway's ``gateway/diagnostics`` (10 Hz): state and reason, loop overruns, skipped ticks
  (deadlines missed outright), and the compute/lateness figures of each one-minute window;
- the daemon's and the ECU's resident memory (``VmRSS`` in ``/proc/PID/status``) every 5 s;
  "start" is the first sample after ``--warmup`` (imports done, buffers grown);
- a sniffer bus on the same group: gaps in the 4-bit alive counter (byte 6, low nibble) of each
  gateway command ID and ECU report ID are frames lost on the way to this receiver (multicast
  drops them when a receiver falls behind); the ECU's own count of rejected command frames
  (DBW_SYSTEM_RPT ``rx_error_count``: bad CRC and counters that did not advance by one, so a
  frame the ECU missed counts there) and its CMD_TIMEOUT episodes are read from the same bus.

A progress line goes to stderr every minute. The exit status is 1 when a goal is missed — no
gateway loop overrun, daemon memory growth under ``--max-growth-mb`` (20 MB), at least one
maneuver completed, both processes alive to the end — unless ``--no-fail``.

Run: ``.venv/bin/python tools/soak.py --duration 1800 [--out soak.json] [--no-fail]``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from _common import free_port

from leafgate.messages import Pose, Trajectory

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "leafgate.cli"]

COUNTER_MODULO = 16  # the alive counter is 4 bits (byte 6, low nibble)
RSS_PERIOD = 5.0  # s between memory samples
PROGRESS_PERIOD = 60.0  # s between progress lines on stderr
WINDOW_PERIOD = 60.0  # s: the daemon's timing figures cover its last 3000 ticks (60 s at 50 Hz)
REPUBLISH_PERIOD = 0.5  # s, as a planner re-publishes its plan (the gateway refuses a stale one)
ENGAGE_PATIENCE = 30.0  # s of refused engages before the maneuver counts as aborted
MANEUVER_SLACK = 30.0  # s beyond the scenario's own time budget before it counts as stuck
START_TIMEOUT = 30.0  # s for the stack to come up (imports on two busy cores)
POLL = 0.05  # s, the driver's loop period
SHORT_ENGAGEMENT = 2.0  # s: an engagement over by then may fall between 10 Hz diagnostics
RESET_PERIOD = 1.0  # s between reset requests while the gateway is in FAULT
DEFAULT_SCENARIOS = ("s-curve", "slalom", "s-curve", "straight")
TRAJECTORY_END = "trajectory end"  # in the gateway's reason when a maneuver ends as planned


# --- pure helpers -------------------------------------------------------------------------------


def start_at(trajectory: Trajectory, pose: Pose) -> Trajectory:
    """``trajectory`` moved rigidly so that its first waypoint lies at ``pose``.

    Rotated about its first waypoint by the difference between the pose's heading and the
    first waypoint's (wrapped to (−π, π]), then translated; speeds are unchanged.
    """
    turn = math.remainder(pose.heading - float(trajectory.heading[0]), math.tau)  # rad
    c, s = math.cos(turn), math.sin(turn)
    dx = trajectory.x - trajectory.x[0]  # m, relative to the first waypoint
    dy = trajectory.y - trajectory.y[0]
    return Trajectory(
        x=pose.x + c * dx - s * dy,
        y=pose.y + s * dx + c * dy,
        heading=trajectory.heading + turn,
        speed=trajectory.speed,
    )


@dataclass
class CounterGaps:
    """Frames missing from each ID's alive-counter sequence, as seen by one receiver.

    A step of ``k`` (mod 16) between consecutive frames means ``k − 1`` frames lost; a step of
    0 is a repeated counter (a stuck sender, or a duplicate). Losses of 16 frames or more in a
    row alias, which is why ``silences`` also counts gaps longer than ``silence`` seconds.

    :param silence: s without a frame of an ID that counts as a silence
    """

    silence: float = 1.0
    frames: Counter[int] = field(default_factory=Counter)
    lost: Counter[int] = field(default_factory=Counter)
    repeated: Counter[int] = field(default_factory=Counter)
    silences: Counter[int] = field(default_factory=Counter)
    _last: dict[int, tuple[int, float]] = field(default_factory=dict)

    def feed(self, frame_id: int, data: bytes | bytearray, timestamp: float) -> None:
        """Account for one received frame (``timestamp`` in s, any monotonic origin)."""
        if len(data) < 7:
            return  # not an E2E-protected frame: no counter to follow
        counter = data[6] & 0x0F
        self.frames[frame_id] += 1
        previous = self._last.get(frame_id)
        self._last[frame_id] = (counter, timestamp)
        if previous is None:
            return
        last_counter, last_time = previous
        step = (counter - last_counter) % COUNTER_MODULO
        if step == 0:
            self.repeated[frame_id] += 1
        elif step > 1:
            self.lost[frame_id] += step - 1
        if timestamp - last_time > self.silence:
            self.silences[frame_id] += 1

    def summary(self, ids: Iterable[int]) -> dict[str, dict[str, int]]:
        """Per ID (``"0x0A0"``): frames, lost, repeated, silences."""
        return {
            f"0x{i:03X}": {
                "frames": self.frames[i],
                "lost": self.lost[i],
                "repeated": self.repeated[i],
                "silences": self.silences[i],
            }
            for i in sorted(ids)
        }


_MEASURED = re.compile(r"-?\d+(?:\.\d+)? (s|m|rad) >")


def reason_kind(reason: str) -> str:
    """A reason without its measured value, so that like aborts count together.

    >>> reason_kind("FAULT: steer_report age 0.037 s > 0.03 s")
    'FAULT: steer_report age … s > 0.03 s'
    """
    return _MEASURED.sub(lambda m: f"… {m.group(1)} >", reason)


@dataclass
class Maneuver:
    """One maneuver's outcome."""

    scenario: str
    outcome: str  # completed | aborted | interrupted (the soak ended during it)
    reason: str  # the gateway's reason at the end
    duration: float  # s from engage accepted (or first try) to the end


@dataclass
class MemoryTrack:
    """Resident memory of one process, MB."""

    start: float | None = None  # the first sample after warm-up
    end: float | None = None
    max: float | None = None

    def add(self, rss_mb: float, after_warmup: bool) -> None:
        if after_warmup and self.start is None:
            self.start = rss_mb
        self.end = rss_mb
        self.max = rss_mb if self.max is None else max(self.max, rss_mb)

    def summary(self) -> dict[str, float | None]:
        growth = None if self.start is None or self.end is None else self.end - self.start
        return {
            "start_mb": _round(self.start),
            "end_mb": _round(self.end),
            "max_mb": _round(self.max),
            "growth_mb": _round(growth),
        }


def _round(value: float | None, digits: int = 2) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, digits)


def loop_figures(windows: Sequence[Mapping[str, Any]], last: Mapping[str, Any]) -> dict[str, Any]:
    """The gateway loop over the run from its diagnostics ``loop`` objects.

    :param windows: one ``loop`` object per one-minute window (each covers the last 3000
        ticks); p50 is the median of the windows' medians, p99 and max the worst window's
    :param last: the newest ``loop`` object (its counters are totals since start)
    """

    def values(key: str) -> list[float]:
        out = [w.get(key) for w in windows]
        return [float(v) for v in out if isinstance(v, (int, float)) and math.isfinite(v)]

    def worst(key: str) -> float | None:
        v = values(key)
        return max(v) if v else None

    medians = values("compute_median_s")
    return {
        "ticks": last.get("ticks"),
        "overruns": last.get("overruns"),
        "deadline_misses": last.get("skipped_ticks"),  # ticks dropped after a stall
        "send_errors": last.get("send_errors"),
        "encode_errors": last.get("encode_errors"),
        "publish_dropped": last.get("publish_dropped"),
        "compute_p50_s": float(np.median(medians)) if medians else None,
        "compute_p99_s": worst("compute_p99_s"),
        "compute_max_s": worst("compute_max_s"),
        "start_lateness_p99_s": worst("start_lateness_p99_s"),
    }


def goals(report: Mapping[str, Any], max_growth_mb: float) -> dict[str, bool]:
    """Each goal of the soak and whether it was met."""
    loop = report["gateway_loop"]
    growth = report["memory"]["gateway"]["growth_mb"]
    return {
        "zero_overruns": loop.get("overruns") == 0,
        f"memory_growth_under_{max_growth_mb:g}_mb": growth is not None and growth < max_growth_mb,
        "maneuvers_completed": report["maneuvers"]["completed"] > 0,
        "processes_alive": not report["final"].get("died"),
    }


def assemble_report(
    *,
    duration: float,
    maneuvers: Sequence[Maneuver],
    refusals: Mapping[str, int],
    loop: Mapping[str, Any],
    memory: Mapping[str, MemoryTrack],
    gaps: CounterGaps,
    command_ids: Iterable[int],
    report_ids: Iterable[int],
    ecu: Mapping[str, Any],
    final: Mapping[str, Any],
    max_growth_mb: float,
) -> dict[str, Any]:
    """The soak's JSON report, with its goals and ``passed``."""
    done = Counter(m.outcome for m in maneuvers)
    command_ids = sorted(command_ids)
    report: dict[str, Any] = {
        "duration_s": round(duration, 1),
        "maneuvers": {
            "completed": done["completed"],
            "aborted": done["aborted"],
            "interrupted": done["interrupted"],
            "abort_reasons": dict(
                Counter(
                    reason_kind(m.reason) for m in maneuvers if m.outcome == "aborted"
                ).most_common()
            ),
            "engage_refusals": dict(
                sum((Counter({reason_kind(k): v}) for k, v in refusals.items()), Counter())
            ),
            "by_scenario": {
                name: dict(Counter(m.outcome for m in maneuvers if m.scenario == name))
                for name in sorted({m.scenario for m in maneuvers})
            },
            "completed_duration_median_s": _round(
                float(np.median([m.duration for m in maneuvers if m.outcome == "completed"]))
                if done["completed"]
                else None
            ),
        },
        "gateway_loop": dict(loop),
        "memory": {name: track.summary() for name, track in memory.items()},
        "frames": {
            "commands": gaps.summary(command_ids),
            "reports": gaps.summary(report_ids),
            "commands_lost": sum(gaps.lost[i] for i in command_ids),
            "ecu": dict(ecu),
        },
        "final": dict(final),
    }
    report["goals"] = goals(report, max_growth_mb)
    report["passed"] = all(report["goals"].values())
    return report


def progress_line(elapsed: float, total: float, report: Mapping[str, Any]) -> str:
    """One line for stderr."""
    m, loop, mem = report["maneuvers"], report["gateway_loop"], report["memory"]["gateway"]
    rss = mem["end_mb"]
    growth = mem["growth_mb"]
    return (
        f"soak {elapsed / 60:5.1f}/{total / 60:.1f} min: maneuvers {m['completed']} completed, "
        f"{m['aborted']} aborted; overruns {loop.get('overruns')}, "
        f"deadline misses {loop.get('deadline_misses')}; gateway RSS "
        f"{'?' if rss is None else f'{rss:.1f}'} MB "
        f"({'warming up' if growth is None else f'{growth:+.1f} MB'}); "
        f"command frames lost {report['frames']['commands_lost']}"
    )


# --- the processes ------------------------------------------------------------------------------


def private_config(base: Path, directory: Path) -> Path:
    """``base`` with a free Zenoh port and a private CAN multicast group and port."""
    cfg = yaml.safe_load(base.read_text())
    cfg.setdefault("zenoh", {})["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    dbw = cfg.setdefault("can", {}).setdefault("dbw", {})
    dbw["channel"] = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    dbw["kwargs"] = {**(dbw.get("kwargs") or {}), "port": free_port()}
    path = directory / "soak.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def rss_mb(pid: int) -> float | None:
    """``VmRSS`` of a process in MB (10⁶ bytes), None when it is gone."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024 / 1e6  # kB → MB
    except OSError:
        return None
    return None


_ECU_STOPPED = re.compile(r"simulated ECU stopped: (\d+) ticks, .*?(\d+) overruns")


def ecu_log_figures(text: str) -> dict[str, int]:
    """Ticks and overruns from ``sim-ecu``'s closing log line (empty when it is missing)."""
    found = _ECU_STOPPED.search(text)
    return {"ticks": int(found.group(1)), "overruns": int(found.group(2))} if found else {}


class Sniffer:
    """Receives every frame of the dbw bus on its own thread: counter gaps and ECU reports."""

    def __init__(self, bus: Any, codec: Any, system_id: int) -> None:
        self.bus = bus
        self.codec = codec
        self.system_id = system_id
        self.gaps = CounterGaps()
        self.ecu_state: str | None = None
        self.rx_error_count_max = 0
        self.cmd_timeout_episodes = 0
        self._cmd_timeout = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak-sniffer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.2)
            if msg is None or msg.is_extended_id:
                continue
            with self._lock:
                self.gaps.feed(msg.arbitration_id, msg.data, msg.timestamp)
                if msg.arbitration_id == self.system_id:
                    value = self.codec.decode(msg).value
                    if value is not None and hasattr(value, "rx_error_count"):
                        self.ecu_state = value.state.name
                        self.rx_error_count_max = max(self.rx_error_count_max, value.rx_error_count)
                        if value.fault_cmd_timeout and not self._cmd_timeout:
                            self.cmd_timeout_episodes += 1
                        self._cmd_timeout = bool(value.fault_cmd_timeout)

    def snapshot(self) -> tuple[CounterGaps, dict[str, Any]]:
        with self._lock:
            gaps = dataclasses.replace(
                self.gaps,
                frames=Counter(self.gaps.frames),
                lost=Counter(self.gaps.lost),
                repeated=Counter(self.gaps.repeated),
                silences=Counter(self.gaps.silences),
                _last=dict(self.gaps._last),
            )
            ecu = {
                "state": self.ecu_state,
                "rx_error_count_max": self.rx_error_count_max,
                "cmd_timeout_episodes": self.cmd_timeout_episodes,
            }
        return gaps, ecu

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.bus.shutdown()


class Observer:
    """Zenoh side of this process: the latest diagnostics and localization, and the plan."""

    def __init__(self, session: Any, zcfg: Any) -> None:
        from leafgate.transport import keys
        from leafgate.transport.client import TrajectoryPublisher
        from leafgate.transport.payloads import codecs

        self._lock = threading.Lock()
        self.diag: dict[str, Any] = {}
        self.diag_time = 0.0  # time.monotonic of the newest diagnostics
        self.pose: Pose | None = None
        self._pose_payload: bytes | None = None
        self._pose_codec = codecs(zcfg.encoding).pose
        self._subs = [
            session.declare_subscriber(zcfg.key(keys.DIAGNOSTICS), self._on_diag),
            session.declare_subscriber(zcfg.key(keys.KINEMATIC_STATE), self._on_pose),
        ]
        self.publisher = TrajectoryPublisher(session, zcfg)
        self.plan: Trajectory | None = None
        self.publish_errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._planner, name="soak-planner", daemon=True)
        self._thread.start()

    def _on_diag(self, sample: Any) -> None:
        try:
            data = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if isinstance(data, dict):
            with self._lock:
                self.diag, self.diag_time = data, time.monotonic()

    def _on_pose(self, sample: Any) -> None:
        # Kept raw: 50 Hz of decoding for a pose read once per maneuver would only load the CPU
        # the stack under test shares.
        payload = sample.payload.to_bytes()
        with self._lock:
            self._pose_payload = payload

    def _planner(self) -> None:
        while not self._stop.wait(REPUBLISH_PERIOD):
            plan = self.plan
            if plan is not None:
                try:
                    self.publisher.publish(plan)
                except Exception:
                    self.publish_errors += 1

    def latest(self) -> tuple[dict[str, Any], float]:
        """The newest diagnostics and their arrival (time.monotonic; 0 before the first)."""
        with self._lock:
            return self.diag, self.diag_time

    def current_pose(self) -> Pose | None:
        """The newest localization (decoded now), None before the first."""
        with self._lock:
            payload = self._pose_payload
        if payload is not None:
            with contextlib.suppress(Exception):  # a bad sample: keep the previous pose
                self.pose = self._pose_codec.decode(payload)
        return self.pose

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for sub in self._subs:
            sub.undeclare()
        self.publisher.close()


def _start(
    args: Sequence[str], log: Path, rt_priority: int | None = None
) -> subprocess.Popen[bytes]:
    """Start a leafgate command; under SCHED_FIFO at ``rt_priority`` (``chrt -f``) when given,
    as ``tools/leafgate.service`` runs the daemon on the car."""
    prefix = ["chrt", "-f", str(rt_priority)] if rt_priority is not None else []
    return subprocess.Popen(
        [*prefix, *CLI, *args], stdout=log.open("wb"), stderr=subprocess.STDOUT, cwd=ROOT
    )


def _stop(proc: subprocess.Popen[bytes]) -> int | None:
    """SIGTERM, then SIGKILL after 10 s; the exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


class Driver:
    """Plans, engages and watches maneuvers one after another."""

    def __init__(self, observer: Observer, zcfg: Any, session: Any, scenarios: Sequence[str]):
        from leafgate.sim.scenarios import get_scenario

        self.observer = observer
        self.zcfg = zcfg
        self.session = session
        self.scenarios = [get_scenario(name) for name in scenarios]
        self.index = 0
        self.maneuvers: list[Maneuver] = []
        self.refusals: Counter[str] = Counter()
        self._phase = "plan"  # plan → engage → drive → (recover) → plan
        self._since = 0.0
        self._engaged_seen = False
        self._current = self.scenarios[0]

    def _request(self, what: str) -> dict[str, Any]:
        from leafgate.errors import TransportError
        from leafgate.transport.client import request

        try:
            return request(self.zcfg, what, timeout=2.0, session=self.session)
        except TransportError as exc:
            return {"accepted": False, "state": None, "reason": f"no answer: {exc}"}

    def step(self, now: float) -> None:
        """Advance by one poll (``now``: time.monotonic)."""
        diag, diag_time = self.observer.latest()
        state, reason = diag.get("state"), str(diag.get("reason", ""))
        if self._phase == "plan":
            pose = self.observer.current_pose() if state == "STANDBY" else None
            if pose is None:
                if state == "FAULT" and now - self._since > RESET_PERIOD:
                    self._since = now  # a reset at most once a second
                    self._request("reset")
                return
            self._current = self.scenarios[self.index % len(self.scenarios)]
            self.index += 1
            self.observer.plan = start_at(self._current.trajectory, pose)
            self.observer.publisher.publish(self.observer.plan)
            self._phase, self._since, self._engaged_seen = "engage", now, False
        elif self._phase == "engage":
            if now - self._since < REPUBLISH_PERIOD:
                return  # the new plan first: engaging on the old one would end at once
            reply = self._request("engage")
            # "already engaged" (accepted: false since issue 19) after a reply that was lost
            if reply.get("accepted") or reply.get("state") == "ENGAGED":
                self._phase, self._since = "drive", now
                return
            self.refusals[str(reply.get("reason"))] += 1
            if reply.get("state") == "FAULT":
                self._request("reset")  # a fault latched before the engage: clear it, retry
            if now - self._since > ENGAGE_PATIENCE:
                self._finish("aborted", f"engage refused: {reply.get('reason')}", now)
            else:
                time.sleep(REPUBLISH_PERIOD)
        elif self._phase == "drive":
            if diag_time < self._since:
                return  # no diagnostics since the engage yet
            if state == "ENGAGED":
                self._engaged_seen = True
            # STANDBY ends the maneuver once ENGAGED was seen (or was too short to be seen).
            if state == "STANDBY" and (self._engaged_seen or now - self._since > SHORT_ENGAGEMENT):
                outcome = "completed" if TRAJECTORY_END in reason else "aborted"
                self._finish(outcome, reason, now)
            elif state == "FAULT":
                self._finish("aborted", f"FAULT: {diag.get('fault') or reason}", now)
            elif now - self._since > self._current.duration + MANEUVER_SLACK:
                self._request("disengage")
                self._finish("aborted", f"stuck in {state}: {reason}", now)

    def _finish(self, outcome: str, reason: str, now: float) -> None:
        self.maneuvers.append(Maneuver(self._current.name, outcome, reason, now - self._since))
        self.observer.plan = None
        self._phase = "plan"

    def interrupt(self, now: float) -> None:
        """The soak ends: a maneuver under way is recorded as interrupted."""
        if self._phase in ("engage", "drive"):
            self._finish("interrupted", "the soak ended", now)


def run_soak(args: argparse.Namespace) -> dict[str, Any]:
    """Start the stack, drive maneuvers for ``args.duration`` s, stop it; the report."""
    import can

    from leafgate.can.codec import CanCodec
    from leafgate.runtime.daemon import tool_view
    from leafgate.settings import load_config
    from leafgate.transport.session import open_session

    workdir = Path(tempfile.mkdtemp(prefix="leafgate-soak-"))
    config = private_config(Path(args.config), workdir)
    cfg = load_config(str(config))
    # Peers do not forward between peers: this process listens too, so that the ECU (told of
    # it by the daemon's gossip) connects and its localization reaches us directly.
    zcfg = dataclasses.replace(tool_view(cfg.zenoh), listen=(f"tcp/127.0.0.1:{free_port()}",))
    codec = CanCodec.for_config(cfg)
    command_ids = sorted(codec.receive_ids("commands"))
    report_ids = sorted(codec.receive_ids("reports"))
    system_id = next(i for i in report_ids if codec.name_of(i) == "DBW_SYSTEM_RPT")
    dbw = cfg.can.dbw
    sniffer = Sniffer(
        can.Bus(interface=dbw.interface, channel=dbw.channel, **dict(dbw.kwargs)),
        codec,
        system_id,
    )
    first = args.scenarios[0]
    rt = args.rt_priority
    ecu = _start(["sim-ecu", "--config", str(config), "--scenario", first], workdir / "ecu.log", rt)
    daemon = _start(["run", "--config", str(config)], workdir / "gateway.log", rt)
    session = open_session(zcfg)
    observer = Observer(session, zcfg)
    driver = Driver(observer, zcfg, session, args.scenarios)
    memory = {"gateway": MemoryTrack(), "ecu": MemoryTrack()}
    windows: list[dict[str, Any]] = []
    warmup = args.warmup if args.warmup is not None else min(60.0, args.duration / 3)
    died: list[str] = []

    def current_report(elapsed: float, final: Mapping[str, Any]) -> dict[str, Any]:
        diag, _ = observer.latest()
        last = diag.get("loop") or {}
        gaps, ecu_figures = sniffer.snapshot()
        return assemble_report(
            duration=elapsed,
            maneuvers=driver.maneuvers,
            refusals=driver.refusals,
            loop=loop_figures([*windows, last] if last else windows, last),
            memory=memory,
            gaps=gaps,
            command_ids=command_ids,
            report_ids=report_ids,
            ecu=ecu_figures,
            final=final,
            max_growth_mb=args.max_growth_mb,
        )

    load_before = os.getloadavg()  # other work on the machine shows in every timing figure
    t0 = time.monotonic()
    try:
        # The stack is up when the gateway's diagnostics and the ECU's localization arrive.
        while time.monotonic() - t0 < START_TIMEOUT:
            if observer.latest()[0] and observer.current_pose() is not None:
                break
            if daemon.poll() is not None or ecu.poll() is not None:
                break
            time.sleep(0.2)
        start = time.monotonic()
        next_rss = next_progress = next_window = start
        next_window += WINDOW_PERIOD
        next_progress += PROGRESS_PERIOD
        while (now := time.monotonic()) - start < args.duration:
            for name, proc in (("gateway", daemon), ("ecu", ecu)):
                if proc.poll() is not None and name not in died:
                    died.append(name)
            if died:
                break
            driver.step(now)
            if now >= next_rss:
                next_rss += RSS_PERIOD
                for name, proc in (("gateway", daemon), ("ecu", ecu)):
                    value = rss_mb(proc.pid)
                    if value is not None:
                        memory[name].add(value, now - start >= warmup)
            if now >= next_window:
                next_window += WINDOW_PERIOD
                loop = observer.latest()[0].get("loop")
                if loop:
                    windows.append(dict(loop))
            if now >= next_progress:
                next_progress += PROGRESS_PERIOD
                print(
                    progress_line(now - start, args.duration, current_report(now - start, {})),
                    file=sys.stderr,
                    flush=True,
                )
            time.sleep(POLL)
        end = time.monotonic()
        driver.interrupt(end)
        diag, _ = observer.latest()
        for name, proc in (("gateway", daemon), ("ecu", ecu)):
            value = rss_mb(proc.pid)
            if value is not None:
                memory[name].add(value, True)
        final_diag = dict(diag)
    finally:
        observer.close()
        gateway_exit = _stop(daemon)
        ecu_exit = _stop(ecu)
        session.close()
        time.sleep(0.3)  # the ECU's last reports reach the sniffer
        sniffer.close()
    ecu_log = (workdir / "ecu.log").read_text(errors="replace")
    final = {
        "gateway_state": final_diag.get("state"),
        "gateway_reason": final_diag.get("reason"),
        "gateway_fault": final_diag.get("fault"),
        "ecu_state": sniffer.ecu_state,
        "gateway_exit": gateway_exit,
        "ecu_exit": ecu_exit,
        "died": died,
        "ecu_loop": ecu_log_figures(ecu_log),
        # 1, 5 and 15 min load averages: on a 2-core machine anything above ~2 besides the
        # stack means the timing figures measure the neighbours too
        "load_average_start": [round(v, 2) for v in load_before],
        "load_average_end": [round(v, 2) for v in os.getloadavg()],
        "cpus": os.cpu_count(),
        "rt_priority": args.rt_priority,
        "logs": str(workdir),
    }
    return current_report(end - start, final)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=1800.0, help="s (default 1800)")
    parser.add_argument("--config", default=str(ROOT / "config" / "sim.yaml"))
    parser.add_argument(
        "--scenarios",
        type=lambda text: tuple(text.split(",")),
        default=DEFAULT_SCENARIOS,
        help=f"maneuvers in turn (default {','.join(DEFAULT_SCENARIOS)})",
    )
    parser.add_argument(
        "--warmup", type=float, default=None, help="s before the memory baseline (min(60, T/3))"
    )
    parser.add_argument("--max-growth-mb", type=float, default=20.0)
    parser.add_argument("--out", help="also write the JSON report here")
    parser.add_argument("--no-fail", action="store_true", help="exit 0 whatever the goals")
    parser.add_argument(
        "--rt-priority",
        type=int,
        metavar="N",
        help="run the gateway and the simulated ECU under SCHED_FIFO priority N (chrt -f), as "
        "tools/leafgate.service runs the daemon on the car (needs CAP_SYS_NICE)",
    )
    args = parser.parse_args(argv)
    report = run_soak(args)
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    if not report["passed"]:
        missed = [name for name, ok in report["goals"].items() if not ok]
        print(f"soak: goals missed: {', '.join(missed)}", file=sys.stderr)
    return 0 if report["passed"] or args.no_fail else 1


if __name__ == "__main__":
    sys.exit(main())
