"""Tools see everything: with the shipped configs, a tool connected to the daemon receives what
another tool publishes (the daemon routes for the processes connected to it).

Three processes: ``leafgate run`` (config/sim.yaml on a free port and a private multicast
group), ``leafgate publish-trajectory`` (one tool), and this test's own session, opened as
every tool opens it (:func:`~leafgate.runtime.daemon.tool_view`).
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from test_transport import free_port

from leafgate.runtime.daemon import tool_view
from leafgate.settings import load_config
from leafgate.transport import keys
from leafgate.transport.session import open_session

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "leafgate.cli"]
WAIT = 30.0  # s, generous: processes start slowly on a loaded machine

pytestmark = pytest.mark.slow


def test_a_tool_receives_what_another_tool_publishes(tmp_path: Path) -> None:
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    cfg["can"]["dbw"]["channel"] = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    cfg["can"]["dbw"]["kwargs"] = {"port": free_port()}
    config = tmp_path / "sim.yaml"
    config.write_text(yaml.safe_dump(cfg))

    seen: dict[str, int] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            key = str(sample.key_expr)
            seen[key] = seen.get(key, 0) + 1

    def start(*args: str, log: str) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [*CLI, *args], stdout=(tmp_path / log).open("wb"), stderr=subprocess.STDOUT, cwd=ROOT
        )

    zcfg = tool_view(load_config(str(config)).zenoh)
    daemon = start("run", "--config", str(config), log="gw.log")
    planner = None
    session = None
    try:
        deadline = time.monotonic() + WAIT
        while session is None:  # the daemon listens once it has started
            try:
                session = open_session(zcfg)
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        subscriber = session.declare_subscriber(f"{zcfg.prefix}/**", on_sample)
        planner = start(
            "publish-trajectory", "--scenario", "s-curve", "--config", str(config), log="pub.log"
        )
        trajectory = zcfg.key(keys.TRAJECTORY)
        diagnostics = zcfg.key(keys.DIAGNOSTICS)

        def both() -> bool:
            with lock:
                return seen.get(trajectory, 0) > 0 and seen.get(diagnostics, 0) > 0

        deadline = time.monotonic() + WAIT
        while not both() and time.monotonic() < deadline:
            time.sleep(0.1)
        with lock:
            assert seen.get(diagnostics, 0) > 0, (seen, (tmp_path / "gw.log").read_text()[-2000:])
            # The planner's publication reaches this tool through the daemon.
            assert seen.get(trajectory, 0) > 0, (seen, (tmp_path / "pub.log").read_text()[-2000:])
        subscriber.undeclare()
    finally:
        if session is not None:
            session.close()
        for proc in (planner, daemon):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in (planner, daemon):
            if proc is not None:
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
