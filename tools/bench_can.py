"""CAN codec throughput against plain cantools, and the simulated ECU's report jitter.

Decode. Leaf-like traffic is generated with the codec itself, at the periods of docs/can-protocol.md: DBW
reports at 10 (steer), 20 (long) and 100 ms (system), commands at 20 and 100 ms, CAR-CAN
0x002 at 100 Hz, 0x284/0x285 at 50 Hz, 0x421 at 10 Hz and 0x176 at its DBC period. Each frame
is decoded by

* ``codec``: :meth:`CanCodec.decode` — length, CRC and counter checks, dataclass built;
* ``cantools``: ``Database.decode_message(id, data, decode_choices=False)`` on the right
  database — signals only, no E2E, no dataclass;
* ``naive``: what the codec would cost built on cantools — ``decode_message``, the same CRC
  and counter checks, and the same message dataclass built from the signal dict.

Encode (``encode``): the same traffic's message values encoded into frames by
:meth:`CanCodec.encode` (range checks, scaling and packing compiled from the DBC) and by
cantools' strict ``Message.encode`` with the same checks, alive counters, E2E and
``can.Message`` around it (what ``CanCodec.encode`` did before it was compiled). Both must
produce the same bytes (``identical``).

ECU report jitter (``ecu_jitter``): ``python -m leafgate.cli sim-ecu`` runs as a subprocess on
a copy of ``config/sim.yaml`` with a private multicast group (239.74.x.y), a free UDP port and a
free Zenoh listen port. This process receives on a python-can ``udp_multicast`` bus for
``--jitter-seconds``, starting 1 s after the first DBW_STEER_RPT (0x0B0; the second skips the
ECU's start-up), and takes the frames' receive timestamps (the kernel's, SO_TIMESTAMP, so this
process's own scheduling does not count). Jitter is ``|period - 10 ms|`` between consecutive
frames with no frame lost between them: a late frame counts (also one late because the ECU
skipped a period after an overrun), a lost one does not. ``frames_lost`` counts the gaps in the
alive counter. ``--jitter-seconds 0`` skips it. The sender shares this machine's cores with the
receiver, so the figures hold for an idle machine only.

Prints one JSON object on stdout (nothing else; failures go to stderr with exit status 1).

    .venv/bin/python tools/bench_can.py [--seconds 20] [--repeat 5] [--jitter-seconds 10]
    .venv/bin/python tools/bench_can.py --jitter-seconds 0     # codec only, no subprocess
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
import yaml
from _common import free_port

from leafgate.can import e2e
from leafgate.can.codec import CanCodec, Decoded, EncodableMessage
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


def traffic_values(codec: CanCodec, seconds: float) -> list[tuple[float, int, EncodableMessage]]:
    """``seconds`` of Leaf traffic as (time in s, CAN ID, message value), time-ordered."""
    dbw, car = codec.databases
    period = {m.frame_id: (m.cycle_time or 100) / 1000.0 for m in [*dbw.messages, *car.messages]}
    ids = {
        "steer_rpt": 0x0B0,
        "long_rpt": 0x0B1,
        "sys_rpt": 0x0B2,
        "steer_cmd": 0x0A0,
        "long_cmd": 0x0A1,
        "sys_cmd": 0x0A2,
        "swa": 0x002,
        "front": 0x284,
        "rear": 0x285,
        "gear": 0x421,
        "motor": 0x176,
    }

    def value(kind: str, t: float) -> EncodableMessage:
        angle = 0.4 * math.sin(0.5 * t)  # rad
        speed = 2.0 + math.sin(0.2 * t)  # m/s
        makers: dict[str, Callable[[], EncodableMessage]] = {
            "steer_rpt": lambda: SteerReport(angle, 0.2, 0.5, True, False, False, False),
            "long_rpt": lambda: LongReport(
                speed, 0.3, Gear.D, 0.0, 12.5, True, False, False, False
            ),
            "sys_rpt": lambda: SystemReport(EcuState.ENGAGED, False, False, False, False, 0),
            "steer_cmd": lambda: SteerCommand(angle, 0.3, True, False),
            "long_cmd": lambda: LongCommand(LongMode.SPEED, 0.0, speed, Gear.D, True, False),
            "sys_cmd": lambda: SystemCommand(GatewayState.ENGAGED),
            "swa": lambda: SteeringWheelAngle(angle * 18.25),
            "front": lambda: WheelSpeeds(speed, speed, "front"),
            "rear": lambda: WheelSpeeds(speed, speed, "rear"),
            "gear": lambda: GearPosition(Gear.D),
            "motor": lambda: MotorSpeed(speed),
        }
        return makers[kind]()

    values: list[tuple[float, int, EncodableMessage]] = []
    for kind, frame_id in ids.items():
        dt = period[frame_id]
        values.extend((k * dt, frame_id, value(kind, k * dt)) for k in range(int(seconds / dt)))
    values.sort(key=lambda item: item[0])
    return values


def traffic(codec: CanCodec, seconds: float) -> list[can.Message]:
    """A time-ordered recording of ``seconds`` of Leaf traffic, values varying over time."""
    return [codec.encode(v, timestamp=t) for t, _, v in traffic_values(codec, seconds)]


def _cantools_encoder(codec: CanCodec) -> Callable[[float, int, EncodableMessage], can.Message]:
    """Encode as CanCodec.encode did on cantools: strict ``Message.encode``, then E2E."""
    counters: dict[int, int] = {}

    def encode(t: float, frame_id: int, value: EncodableMessage) -> can.Message:
        counter = counters.get(frame_id, 0)
        data = codec._encode_with_cantools(value, counter)
        counters[frame_id] = counter + 1  # taken modulo the frame's counter width
        return can.Message(
            timestamp=t, arbitration_id=frame_id, is_extended_id=False, dlc=len(data), data=data
        )

    return encode


def _naive_decoder(codec: CanCodec) -> Callable[[can.Message], object]:
    """Decode as a straightforward cantools-based codec would, to the same dataclasses."""
    dbw, car = codec.databases
    by_id = {
        m.frame_id: (m, m.frame_id in codec.receive_ids("car"))
        for m in [*dbw.messages, *car.messages]
    }
    checker = e2e.CounterChecker()
    deg, kmh = math.pi / 180.0, 3.6
    build = {
        "DBW_STEER_CMD": lambda s: SteerCommand(
            s["STEER_ANGLE_CMD"],
            s["STEER_RATE_LIMIT"],
            bool(s["ENABLE"]),
            bool(s["CLEAR_OVERRIDE"]),
        ),
        "DBW_LONG_CMD": lambda s: LongCommand(
            LongMode(s["MODE"]),
            s["ACCEL_CMD"],
            s["SPEED_CMD"],
            Gear(s["GEAR_REQ"]),
            bool(s["ENABLE"]),
            bool(s["CLEAR_OVERRIDE"]),
        ),
        "DBW_SYSTEM_CMD": lambda s: SystemCommand(
            GatewayState(s["GATEWAY_STATE"]), bool(s["CLEAR_FAULTS"])
        ),
        "DBW_STEER_RPT": lambda s: SteerReport(
            s["STEER_ANGLE"],
            s["STEER_RATE"],
            s["DRIVER_TORQUE"],
            bool(s["ENABLED"]),
            bool(s["OVERRIDE"]),
            bool(s["FAULT"]),
            bool(s["CMD_TIMEOUT"]),
        ),
        "DBW_LONG_RPT": lambda s: LongReport(
            s["SPEED"],
            s["ACCEL"],
            Gear(s["GEAR"]),
            s["BRAKE_PEDAL"],
            s["ACCEL_PEDAL"],
            bool(s["ENABLED"]),
            bool(s["OVERRIDE"]),
            bool(s["FAULT"]),
            bool(s["CMD_TIMEOUT"]),
        ),
        "DBW_SYSTEM_RPT": lambda s: SystemReport(
            EcuState(s["ECU_STATE"]),
            bool(s["FAULT_CMD_TIMEOUT"]),
            bool(s["FAULT_BAD_CRC"]),
            bool(s["FAULT_BAD_COUNTER"]),
            bool(s["FAULT_ACTUATOR"]),
            int(s["RX_ERROR_COUNT"]),
        ),
        "STEER_ANGLE_SENSOR": lambda s: SteeringWheelAngle(s["STEER_ANGLE"] * deg),
        "OUTPUT_SPEED": lambda s: MotorSpeed(s["OUTPUT_REVS"] * 0.004),
        "WHEEL_SPEEDS_FRONT": lambda s: WheelSpeeds(
            s["WHEEL_SPEED_FL"] / kmh, s["WHEEL_SPEED_FR"] / kmh, "front"
        ),
        "WHEEL_SPEEDS_REAR": lambda s: WheelSpeeds(
            s["WHEEL_SPEED_RL"] / kmh, s["WHEEL_SPEED_RR"] / kmh, "rear"
        ),
        "GEAR_POSITION": lambda s: GearPosition(Gear(s["GEAR_SHIFTER"])),
    }

    def decode(msg: can.Message) -> object:
        message, is_car = by_id[msg.arbitration_id]
        data = bytes(msg.data)
        ok = is_car or (
            e2e.verify(msg.arbitration_id, data)
            and checker.check(msg.arbitration_id, e2e.counter_of(data)).ok
        )
        value = build[message.name](message.decode(data, decode_choices=False))
        return Decoded(msg.arbitration_id, message.name, value, ok, None if ok else "bad_crc")

    return decode


def _best_interleaved(runs: dict[str, Callable[[], None]], repeat: int) -> dict[str, float]:
    """Best wall time of each run, the runs taking turns so that they share the machine's load."""
    best = dict.fromkeys(runs, math.inf)
    for _ in range(repeat):
        for name, run in runs.items():
            t0 = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def bench(seconds: float, repeat: int) -> dict[str, object]:
    values = traffic_values(CanCodec(profile="leafgate-dbw"), seconds)
    frames = traffic(CanCodec(profile="leafgate-dbw"), seconds)
    dbw, car = CanCodec(profile="leafgate-dbw").databases
    car_ids = {m.frame_id for m in car.messages}
    plain = [
        (car if f.arbitration_id in car_ids else dbw, f.arbitration_id, bytes(f.data))
        for f in frames
    ]
    invalid: list[int] = []
    encoded: dict[str, list[bytes]] = {}

    def run_codec() -> None:
        codec = CanCodec(
            profile="leafgate-dbw"
        )  # fresh counter state: every frame of the recording is valid
        for f in frames:
            codec.decode(f)
        invalid.append(sum(s.errors for s in codec.stats.values()))

    def run_cantools() -> None:
        for db, frame_id, data in plain:
            db.decode_message(frame_id, data, decode_choices=False)

    def run_naive() -> None:
        decode = _naive_decoder(CanCodec(profile="leafgate-dbw"))
        for f in frames:
            decode(f)

    def run_encode_codec() -> None:
        codec = CanCodec(profile="leafgate-dbw")
        encoded["codec"] = [bytes(codec.encode(v, timestamp=t).data) for t, _, v in values]

    def run_encode_cantools() -> None:
        encode = _cantools_encoder(CanCodec(profile="leafgate-dbw"))
        encoded["cantools"] = [bytes(encode(t, i, v).data) for t, i, v in values]

    best = _best_interleaved(
        {
            "codec": run_codec,
            "cantools": run_cantools,
            "naive": run_naive,
            "encode_codec": run_encode_codec,
            "encode_cantools": run_encode_cantools,
        },
        repeat,
    )
    codec_s, cantools_s, naive_s = best["codec"], best["cantools"], best["naive"]
    enc_codec_s, enc_cantools_s = best["encode_codec"], best["encode_cantools"]
    n = len(frames)
    return {
        "benchmark": "can",
        "frames": n,
        "traffic_seconds": seconds,
        "repeat": repeat,
        "invalid_frames": max(invalid),
        "codec_frames_per_s": round(n / codec_s),
        "cantools_frames_per_s": round(n / cantools_s),
        "naive_frames_per_s": round(n / naive_s),
        "codec_us_per_frame": round(1e6 * codec_s / n, 3),
        "cantools_us_per_frame": round(1e6 * cantools_s / n, 3),
        "naive_us_per_frame": round(1e6 * naive_s / n, 3),
        "ratio_codec_over_cantools": round(cantools_s / codec_s, 2),
        "ratio_codec_over_naive": round(naive_s / codec_s, 2),
        "encode": {
            "frames": len(values),
            "codec_frames_per_s": round(len(values) / enc_codec_s),
            "cantools_frames_per_s": round(len(values) / enc_cantools_s),
            "codec_us_per_frame": round(1e6 * enc_codec_s / len(values), 3),
            "cantools_us_per_frame": round(1e6 * enc_cantools_s / len(values), 3),
            "ratio_codec_over_cantools": round(enc_cantools_s / enc_codec_s, 2),
            "identical": encoded["codec"] == encoded["cantools"],
        },
        "python": platform.python_version(),
    }


