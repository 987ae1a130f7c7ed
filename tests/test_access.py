"""Access control over mutual TLS (``config/zenoh/secure.json5``) against the real daemon.

Certificates are made at test time with the ``openssl`` command (no Python dependency; the test
is skipped without it): one CA signs the gateway's server certificate (subjectAltName
127.0.0.1/localhost) and client certificates for the planner, localization, the operator and an
intruder whose only fault is its Common Name. ``leafgate run`` is started as a subprocess on
that file (a free loopback port, a private CAN multicast group, no ECU: the gateway stays in
STANDBY and answers engage with a refusal, which is still an answer). The clients are sessions
of this process, each configured the way the file's header tells a tool to be.

Whether the gateway received a trajectory is read on the gateway's side: the age of its latest
trajectory in ``gateway/diagnostics``. A publication at ``t_pub`` that arrived makes that age at
most ``t_read - t_pub``; an age above it (or none) means nothing arrived since ``t_pub``.
"""

from __future__ import annotations

import json
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
import zenoh

from leafgate.config.transport import ZenohConfig
from leafgate.errors import TransportError
from leafgate.messages import GatewayState
from leafgate.runtime.node import GatewayTransport
from leafgate.sim.scenarios import get_scenario
from leafgate.transport import client, keys
from leafgate.transport.client import OdometryPublisher, TrajectoryPublisher
from leafgate.transport.session import build_config, open_session
from tests.conftest import free_port

ROOT = Path(__file__).resolve().parent.parent
SECURE = ROOT / "config" / "zenoh" / "secure.json5"
OPENSSL = shutil.which("openssl")
IDENTITIES = ("planner", "localization", "operator", "intruder")
START_TIMEOUT = 20.0  # s for the daemon to answer its first query (imports, two cores)
DENIED_WAIT = 1.0  # s a denied client waits before it gives up
ARRIVAL_WAIT = 0.5  # s for a publication to cross loopback before the gateway is asked

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        OPENSSL is None, reason="the openssl command is needed to make certificates"
    ),
]


def openssl(*args: str, cwd: Path) -> None:
    assert OPENSSL is not None
    subprocess.run([OPENSSL, *args], cwd=cwd, check=True, capture_output=True, timeout=30)


