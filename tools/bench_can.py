"""Decode throughput of CanCodec.decode against plain cantools, on Leaf-like traffic.

The traffic is generated with the codec itself, at the DESIGN periods: DBW reports at 10
(steer), 20 (long) and 100 ms (system), commands at 20 and 100 ms, CAR-CAN 0x002 at 100 Hz,
0x284/0x285 at 50 Hz, 0x421 at 10 Hz and 0x176 at its DBC period. Each frame is decoded by

* ``codec``: :meth:`CanCodec.decode` — length, CRC and counter checks, dataclass built;
* ``cantools``: ``Database.decode_message(id, data, decode_choices=False)`` on the right
  database — signals only, no E2E, no dataclass;
* ``naive``: what the codec would cost built on cantools — ``decode_message``, the same CRC
  and counter checks, and the same message dataclass built from the signal dict.

Prints one JSON object: frames per second of each, and the codec's speed-up over both.

    .venv/bin/python tools/bench_can.py [--seconds 20] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Callable

import can

from leafgate.can import e2e
from leafgate.can.codec import CanCodec, Decoded
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


def traffic(codec: CanCodec, seconds: float) -> list[can.Message]:
    """A time-ordered recording of ``seconds`` of Leaf traffic, values varying over time."""
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

    def value(kind: str, t: float) -> object:
        angle = 0.4 * math.sin(0.5 * t)  # rad
        speed = 2.0 + math.sin(0.2 * t)  # m/s
        return {
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
        }[kind]()

    frames: list[tuple[float, can.Message]] = []
    for kind, frame_id in ids.items():
        dt = period[frame_id]
        for k in range(int(seconds / dt)):
            t = k * dt
            frames.append((t, codec.encode(value(kind, t), timestamp=t)))  # type: ignore[arg-type]
    frames.sort(key=lambda item: item[0])
    return [msg for _, msg in frames]


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
        "MOTOR_SPEED": lambda s: MotorSpeed(s["MOTOR_REVS"] * 0.004),
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
    frames = traffic(CanCodec(), seconds)
    dbw, car = CanCodec().databases
    car_ids = {m.frame_id for m in car.messages}
    plain = [
        (car if f.arbitration_id in car_ids else dbw, f.arbitration_id, bytes(f.data))
        for f in frames
    ]
    invalid: list[int] = []

    def run_codec() -> None:
        codec = CanCodec()  # fresh counter state: every frame of the recording is valid
        for f in frames:
            codec.decode(f)
        invalid.append(sum(s.errors for s in codec.stats.values()))

    def run_cantools() -> None:
        for db, frame_id, data in plain:
            db.decode_message(frame_id, data, decode_choices=False)

    def run_naive() -> None:
        decode = _naive_decoder(CanCodec())
        for f in frames:
            decode(f)

    best = _best_interleaved(
        {"codec": run_codec, "cantools": run_cantools, "naive": run_naive}, repeat
    )
    codec_s, cantools_s, naive_s = best["codec"], best["cantools"], best["naive"]
    n = len(frames)
    return {
        "benchmark": "can_decode",
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
        "python": platform.python_version(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="traffic to generate, s")
    parser.add_argument("--repeat", type=int, default=5, help="runs; the best one counts")
    args = parser.parse_args()
    print(json.dumps(bench(args.seconds, args.repeat)))


if __name__ == "__main__":
    main()
