"""Recording section of the configuration (``recording:``).

.. code-block:: yaml

    recording:
      enabled: true
      directory: /var/log/leafgate
      can_log: "can-{start}.blf"        # .blf (default), .log (candump -L) or .asc; null: none
      session: "session-{start}.mcap"   # the whole session for replay/rerun; null: none
      max_bytes: 104857600              # rotate the CAN log at 100 MiB (0: never)
      flush_period: 1.0                 # s, a crash loses at most this much

``{start}`` in a file name becomes the start time of the recording (local time,
``20250131T141500``). The CAN log rotates: the first file is ``can-…_000.blf``, then ``_001`` …
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import PurePath
from typing import Literal

from leafgate.config import positive

#: CAN log suffixes the recorder writes (each read back by python-can's ``LogReader``).
CAN_LOG_SUFFIXES: tuple[str, ...] = (".blf", ".log", ".asc")


@dataclass(frozen=True)
class RecordingConfig:
    """What the daemon records, where, and how often it makes the files crash-safe."""

    enabled: bool = False
    directory: str = "recordings"  # relative paths are taken from the daemon's working directory
    can_log: str | None = "can-{start}.blf"
    session: str | None = "session-{start}.mcap"
    max_bytes: int = 100 * 1024 * 1024  # bytes per CAN log file before rotating; 0 = never
    flush_period: float = 1.0  # s, at most this much is lost in a crash or power loss
    queue_size: int = 20_000  # items waiting for the writer thread (≈ 10 s of CAN at 2 kHz)
    # bytes those items may hold together (a flood of 10 MB junk payloads took 1.29 GB before)
    queue_bytes: int = 64 * 1024 * 1024
    # while a recorder fails (or recording is off), engage is refused: the car's default
    required: bool = False
    compression: Literal["zstd", "lz4", "none"] = "zstd"  # MCAP chunk compression
    diagnostics: bool = True  # record the gateway diagnostics of every tick in the session

    def __post_init__(self) -> None:
        positive(self, "flush_period", "queue_size", "queue_bytes")
        if self.flush_period > 1.0:
            # docs/design.md, "Recording": a crash or power loss loses at most the last second
            raise ValueError(f"flush_period must be at most 1 s, got {self.flush_period!r}")
        if self.max_bytes < 0:
            raise ValueError(
                f"max_bytes must be 0 (never rotate) or positive, got {self.max_bytes}"
            )
        if not self.directory.strip():
            raise ValueError("directory must not be empty")
        if self.can_log is not None:
            suffix = PurePath(self.can_log).suffix.lower()
            if suffix not in CAN_LOG_SUFFIXES:
                raise ValueError(
                    f"can_log {self.can_log!r}: the suffix selects the format, one of "
                    f"{', '.join(CAN_LOG_SUFFIXES)}"
                )
        if self.session is not None and PurePath(self.session).suffix.lower() != ".mcap":
            raise ValueError(f"session {self.session!r}: must end in .mcap")
