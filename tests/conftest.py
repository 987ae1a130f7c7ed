"""Helpers shared by the test suite: one copy each, imported as ``from tests.conftest import …``.

Every cross-process test takes its own free TCP/UDP port and its own multicast group, so parallel
runs (and a daemon on the defaults) never meet.
"""

from __future__ import annotations

import errno
import json
import os
import random
import time
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import pytest

from tools._common import free_port  # one copy for the tests and the tools

if TYPE_CHECKING:
    from cantools.database.can import Database


#: Watchdog thresholds relaxed for tests that run several processes on two shared cores, where a
#: scheduling stall is not the failure the test is about. The defaults are tested in
#: test_watchdog.py, and tests/faults/ keeps them where a test is about that watchdog.
RELAXED_WATCHDOG = {
    "localization_stop_age": 0.5,  # 0.304 s stalls were seen beside two other test sessions
    "localization_fault_age": 1.5,
    "report_timeout_periods": 25,
    "max_overruns": 25,
    "max_stall_periods": 25.0,
    "max_receive_lag": 1.0,
}


def relax_for_shared_cores(cfg: dict) -> None:
    """Relax, in a config mapping, every deadline a scheduling stall of another process can miss.

    Several Python processes on two loaded cores stall each other for 100 ms and more. Here that
    is not the failure under test, and each default below is tested where a test is about it
    (test_watchdog.py, test_state_machine.py, test_ecu.py, tests/faults/):

    - the watchdog thresholds above;
    - the time the ECU has to confirm an engage (0.5 s);
    - the report-frame error count (5: counter errors were seen with two busy loops beside the
      test, their cause not traced);
    - the simulated ECU's command timeout (0.1 s; after a timeout the ECU needs a fresh ENABLE
      edge, so a stalled daemon at the moment of the engage leaves the car standing).
    """
    gateway = cfg.setdefault("gateway", {})
    gateway.setdefault("watchdog", {}).update(RELAXED_WATCHDOG, max_report_errors=50)
    gateway.setdefault("engage", {})["confirm_timeout"] = 3.0
    cfg.setdefault("sim", {}).setdefault("ecu", {})["cmd_timeout"] = 0.5


def private_group() -> str:
    """An administratively scoped IPv4 group no other test run uses (with a free port)."""
    return f"239.75.{random.randint(1, 250)}.{random.randint(1, 250)}"


def udp_multicast_works() -> bool:
    """python-can's udp_multicast can be opened here (msgpack installed, multicast allowed)."""
    try:
        import msgpack  # noqa: F401  (python-can's udp_multicast needs it)

        bus = can.Bus(interface="udp_multicast", channel=private_group(), port=free_port())
    except Exception:
        return False
    bus.shutdown()
    return True


def packaged_dbc(name: str) -> Database:
    """A DBC file shipped in the package (``leafgate/data/dbc``), loaded strictly by cantools
    itself, not through leafgate's codec."""
    import cantools
    from cantools.database.can import Database

    text = (resources.files("leafgate") / "data/dbc" / name).read_text(encoding="utf-8")
    db = cantools.database.load_string(text, database_format="dbc", strict=True)
    assert isinstance(db, Database)
    return db


@pytest.fixture
def router() -> Iterator[str]:
    """A Zenoh router on a free loopback port (what ``rmw_zenohd`` is to ROS 2 nodes): its
    endpoint, for the sessions that connect to it."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    yield endpoint
    session.close()


# --- a disk that fills up -----------------------------------------------------------------------


class Disk:
    """A disk whose free space the test sets: a write beyond it fails with ENOSPC, as on a
    full tmpfs (files opened for writing under ``root`` only)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.free = 10**9  # bytes

    def install(self, monkeypatch: pytest.MonkeyPatch) -> None:
        real_open = Path.open
        disk = self

        def open_(path: Path, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
            file = real_open(path, mode, *args, **kwargs)
            if mode[0] in "wa" and path.is_relative_to(disk.root):
                return _DiskFile(file, disk)
            return file

        monkeypatch.setattr(Path, "open", open_)


class _DiskFile:
    def __init__(self, file: Any, disk: Disk) -> None:
        self._file = file
        self._disk = disk

    def write(self, data: Any) -> int:
        if len(data) > self._disk.free:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._disk.free -= len(data)
        n: int = self._file.write(data)
        return n

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)

    def __iter__(self) -> Any:
        return iter(self._file)


def wait_for(condition: Callable[[], bool], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def process_cluster() -> Any:
    """A local Dask cluster of one worker process with one thread, on loopback with its HTTP
    server on a free port: as the batch engine starts its own (``leafgate.batch.engine``), for
    the tests that give the batch a ``--scheduler`` of their own."""
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    )
