"""Incremental frame decoder for one received byte stream (one sender).

This module owns :class:`FrameDecoder`: fed chunks of any size (20-byte BLE notifications,
serial reads), it splits the stream at 0x00 delimiters, decodes and checks every frame
(:func:`~stipi_daemon.protocol.messages.unpack_frame`), tracks the sender's sequence
numbers and unwraps its clock (:mod:`~stipi_daemon.protocol.timestamps`), and returns
:class:`DecodedFrame` objects annotated with gaps. Every byte is accounted for in
:class:`DecoderStats`, and every rejected frame is recorded as a :class:`DecodeErrorEvent`
with the stream byte offset where it started. Its buffer is bounded: a run of bytes
longer than the longest encoded frame (75 bytes) is counted and discarded as it arrives,
never stored. It does no I/O and knows nothing of BLE or serial ports.

Sender restarts
---------------
Links deliver bytes in order, so a frame with a sequence number older than expected is
either an exact duplicate (not delivered again) or the sender restarted its counter. A
restart is also recognised from the content: SAMPLES ``first_index`` or STATUS
``dropped`` going backwards (modulo 2^32). After a restart the sequence tracker and the
clock unwrapper start afresh and the frame is delivered with event
:attr:`~stipi_daemon.protocol.timestamps.SeqEvent.RESTART`.

Frames of the wrong direction
-----------------------------
A decoder told which types its sender sends (``accept``; the probe link gives
:data:`PROBE_TO_HOST_TYPES`) drops a CRC-valid frame of any other type - a host → probe
COMMAND echoed or looped back onto the probe's stream - before it reaches the sequence
tracker or the clock: counted in ``wrong_direction`` and recorded as a
:attr:`~stipi_daemon.protocol.errors.FrameErrorKind.DIRECTION` error, it cannot fake a
restart, a gap or a clock jump (the host's own seq and t_us count on another clock).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Collection
from dataclasses import dataclass, fields, replace
from typing import Final

from stipi_daemon.protocol.cobs import cobs_decode
from stipi_daemon.protocol.errors import FrameError, FrameErrorKind
from stipi_daemon.protocol.messages import (
    MAX_ENCODED_SIZE,
    Message,
    MsgType,
    Samples,
    Status,
    unpack_frame,
)
from stipi_daemon.protocol.timestamps import (
    SeqEvent,
    SequenceTracker,
    TimestampUnwrapper,
)

__all__ = [
    "HOST_TO_PROBE_TYPES",
    "PROBE_TO_HOST_TYPES",
    "DecodeErrorEvent",
    "DecodedFrame",
    "DecoderStats",
    "FrameDecoder",
]

#: Message types the probe sends (its stream's decoder accepts only these).
PROBE_TO_HOST_TYPES: Final = frozenset({MsgType.SAMPLES, MsgType.STATUS, MsgType.ACK})
#: Message types the host sends.
HOST_TO_PROBE_TYPES: Final = frozenset({MsgType.COMMAND})

_HALF_U32: Final = 1 << 31
_U32: Final = 1 << 32


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """One valid frame taken from the stream, with its sequence annotation.

    Parameters
    ----------
    message : Message
        The message carried.
    seq : int
        The frame's sequence number, 0..65535.
    t_us : int
        Raw sender clock from the header [µs], 0..2^32-1.
    t_us_unwrapped : int
        Sender clock unwrapped to 64 bits [µs] (restarts from the raw value after a sender
        restart).
    event : SeqEvent
        First, in order, gap, duplicate or restart.
    lost_before : int
        Frames lost between the previous frame and this one (``event`` GAP).
    seq_wrapped : bool
        Whether the sequence counter passed 65535 → 0 just before this frame.
    stream_offset : int
        Byte offset in the stream of the frame's first encoded byte [bytes].
    """

    message: Message
    seq: int
    t_us: int
    t_us_unwrapped: int
    event: SeqEvent
    lost_before: int
    seq_wrapped: bool
    stream_offset: int

    @property
    def is_duplicate(self) -> bool:
        """Whether this frame repeats one already delivered."""
        return self.event == SeqEvent.DUPLICATE


@dataclass(frozen=True, slots=True)
class DecodeErrorEvent:
    """One rejected run of bytes between two delimiters.

    Parameters
    ----------
    kind : FrameErrorKind
        The check it failed.
    stream_offset : int
        Byte offset in the stream where the rejected bytes start [bytes].
    length : int
        Number of bytes rejected, delimiter excluded [bytes]. An over-long run is counted
        in :class:`DecoderStats` as soon as it passes 75 bytes, but its event is recorded
        when its delimiter arrives, with its whole length.
    offset_in_frame : int
        Offset of the problem inside the frame (:attr:`FrameError.offset`) [bytes].
    detail : str
        What was wrong.
    """

    kind: FrameErrorKind
    stream_offset: int
    length: int
    offset_in_frame: int
    detail: str

    def __str__(self) -> str:
        return (
            f"{self.kind.value} error in {self.length}-byte frame at stream byte offset "
            f"{self.stream_offset}: {self.detail}"
        )


@dataclass(slots=True)
class DecoderStats:
    """Exact counters of one decoder since creation (or :meth:`FrameDecoder.reset`).

    Byte accounting: ``bytes_received == bytes_ok + bytes_discarded + delimiters +
    buffered`` where ``buffered`` is :attr:`FrameDecoder.buffered_bytes`.
    """

    bytes_received: int = 0
    """Bytes fed [bytes]."""
    bytes_ok: int = 0
    """Encoded bytes of valid frames, delimiters excluded [bytes]."""
    bytes_discarded: int = 0
    """Bytes of rejected runs, delimiters excluded [bytes]."""
    delimiters: int = 0
    """0x00 bytes seen (including those of empty frames)."""
    frames_ok: int = 0
    """Valid frames, duplicates included."""
    empty_frames: int = 0
    """Empty frames (0x00 right after 0x00 or at stream start), ignored."""
    crc_errors: int = 0
    """Frames failing the CRC."""
    cobs_errors: int = 0
    """Runs that are not valid COBS."""
    length_errors: int = 0
    """Runs or decoded frames outside 11..75 encoded / 10..74 decoded bytes."""
    version_errors: int = 0
    """CRC-valid frames of another protocol version."""
    unknown_type: int = 0
    """CRC-valid frames of an unknown message type."""
    body_errors: int = 0
    """CRC-valid frames whose body does not fit their type."""
    wrong_direction: int = 0
    """CRC-valid frames of a type this sender never sends (a COMMAND on the probe's
    stream), dropped before sequence and clock tracking."""
    resyncs: int = 0
    """Valid frames that followed one or more rejected runs (regained synchronisation)."""
    gaps: int = 0
    """Sequence gaps (events)."""
    frames_lost: int = 0
    """Frames missing in those gaps (sum)."""
    duplicates: int = 0
    """Frames repeating a recently received one."""
    restarts: int = 0
    """Sender restarts detected."""
    seq_wraps: int = 0
    """Sequence counter wraps 65535 → 0."""
    t_us_wraps: int = 0
    """Clock wraps 2^32 → 0, summed over sender runs."""

    @property
    def errors(self) -> int:
        """Rejected runs of all kinds."""
        return (
            self.crc_errors
            + self.cobs_errors
            + self.length_errors
            + self.version_errors
            + self.unknown_type
            + self.body_errors
            + self.wrong_direction
        )

    def as_dict(self) -> dict[str, int]:
        """All counters by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


