"""What can be checked of a deployment without the car and without the network.

``leafgate check-config`` and the daemon's start-up (:func:`leafgate.runtime.daemon.run_daemon`)
run the same :func:`offline_checks`, so a config that check-config calls ok is not refused at
start-up for a reason it could have seen:

- each CAN bus's ``interface`` is one python-can knows;
- the Zenoh configuration builds (``zenoh.config_file`` exists and parses, the ``extra``
  settings apply), every endpoint is ``proto/host:port`` with a port in 1–65535 (0 allowed for
  ``listen``), and the TLS certificates and keys the session will load exist;
- with recording enabled, ``recording.directory`` exists and is writable, or can be created.
  Nothing is left behind: the check creates a probe file (or directory, in the nearest existing
  parent) and removes it at once; the recording directory itself is made by the recorder.
  An unusable directory is an error when ``recording.required`` (the car could never engage),
  a warning otherwise (the gateway runs, its recording fails).

What needs the car or the network (the bus is up, a port is free, the router answers) is
returned as "not checked here", for check-config to say so.

Every error is one :class:`~leafgate.errors.ConfigError` line naming the file and dotted key.
"""

from __future__ import annotations

import errno
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from leafgate.errors import ConfigError, TransportError

if TYPE_CHECKING:
    from leafgate.config.can import BusConfig
    from leafgate.settings import LeafgateConfig


@dataclass
class OfflineReport:
    """What :func:`offline_checks` found short of an error."""

    warnings: list[str] = field(default_factory=list)  # one line each, file and key named
    unchecked: list[str] = field(default_factory=list)  # what needs the car or the network


def offline_checks(cfg: LeafgateConfig, *, zenoh: bool = True) -> OfflineReport:
    """Check ``cfg`` as far as possible without opening a bus or a socket.

    :param zenoh: check the Zenoh configuration (False where a session is handed in)
    :raises ConfigError: one line, ``FILE: dotted.key: problem``
    """
    source = cfg.source
    report = OfflineReport()
    buses: list[tuple[str, BusConfig]] = [("can.dbw", cfg.can.dbw)]
    if cfg.can.car is not None:
        buses.append(("can.car", cfg.can.car))
    for key, bus in buses:
        _check_bus(source, key, bus, report)
    if zenoh:
        _check_zenoh(cfg, report)
    profile = cfg.profile
    for name in profile.dbc_from_package:
        report.warnings.append(
            f"{source}: vehicle.profile: {profile.where} names the DBC {name}, which is not "
            "beside it: leafgate's packaged one of that name is used"
        )
    if cfg.recording.enabled:
        problem = recording_directory_problem(cfg.recording.directory)
        if problem is not None:
            line = f"{source}: recording.directory: {problem}"
            if cfg.recording.required:
                raise ConfigError(f"{line} (recording.required: engage would be refused)")
            report.warnings.append(f"{line} (recording will fail; not required)")
    return report


def _check_bus(source: str, key: str, bus: BusConfig, report: OfflineReport) -> None:
    import can.interfaces

    known = set(can.interfaces.VALID_INTERFACES)
    if bus.interface not in known:
        raise ConfigError(
            f"{source}: {key}.interface: {bus.interface!r} is not a python-can interface "
            f"(known: {', '.join(sorted(known))})"
        )
    if bus.interface == "socketcan":
        report.unchecked.append(f"the bus {bus.channel} exists and is up (needs the car)")
    elif bus.interface not in ("virtual", "udp_multicast"):
        report.unchecked.append(
            f"the {bus.interface} adapter {bus.channel} is present (needs the hardware)"
        )


def _check_zenoh(cfg: LeafgateConfig, report: OfflineReport) -> None:
    from leafgate.transport.session import checked_config

    z = cfg.zenoh
    if z.config_file is not None and not Path(z.config_file).is_file():
        raise ConfigError(f"{cfg.source}: zenoh.config_file: {z.config_file}: no such file")
    try:
        checked_config(z)
    except TransportError as exc:
        text = str(exc)
        if not text.startswith("zenoh."):  # from the JSON5 file (its name is in the text)
            text = f"zenoh.config_file: {text}"
        raise ConfigError(f"{cfg.source}: {text}") from None
    if z.listen or z.connect or z.config_file is not None:
        report.unchecked.append(
            "the Zenoh endpoints are free to listen on / reachable (needs the network)"
        )


def recording_directory_problem(directory: str) -> str | None:
    """Why the recorder could not write into ``directory``, or None.

    Probes by creating and removing a file in it (or, when it does not exist yet, a directory
    in its nearest existing parent); leaves nothing behind and does not create ``directory``.
    """
    path = Path(directory).expanduser()
    probe_in = path
    while not probe_in.exists():
        if probe_in.parent == probe_in:
            break
        probe_in = probe_in.parent
    if not probe_in.is_dir():
        return f"{directory}: cannot be created ({probe_in} is not a directory)"
    try:
        if probe_in == path:
            with tempfile.TemporaryFile(dir=path, prefix=".leafgate-probe-"):
                pass
        else:
            os.rmdir(tempfile.mkdtemp(dir=probe_in, prefix=".leafgate-probe-"))
    except OSError as exc:
        why = exc.strerror or errno.errorcode.get(exc.errno or 0, str(exc))
        if probe_in == path:
            return f"{directory}: not writable ({why})"
        return f"{directory}: cannot be created in {probe_in} ({why})"
    return None