# --- the simulated ECU's report period, seen from another process ------------------------------

ROOT = Path(__file__).resolve().parent.parent
STEER_RPT = 0x0B0  # DBW_STEER_RPT, sent every 10 ms by the ECU
WARMUP = 1.0  # s after the first frame not measured: the ECU's start-up (first ticks, Zenoh)


class BenchError(Exception):
    """The jitter measurement could not run (the ECU did not start, or sent nothing)."""


def _private_config(directory: Path) -> tuple[Path, str, int]:
    """config/sim.yaml with its own multicast group, UDP port and Zenoh port, so that parallel
    runs (and a daemon already running on the defaults) do not meet; (path, group, port)."""
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text(encoding="utf-8"))
    group = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    port = free_port(socket.SOCK_DGRAM)
    cfg["can"]["dbw"]["channel"] = group
    cfg["can"]["dbw"]["kwargs"] = {"port": port}
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    path = directory / "sim.yaml"
    path.write_text(yaml.safe_dump(cfg), encoding="utf-8")
    return path, group, port


def _receive_steer_reports(
    bus: can.BusABC, ecu: subprocess.Popen[bytes], seconds: float, startup_timeout: float
) -> list[can.Message]:
    """The 0x0B0 frames received over ``seconds``, from ``WARMUP`` after the first one."""
    frames: list[can.Message] = []
    start_by = time.monotonic() + startup_timeout
    begin: float | None = None
    while begin is None or time.monotonic() < begin + seconds:
        if begin is None and time.monotonic() > start_by:
            raise BenchError(f"no DBW_STEER_RPT within {startup_timeout:.0f} s of start-up")
        if ecu.poll() is not None:
            raise BenchError(f"sim-ecu exited with status {ecu.returncode}")
        msg = bus.recv(timeout=0.1)
        if msg is None or msg.arbitration_id != STEER_RPT or msg.is_extended_id:
            continue
        if begin is None:
            begin = time.monotonic() + WARMUP
        elif time.monotonic() >= begin:
            frames.append(msg)
    return frames


