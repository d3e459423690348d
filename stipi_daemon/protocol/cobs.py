"""Consistent Overhead Byte Stuffing (Cheshire & Baker 1999), the framing of the wire protocol.

:func:`cobs_encode` turns any byte string into one without 0x00 (the frame delimiter is
not appended here); :func:`cobs_decode` reverses it and raises
:class:`~stipi_daemon.protocol.errors.FrameError` (kind ``cobs``) naming the offending byte
offset for input that no encoder could have produced. The encoding is canonical: a block
of 254 non-zero bytes is coded 0xFF, and a trailing 0xFF block is not followed by an empty
block. This module knows nothing of frame lengths or CRCs.
"""

from __future__ import annotations

from typing import Final

from stipi_daemon.protocol.errors import FrameError, FrameErrorKind

__all__ = ["COBS_MAX_BLOCK", "cobs_decode", "cobs_encode", "cobs_max_encoded_length"]

COBS_MAX_BLOCK: Final = 254
"""Longest run of non-zero data bytes one code byte covers."""


def cobs_max_encoded_length(n: int) -> int:
    """Longest COBS encoding of ``n`` data bytes: ``n + 1 + n // 254`` [bytes]."""
    return n + 1 + n // COBS_MAX_BLOCK


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """COBS-encode ``data``; the result contains no 0x00 and has no delimiter.

    Parameters
    ----------
    data : bytes-like
        Any bytes, including none.

    Returns
    -------
    bytes
        The encoding, ``len(data) + 1`` bytes for data shorter than 254 bytes.
    """
    out = bytearray()
    chunks = bytes(data).split(b"\x00")
    last = len(chunks) - 1
    for i, chunk in enumerate(chunks):
        split = False
        while len(chunk) >= COBS_MAX_BLOCK:
            out.append(0xFF)
            out += chunk[:COBS_MAX_BLOCK]
            chunk = chunk[COBS_MAX_BLOCK:]
            split = True
        if chunk or i != last or not split:
            out.append(len(chunk) + 1)
            out += chunk
    return bytes(out)


def cobs_decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS-encoded frame (without its 0x00 delimiter).

    Parameters
    ----------
    encoded : bytes-like
        The encoded frame.

    Returns
    -------
    bytes
        The original data.

    Raises
    ------
    FrameError
        Kind ``cobs``: empty input, a 0x00 byte inside the frame, or a code byte whose block
        runs past the end; the error's ``offset`` is the offending byte's position in
        ``encoded``.
    """
    enc = bytes(encoded)
    n = len(enc)
    if n == 0:
        raise FrameError(FrameErrorKind.COBS, 0, "empty input is not a COBS encoding")
    zero = enc.find(0)
    if zero >= 0:
        raise FrameError(FrameErrorKind.COBS, zero, "0x00 inside a COBS-encoded frame")
    out = bytearray()
    i = 0
    while i < n:
        code = enc[i]
        end = i + code
        if end > n:
            raise FrameError(
                FrameErrorKind.COBS,
                i,
                f"code byte 0x{code:02X} announces a block ending at offset {end}, "
                f"past the end of the {n}-byte frame",
            )
        out += enc[i + 1 : end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)
