"""tools/leafgate.service and tools/leafgate.sysusers: hardened, verified, watchdog, the user.

The systemd tools' checks skip, with the reason, where ``systemd-analyze`` or
``systemd-sysusers`` is not installed (``apt-get install systemd``).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "tools" / "leafgate.service"
SYSUSERS = ROOT / "tools" / "leafgate.sysusers"
README = ROOT / "README.md"
INSTALLED = "/opt/leafgate/.venv/bin/leafgate"
MAX_EXPOSURE = 3.0


def _unit() -> dict[str, dict[str, list[str]]]:
    """The unit's sections as key → every value given (systemd keys may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] = {}
    for raw in UNIT.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            current = sections.setdefault(line.strip("[]"), {})
            continue
        key, _, value = line.partition("=")
        current.setdefault(key, []).append(value)
    return sections


def _analyze() -> str:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    return tool


def test_unit_has_watchdog_bindsto_and_no_process_wide_realtime() -> None:
    unit = _unit()
    service, head = unit["Service"], unit["Unit"]
    assert service["Type"] == ["notify"] and service["WatchdogSec"] == ["2s"]
    bound = " ".join(head["BindsTo"]).split()
    assert "sys-subsystem-net-devices-can0.device" in bound
    assert "sys-subsystem-net-devices-can1.device" in bound
    # SCHED_FIFO for every thread (Zenoh, recorder …) is what the daemon must not get:
    assert "CPUSchedulingPolicy" not in service and "CPUSchedulingPriority" not in service
    assert service["LimitRTPRIO"] == ["50"]
    assert service["CapabilityBoundingSet"] == [""] and service["AmbientCapabilities"] == [""]
    assert "RestrictRealtime" not in service  # the control thread needs SCHED_FIFO


def test_unit_starts_again_when_its_buses_return() -> None:
    """BindsTo= only stops the unit when can0 or can1 goes away, and Restart= does not undo
    a stop a dependency caused: the device units' wants (WantedBy=) start it when they return.
    The comment once promised that without anything doing it."""
    unit = _unit()
    bound = set(" ".join(unit["Unit"]["BindsTo"]).split())
    wanted_by = set(" ".join(unit["Install"]["WantedBy"]).split())
    assert bound <= wanted_by and "multi-user.target" in wanted_by
    text = UNIT.read_text(encoding="utf-8")
    assert "start again when they return" not in text


def test_unit_names_no_score_of_its_own_and_its_readme_exists_where_it_says() -> None:
    """One figure for ``systemd-analyze security``: README's (the unit said 2.x, README 1.6);
    the Documentation= README is the clone's under the install the unit assumes."""
    text = UNIT.read_text(encoding="utf-8")
    assert not re.search(r"scores? (this unit )?\d", text)
    (doc,) = _unit()["Unit"]["Documentation"]
    clone = INSTALLED.removesuffix("/.venv/bin/leafgate")
    assert doc == f"file://{clone}/README.md"
    assert f"clone in\n`{clone}`" in README.read_text(encoding="utf-8")


def test_readme_security_score_is_the_measured_one() -> None:
    tool = _analyze()
    readme = README.read_text(encoding="utf-8")
    match = re.search(r"`systemd-analyze security`: (\d+\.\d) OK with\s+systemd (\d+)", readme)
    assert match, "README no longer gives the unit's score and the systemd it was measured with"
    version = subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.split()
    if version[1] != match.group(2):
        pytest.skip(f"systemd {version[1]} here, README's figure is systemd {match.group(2)}'s")
    done = subprocess.run(
        [tool, "security", "--offline=true", str(UNIT)], capture_output=True, text=True, timeout=60
    )
    score = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", done.stdout)
    assert score and score.group(1) == match.group(1), done.stdout[-300:]


def test_shipped_car_config_asks_for_the_units_realtime_priority() -> None:
    from leafgate.settings import load_config

    cfg = load_config(ROOT / "config" / "leafgate.yaml")
    assert 0 < cfg.gateway.rt_priority <= int(_unit()["Service"]["LimitRTPRIO"][0])


