"""Pure model of the probe's BLE module (nRF51822 Bluefruit) transmit side, with faults.

This module owns the byte-level behaviour between the firmware handing a frame to the
BLE module and a notification leaving the antenna, as plain state machines with no I/O
and no Bumble objects:

* :class:`UartTxFifo` - the module's UART TX buffer (about 1 KB, reference/hardware.md):
  a frame is accepted whole or refused (the firmware then counts it as lost on BLE, which
  the host sees as a ``seq`` gap), notifications are cut from its front at ATT MTU - 3
  bytes regardless of frame boundaries, and it remembers which frames left complete.
* :class:`ConnectionEventPacer` - notifications leave only at connection events, at most
  ``per_event`` per event, one event every ``interval_s`` of session time.
* :class:`NotificationFaults` / :class:`FaultInjector` - seeded drop / corruption / delay
  of single notifications for fault-injection tests.

Link-level faults (drop the link, go silent, disappear) are actions of the Bumble
peripheral in :mod:`stipi_daemon.sim.ble.peripheral`, which drives these models.
"""

from __future__ import annotations

import math
import random
from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Final

__all__ = [
    "BLUEFRUIT_TX_BUFFER_BYTES",
    "ConnectionEventPacer",
    "FaultInjector",
    "FaultOutcome",
    "NotificationFaults",
    "ReceiverSyncModel",
    "TxChunk",
    "TxPiece",
    "UartTxFifo",
]

#: Size of the Bluefruit module's UART TX buffer [bytes] (reference/hardware.md, ~1 KB).
BLUEFRUIT_TX_BUFFER_BYTES: Final = 1024
#: Longest run a receiver keeps between delimiters [bytes] (longer runs are garbage).
MAX_RUN_BYTES: Final = 80


@dataclass(frozen=True, slots=True)
class TxPiece:
    """The part of one frame inside one notification.

    Parameters
    ----------
    tag : hashable
        The frame's tag (as offered).
    start : int
        Offset of the piece in the frame [bytes].
    length : int
        Bytes of the frame in this notification.
    frame_length : int
        Length of the whole frame, delimiter included [bytes].
    frame : bytes
        The whole frame as offered (delimiter included).
    """

    tag: Hashable
    start: int
    length: int
    frame_length: int
    frame: bytes = b""

    @property
    def ends_frame(self) -> bool:
        """Whether the frame's last byte (its 0x00 delimiter) is in this piece."""
        return self.start + self.length == self.frame_length


@dataclass(frozen=True, slots=True)
class TxChunk:
    """One notification's payload cut from the FIFO.

    Parameters
    ----------
    payload : bytes
        Bytes to notify, 1..max_len.
    pieces : tuple of TxPiece
        The frames the payload holds parts of, in order.
    """

    payload: bytes
    pieces: tuple[TxPiece, ...]

    @property
    def touched(self) -> tuple[Hashable, ...]:
        """Tags of every frame with bytes in this payload."""
        return tuple(p.tag for p in self.pieces)

    @property
    def finished(self) -> tuple[Hashable, ...]:
        """Tags of frames whose last byte is in this payload."""
        return tuple(p.tag for p in self.pieces if p.ends_frame)


