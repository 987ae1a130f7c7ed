"""Throughput of ``leafgate replay check`` against reading the log bare and ``cantools decode``.

A candump ``.log`` of realistic Leaf traffic is generated (default 10 minutes at ≈ 2,000
frames/s): the leafgate DBW frames at their DBC periods (an engaged drive with steering and
speed within the safety limits), the decoded CAR-CAN frames (0x002, 0x176, 0x284, 0x285, 0x421)
and, to fill the bus as the real Leaf does, other CAR-CAN IDs with changing payloads that no
leafgate DBC describes. Then, on the same file:

* ``logreader``: ``for msg in can.LogReader(path)`` — the ceiling, parsing only;
* ``check``: :func:`leafgate.replay.check.check_log` — parsing, E2E, periods and gaps, the
  safety re-check of every engaged command;
* ``cantools_decode``: ``python -m cantools decode dbc/leafgate_dbw.dbc < log`` — what a user
  would run instead (decodes the DBW frames it knows, prints every line; no checks).

Prints one JSON object (frames/s of each, and check's share of the ceiling).

    .venv/bin/python tools/bench_replay.py [--minutes 10] [--rate 2000] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can

from leafgate.can.codec import CanCodec
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    GearPosition,
    LongCommand,
    LongMode,
    LongReport,
    MotorSpeed,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    WheelSpeeds,
)
from leafgate.replay.check import check_log

ROOT = Path(__file__).resolve().parents[1]
# (period s) of the decoded frames; the DBW periods are the DBC's
DECODED = {
    "steer_cmd": 0.020,
    "long_cmd": 0.020,
    "sys_cmd": 0.100,
    "steer_rpt": 0.010,
    "long_rpt": 0.020,
    "sys_rpt": 0.100,
    "swa": 0.010,
    "motor": 0.010,
    "front": 0.020,
    "rear": 0.020,
    "gear": 0.100,
}
FILLER_PERIODS = (0.010, 0.010, 0.020, 0.020, 0.020, 0.040, 0.050, 0.100, 0.100, 0.500)  # s


def _value(kind: str, t: float) -> object:
    angle = 0.3 * math.sin(2.0 * math.pi * t / 12.0)  # rad, ≤ 0.16 rad/s: inside every rate limit
    speed = 1.5 + 0.5 * math.sin(2.0 * math.pi * t / 60.0)  # m/s, under the 3 m/s limit
    accel = 0.5 * 2.0 * math.pi / 60.0 * math.cos(2.0 * math.pi * t / 60.0)  # m/s², d(speed)/dt
    return {
        "steer_cmd": lambda: SteerCommand(angle, 0.0, True, False),
        "long_cmd": lambda: LongCommand(LongMode.ACCELERATION, accel, 0.0, Gear.NONE, True, False),
        "sys_cmd": lambda: SystemCommand(GatewayState.ENGAGED),
        "steer_rpt": lambda: SteerReport(angle, 0.1, 0.3, True, False, False, False),
        "long_rpt": lambda: LongReport(speed, accel, Gear.D, 0.0, 10.0, True, False, False, False),
        "sys_rpt": lambda: SystemReport(EcuState.ENGAGED, False, False, False, False, 0),
        "swa": lambda: SteeringWheelAngle(angle * 18.25),
        "motor": lambda: MotorSpeed(speed),
        "front": lambda: WheelSpeeds(speed, speed, "front"),
        "rear": lambda: WheelSpeeds(speed, speed, "rear"),
        "gear": lambda: GearPosition(Gear.D),
    }[kind]()


def generate(path: Path, seconds: float, rate: float) -> int:
    """Write the traffic to a candump log; return the number of frames."""
    sender, ecu = (
        CanCodec(profile="leafgate-dbw"),
        CanCodec(profile="leafgate-dbw"),
    )  # separate alive counters, as on the car
    t0 = 1_700_000_000.0  # s, an epoch time as a logger writes
    rows: list[tuple[float, int, object]] = []  # (t, order, what)
    for kind, period in DECODED.items():
        for k in range(int(seconds / period)):
            rows.append((k * period, 0, kind))
    decoded_rate = sum(1.0 / p for p in DECODED.values())
    filler_ids = [0x100 + 0x11 * i for i in range(64)]
    per_id = sum(1.0 / p for p in FILLER_PERIODS) / len(FILLER_PERIODS)
    n_fill = max(0, round((rate - decoded_rate) / per_id))
    for j in range(n_fill):
        period = FILLER_PERIODS[j % len(FILLER_PERIODS)]
        offset = (j * 0.00037) % period  # spread the IDs over the period
        for k in range(int(seconds / period)):
            rows.append((offset + k * period, 1, filler_ids[j % len(filler_ids)] + j // 64))
    rows.sort(key=lambda r: r[0])
    with can.CanutilsLogWriter(path, channel="can0") as writer:
        for t, _, what in rows:
            if isinstance(what, str):
                codec = sender if what.endswith("cmd") else ecu
                msg = codec.encode(_value(what, t), timestamp=t0 + t)  # type: ignore[arg-type]
                msg.is_rx = not what.endswith("cmd")
            else:
                k = int(t * 1000) & 0xFF
                msg = can.Message(
                    timestamp=t0 + t,
                    arbitration_id=int(what),
                    data=bytes((k + i) & 0xFF for i in range(8)),
                    is_extended_id=False,
                )
            writer.on_message_received(msg)
    return len(rows)


def time_logreader(path: Path) -> tuple[int, float]:
    t = time.perf_counter()
    n = sum(1 for _ in can.LogReader(path))
    return n, time.perf_counter() - t


def time_check(path: Path) -> tuple[int, float, dict[str, object]]:
    t = time.perf_counter()
    report = check_log(path, profile="leafgate-dbw")
    elapsed = time.perf_counter() - t
    summary = report.to_dict()
    return report.frames, elapsed, {k: summary[k] for k in ("violations", "e2e_errors", "gaps")}


def time_cantools(path: Path) -> float:
    dbc = ROOT / "dbc" / "leafgate_dbw.dbc"
    t = time.perf_counter()
    with path.open("rb") as src:
        subprocess.run(
            [sys.executable, "-m", "cantools", "decode", str(dbc)],
            stdin=src,
            stdout=subprocess.DEVNULL,
            check=True,
        )
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the log")
    parser.add_argument("--rate", type=float, default=2000.0, help="frames/s on the bus")
    parser.add_argument("--keep", type=Path, help="write the log into this directory")
    parser.add_argument("--no-cantools", action="store_true", help="skip cantools decode")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        directory = args.keep or Path(tmp)
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "leaf-traffic.log"
        t = time.perf_counter()
        frames = generate(path, args.minutes * 60.0, args.rate)
        generate_s = time.perf_counter() - t
        n_reader, reader_s = time_logreader(path)
        n_check, check_s, findings = time_check(path)
        cantools_s = None if args.no_cantools else time_cantools(path)
        result = {
            "log": {
                "format": "candump .log",
                "frames": frames,
                "seconds": args.minutes * 60.0,
                "frames_per_s_on_bus": frames / (args.minutes * 60.0),
                "bytes": path.stat().st_size,
                "generate_s": generate_s,
            },
            "logreader": {"frames": n_reader, "s": reader_s, "frames_per_s": n_reader / reader_s},
            "check": {
                "frames": n_check,
                "s": check_s,
                "frames_per_s": n_check / check_s,
                "findings": findings,
            },
            "cantools_decode": None
            if cantools_s is None
            else {"frames": frames, "s": cantools_s, "frames_per_s": frames / cantools_s},
            "check_share_of_logreader": reader_s / check_s,
            "check_speedup_over_cantools": None if cantools_s is None else cantools_s / check_s,
            "python": platform.python_version(),
            "machine": platform.machine(),
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