def test_sysusers_creates_the_units_user(tmp_path: Path) -> None:
    user = _unit()["Service"]["User"][0]
    fields = [
        line.split()
        for line in SYSUSERS.read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert fields and fields[0][:2] == ["u", user]
    tool = shutil.which("systemd-sysusers")
    if tool is None:
        pytest.skip("systemd-sysusers is not installed (apt-get install systemd)")
    etc = tmp_path / "etc"
    etc.mkdir()
    for name in ("passwd", "group", "shadow", "gshadow"):
        (etc / name).touch()
    subprocess.run([tool, f"--root={tmp_path}", str(SYSUSERS)], check=True, capture_output=True)
    passwd = (etc / "passwd").read_text(encoding="utf-8")
    assert re.search(rf"^{user}:x:\d+:\d+:.*:/var/lib/leafgate:", passwd, re.M), passwd
    assert re.search(rf"^{user}:x:\d+:", (etc / "group").read_text(encoding="utf-8"), re.M)


def test_security_exposure_at_most_3() -> None:
    tool = _analyze()
    done = subprocess.run(
        [tool, "security", "--offline=true", str(UNIT)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    match = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", done.stdout)
    assert match, done.stdout + done.stderr
    score = float(match.group(1))
    print(f"systemd-analyze security: {score}")
    assert score <= MAX_EXPOSURE, done.stdout


def test_unit_verifies_without_warnings(tmp_path: Path) -> None:
    tool = _analyze()
    # verify checks that every command exists: point the unit at this checkout's leafgate.
    here = Path(sys.executable).with_name("leafgate")
    if not here.exists():
        pytest.skip(f"{here} is not installed (pip install -e .)")
    text = UNIT.read_text(encoding="utf-8").replace(INSTALLED, str(here))
    unit = tmp_path / "leafgate.service"
    unit.write_text(text, encoding="utf-8")
    done = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    # verify exits 0 on unknown keys and bad values too, with a warning: none is allowed
    problems = [line for line in done.stderr.splitlines() if str(unit) in line]
    assert done.returncode == 0 and not problems, done.stderr


def test_a_start_that_fails_on_the_bus_leaves_no_recording(tmp_path: Path) -> None:
    """With Restart=on-failure every failed start would leave an empty .blf + .mcap pair."""
    import dataclasses

    from leafgate.config.can import BusConfig
    from leafgate.errors import LeafgateError
    from leafgate.runtime.daemon import run_daemon
    from leafgate.settings import load_config

    cfg = load_config(ROOT / "config" / "sim.yaml")
    rec = tmp_path / "recordings"
    cfg = dataclasses.replace(
        cfg,
        can=dataclasses.replace(
            cfg.can, dbw=BusConfig(interface="socketcan", channel="leafgate-none0")
        ),
        recording=dataclasses.replace(cfg.recording, enabled=True, directory=str(rec)),
    )
    with pytest.raises(LeafgateError):
        run_daemon(cfg)
    assert not rec.exists() or not any(rec.iterdir()), sorted(rec.iterdir())


@pytest.mark.timeout(60)
def test_ready_goes_out_before_the_first_watchdog_ping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """systemd counts WatchdogSec from READY=1; the first tick's WATCHDOG=1 went out before it."""
    import dataclasses
    import os
    import socket
    import threading

    from leafgate.config.can import BusConfig
    from leafgate.runtime.daemon import run_daemon
    from leafgate.settings import load_config
    from tests.conftest import free_port

    cfg = load_config(ROOT / "config" / "sim.yaml")
    cfg = dataclasses.replace(
        cfg,
        can=dataclasses.replace(
            cfg.can, dbw=BusConfig(interface="virtual", channel=f"notify-{os.getpid()}")
        ),
        zenoh=dataclasses.replace(cfg.zenoh, listen=(f"tcp/127.0.0.1:{free_port()}",)),
    )
    address = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(address)
        server.settimeout(20.0)
        monkeypatch.setenv("NOTIFY_SOCKET", address)
        monkeypatch.setenv("WATCHDOG_USEC", "200000")  # a ping every 0.1 s
        monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
        stop = threading.Event()
        thread = threading.Thread(target=run_daemon, args=(cfg, stop))
        thread.start()
        sent: list[str] = []
        try:
            while sent.count("WATCHDOG=1") < 3:
                sent.append(server.recv(64).decode())
        finally:
            stop.set()
            thread.join(timeout=20)
    assert not thread.is_alive()
    assert sent[0] == "READY=1", sent
