"""Opening a Zenoh session from :class:`~leafgate.config.transport.ZenohConfig`.

Every failure (unreadable or invalid JSON5 file, a malformed endpoint, a port in use, an
unknown setting) becomes one :class:`~leafgate.errors.TransportError` whose one-line message
names the file or endpoint at fault.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from leafgate.config.transport import RMW_ZENOHD, ZenohConfig
from leafgate.errors import TransportError

# TLS settings naming a file (eclipse-zenoh 1.10 ``transport/link/tls``), by the side that uses
# them: checked before opening, because Zenoh's own error ("Invalid TLS private key file: No such
# file …") names neither the setting nor the path.
TLS_LISTEN_FILES = ("root_ca_certificate", "listen_certificate", "listen_private_key")
TLS_CONNECT_FILES = ("root_ca_certificate", "connect_certificate", "connect_private_key")
_TLS_SCHEMES = ("tls/", "quic/")  # endpoints that use the TLS settings
TX_DATA_BATCHES = 16  # batches of the data priority in the transmit queue (Zenoh's maximum)
OPEN_TIMEOUT_MS = 2000  # ms a peer has to complete Zenoh's handshake (Zenoh's default: 10000)

# Zenoh's messages end with " at /path/to/file.rs:123." and may span lines; keep the gist.
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_JSON5_MSG = re.compile(r'msg: "((?:[^"\\]|\\.)*)"')
_PARSE_ERROR = re.compile(r"-->\s*(\d+):(\d+).*?=\s*([^\n]+)", re.DOTALL)


def zenoh_message(exc: BaseException) -> str:
    """One line of a Zenoh error, without Rust source locations or debug wrappers."""
    text = _RUST_LOCATION.sub("", str(exc))
    inner = _JSON5_MSG.search(text)
    if inner:  # Json5Err(Message { msg: "…", location: … })
        return inner.group(1)
    parse = _PARSE_ERROR.search(text)
    if parse:  # pest parser output: " --> 1:63 | <source line> | ^--- = expected …"
        return f"line {parse.group(1)}, column {parse.group(2)}: {parse.group(3).strip()}"
    return " ".join(text.split()) or type(exc).__name__


def build_config(cfg: ZenohConfig) -> zenoh.Config:
    """The Zenoh configuration for ``cfg``, without opening anything.

    :raises TransportError: naming the file, endpoint or setting that Zenoh rejected
    """
    if cfg.config_file is not None:
        path = Path(cfg.config_file)
        if not path.is_file():
            raise TransportError(f"{path}: Zenoh config file not found")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise TransportError(f"{path}: invalid Zenoh config: {zenoh_message(exc)}") from None
    else:
        config = zenoh.Config()
        _insert(config, "mode", json.dumps(cfg.mode), f"zenoh.mode {cfg.mode!r}")
        _insert(
            config,
            "scouting/multicast/enabled",
            json.dumps(cfg.multicast_scouting),
            "zenoh.multicast_scouting",
        )
        if not cfg.multicast_scouting:
            # Zenoh waits scouting/delay (500 ms) at open for peers to be discovered; with
            # explicit endpoints there is nothing to discover, and the tools wait for a
            # matching subscriber or queryable instead. ``extra`` may set it back.
            _insert(config, "scouting/delay", "0", "zenoh.multicast_scouting")
        # The gateway publishes its statuses in bursts (six express messages per tick, each a
        # batch of its own): Zenoh's default of 2 data batches in the transmit queue drops
        # the burst's tail whenever the transmit thread is a moment late (measured: ~2 % of
        # the later statuses on a loaded machine). 16 is Zenoh's maximum. ``extra`` may
        # set it back.
        _insert(config, "transport/link/tx/queue/size/data", str(TX_DATA_BATCHES), "tx queue")
        # A ``connect`` endpoint that accepts the connection but never answers Zenoh's handshake
        # (another service on the port, a hung process) leaves the handshake pending, and
        # closing the session waits for it: up to Zenoh's 10 s, which every tool and the
        # daemon's stop waited at exit (measured: `status --duration 1` took 11 s). A handshake
        # takes milliseconds on loopback or the car's network. ``extra`` may set it back.
        _insert(config, "transport/unicast/open_timeout", str(OPEN_TIMEOUT_MS), "open timeout")
    for name in ("listen", "connect"):
        endpoints: tuple[str, ...] = getattr(cfg, name)
        if cfg.ros == "rmw_zenoh" and cfg.config_file is None and not endpoints:
            # As an rmw_zenoh session: connect to rmw_zenohd, listen on a loopback port of
            # the system's choosing for the peers the router tells about (gossip).
            endpoints = (RMW_ZENOHD,) if name == "connect" else ("tcp/127.0.0.1:0",)
        if cfg.config_file is None or endpoints:
            for endpoint in endpoints:  # one at a time, so the error names the culprit
                _insert(
                    config,
                    f"{name}/endpoints",
                    json.dumps([endpoint]),
                    f"zenoh.{name}: bad endpoint {endpoint!r}",
                )
            _insert(config, f"{name}/endpoints", json.dumps(list(endpoints)), f"zenoh.{name}")
    for key, value in cfg.extra.items():
        _insert(config, key, value, f"zenoh.extra.{key}: bad value {value!r}")
    return config


def _get(config: zenoh.Config, key: str) -> Any:
    """A setting as a Python value; None when this Zenoh does not have it."""
    try:
        return json.loads(config.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


def _uses_tls(config: zenoh.Config, side: str, mode: str) -> bool:
    """Whether ``side`` ("listen" or "connect") has a TLS endpoint in ``mode``."""
    endpoints = _get(config, f"{side}/endpoints")
    if isinstance(endpoints, dict):  # per mode: {router: [...], peer: [...]}
        endpoints = endpoints.get(mode)
    return any(str(e).startswith(_TLS_SCHEMES) for e in endpoints or ())


def _check_tls_files(config: zenoh.Config, config_file: str | None) -> None:
    """Every TLS certificate or key the session will load must name an existing file.

    Only the side with a ``tls/`` endpoint is checked: a tool sharing the gateway's file
    connects, and never loads the gateway's listening certificate.

    :raises TransportError: naming the setting, the path and where the setting came from
    """
    mode = _get(config, "mode") or "peer"
    names: list[str] = []
    if mode != "client" and _uses_tls(config, "listen", mode):
        names += TLS_LISTEN_FILES
    if _uses_tls(config, "connect", mode):
        names += TLS_CONNECT_FILES
    for name in dict.fromkeys(names):
        key = f"transport/link/tls/{name}"
        value = _get(config, key)
        if value is not None and not Path(str(value)).is_file():
            where = f"{config_file} or zenoh.extra" if config_file else "zenoh.extra"
            raise TransportError(f"{key}: {value}: no such file (from {where})")


# Endpoints of the IP-based links: ``proto/host:port`` (an IPv6 host in brackets), with optional
# ``?metadata`` and ``#config`` tails.
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_ENDPOINT = re.compile(r"([A-Za-z0-9][A-Za-z0-9-]*)/([^?#]+)(?:[?#].*)?")
_HOST_PORT = re.compile(r"(\[[0-9A-Fa-f:.%\w]+\]|[^\s:/\[\]]+):(\d+)")


def endpoint_problem(endpoint: str, side: str) -> str | None:
    """Why ``endpoint`` is not a well-formed Zenoh endpoint, or None.

    ``proto/host:port`` with a port in 1–65535 for the IP links (tcp, udp, tls, quic, ws); a
    ``listen`` endpoint may also give port 0 (a port of the system's choosing). Other links
    (``unixsock-stream/PATH``, ``serial/…``) need a non-empty address after the ``/``.
    """
    match = _ENDPOINT.fullmatch(endpoint.strip())
    if match is None:
        return "expected proto/host:port, e.g. tcp/127.0.0.1:7447"
    proto, address = match.group(1), match.group(2)
    if proto not in _IP_PROTOCOLS:
        return None
    hp = _HOST_PORT.fullmatch(address)
    if hp is None:
        return f"expected {proto}/host:port, e.g. {proto}/127.0.0.1:7447"
    port = int(hp.group(2))
    lowest = 0 if side == "listen" else 1
    if not lowest <= port <= 65535:
        return f"port {port} is not in {lowest}–65535"
    return None


def _check_endpoints(config: zenoh.Config, cfg: ZenohConfig) -> None:
    """Every endpoint the session would listen on or connect to is well formed.

    :raises TransportError: naming the key (``zenoh.listen``, or the JSON5 file) and endpoint
    """
    mode = _get(config, "mode") or "peer"
    for side in ("listen", "connect"):
        endpoints = _get(config, f"{side}/endpoints")
        if isinstance(endpoints, dict):  # per mode: {router: [...], peer: [...]}
            endpoints = endpoints.get(mode)
        for endpoint in endpoints or ():
            problem = endpoint_problem(str(endpoint), side)
            if problem is None:
                continue
            ours = str(endpoint) in getattr(cfg, side)
            where = f"zenoh.{side}" if ours or cfg.config_file is None else cfg.config_file
            raise TransportError(f"{where}: bad endpoint {str(endpoint)!r}: {problem}")


def checked_config(cfg: ZenohConfig) -> zenoh.Config:
    """:func:`build_config`, then what can be checked without opening anything: the endpoints
    are well formed and the TLS certificates and keys the session will load exist.

    ``leafgate check-config`` and the daemon's start-up run this same check.

    :raises TransportError: one line naming the file, key, endpoint or TLS setting at fault
    """
    config = build_config(cfg)
    _check_endpoints(config, cfg)
    _check_tls_files(config, cfg.config_file)
    return config


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """Open a Zenoh session as ``cfg`` says.

    Peer mode with explicit endpoints and multicast scouting off unless a JSON5 file is given
    (see :mod:`leafgate.config.transport`). The caller owns the session and closes it.

    :raises TransportError: one line naming the file, endpoint or TLS certificate at fault
    """
    config = checked_config(cfg)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        where = cfg.config_file or (
            f"listen {list(cfg.listen)}, connect {list(cfg.connect)}"
            if cfg.listen or cfg.connect
            else "no endpoints"
        )
        raise TransportError(f"cannot open Zenoh session ({where}): {zenoh_message(exc)}") from None


CONNECT_WAIT = 1.0  # s, how long start-up waits for a ``connect`` endpoint to answer


def unanswered_connect(
    session: zenoh.Session,
    cfg: ZenohConfig,
    wait: float = CONNECT_WAIT,
    clock: Callable[[], float] = time.monotonic,
) -> tuple[str, ...]:
    """The ``connect`` endpoints, when none of them answered within ``wait``; else ``()``.

    In client mode an unreachable router fails :func:`open_session`. A peer or a router opens
    anyway and goes on trying in the background (an ``rmw_zenohd`` started after the
    gateway is found then), so its start-up must say that it is, for now, cut off: no
    localization and no plan will come. Only the endpoints leafgate configured are judged;
    with ``zenoh.config_file`` the file decides, and ``()`` is returned.
    """
    if cfg.mode == "client" or not cfg.connect or cfg.config_file:
        return ()
    end = clock() + wait
    while True:
        if list(session.info.peers_zid()) or list(session.info.routers_zid()):
            return ()
        if clock() >= end:
            return tuple(cfg.connect)
        time.sleep(0.02)


def _insert(config: zenoh.Config, key: str, value: str, what: str) -> None:
    try:
        config.insert_json5(key, value)
    except zenoh.ZError as exc:
        raise TransportError(f"{what}: {zenoh_message(exc)}") from None