class UartTxFifo:
    """The BLE module's transmit buffer: whole frames in, MTU-sized chunks out.

    Parameters
    ----------
    capacity_bytes : int
        Buffer size [bytes], > 0.
    """

    def __init__(self, capacity_bytes: int = BLUEFRUIT_TX_BUFFER_BYTES) -> None:
        if capacity_bytes <= 0:
            raise ValueError(f"TX buffer capacity must be > 0 bytes, got {capacity_bytes}")
        self.capacity_bytes = capacity_bytes
        # (tag, frame bytes, bytes of it already taken)
        self._segments: deque[tuple[Hashable, bytes, int]] = deque()
        self._used = 0
        self.refused_frames = 0
        self.refused_bytes = 0

    @property
    def used_bytes(self) -> int:
        """Bytes waiting to be notified [bytes]."""
        return self._used

    @property
    def free_bytes(self) -> int:
        """Room left [bytes]."""
        return self.capacity_bytes - self._used

    def offer(self, data: bytes, tag: Hashable = None) -> bool:
        """Queue ``data`` whole if it fits; otherwise refuse it and count the refusal.

        Parameters
        ----------
        data : bytes
            One encoded frame with its delimiter (or a lone 0x00 resync byte), non-empty.
        tag : hashable
            Identifies the frame in later :class:`TxChunk` results.

        Returns
        -------
        bool
            Whether the data was queued.
        """
        if not data:
            raise ValueError("cannot queue an empty frame")
        if len(data) > self.free_bytes:
            self.refused_frames += 1
            self.refused_bytes += len(data)
            return False
        self._segments.append((tag, bytes(data), 0))
        self._used += len(data)
        return True

    def take(self, max_len: int) -> TxChunk | None:
        """Cut the next notification payload (up to ``max_len`` bytes), or None if empty."""
        if max_len <= 0:
            raise ValueError(f"notification payload size must be > 0, got {max_len}")
        if not self._segments:
            return None
        out = bytearray()
        pieces: list[TxPiece] = []
        while self._segments and len(out) < max_len:
            tag, data, taken = self._segments[0]
            n = min(max_len - len(out), len(data) - taken)
            out += data[taken : taken + n]
            pieces.append(TxPiece(tag, taken, n, len(data), data))
            if taken + n == len(data):
                self._segments.popleft()
            else:
                self._segments[0] = (tag, data, taken + n)
        self._used -= len(out)
        return TxChunk(bytes(out), tuple(pieces))

    def clear(self) -> tuple[Hashable, ...]:
        """Empty the buffer (the link went down); return the tags of the frames discarded."""
        tags = tuple(tag for tag, _, _ in self._segments)
        self._segments.clear()
        self._used = 0
        return tags


class ConnectionEventPacer:
    """Notification budget of a connection: ``per_event`` notifications every ``interval_s``.

    Connection events fall at ``start_s + k * interval_s`` (session time). :meth:`grant`
    returns how many notifications the events since the previous call allow; a caller that
    wakes late gets the events it missed, up to ``max_backlog_events`` of them (a stalled
    host does not turn into an unbounded burst).

    Parameters
    ----------
    interval_s : float
        Connection interval [s], > 0 (BLE allows 7.5 ms .. 4 s).
    per_event : int
        Notifications the module fits into one connection event, >= 1.
    start_s : float
        Session time of the first connection event [s].
    max_backlog_events : int
        Most events granted at once, >= 1.
    """

    def __init__(
        self,
        interval_s: float,
        per_event: int,
        start_s: float,
        max_backlog_events: int = 64,
    ) -> None:
        if not (interval_s > 0.0 and math.isfinite(interval_s)):
            raise ValueError(f"connection interval must be a finite time > 0 s, got {interval_s}")
        if per_event < 1:
            raise ValueError(f"notifications per connection event must be >= 1, got {per_event}")
        if max_backlog_events < 1:
            raise ValueError(f"max_backlog_events must be >= 1, got {max_backlog_events}")
        self.interval_s = float(interval_s)
        self.per_event = per_event
        self.max_backlog_events = max_backlog_events
        self._start_s = float(start_s)
        self._k_next = 0

    @property
    def next_event_s(self) -> float:
        """Session time of the next connection event not yet granted [s]."""
        return self._start_s + self._k_next * self.interval_s

    def grant(self, now_s: float) -> int:
        """Notifications allowed by the connection events at or before ``now_s``."""
        if now_s < self.next_event_s - 1e-9 * self.interval_s:
            return 0
        # Count events on an integer grid (start + k * interval) so rounding never drifts.
        k_now = math.floor((now_s - self._start_s) / self.interval_s + 1e-9)
        events = k_now - self._k_next + 1
        self._k_next = k_now + 1
        return min(events, self.max_backlog_events) * self.per_event


@dataclass(frozen=True, slots=True)
class NotificationFaults:
    """Faults applied to single notifications on the air.

    Parameters
    ----------
    drop_probability : float
        Chance a notification is lost [-], 0..1.
    corrupt_probability : float
        Chance one bit of a notification is flipped [-], 0..1 (applied to those not dropped).
    delay_s : float
        Extra latency of every notification [s], >= 0 (order is kept).
    """

    drop_probability: float = 0.0
    corrupt_probability: float = 0.0
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drop_probability", "corrupt_probability"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be within 0..1, got {p}")
        if not (self.delay_s >= 0.0 and math.isfinite(self.delay_s)):
            raise ValueError(f"delay_s must be a finite time >= 0 s, got {self.delay_s}")

    @property
    def active(self) -> bool:
        """Whether any fault is configured."""
        return self.drop_probability > 0.0 or self.corrupt_probability > 0.0 or self.delay_s > 0