def make_certificate(directory: Path, name: str, common_name: str, extensions: str) -> None:
    """A P-256 key and a certificate for ``common_name`` signed by the CA in ``directory``."""
    openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
        "-out", f"{name}.key", cwd=directory,
    )  # fmt: skip
    openssl(
        "req", "-new", "-key", f"{name}.key", "-subj", f"/CN={common_name}",
        "-out", f"{name}.csr", cwd=directory,
    )  # fmt: skip
    (directory / f"{name}.ext").write_text(extensions)
    openssl(
        "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
        "-CAcreateserial", "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext",
        cwd=directory,
    )  # fmt: skip


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CA, gateway server certificate and one client certificate per identity."""
    directory = tmp_path_factory.mktemp("tls")
    openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", "ca.key",
        cwd=directory,
    )  # fmt: skip
    openssl(
        "req", "-x509", "-new", "-key", "ca.key", "-subj", "/CN=leafgate test CA", "-days", "2",
        "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-out", "ca.pem", cwd=directory,
    )  # fmt: skip
    end_entity = "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
    make_certificate(
        directory,
        "gateway",
        "gateway.leaf.local",
        end_entity
        + "extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=IP:127.0.0.1,DNS:localhost\n",
    )
    for name in IDENTITIES:
        make_certificate(
            directory, name, f"{name}.leaf.local", end_entity + "extendedKeyUsage=clientAuth\n"
        )
    return directory


def _path(value: Path) -> str:
    return json.dumps(str(value))  # zenoh.extra values are JSON5: a path keeps its quotes


@dataclass(frozen=True)
class Gateway:
    endpoint: str
    certificates: Path

    def client(self, identity: str | None) -> ZenohConfig:
        """A tool's Zenoh settings as secure.json5's header says (None: no certificate)."""
        extra = {
            "mode": '"client"',
            "listen/endpoints": "[]",
            "access_control/enabled": "false",
            "transport/link/tls/root_ca_certificate": _path(self.certificates / "ca.pem"),
        }
        if identity is not None:
            extra["transport/link/tls/connect_certificate"] = _path(
                self.certificates / f"{identity}.pem"
            )
            extra["transport/link/tls/connect_private_key"] = _path(
                self.certificates / f"{identity}.key"
            )
        return ZenohConfig(
            config_file=str(SECURE),
            connect=(self.endpoint,),
            extra=extra,
            query_timeout=DENIED_WAIT,
        )


@pytest.fixture(scope="module")
def gateway(certificates: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    """``leafgate run`` on secure.json5 with the test certificates, until the module ends."""
    directory = tmp_path_factory.mktemp("gateway")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["can"]["dbw"]["channel"] = f"239.74.{random.randint(164, 250)}.{random.randint(1, 250)}"
    cfg["can"]["dbw"]["kwargs"] = {"port": free_port()}
    cfg["zenoh"] = {
        "prefix": "leaf",
        "config_file": str(SECURE),
        "listen": [endpoint],
        "encoding": "cdr",
        "extra": {
            "transport/link/tls/root_ca_certificate": _path(certificates / "ca.pem"),
            "transport/link/tls/listen_certificate": _path(certificates / "gateway.pem"),
            "transport/link/tls/listen_private_key": _path(certificates / "gateway.key"),
        },
    }
    config = directory / "gateway.yaml"
    config.write_text(yaml.safe_dump(cfg))
    log = directory / "gateway.log"
    daemon = subprocess.Popen(
        [sys.executable, "-m", "leafgate.cli", "run", "--config", str(config)],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        cwd=ROOT,
    )
    gw = Gateway(endpoint, certificates)
    try:
        operator = gw.client("operator")
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            if daemon.poll() is not None:
                pytest.fail(f"the daemon exited: {log.read_text()[-2000:]}")
            try:
                client.request(operator, "disengage", timeout=1.0)
                break
            except TransportError:
                if time.monotonic() > deadline:
                    pytest.fail(f"the daemon never answered: {log.read_text()[-2000:]}")
        yield gw
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(timeout=10)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait()


@pytest.fixture
def observer(gateway: Gateway) -> Iterator[zenoh.Session]:
    """The operator's session, reading the gateway's diagnostics."""
    session = open_session(gateway.client("operator"))
    yield session
    session.close()


def latest_diagnostics(cfg: ZenohConfig, session: zenoh.Session) -> dict:
    """The newest diagnostics object seen in 0.3 s (10 Hz: a few arrive)."""
    seen: list[dict] = []
    client.watch_diagnostics(cfg, seen.append, 0.3, session=session)
    assert seen, "the operator reads no diagnostics"
    return seen[-1]


def arrived_since(
    gateway: Gateway, observer: zenoh.Session, t_pub: float, watchdog: str = "trajectory"
) -> bool:
    """Whether the gateway received an input at or after ``t_pub`` (time.monotonic).

    :param watchdog: the input's watchdog in the diagnostics (trajectory, localization)
    """
    time.sleep(ARRIVAL_WAIT)
    diag = latest_diagnostics(gateway.client("operator"), observer)
    t_read = time.monotonic()
    age = diag["watchdogs"][watchdog]["age"]
    return age is not None and age <= t_read - t_pub


def publish_regardless(session: zenoh.Session, cfg: ZenohConfig, count: int = 5) -> float:
    """Publish a trajectory like a planner would, without waiting for a subscriber.

    :returns: the time of the first publication (time.monotonic)
    """
    trajectory = get_scenario("s-curve").trajectory
    with TrajectoryPublisher(session, cfg) as publisher:
        t_pub = time.monotonic()
        for _ in range(count):
            publisher.publish(trajectory)
            time.sleep(0.05)
    return t_pub


def publish_poses(
    session: zenoh.Session, cfg: ZenohConfig, count: int = 10, wait: float = 0.0
) -> float:
    """Publish localization at 20 Hz; the first one's time (time.monotonic).

    :param wait: s to wait for the gateway's subscriber first (not waited for when 0)
    """
    pose = get_scenario("s-curve").start
    with OdometryPublisher(session, cfg) as publisher:
        if wait > 0:
            assert publisher.wait_for_subscriber(wait), "the gateway's subscriber is not known"
        t_pub = time.monotonic()
        for _ in range(count):
            publisher.publish(pose, stamp=time.time())
            time.sleep(0.05)
    return t_pub


def engage_replies(session: zenoh.Session) -> list[dict]:
    """Raw replies to an ``engage`` query sent without waiting for a queryable."""
    replies = session.get(f"leaf/{keys.ENGAGE}", payload=b"engage", timeout=DENIED_WAIT)
    return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]


def test_client_without_certificate_cannot_connect(gateway: Gateway) -> None:
    with pytest.raises(TransportError, match="cannot open Zenoh session"):
        open_session(gateway.client(None))


def test_intruder_with_valid_certificate_cannot_publish_a_trajectory(
    gateway: Gateway, observer: zenoh.Session
) -> None:
    cfg = gateway.client("intruder")
    with open_session(cfg) as session:
        # The gateway's subscriber is not even announced to it …
        with pytest.raises(TransportError, match="nobody subscribes"):
            client.publish_trajectory(cfg, get_scenario("s-curve").trajectory, session=session)
        # … and what it publishes anyway never reaches the gateway.
        t_pub = publish_regardless(session, cfg)
    assert not arrived_since(gateway, observer, t_pub)


def test_intruder_with_valid_certificate_cannot_engage(gateway: Gateway) -> None:
    cfg = gateway.client("intruder")
    with open_session(cfg) as session:
        with pytest.raises(TransportError, match="no gateway answered"):
            client.request(cfg, "engage", session=session)
        assert engage_replies(session) == []


def alive_tokens(session: zenoh.Session) -> list[str]:
    replies = session.liveliness().get(f"leaf/{keys.ALIVE}", timeout=0.5)
    return [str(r.ok.key_expr) for r in replies if r.ok is not None]


def test_intruder_cannot_read_diagnostics_nor_see_the_gateway_alive(gateway: Gateway) -> None:
    cfg = gateway.client("intruder")
    with open_session(cfg) as session:
        assert client.watch_diagnostics(cfg, lambda _d: None, 0.5, session=session) == 0
        assert alive_tokens(session) == []


@pytest.mark.parametrize("identity", ["planner", "localization", "operator"])
def test_known_identities_see_the_gateway_alive(identity: str, gateway: Gateway) -> None:
    with open_session(gateway.client(identity)) as session:
        assert alive_tokens(session) == [f"leaf/{keys.ALIVE}"]


def test_planner_publishes_a_trajectory_the_gateway_receives(
    gateway: Gateway, observer: zenoh.Session
) -> None:
    cfg = gateway.client("planner")
    with open_session(cfg) as session:
        t_pub = time.monotonic()
        client.publish_trajectory(cfg, get_scenario("s-curve").trajectory, session=session)
    assert arrived_since(gateway, observer, t_pub)


def test_planner_cannot_engage(gateway: Gateway) -> None:
    cfg = gateway.client("planner")
    with open_session(cfg) as session:
        with pytest.raises(TransportError, match="no gateway answered"):
            client.request(cfg, "engage", session=session)
        assert engage_replies(session) == []


def test_operator_engage_gets_the_gateways_answer(gateway: Gateway) -> None:
    reply = client.request(gateway.client("operator"), "engage", timeout=5.0)
    # No ECU runs here, so the gateway refuses; the refusal is its answer, with its reason.
    assert set(reply) >= {"accepted", "state", "reason"}
    assert reply["state"] in GatewayState.__members__
    assert reply["accepted"] or reply["reason"]


def test_operator_cannot_publish_a_trajectory(gateway: Gateway, observer: zenoh.Session) -> None:
    cfg = gateway.client("operator")
    with open_session(cfg) as session:
        t_pub = publish_regardless(session, cfg)
    assert not arrived_since(gateway, observer, t_pub)


def test_localization_cannot_publish_a_trajectory(
    gateway: Gateway, observer: zenoh.Session
) -> None:
    cfg = gateway.client("localization")
    with open_session(cfg) as session:
        t_pub = publish_regardless(session, cfg)
    assert not arrived_since(gateway, observer, t_pub)


def test_localization_publishes_the_pose_the_gateway_receives(
    gateway: Gateway, observer: zenoh.Session
) -> None:
    cfg = gateway.client("localization")
    with open_session(cfg) as session:
        t_pub = publish_poses(session, cfg, wait=DENIED_WAIT)
    assert arrived_since(gateway, observer, t_pub, "localization")


@pytest.mark.parametrize("identity", ["intruder", "planner", "operator"])
def test_only_localization_publishes_the_pose(
    identity: str, gateway: Gateway, observer: zenoh.Session
) -> None:
    cfg = gateway.client(identity)
    with open_session(cfg) as session:
        t_pub = publish_poses(session, cfg)
    assert not arrived_since(gateway, observer, t_pub, "localization")


def test_missing_certificate_file_is_named_before_connecting(gateway: Gateway) -> None:
    cfg = gateway.client("operator")
    missing = gateway.certificates / "nobody.pem"
    extra = {**cfg.extra, "transport/link/tls/connect_certificate": _path(missing)}
    with pytest.raises(TransportError, match=f"connect_certificate: {missing}"):
        open_session(ZenohConfig(config_file=cfg.config_file, connect=cfg.connect, extra=extra))


def test_inputs_stay_denied_when_the_intruder_is_shown_the_gateways_endpoints(
    certificates: Path,
) -> None:
    """The ingress rules bite on their own: with the intruder allowed to *see* the gateway's
    subscribers and queryable (the egress rules), its publications and queries still do not
    get in. The gateway runs in this process here, to count what arrives in its slots."""
    base = build_config(ZenohConfig(config_file=str(SECURE)))
    subjects = json.loads(base.get_json("access_control/subjects"))
    policies = json.loads(base.get_json("access_control/policies"))
    subjects.append({"id": "intruder", "cert_common_names": ["intruder.leaf.local"]})
    policies.append(
        {
            "id": "intruder-sees",
            "rules": ["trajectory-subscriber", "localization-subscriber", "engage-answer"],
            "subjects": ["intruder"],
        }
    )
    endpoint = f"tls/127.0.0.1:{free_port()}"
    gateway_cfg = ZenohConfig(
        config_file=str(SECURE),
        listen=(endpoint,),
        extra={
            "transport/link/tls/root_ca_certificate": _path(certificates / "ca.pem"),
            "transport/link/tls/listen_certificate": _path(certificates / "gateway.pem"),
            "transport/link/tls/listen_private_key": _path(certificates / "gateway.key"),
            "access_control/subjects": json.dumps(subjects),
            "access_control/policies": json.dumps(policies),
        },
    )
    answered: list[object] = []

    def handler(request: object) -> dict[str, object]:
        answered.append(request)
        return {"accepted": True, "state": "STANDBY", "reason": "test"}

    cfg = Gateway(endpoint, certificates).client("intruder")
    with GatewayTransport.open(gateway_cfg, handler) as gateway, open_session(cfg) as session:
        with TrajectoryPublisher(session, cfg) as trajectories:
            assert trajectories.wait_for_subscriber(START_TIMEOUT)  # it sees the subscriber …
            for _ in range(5):
                trajectories.publish(get_scenario("s-curve").trajectory)
        publish_poses(session, cfg, wait=START_TIMEOUT)
        replies = engage_replies(session)
        time.sleep(ARRIVAL_WAIT)
        # … but nothing it sends arrives.
        assert gateway.trajectory.received == 0
        assert gateway.pose.received == 0
        assert replies == [] and answered == []