_ERROR_FIELD: Final[dict[FrameErrorKind, str]] = {
    FrameErrorKind.CRC: "crc_errors",
    FrameErrorKind.COBS: "cobs_errors",
    FrameErrorKind.LENGTH: "length_errors",
    FrameErrorKind.VERSION: "version_errors",
    FrameErrorKind.TYPE: "unknown_type",
    FrameErrorKind.BODY: "body_errors",
    FrameErrorKind.DIRECTION: "wrong_direction",
}


class FrameDecoder:
    """Turns a byte stream from one sender into :class:`DecodedFrame` objects.

    Parameters
    ----------
    deliver_duplicates : bool
        Also return duplicate frames (annotated :attr:`SeqEvent.DUPLICATE`); by default
        they are only counted, as docs/protocol.md requires.
    max_error_events : int
        How many recent :class:`DecodeErrorEvent` objects :attr:`errors` keeps.
    accept : collection of MsgType, optional
        The message types this sender sends (:data:`PROBE_TO_HOST_TYPES` for the probe's
        stream); CRC-valid frames of other types are dropped as
        :attr:`FrameErrorKind.DIRECTION` errors. Default: every type.
    """

    def __init__(
        self,
        *,
        deliver_duplicates: bool = False,
        max_error_events: int = 256,
        accept: Collection[MsgType] | None = None,
    ) -> None:
        self._accept = None if accept is None else frozenset(accept)
        self._deliver_duplicates = deliver_duplicates
        self._max_error_events = max_error_events
        self.reset()

    def reset(self) -> None:
        """Forget buffer, sequence and clock state and zero the statistics."""
        self._stats = DecoderStats()
        self._buf = bytearray()
        self._discarding = False
        self._discard_len = 0
        self._in_sync = True
        self._offset = 0
        self._seg_start = 0
        self._seq = SequenceTracker()
        self._clock = TimestampUnwrapper()
        self._next_index: int | None = None
        self._last_dropped: int | None = None
        self.errors: deque[DecodeErrorEvent] = deque(maxlen=self._max_error_events)
        """Most recent rejected runs, oldest first."""

    @property
    def stats(self) -> DecoderStats:
        """A copy of the counters."""
        return replace(self._stats, t_us_wraps=self._clock.wraps)

    @property
    def buffered_bytes(self) -> int:
        """Bytes of an unfinished frame held in the buffer (at most 75) [bytes]."""
        return len(self._buf)

    @property
    def stream_offset(self) -> int:
        """Bytes fed so far [bytes]."""
        return self._offset

    def pop_errors(self) -> list[DecodeErrorEvent]:
        """Return and forget the recorded error events."""
        events = list(self.errors)
        self.errors.clear()
        return events

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[DecodedFrame]:
        """Consume ``chunk`` and return the frames it completed, in stream order.

        Parameters
        ----------
        chunk : bytes-like
            Next bytes of the stream, any length (including 0).

        Returns
        -------
        list of DecodedFrame
            Valid frames whose delimiter is in ``chunk`` (duplicates only with
            ``deliver_duplicates``).
        """
        data = chunk if isinstance(chunk, bytes) else bytes(chunk)
        n = len(data)
        out: list[DecodedFrame] = []
        if n == 0:
            return out
        stats = self._stats
        base = self._offset
        self._offset = base + n
        stats.bytes_received += n
        buf = self._buf
        pos = 0
        while pos < n:
            z = data.find(0, pos)
            if z < 0:
                tail = n - pos
                if self._discarding:
                    self._discard_len += tail
                    stats.bytes_discarded += tail
                elif len(buf) + tail > MAX_ENCODED_SIZE:
                    self._start_discarding(len(buf) + tail)
                    buf.clear()
                else:
                    buf += data[pos:] if pos else data
                break
            stats.delimiters += 1
            if self._discarding:
                self._discard_len += z - pos
                stats.bytes_discarded += z - pos
                self._discarding = False
                self._record_overlong(self._discard_len)
            elif buf:
                if len(buf) + z - pos > MAX_ENCODED_SIZE:
                    self._start_discarding(len(buf) + z - pos)
                    self._discarding = False
                    self._record_overlong(self._discard_len)
                else:
                    buf += data[pos:z]
                    self._segment(bytes(buf), out)
                buf.clear()
            elif z > pos:
                self._segment(data[pos:z], out)
            else:
                stats.empty_frames += 1
            pos = z + 1
            self._seg_start = base + pos
        return out

    # ----------------------------------------------------------------------- internals

    def _count(self, kind: FrameErrorKind, length: int) -> None:
        stats = self._stats
        setattr(stats, _ERROR_FIELD[kind], getattr(stats, _ERROR_FIELD[kind]) + 1)
        stats.bytes_discarded += length
        self._in_sync = False

    def _reject(self, kind: FrameErrorKind, length: int, offset: int, detail: str) -> None:
        self._count(kind, length)
        self.errors.append(DecodeErrorEvent(kind, self._seg_start, length, offset, detail))

    def _start_discarding(self, length: int) -> None:
        """A run outgrew the longest frame: count it now, discard the rest as it comes."""
        self._count(FrameErrorKind.LENGTH, length)
        self._discarding = True
        self._discard_len = length

    def _record_overlong(self, length: int) -> None:
        self.errors.append(
            DecodeErrorEvent(
                FrameErrorKind.LENGTH,
                self._seg_start,
                length,
                MAX_ENCODED_SIZE,
                f"{length} bytes between delimiters exceed the {MAX_ENCODED_SIZE}-byte limit",
            )
        )

    def _segment(self, seg: bytes, out: list[DecodedFrame]) -> None:
        if len(seg) > MAX_ENCODED_SIZE:
            self._count(FrameErrorKind.LENGTH, len(seg))
            self._record_overlong(len(seg))
            return
        try:
            frame = unpack_frame(cobs_decode(seg))
        except FrameError as exc:
            self._reject(exc.kind, len(seg), exc.offset, exc.detail)
            return
        msg_type = frame.message.MSG_TYPE
        if self._accept is not None and msg_type not in self._accept:
            self._reject(
                FrameErrorKind.DIRECTION,
                len(seg),
                1,
                f"{msg_type.name} frame (seq {frame.seq}) is sent by the other end; dropped "
                "without touching sequence or clock tracking",
            )
            return
        stats = self._stats
        stats.frames_ok += 1
        stats.bytes_ok += len(seg)
        if not self._in_sync:
            stats.resyncs += 1
            self._in_sync = True
        msg = frame.message
        restart = False
        if isinstance(msg, Samples):
            if self._next_index is not None:
                restart = (msg.first_index - self._next_index) % _U32 >= _HALF_U32
        elif isinstance(msg, Status) and self._last_dropped is not None:
            restart = (msg.dropped - self._last_dropped) % _U32 >= _HALF_U32
        obs = self._seq.observe(frame.seq, seg, restart=restart)
        event = obs.event
        if event == SeqEvent.DUPLICATE:
            stats.duplicates += 1
            if self._deliver_duplicates:
                out.append(
                    DecodedFrame(
                        msg,
                        frame.seq,
                        frame.t_us,
                        self._clock.peek(frame.t_us),
                        event,
                        0,
                        False,
                        self._seg_start,
                    )
                )
            return
        if event == SeqEvent.RESTART:
            stats.restarts += 1
            self._clock.reset()
            self._next_index = None
            self._last_dropped = None
        elif event == SeqEvent.GAP:
            stats.gaps += 1
            stats.frames_lost += obs.lost
        if obs.wrapped:
            stats.seq_wraps += 1
        if isinstance(msg, Samples):
            self._next_index = (msg.first_index + len(msg.adc)) % _U32
        elif isinstance(msg, Status):
            self._last_dropped = msg.dropped
        out.append(
            DecodedFrame(
                msg,
                frame.seq,
                frame.t_us,
                self._clock.unwrap(frame.t_us),
                event,
                obs.lost,
                obs.wrapped,
                self._seg_start,
            )
        )