@dataclass(frozen=True, slots=True)
class FaultOutcome:
    """What happened to one notification.

    Parameters
    ----------
    payload : bytes or None
        Bytes to send (None when dropped).
    dropped, corrupted : bool
        Which fault struck.
    flipped_byte : int or None
        Offset in the payload of the byte with a flipped bit (when corrupted).
    """

    payload: bytes | None
    dropped: bool
    corrupted: bool
    flipped_byte: int | None = None


class FaultInjector:
    """Applies :class:`NotificationFaults` with a seeded generator (reproducible runs).

    Parameters
    ----------
    faults : NotificationFaults
        Initial settings (replace :attr:`faults` to change them).
    seed : int
        Generator seed.
    """

    def __init__(self, faults: NotificationFaults | None = None, seed: int = 0) -> None:
        self.faults = faults or NotificationFaults()
        self._rng = random.Random(seed)
        self.dropped = 0
        self.corrupted = 0

    def apply(self, payload: bytes) -> FaultOutcome:
        """Decide the fate of one notification ``payload``."""
        f = self.faults
        if f.drop_probability > 0.0 and self._rng.random() < f.drop_probability:
            self.dropped += 1
            return FaultOutcome(None, dropped=True, corrupted=False)
        if payload and f.corrupt_probability > 0.0 and self._rng.random() < f.corrupt_probability:
            bit = self._rng.randrange(len(payload) * 8)
            out = bytearray(payload)
            out[bit // 8] ^= 1 << (bit % 8)
            self.corrupted += 1
            return FaultOutcome(bytes(out), dropped=False, corrupted=True, flipped_byte=bit // 8)
        return FaultOutcome(payload, dropped=False, corrupted=False)


class ReceiverSyncModel:
    """Which frames a COBS receiver will decode, given the fate of every notification.

    A receiver decodes a frame when the bytes it gets between one 0x00 and the next are
    exactly that frame. This model follows the bytes that really arrive (dropped
    notifications contribute none, corrupted ones their damaged bytes) and reports the
    tag of every frame whose own delimiter closes a run equal to the frame as sent. So a
    lost notification costs the frames it held parts of, and also the next frame when it
    swallowed a delimiter while the receiver held part of a frame (the part merges with
    the next frame) - unless the merged bytes happen to equal that frame, which the model
    sees too. It ignores the ~2^-30 chance that damaged bytes pass the receiver's checks
    as some other frame (docs/protocol.md, "False acceptance").
    """

    def __init__(self) -> None:
        self._run = bytearray()
        self._first: TxPiece | None = None

    def reset(self) -> None:
        """A new connection: the receiver starts empty (the host flushes its decoder)."""
        self._run.clear()
        self._first = None

    def observe(self, chunk: TxChunk, outcome: FaultOutcome) -> list[Hashable]:
        """Feed one notification's fate; return the tags of frames now decoded."""
        payload = outcome.payload
        if payload is None:
            return []  # nothing of it arrives: the receiver's state does not change
        delivered: list[Hashable] = []
        pos = 0
        for piece in chunk.pieces:
            received = payload[pos : pos + piece.length]
            pos += piece.length
            for byte in received:
                if byte != 0:
                    if not self._run:
                        self._first = piece
                    if len(self._run) <= MAX_RUN_BYTES:
                        self._run.append(byte)
                    continue
                # A delimiter ends the run. It is a frame if it equals, whole, the frame it
                # began in or the frame this 0x00 belongs to (a lost stretch can join the
                # head of one frame to the tail of another that ends the same way).
                run = bytes(self._run) + b"\x00"
                for cand in (self._first, piece) if self._run else ():
                    if cand is not None and run == cand.frame:
                        delivered.append(cand.tag)
                        break
                self._run.clear()
                self._first = None
        return delivered
