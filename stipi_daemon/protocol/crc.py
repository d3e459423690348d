"""CRC-16/CCITT-FALSE, the frame check of the wire protocol (docs/protocol.md).

Polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR; the check value for
ASCII ``123456789`` is 0x29B1. :func:`crc16_ccitt_table` is the table-driven reference,
byte for byte what the firmware computes; :func:`crc16_ccitt` gives the same result
through the C implementation in :func:`binascii.crc_hqx` (same polynomial, no reflection,
caller-chosen initial value) and is what the codec uses. This module does not frame or
append the CRC: :mod:`~stipi_daemon.protocol.messages` does.
"""

from __future__ import annotations

from binascii import crc_hqx
from typing import Final

__all__ = [
    "CRC16_CHECK",
    "CRC16_INIT",
    "CRC16_POLY",
    "CRC16_TABLE",
    "crc16_ccitt",
    "crc16_ccitt_table",
]

CRC16_POLY: Final = 0x1021
"""Generator polynomial x^16 + x^12 + x^5 + 1 (MSB-first, implicit x^16)."""
CRC16_INIT: Final = 0xFFFF
"""Initial register value."""
CRC16_CHECK: Final = 0x29B1
"""CRC of ASCII ``123456789`` (the catalogue's check value)."""


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC16_POLY) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
        table.append(crc)
    return tuple(table)


CRC16_TABLE: Final[tuple[int, ...]] = _make_table()
"""``CRC16_TABLE[b]`` is the CRC register after shifting byte ``b`` through a zero register."""


def crc16_ccitt_table(data: bytes | bytearray | memoryview, crc: int = CRC16_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data`` by table lookup, one byte at a time.

    Parameters
    ----------
    data : bytes-like
        Bytes to check.
    crc : int
        Register value to continue from (``CRC16_INIT`` to start a new CRC).

    Returns
    -------
    int
        CRC register after ``data``, 0..0xFFFF.
    """
    table = CRC16_TABLE
    for byte in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def crc16_ccitt(data: bytes | bytearray | memoryview, crc: int = CRC16_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (fast path, equal to :func:`crc16_ccitt_table`).

    Parameters
    ----------
    data : bytes-like
        Bytes to check.
    crc : int
        Register value to continue from (``CRC16_INIT`` to start a new CRC).

    Returns
    -------
    int
        CRC register after ``data``, 0..0xFFFF.
    """
    return crc_hqx(data, crc)
