"""``leafgate status`` cannot be spoofed (issue 17, finding 9): like ``disengage``, it believes
only diagnostics published by the session holding the gateway's liveliness token, and reports
records from anyone else, and conflicting gateways.

Before, any peer could publish on ``gateway/diagnostics`` and ``status`` showed its fake state.
Every test opens its own sessions on a free loopback port with multicast scouting off.
"""

from __future__ import annotations

import io
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from leafgate import cli
from leafgate.config.transport import ZenohConfig
from leafgate.messages import OperatorRequest
from leafgate.runtime.daemon import tool_view
from leafgate.runtime.node import GatewayTransport
from leafgate.transport import client, keys
from leafgate.transport.session import open_session
from tests.conftest import free_port

DURATION = 1.0  # s of watching: 10 Hz diagnostics give several records


def _refuse(_request: OperatorRequest) -> dict[str, Any]:
    return {"accepted": False, "state": "STANDBY", "reason": "test"}


class Publishing:
    """Publishes a diagnostics record every 20 ms on a thread until closed."""

    def __init__(self, put: Any, record: dict[str, Any]) -> None:
        self._put, self._record = put, record
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._put(self._record)
            time.sleep(0.02)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def gateway(port: int) -> Iterator[GatewayTransport]:
    cfg = ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",))
    with GatewayTransport.open(cfg, _refuse) as transport:
        pub = Publishing(transport.publish_diagnostics, {"state": "STANDBY", "reason": "genuine"})
        yield transport
        pub.close()


@pytest.fixture
def tool_cfg(port: int) -> ZenohConfig:
    # as the tools run: connected to the gateway, listening on a port of their own, so the
    # gateway's gossip connects them to each other (an impostor reaches the operator directly)
    return tool_view(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)))


@pytest.fixture
def impostor(tool_cfg: ZenohConfig) -> Iterator[zenoh.Session]:
    session = open_session(tool_cfg)
    yield session
    session.close()


def _forge(session: zenoh.Session, cfg: ZenohConfig, hold_token: bool) -> Publishing:
    """Forged diagnostics (ENGAGED) from ``session``, with Zenoh's source info like the
    gateway's; ``hold_token``: it also declares a liveliness token of its own, as a second
    gateway would."""
    token = (
        session.liveliness().declare_token(f"{cfg.key(keys.ALIVE)}/{session.info.zid()}")
        if hold_token
        else None
    )
    publisher = session.declare_publisher(cfg.key(keys.DIAGNOSTICS))
    sequence = iter(range(1, 1 << 30))

    def put(record: dict[str, Any]) -> None:
        assert token is not None or not hold_token  # kept alive as long as the publishing
        info = zenoh.SourceInfo(publisher.id, next(sequence))
        publisher.put(json.dumps(record).encode(), source_info=info)

    return Publishing(put, {"state": "ENGAGED", "reason": "forged"})


def test_forged_diagnostics_are_not_shown_and_are_reported(
    gateway: GatewayTransport, tool_cfg: ZenohConfig, impostor: zenoh.Session
) -> None:
    forged = _forge(impostor, tool_cfg, hold_token=False)
    plain = Publishing(
        lambda r: impostor.put(tool_cfg.key(keys.DIAGNOSTICS), json.dumps(r).encode()),
        {"state": "ENGAGED", "reason": "forged, no identity"},
    )
    try:
        seen: list[dict[str, Any]] = []
        watch = client.DiagnosticsWatch()
        with open_session(tool_cfg) as tool:
            count = client.watch_diagnostics(
                tool_cfg, seen.append, DURATION, session=tool, watch=watch
            )
    finally:
        forged.close()
        plain.close()
    assert count == len(seen) > 0
    assert {r["reason"] for r in seen} == {"genuine"}  # the old status showed ENGAGED too
    foreign = watch.foreign()
    assert foreign.get("unidentified", 0) > 0
    assert any(who.startswith(f"zid:{impostor.info.zid()}/") for who in foreign), foreign
    assert len(watch.gateways) == 1


def _status(tmp_path: Path, port: int, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    config = tmp_path / "status.yaml"
    config.write_text(yaml.safe_dump({"zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    code = cli.main(["status", "--config", str(config), "--duration", str(DURATION), "--json"])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("second_gateway", [False, True])
def test_status_shows_only_the_gateway_and_reports_the_others(
    gateway: GatewayTransport,
    tool_cfg: ZenohConfig,
    impostor: zenoh.Session,
    port: int,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    second_gateway: bool,
) -> None:
    forged = _forge(impostor, tool_cfg, hold_token=second_gateway)
    try:
        code, out, err = _status(tmp_path, port, capsys)
    finally:
        forged.close()
    records = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert str(impostor.info.zid()) in err
    if second_gateway:  # two sessions hold a token: which one is the gateway? an error
        assert code == 1 and "conflicting" in err
    else:  # a forger without the token: never shown, warned of
        assert code == 0, err
        assert records and all(r["state"] == "STANDBY" for r in records)
        assert "without the gateway's liveliness token" in err


def test_a_request_waits_for_a_starting_gateways_token(port: int, tool_cfg: ZenohConfig) -> None:
    """A gateway whose queryable is up a moment before its liveliness token still gets the
    operator's request: the request waits for the token until its deadline (it looked once,
    and a starting gateway was reported as "no gateway liveliness token")."""
    cfg = ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",))
    session = open_session(cfg)
    tokens: list[Any] = []

    def answer(query: zenoh.Query) -> None:
        reply = {"accepted": False, "state": "STANDBY", "reason": "starting", "changed": False}
        query.reply(query.key_expr, json.dumps(reply).encode())

    def token_later() -> None:
        time.sleep(1.0)
        alive = f"{cfg.key(keys.ALIVE)}/{session.info.zid()}"
        tokens.append(session.liveliness().declare_token(alive))

    queryable = session.declare_queryable(cfg.key(keys.ENGAGE), answer)
    later = threading.Thread(target=token_later)
    later.start()
    try:
        reply = client.request(tool_cfg, "engage", timeout=10.0)
    finally:
        later.join()
        for token in tokens:
            token.undeclare()
        queryable.undeclare()
        session.close()
    assert reply["reason"] == "starting"


class _ReaderGone:
    """stdout of ``leafgate status | head -1`` once head has its line: every write fails."""

    def write(self, _text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self) -> None:
        raise BrokenPipeError(32, "Broken pipe")

    def fileno(self) -> int:
        raise io.UnsupportedOperation("fileno")  # as pytest's capture: no descriptor


WATCHED = 120.0  # s of --duration: a status that watches on after its reader left takes this


def test_status_stops_watching_when_its_reader_is_gone(
    gateway: GatewayTransport,
    port: int,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``leafgate status --duration 120 | head -1`` ends once head has gone (status 141), not
    after the two minutes: the closed pipe was noted on Zenoh's thread and the main thread
    slept on to the end of --duration, the pipeline hanging with it."""
    config = tmp_path / "status.yaml"
    config.write_text(yaml.safe_dump({"zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}))
    capsys.readouterr()
    monkeypatch.setattr("sys.stdout", _ReaderGone())
    start = time.monotonic()
    code = cli.main(["status", "--config", str(config), "--duration", str(WATCHED), "--json"])
    took = time.monotonic() - start
    assert code == cli.EXIT_PIPE
    assert took < WATCHED / 2, f"status watched on for {took:.0f} s after its reader left"
    assert "output closed by the reader" in capsys.readouterr().err
