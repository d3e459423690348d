"""CRC-16/CCITT-FALSE: catalogue check value, table against the C fast path, properties."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.protocol.crc import (
    CRC16_CHECK,
    CRC16_TABLE,
    crc16_ccitt,
    crc16_ccitt_table,
)


def bitwise_crc(data: bytes) -> int:
    """Bit-by-bit CRC straight from the definition (poly 0x1021, init 0xFFFF, MSB first)."""
    crc = 0xFFFF
    for byte in data:
        for bit in range(7, -1, -1):
            feedback = ((crc >> 15) & 1) ^ ((byte >> bit) & 1)
            crc = ((crc << 1) & 0xFFFF) ^ (0x1021 if feedback else 0)
    return crc


def test_check_value() -> None:
    assert CRC16_CHECK == 0x29B1
    assert crc16_ccitt_table(b"123456789") == 0x29B1
    assert crc16_ccitt(b"123456789") == 0x29B1
    assert bitwise_crc(b"123456789") == 0x29B1


def test_table_entries() -> None:
    assert len(CRC16_TABLE) == 256
    assert CRC16_TABLE[0] == 0 and CRC16_TABLE[1] == 0x1021 and CRC16_TABLE[255] == 0x1EF0


def test_empty_input_is_initial_value() -> None:
    assert crc16_ccitt_table(b"") == 0xFFFF == crc16_ccitt(b"")


@given(st.binary(max_size=300))
def test_table_equals_fast_path_and_definition(data: bytes) -> None:
    assert crc16_ccitt_table(data) == crc16_ccitt(data) == bitwise_crc(data)


@given(st.binary(max_size=100), st.binary(max_size=100))
def test_incremental(a: bytes, b: bytes) -> None:
    assert crc16_ccitt_table(b, crc16_ccitt_table(a)) == crc16_ccitt(a + b)


@given(st.binary(min_size=1, max_size=74), st.data())
def test_detects_every_single_and_double_bit_error(data: bytes, draw: st.DataObject) -> None:
    nbits = 8 * len(data)
    i = draw.draw(st.integers(0, nbits - 1))
    j = draw.draw(st.integers(0, nbits - 1))
    damaged = bytearray(data)
    damaged[i // 8] ^= 0x80 >> (i % 8)
    if j != i:  # else a single-bit error
        damaged[j // 8] ^= 0x80 >> (j % 8)
    assert crc16_ccitt(bytes(damaged)) != crc16_ccitt(data)
