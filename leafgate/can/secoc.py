"""Authenticated command frames in the style of AUTOSAR SecOC (profile ``leafgate-dbw-auth``).

Every authenticated frame is 8 bytes (classic CAN)::

    bytes 0-3   the command's signals (32 bits; the DBC of the profile packs them)
    byte  4     FRESHNESS: the low 8 bits of the full freshness value F
    bytes 5-7   MAC: HMAC-SHA256(key, data ID ‖ bytes 0-3 ‖ F), truncated to its first 24 bits

The data ID is the 11-bit CAN ID as two big-endian bytes, F eight big-endian bytes: the MAC
covers the full freshness value, of which only the low byte travels (SecOC's truncated
freshness value).

**Freshness** is time: F counts :data:`FRESHNESS_UNIT` (5 ms) steps of the sender's wall clock
(Unix time), and never repeats per ID: a sender takes ``max(clock / unit, last F + 1)``. The
receiver rebuilds F from the 8 transmitted bits as the value nearest to its own clock (unique
while sender and receiver clocks, plus the bus latency, differ by less than 128 steps, 640
ms), and accepts a frame only when

1. F is within :data:`FRESHNESS_WINDOW` (0.5 s) of the receiver's clock — a frame recorded
   earlier than that, in this run or any before a restart of either end, is refused without
   any state kept on disk;
2. F is above the last F accepted on that ID — a frame replayed within the window is refused;
3. the MAC verifies (only then does F become the last accepted one).

What it does not cover: replay within the first 0.5 s after the receiver starts (it knows no
last F yet); senders and receivers whose clocks differ by more than the window (a step of the
wall clock, or no time sync — the car's ECU needs its time from an authenticated source);
and a stolen key. See docs/can-protocol.md for the layout's reasoning (MAC length against the
attempts an attacker gets).

**The key** is at least :data:`KEY_MIN_BYTES` random bytes, written as hex text in a file that
only its owner, the service user, may read (:func:`load_key`, like ssh's private keys). The
key never appears in a log line, an error message, diagnostics or a recording.

>>> key = bytes(range(32))
>>> tx, rx = Sealer(key), Verifier(key)
>>> frame = tx.seal(0x0A0, bytes(4), now=1000.0)
>>> rx.verify(0x0A0, frame, now=1000.01)
'ok'
>>> rx.verify(0x0A0, frame, now=1000.02)   # the same frame again
'stale'
>>> rx.verify(0x0A0, Sealer(key).seal(0x0A0, bytes(4), now=900.0), now=1000.0)  # an old run
'stale'
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import secrets
import stat
import string
from pathlib import Path
from typing import Any, Final, Literal

from leafgate.errors import ConfigError

__all__ = [
    "FRAME_LENGTH",
    "FRESHNESS_BITS",
    "FRESHNESS_BYTE",
    "FRESHNESS_UNIT",
    "FRESHNESS_WINDOW",
    "KEY_MIN_BYTES",
    "MAC_BITS",
    "PAYLOAD_BYTES",
    "Sealer",
    "Verdict",
    "Verifier",
    "freshness_at",
    "load_key",
    "mac",
    "reconstruct",
    "tool_key",
    "write_key",
]

FRAME_LENGTH: Final = 8  # bytes, every authenticated frame
PAYLOAD_BYTES: Final = 4  # bytes 0-3: the signals
FRESHNESS_BYTE: Final = 4  # the low bits of F
FRESHNESS_BITS: Final = 8
MAC_BITS: Final = 24  # bytes 5-7
FRESHNESS_RATE: Final = 200  # freshness steps per second
FRESHNESS_UNIT: Final = 1.0 / FRESHNESS_RATE  # s, 5 ms: below the shortest command period
FRESHNESS_WINDOW: Final = 0.5  # s, the largest |sender clock - receiver clock| accepted
_MODULO: Final = 1 << FRESHNESS_BITS
_WINDOW_STEPS: Final = round(FRESHNESS_WINDOW / FRESHNESS_UNIT)  # 100 < 128: F is unambiguous
KEY_MIN_BYTES: Final = 16  # 128 bits
KEY_BYTES: Final = 32  # what keygen writes (256 bits, the HMAC-SHA256 block's natural size)

Verdict = Literal["ok", "stale", "bad_mac"]


def freshness_at(t: float) -> int:
    """The freshness step of Unix time ``t`` (s)."""
    return math.floor(t * FRESHNESS_RATE)


def reconstruct(low: int, reference: int) -> int:
    """The full freshness value whose low bits are ``low`` nearest to ``reference``.

    >>> reconstruct(0x02, 0x1FE)   # the low byte wrapped since the reference
    514
    >>> reconstruct(0xFE, 0x202)   # a frame from just before the wrap
    510
    """
    delta = (low - reference) % _MODULO
    if delta >= _MODULO // 2:
        delta -= _MODULO
    return reference + delta


def mac(key: bytes, frame_id: int, payload: bytes | bytearray, freshness: int) -> bytes:
    """The truncated MAC (3 bytes) of a frame's payload (bytes 0-3) at full freshness F."""
    data = (
        frame_id.to_bytes(2, "big") + bytes(payload[:PAYLOAD_BYTES]) + freshness.to_bytes(8, "big")
    )
    return hmac.digest(key, data, hashlib.sha256)[: MAC_BITS // 8]


class Sealer:
    """The sender's side: fills FRESHNESS and MAC, one strictly rising F per ID."""

    __slots__ = ("_key", "_last")

    def __init__(self, key: bytes) -> None:
        self._key = key
        self._last: dict[int, int] = {}

    def __repr__(self) -> str:  # never the key
        return f"Sealer({len(self._last)} IDs)"

    def seal(self, frame_id: int, data: bytes | bytearray, now: float) -> bytes:
        """``data`` (at least the 4 signal bytes) as a sealed 8-byte frame at Unix time ``now``."""
        f = max(freshness_at(now), self._last.get(frame_id, -1) + 1)
        self._last[frame_id] = f
        out = bytearray(FRAME_LENGTH)
        out[:PAYLOAD_BYTES] = data[:PAYLOAD_BYTES]
        out[FRESHNESS_BYTE] = f % _MODULO
        out[FRESHNESS_BYTE + 1 :] = mac(self._key, frame_id, out, f)
        return bytes(out)


class Verifier:
    """The receiver's side: rebuilds F, checks its window and rise, and the MAC."""

    __slots__ = ("_key", "_last")

    def __init__(self, key: bytes) -> None:
        self._key = key
        self._last: dict[int, int] = {}  # last accepted F per ID

    def __repr__(self) -> str:  # never the key
        return f"Verifier({len(self._last)} IDs)"

    def verify(self, frame_id: int, data: bytes | bytearray, now: float) -> Verdict:
        """``"ok"`` (and F is remembered), ``"stale"`` (outside the window, or not above the
        last accepted F: a replay) or ``"bad_mac"`` for an 8-byte frame received at ``now``."""
        reference = freshness_at(now)
        f = reconstruct(data[FRESHNESS_BYTE], reference)
        if abs(f - reference) > _WINDOW_STEPS or f <= self._last.get(frame_id, -1):
            return "stale"
        expected = mac(self._key, frame_id, data, f)
        if not hmac.compare_digest(expected, bytes(data[FRESHNESS_BYTE + 1 : FRAME_LENGTH])):
            return "bad_mac"
        self._last[frame_id] = f
        return "ok"


# --- the key file -------------------------------------------------------------------------------


def load_key(path: str | Path) -> bytes:
    """The key in ``path``: hex text of at least 16 bytes, in a file only its owner may use.

    Refused, like ssh refuses a private key: a file that is missing, not a regular file, readable
    or writable by group or others (the mode must be 0600 or 0400), owned by another user than
    the one running leafgate, not hex, or shorter than 128 bits.

    :raises ConfigError: one line naming the file and the reason (never the key's content)
    """
    where = str(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ConfigError(
            f"{where}: no such key file (make one with `leafgate keygen {where}`)"
        ) from None
    except OSError as exc:
        raise ConfigError(f"{where}: cannot read the key file: {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"{where}: the key file is not a regular file")
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"{where}: the key file is accessible by group or others (mode {mode:04o}); "
            f"it must be 0600 or 0400: chmod 600 {where}"
        )
    if st.st_uid != os.geteuid():
        raise ConfigError(
            f"{where}: the key file belongs to uid {st.st_uid}, not to the user running "
            f"leafgate (uid {os.geteuid()})"
        )
    try:
        text = Path(path).read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) else "not ASCII hex text"
        raise ConfigError(f"{where}: cannot read the key file: {reason}") from None
    digits = "".join(text.split())
    other = next((c for c in digits if c not in string.hexdigits), None)
    if other is not None:
        raise ConfigError(f"{where}: the key file holds {other!r}, not a hex digit (0-9, a-f)")
    if len(digits) % 2:
        raise ConfigError(
            f"{where}: the key file holds {len(digits)} hex digits, an odd number: a key is "
            "whole bytes, two digits each"
        )
    key = bytes.fromhex(digits)
    if len(key) < KEY_MIN_BYTES:
        raise ConfigError(
            f"{where}: the key is {len(key) * 8} bits long, at least {KEY_MIN_BYTES * 8} are needed"
        )
    return key


def tool_key(key_file: str | Path | None, config: Any = None) -> bytes | None:
    """The key a tool reading a log verifies MACs with: ``key_file`` (``--key-file``), else the
    ``can.auth_key_file`` of a ``config`` the user gave (a ``LeafgateConfig``), else None.

    :raises ConfigError: the key file is refused (:func:`load_key`)
    """
    if key_file is None and config is not None:
        key_file = config.can.auth_key_file
    return None if key_file is None else load_key(key_file)


def write_key(path: str | Path) -> Path:
    """Write a new random key (32 bytes, hex) to ``path``, mode 0600; never overwrites.

    :raises ConfigError: the file exists or cannot be written
    """
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise ConfigError(f"{path}: exists; a key is never overwritten (remove it first)") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot create the key file: {exc.strerror}") from None
    with os.fdopen(fd, "w", encoding="ascii") as f:
        os.fchmod(f.fileno(), 0o600)  # whatever the umask
        f.write(secrets.token_hex(KEY_BYTES) + "\n")
    return path
