"""Control-loop figures of the daemon; prints JSON.

1. ``compute`` — the time from inputs to frames handed to the bus, for one control tick
   (``Runtime.tick``: read slots, ``Gateway.step`` with the MPC, encode, send on a ``virtual``
   bus), over the whole s-curve while engaged, in one process with nothing else running. Beside
   it the controller's own step time, and ``Gateway.step`` alone, from the same ticks.
2. ``jitter`` — the period of DBW_STEER_CMD (0x0A0, nominal 20 ms) as received by this process
   from ``leafgate run`` in another process (with ``leafgate sim-ecu`` on the same
   ``udp_multicast`` bus, the s-curve published and the gateway engaged): median, p99 and max of
   |period − 20 ms|, first idle, then with 4,000 frames/s of unrelated traffic on the bus (a
   saturated 500 kbit/s bus). The daemon's own overrun count comes from its diagnostics.

Run: ``.venv/bin/python tools/bench_loop.py [--seconds 10] [--skip-jitter]``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import yaml
from _common import free_port

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "leafgate.cli"]
STEER_CMD = 0x0A0
LOAD_ID = 0x3FF  # not a leafgate ID: traffic the gateway must receive and discard
LOAD_FPS = 4000  # frames/s, a saturated 500 kbit/s bus


def stats_us(values: list[float] | np.ndarray) -> dict[str, float]:
    arr = np.asarray(values, dtype=float) * 1e6
    return {
        "median_us": round(float(np.median(arr)), 1),
        "p99_us": round(float(np.percentile(arr, 99)), 1),
        "max_us": round(float(np.max(arr)), 1),
        "n": int(arr.size),
    }


def bench_compute() -> dict[str, Any]:
    """Runtime.tick on a simulated clock, with the simulated ECU stepped between ticks."""
    from leafgate.can.codec import CanCodec
    from leafgate.messages import GatewayState, OperatorRequest, Pose, Stamped
    from leafgate.runtime.daemon import build_gateway
    from leafgate.runtime.loop import Runtime
    from leafgate.runtime.receiver import CanReceiver
    from leafgate.settings import LeafgateConfig
    from leafgate.sim.ecu import SimulatedEcu
    from leafgate.sim.plant import make_plant
    from leafgate.sim.scenarios import get_scenario

    cfg = LeafgateConfig()
    scenario = get_scenario("s-curve")
    clock = [0.0]
    gateway = build_gateway(cfg)
    plant = make_plant(cfg.sim.plant, cfg.vehicle, scenario.start)
    ecu = SimulatedEcu(cfg.sim.ecu, plant, cfg.vehicle, CanCodec(profile="leafgate-dbw"))
    codec = CanCodec(profile="leafgate-dbw")
    receiver = CanReceiver(codec, lambda: clock[0])

    class Inputs:
        def latest_pose(self) -> Stamped[Pose]:
            return Stamped(plant.pose(), clock[0])

        def latest_trajectory(self) -> Stamped[Any]:
            return Stamped(scenario.trajectory, 0.0)

    with (
        can.Bus(interface="virtual", channel="bench-loop") as gw_bus,
        can.Bus(interface="virtual", channel="bench-loop") as ecu_bus,
    ):
        runtime = Runtime(gateway, codec, gw_bus, receiver, Inputs(), 0.02, clock=lambda: clock[0])
        # Time the tick with the real clock, not the simulated one.
        runtime.clock = time.perf_counter
        step_times: list[float] = []
        controller_times: list[float] = []
        real_step = gateway.step

        def timed_step(now: float, inputs: Any) -> Any:
            t0 = time.perf_counter()
            result = real_step(now, inputs)
            step_times.append(time.perf_counter() - t0)
            if result.diagnostics.controller is not None:
                controller_times.append(result.diagnostics.controller.solve_time)
            return result

        gateway.step = timed_step  # type: ignore[method-assign]
        engaged = False
        for k in range(int(scenario.duration / 0.01)):
            clock[0] = k * 0.01
            ecu.step(clock[0], 0.01)
            for msg in ecu.reports(clock[0]):
                ecu_bus.send(msg)
            while (rx := gw_bus.recv(timeout=0)) is not None:
                receiver.on_message_received(rx)
            if k % 2:
                continue
            request = OperatorRequest.ENGAGE if clock[0] == 0.5 else None
            runtime.tick(clock[0], request=request)
            engaged |= gateway.state == GatewayState.ENGAGED
            while (cmd := ecu_bus.recv(timeout=0)) is not None:
                ecu.receive_frame(clock[0], cmd)
            if engaged and gateway.state == GatewayState.STANDBY:
                break
    return {
        "tick_inputs_to_bus": stats_us(list(runtime.stats.compute)),
        "gateway_step": stats_us(step_times),
        "controller_step": stats_us(controller_times),
        "ticks": runtime.stats.ticks,
        "note": "one process, simulated clock, virtual bus; the tick includes encode and send",
    }


def load_generator(channel: str, port: int, fps: int, seconds: float) -> None:
    """Send ``fps`` frames/s of an unrelated ID, in bursts every 2 ms."""
    with can.Bus(interface="udp_multicast", channel=channel, port=port) as bus:
        msg = can.Message(arbitration_id=LOAD_ID, data=bytes(8), is_extended_id=False)
        burst = max(1, fps // 500)
        start = time.perf_counter()
        k = sent = 0
        while time.perf_counter() - start < seconds:
            for _ in range(burst):
                bus.send(msg)
            sent += burst
            k += 1
            delay = start + k * 0.002 - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        print(json.dumps({"load_fps": round(sent / (time.perf_counter() - start))}), flush=True)


def receive_periods(channel: str, port: int, seconds: float) -> list[float]:
    """Local receive times of 0x0A0 (this process's clock), as periods."""
    times: list[float] = []
    with can.Bus(
        interface="udp_multicast",
        channel=channel,
        port=port,
        can_filters=[{"can_id": STEER_CMD, "can_mask": 0x7FF}],
    ) as bus:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            msg = bus.recv(timeout=0.1)
            if msg is not None and msg.arbitration_id == STEER_CMD:
                times.append(time.perf_counter())
    return list(np.diff(times))


def jitter_figures(periods: list[float], nominal: float = 0.02) -> dict[str, float]:
    dev = np.abs(np.asarray(periods) - nominal) * 1e3
    return {
        "frames": len(periods) + 1,
        "period_mean_ms": round(float(np.mean(periods)) * 1e3, 3),
        "deviation_median_ms": round(float(np.median(dev)), 3),
        "deviation_p99_ms": round(float(np.percentile(dev, 99)), 3),
        "deviation_max_ms": round(float(np.max(dev)), 3),
    }


def daemon_loop_stats(config: Path) -> dict[str, Any]:
    out = subprocess.run(
        [*CLI, "status", "--config", str(config), "--duration", "0.5", "--json"],
        capture_output=True,
        text=True,
        timeout=20,
    ).stdout
    lines = [line for line in out.splitlines() if line.startswith("{")]
    return json.loads(lines[-1]).get("loop", {}) if lines else {}


def bench_jitter(seconds: float) -> dict[str, Any]:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    channel = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    port = free_port()
    cfg["can"]["dbw"] = {"interface": "udp_multicast", "channel": channel, "kwargs": {"port": port}}
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    tmp = Path(tempfile.mkdtemp(prefix="bench-loop-"))
    config = tmp / "sim.yaml"
    config.write_text(yaml.safe_dump(cfg))
    procs: list[subprocess.Popen[bytes]] = []

    def start(*args: str) -> subprocess.Popen[bytes]:
        proc = subprocess.Popen([*CLI, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(proc)
        return proc

    result: dict[str, Any] = {}
    try:
        start("sim-ecu", "--config", str(config))
        start("run", "--config", str(config))
        start("publish-trajectory", "--scenario", "slalom", "--config", str(config))
        for _ in range(40):
            engage = subprocess.run(
                [*CLI, "engage", "--config", str(config), "--timeout", "2"],
                capture_output=True,
                timeout=20,
            )
            if engage.returncode == 0:
                break
            time.sleep(0.5)
        result["engaged"] = engage.returncode == 0
        before = daemon_loop_stats(config)
        result["idle"] = jitter_figures(receive_periods(channel, port, seconds))
        after = daemon_loop_stats(config)
        result["idle"]["daemon_overruns"] = after.get("overruns", 0) - before.get("overruns", 0)
        loader = subprocess.Popen(
            [sys.executable, __file__, "--load-generator", channel, str(port), str(seconds + 2)],
            stdout=subprocess.PIPE,
        )
        procs.append(loader)
        time.sleep(1.0)
        before = daemon_loop_stats(config)
        result["with_4000_fps_load"] = jitter_figures(receive_periods(channel, port, seconds))
        after = daemon_loop_stats(config)
        result["with_4000_fps_load"]["daemon_overruns"] = after.get("overruns", 0) - before.get(
            "overruns", 0
        )
        result["daemon_loop"] = after
        loader_out, _ = loader.communicate(timeout=30)
        result["with_4000_fps_load"].update(
            json.loads(loader_out.decode().strip().splitlines()[-1])
        )
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--seconds", type=float, default=10.0, help="s of jitter measurement per case"
    )
    parser.add_argument(
        "--skip-jitter", action="store_true", help="only the in-process compute figures"
    )
    parser.add_argument(
        "--load-generator", nargs=3, metavar=("CHANNEL", "PORT", "SECONDS"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.load_generator:
        channel, port, seconds = args.load_generator
        load_generator(channel, int(port), LOAD_FPS, float(seconds))
        return
    out: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "load_avg_1min": os.getloadavg()[0]}}
    out["compute"] = bench_compute()
    if not args.skip_jitter:
        out["jitter_steer_cmd"] = bench_jitter(args.seconds)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