def period_stats(frames: list[can.Message], period: float) -> dict[str, object]:
    """Period jitter and losses of one periodic E2E frame from its receive timestamps.

    :param period: s, the nominal period
    """
    stamps = np.array([f.timestamp for f in frames])
    counters = [e2e.counter_of(f.data) for f in frames]
    jitter, lost = [], 0
    for k, dt in enumerate(np.diff(stamps)):
        # The alive counter tells lost frames from periods the ECU skipped after an overrun
        # (which it does not send, so they show as a late frame, not a loss). 16 frames lost
        # in a row would look like none.
        gap = (counters[k + 1] - counters[k] - 1) % e2e.COUNTER_MODULO
        lost += gap
        if gap == 0:
            jitter.append(abs(dt - period))
    j = np.array(jitter) * 1e3  # ms
    return {
        "frames": len(frames),
        "frames_lost": lost,
        "seconds": round(float(stamps[-1] - stamps[0]), 3),
        "period_ms": period * 1e3,
        "mean_period_ms": round(float(np.mean(np.diff(stamps))) * 1e3, 4),
        "jitter_ms_median": round(float(np.median(j)), 4),
        "jitter_ms_p99": round(float(np.percentile(j, 99)), 4),
        "jitter_ms_max": round(float(np.max(j)), 4),
        "periods_measured": len(jitter),
    }


