"""E2E protection: CRC-8 SAE J1850 over data ID + bytes 0-6, 4-bit alive counter in byte 6."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from leafgate.can import e2e
from leafgate.can.e2e import CounterChecker, CounterStatus

payloads = st.binary(min_size=8, max_size=8)
frame_ids = st.integers(min_value=0, max_value=0x7FF)


def reference_crc8_j1850(data: bytes) -> int:
    """Bit-by-bit CRC-8 (poly 0x1D, init 0xFF, xor-out 0xFF), the textbook definition."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def test_crc_check_value_of_123456789_is_0x4b() -> None:
    assert e2e.crc8_j1850(b"123456789") == 0x4B


def test_crc_of_empty_input_is_init_xor_out() -> None:
    assert e2e.crc8_j1850(b"") == 0x00


@given(st.binary(max_size=64))
def test_table_crc_matches_bitwise_definition(data: bytes) -> None:
    assert e2e.crc8_j1850(data) == reference_crc8_j1850(data)


@given(frame_ids, payloads)
def test_e2e_crc_covers_data_id_then_bytes_0_to_6(frame_id: int, data: bytes) -> None:
    expected = reference_crc8_j1850(bytes([frame_id & 0xFF]) + data[:7])
    assert e2e.e2e_crc(frame_id, data) == expected


@given(frame_ids, payloads, st.integers(min_value=0, max_value=100))
def test_apply_sets_counter_in_low_nibble_keeps_high_nibble(
    frame_id: int, data: bytes, counter: int
) -> None:
    out = e2e.apply(frame_id, data, counter)
    assert e2e.counter_of(out) == counter % 16
    assert out[6] & 0xF0 == data[6] & 0xF0
    assert out[:6] == data[:6]
    assert e2e.verify(frame_id, out)


@given(frame_ids, payloads, st.integers(min_value=0, max_value=63))
def test_verify_detects_every_single_bit_flip(frame_id: int, data: bytes, bit: int) -> None:
    good = bytearray(e2e.apply(frame_id, data, 5))
    good[bit // 8] ^= 1 << (bit % 8)
    assert not e2e.verify(frame_id, good)


@given(payloads)
def test_frame_under_another_id_fails_verify(data: bytes) -> None:
    frame = e2e.apply(0x0A0, data, 1)
    assert not e2e.verify(0x0A1, frame)


@pytest.mark.parametrize("length", [0, 7, 9])
def test_apply_rejects_frames_that_are_not_8_bytes(length: int) -> None:
    with pytest.raises(ValueError, match="8 bytes"):
        e2e.apply(0x0A0, bytes(length), 0)
    assert not e2e.verify(0x0A0, bytes(length))


def test_first_frame_after_start_is_accepted_whatever_its_counter() -> None:
    checker = CounterChecker()
    assert checker.check(0x0B0, 9) is CounterStatus.FIRST
    assert CounterStatus.FIRST.ok


def test_counter_wraps_from_15_to_0() -> None:
    checker = CounterChecker()
    statuses = [checker.check(0x0B0, n % 16) for n in range(13, 20)]
    assert statuses[0] is CounterStatus.FIRST
    assert all(s is CounterStatus.OK for s in statuses[1:])


def test_repeated_counter_is_an_error() -> None:
    checker = CounterChecker()
    checker.check(0x0B0, 4)
    assert checker.check(0x0B0, 4) is CounterStatus.REPEATED
    assert not CounterStatus.REPEATED.ok


@pytest.mark.parametrize("jump", range(2, 16))
def test_skipped_counter_is_an_error_then_resynchronises(jump: int) -> None:
    checker = CounterChecker()
    checker.check(0x0B0, 14)
    assert checker.check(0x0B0, (14 + jump) % 16) is CounterStatus.SKIPPED
    assert checker.check(0x0B0, (15 + jump) % 16) is CounterStatus.OK


def test_counters_are_checked_per_id() -> None:
    checker = CounterChecker()
    checker.check(0x0B0, 3)
    assert checker.check(0x0B1, 3) is CounterStatus.FIRST
    assert checker.check(0x0B0, 4) is CounterStatus.OK


def test_reset_makes_the_next_frame_first_again() -> None:
    checker = CounterChecker()
    checker.check(0x0B0, 3)
    checker.check(0x0B1, 3)
    checker.reset(0x0B0)
    assert checker.check(0x0B0, 3) is CounterStatus.FIRST
    assert checker.check(0x0B1, 3) is CounterStatus.REPEATED
    checker.reset()
    assert checker.check(0x0B1, 3) is CounterStatus.FIRST
