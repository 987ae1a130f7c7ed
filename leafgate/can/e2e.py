"""End-to-end protection of the leafgate drive-by-wire frames (docs/can-protocol.md).

Every DBW frame is 8 bytes. The low nibble of byte 6 is a 4-bit alive counter that advances
by 1 (mod 16) with every frame of an ID; byte 7 is a CRC-8 SAE J1850 (polynomial 0x1D,
init 0xFF, xor-out 0xFF, not reflected) computed over a *data ID* — the low byte of the CAN
ID — followed by bytes 0–6. Mixing the ID into the CRC catches a frame delivered under the
wrong ID, which a CRC over the payload alone would not.

The checksums of the car's own frames live here too (:data:`SEALS`): the ZE1's LKAS CRC, the
AZE0's 0x002 XOR-of-nibbles and 0x284/0x285 counter-plus-offset; a vehicle profile names the
scheme per frame (:mod:`leafgate.can.profile`).

Pure functions and a small per-ID state machine; no clock, no bus.

>>> hex(crc8_j1850(b"123456789"))
'0x4b'
>>> frame = apply(0x0A0, bytes(8), counter=3)
>>> frame[6] & 0x0F, verify(0x0A0, frame), verify(0x0A1, frame)
(3, True, False)
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Mapping
from types import MappingProxyType

__all__ = [
    "COUNTER_BYTE",
    "COUNTER_MODULO",
    "CRC_BYTE",
    "FRAME_LENGTH",
    "CounterChecker",
    "CounterStatus",
    "apply",
    "counter_of",
    "crc8_j1850",
    "crc8_nissan_lkas",
    "e2e_crc",
    "nissan_nibble_checksum",
    "seal",
    "sealed_ok",
    "verify",
]

FRAME_LENGTH = 8  # bytes, every leafgate DBW frame
COUNTER_BYTE = 6  # alive counter in the low nibble of this byte
CRC_BYTE = 7  # CRC-8 in this byte
COUNTER_MODULO = 16  # 4-bit counter

_POLY = 0x1D  # SAE J1850: x^8 + x^4 + x^3 + x^2 + 1
_INIT = 0xFF
_XOR_OUT = 0xFF


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ _POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE: tuple[int, ...] = _make_table()


def crc8_j1850(data: Iterable[int], *, init: int = _INIT) -> int:
    """CRC-8 SAE J1850 of ``data`` (table-driven).

    :param data: bytes (or any iterable of ints 0–255)
    :param init: the register before the first byte; the default is the standard's 0xFF,
        pass a precomputed register to continue a CRC (see :func:`e2e_crc`)
    :return: the CRC, already xor-ed with 0xFF
    """
    crc = init
    table = _TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc ^ _XOR_OUT


def _register_after_data_id(frame_id: int) -> int:
    """The CRC register after the data ID byte: constant per ID, so callers can cache it."""
    return _TABLE[_INIT ^ (frame_id & 0xFF)]


def e2e_crc(frame_id: int, data: bytes | bytearray) -> int:
    """The E2E CRC of a frame: CRC-8 over the data ID (low byte of ``frame_id``), then bytes 0–6.

    :param frame_id: the CAN ID of the frame
    :param data: the frame's payload, at least 7 bytes (byte 7 is ignored)
    """
    return crc8_j1850(data[:CRC_BYTE], init=_register_after_data_id(frame_id))


def crc8_nissan_lkas(data: bytes | bytearray) -> int:
    """The checksum in byte 7 of the 2018+ Leaf's ProPILOT steering frame 0x169 ``LKAS``.

    CRC-8 with polynomial 0x1D over bytes 0–6, not reflected, xor-out 0xFF. Sources write
    its initial value as 0x00 in the ``crcmod`` convention, where the initial value is the
    CRC of an empty message (the register xor-ed with the xor-out): the shift register
    itself starts at 0xFF. So this is the plain CRC-8 SAE J1850 of bytes 0–6, the same
    computation as opendbc's ``opendbc.car.nissan.nissancan.nissan_checksum``. No data ID
    is mixed in (unlike leafgate's own :func:`e2e_crc`).

    :param data: the frame's payload, at least 7 bytes (byte 7 is ignored)
    :return: the value of byte 7
    :raises ValueError: if ``data`` is shorter than 7 bytes

    Angle +10.00 deg, MAX_TORQUE 1 Nm, LKA_ACTIVE 1, counter 5 (tests/test_vehicle_dbc.py):

    >>> hex(crc8_nissan_lkas(bytes.fromhex("7ef40080648015")))
    '0xc4'
    >>> crc8_nissan_lkas(bytes(8)) == crc8_j1850(bytes(7))  # byte 7 is not covered
    True
    """
    if len(data) < CRC_BYTE:
        raise ValueError(f"LKAS checksum covers bytes 0-6, got {len(data)} bytes")
    return crc8_j1850(data[:CRC_BYTE])


def nissan_nibble_checksum(data: bytes | bytearray) -> int:
    """The checksum nibble of the Leaf's steering-angle frame 0x002 (high nibble of byte 4).

    The XOR of the eight nibbles of bytes 0–3 and the counter nibble (the low nibble of
    byte 4), as every one of 11,870 frames recorded on an AZE0 Leaf and an e-NV200 shows.

    >>> hex(nissan_nibble_checksum(bytes.fromhex("00 00 00 07 03")))  # 7 ^ 3
    '0x4'
    """
    acc = data[4] & 0x0F
    for byte in data[:4]:
        acc ^= (byte >> 4) ^ (byte & 0x0F)
    return acc


# --- checksum schemes ------------------------------------------------------------------------
# A scheme that protects a frame with a checksum computed from its other bytes fills it here:
# ``seal(frame_id, payload, params)`` writes the checksum into the payload (the counter is
# already in place, written by the encoder as a DBC signal). The receiver recomputes it on a
# copy and compares (:func:`sealed_ok`). A new scheme is one function and one entry.


def _seal_leafgate(frame_id: int, data: bytearray, params: Mapping[str, int]) -> None:
    data[CRC_BYTE] = e2e_crc(frame_id, data)


def _seal_nissan_lkas(frame_id: int, data: bytearray, params: Mapping[str, int]) -> None:
    data[7] = crc8_nissan_lkas(data)


def _seal_nissan_nibble(frame_id: int, data: bytearray, params: Mapping[str, int]) -> None:
    data[4] = (data[4] & 0x0F) | (nissan_nibble_checksum(data) << 4)


def _seal_counter_sum(frame_id: int, data: bytearray, params: Mapping[str, int]) -> None:
    data[7] = (data[6] + params["offset"]) & 0xFF


_NO_PARAMS: Mapping[str, int] = MappingProxyType({})
SEALS: Mapping[str, Callable[[int, bytearray, Mapping[str, int]], None]] = {
    "leafgate": _seal_leafgate,
    "nissan-lkas": _seal_nissan_lkas,
    "nissan-nibble": _seal_nissan_nibble,  # 0x002 of the AZE0 Leaf
    "counter-sum": _seal_counter_sum,  # 0x284/0x285: byte 7 = byte 6 + offset
}
# Bytes the payload needs for each checksum (the receiver checks the length first).
SEAL_LENGTH: Mapping[str, int] = {
    "leafgate": FRAME_LENGTH,
    "nissan-lkas": 8,
    "nissan-nibble": 5,
    "counter-sum": 8,
}


def seal(
    scheme: str, frame_id: int, data: bytes | bytearray, params: Mapping[str, int] = _NO_PARAMS
) -> bytes:
    """``data`` with the checksum of ``scheme`` filled in (schemes without one: unchanged).

    >>> seal("counter-sum", 0x284, bytes(6) + bytes((0x10, 0)), {"offset": 0x86}).hex()
    '0000000000001096'
    """
    fill = SEALS.get(scheme)
    if fill is None:
        return bytes(data)
    out = bytearray(data)
    fill(frame_id, out, params)
    return bytes(out)


def sealed_ok(
    scheme: str, frame_id: int, data: bytes | bytearray, params: Mapping[str, int] = _NO_PARAMS
) -> bool:
    """True when the checksum of ``scheme`` in ``data`` is right (always, without one)."""
    fill = SEALS.get(scheme)
    if fill is None:
        return True
    out = bytearray(data)
    fill(frame_id, out, params)
    return out == data


def apply(frame_id: int, data: bytes | bytearray, counter: int) -> bytes:
    """Return ``data`` with the alive counter and CRC set.

    The high nibble of byte 6 is kept (it may carry signals).

    :param frame_id: the CAN ID the frame is sent under
    :param data: an 8-byte payload
    :param counter: the alive counter, taken mod 16
    :raises ValueError: if ``data`` is not 8 bytes long
    """
    if len(data) != FRAME_LENGTH:
        raise ValueError(f"E2E frames are {FRAME_LENGTH} bytes, got {len(data)}")
    out = bytearray(data)
    out[COUNTER_BYTE] = (out[COUNTER_BYTE] & 0xF0) | (counter % COUNTER_MODULO)
    out[CRC_BYTE] = e2e_crc(frame_id, out)
    return bytes(out)


def verify(frame_id: int, data: bytes | bytearray) -> bool:
    """True when ``data`` is 8 bytes long and its byte 7 is the E2E CRC for ``frame_id``."""
    return len(data) == FRAME_LENGTH and data[CRC_BYTE] == e2e_crc(frame_id, data)


def counter_of(data: bytes | bytearray) -> int:
    """The alive counter of a frame (low nibble of byte 6)."""
    return data[COUNTER_BYTE] & 0x0F


class CounterStatus(enum.Enum):
    """Outcome of checking one received alive counter."""

    OK = "ok"  # advanced by exactly 1 mod 16
    FIRST = "first"  # first frame of this ID since start or reset: accepted
    REPEATED = "repeated"  # same counter as the previous frame: a stuck sender or a replay
    SKIPPED = "skipped"  # advanced by 2..15: frames were lost

    @property
    def ok(self) -> bool:
        """True for the statuses that accept the frame."""
        return self in (CounterStatus.OK, CounterStatus.FIRST)


class CounterChecker:
    """Receive-side alive-counter check, one state per CAN ID.

    The counter must advance by exactly 1 mod 16 from the last *accepted or counter-faulty*
    frame; a repeated or skipped counter is an error, and the checker then resynchronises on
    the received value so that one lost frame costs one error, not sixteen. Frames with a bad
    CRC must not be passed in (their counter cannot be trusted).

    >>> c = CounterChecker()
    >>> [c.check(0xB0, n).value for n in (5, 6, 6, 8, 9)]
    ['first', 'ok', 'repeated', 'skipped', 'ok']
    """

    __slots__ = ("_before", "_last", "interleaved")

    #: counter errors in a row that continue the counter before last: two senders take turns
    INTERLEAVED_IN_ROW = 3

    def __init__(self) -> None:
        self._last: dict[int, int] = {}
        self._before: dict[int, int] = {}  # the counter before the last one
        #: per ID, counter errors in a row whose counter continues the one *before* the last:
        #: two interleaved sequences (5, 11, 6, 12, 7 …), i.e. a second sender of the ID
        self.interleaved: dict[int, int] = {}

    def check(self, frame_id: int, counter: int, modulo: int = COUNTER_MODULO) -> CounterStatus:
        """Check ``counter`` of a frame of ``frame_id`` (``modulo``: 16 for a 4-bit counter,
        256 for an 8-bit one) and remember it."""
        last = self._last.get(frame_id)
        self._last[frame_id] = counter
        if last is None:
            return CounterStatus.FIRST
        before = self._before.get(frame_id)
        self._before[frame_id] = last
        step = (counter - last) % modulo
        if step == 1:
            self.interleaved[frame_id] = 0
            return CounterStatus.OK
        if before is not None and (counter - before) % modulo == 1:
            self.interleaved[frame_id] = self.interleaved.get(frame_id, 0) + 1
        else:
            self.interleaved[frame_id] = 0
        if step == 0:
            return CounterStatus.REPEATED
        return CounterStatus.SKIPPED

    def second_senders(self) -> list[int]:
        """IDs whose counters currently run as two interleaved sequences (a second sender)."""
        # list() copies in one step: the receive thread may add an ID meanwhile
        return sorted(i for i, n in list(self.interleaved.items()) if n >= self.INTERLEAVED_IN_ROW)

    def reset(self, frame_id: int | None = None) -> None:
        """Forget the last counter of ``frame_id`` (all IDs when None): the next is FIRST.

        Call it after a receive timeout, when the sender may have restarted.
        """
        if frame_id is None:
            self._last.clear()
            self._before.clear()
            self.interleaved.clear()
        else:
            self._last.pop(frame_id, None)
            self._before.pop(frame_id, None)
            self.interleaved.pop(frame_id, None)