def ecu_jitter(seconds: float, startup_timeout: float = 60.0) -> dict[str, object]:
    """Run ``leafgate sim-ecu`` as a subprocess and measure its 0x0B0 period on the bus.

    :raises BenchError: the ECU did not start or sent too few frames
    """
    message = CanCodec(profile="leafgate-dbw").message(STEER_RPT)
    assert message is not None and message.cycle_time, "the DBW DBC gives 0x0B0 a cycle time"
    period = message.cycle_time / 1000.0  # s, from the DBC
    with tempfile.TemporaryDirectory(prefix="leafgate-bench-") as tmp:
        config, group, port = _private_config(Path(tmp))
        log_path = Path(tmp) / "sim-ecu.log"
        # Listen before the ECU starts, so that its first frames find a receiver.
        with (
            can.Bus(interface="udp_multicast", channel=group, port=port) as bus,
            log_path.open("wb") as log,
        ):
            ecu = subprocess.Popen(
                [sys.executable, "-m", "leafgate.cli", "sim-ecu", "--config", str(config)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                cwd=ROOT,
            )
            try:
                frames = _receive_steer_reports(bus, ecu, seconds, startup_timeout)
            except BenchError as exc:
                raise BenchError(f"{exc}; sim-ecu log: {_tail(log_path)}") from None
            finally:
                _stop(ecu)
    if len(frames) < 3:
        raise BenchError(f"only {len(frames)} DBW_STEER_RPT frames in {seconds} s")
    return {
        "sender": "leafgate sim-ecu (subprocess)",
        "receiver": "python-can udp_multicast, kernel receive timestamps",
        "cpus": _cpus(),
        **period_stats(frames, period),
    }


def _stop(process: subprocess.Popen[bytes]) -> None:
    """SIGINT (the ECU's clean shutdown), then SIGKILL if it does not exit."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _tail(path: Path, lines: int = 5) -> str:
    text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    return " | ".join(text[-lines:]) or "(empty)"


def _cpus() -> int:
    import os

    return len(os.sched_getaffinity(0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="traffic to generate, s")
    parser.add_argument("--repeat", type=int, default=5, help="runs; the best one counts")
    parser.add_argument(
        "--jitter-seconds",
        type=float,
        default=10.0,
        help="s to receive the simulated ECU's DBW_STEER_RPT for (0: skip)",
    )
    args = parser.parse_args()
    result = bench(args.seconds, args.repeat)
    if args.jitter_seconds > 0:
        try:
            result["ecu_jitter"] = ecu_jitter(args.jitter_seconds)
        except BenchError as exc:
            print(f"bench_can: ECU jitter: {exc}", file=sys.stderr)
            return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
