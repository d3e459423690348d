"""Decode errors of the wire protocol, classified by the check that rejected the frame.

This module owns :class:`FrameError`, the :class:`~stipi_daemon.errors.ProtocolError`
raised when received bytes are not a valid frame, and :class:`FrameErrorKind`, the
category the stream decoder counts it under. It does not decide what to do with a bad
frame: :mod:`~stipi_daemon.protocol.decoder` counts and discards it.
"""

from __future__ import annotations

from enum import StrEnum

from stipi_daemon.errors import ProtocolError

__all__ = ["FrameError", "FrameErrorKind", "ProtocolError"]


class FrameErrorKind(StrEnum):
    """The check a received frame failed, in the order the checks run."""

    LENGTH = "length"
    """Encoded or decoded frame length outside the protocol's bounds (10..74 bytes decoded)."""
    COBS = "cobs"
    """The bytes between two delimiters are not a valid COBS encoding."""
    CRC = "crc"
    """The CRC-16/CCITT-FALSE over header and body does not match the frame's last 2 bytes."""
    VERSION = "version"
    """CRC-valid frame of a protocol version other than 1."""
    TYPE = "type"
    """CRC-valid version-1 frame with an unknown message type."""
    BODY = "body"
    """CRC-valid frame whose body does not match its type's layout or field ranges."""
    DIRECTION = "direction"
    """CRC-valid frame of a type the other end sends (a host → probe COMMAND on the probe's
    stream): an echo or loop-back of the host's own bytes, never a probe frame."""


class FrameError(ProtocolError):
    """Received bytes are not a valid frame.

    Parameters
    ----------
    kind : FrameErrorKind
        Which check failed.
    offset : int
        Byte offset of the problem [bytes]: inside the COBS-encoded frame for
        :attr:`FrameErrorKind.COBS` and :attr:`FrameErrorKind.LENGTH` of the encoded form,
        inside the decoded frame (header at offset 0) otherwise.
    detail : str
        Human-readable description naming the field or byte.
    """

    def __init__(self, kind: FrameErrorKind, offset: int, detail: str) -> None:
        self.kind = kind
        self.offset = offset
        self.detail = detail
        super().__init__(f"{kind.value} error at byte offset {offset}: {detail}")
