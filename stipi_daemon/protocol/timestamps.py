"""Wrap-around handling of the header's u32 microsecond clock and u16 sequence counter.

This module owns two small pure state machines fed one received frame at a time:
:class:`TimestampUnwrapper` turns the sender's ``t_us`` (``micros()`` mod 2^32, wrapping
every 4294.97 s ≈ 71.6 min) into a 64-bit count, and :class:`SequenceTracker` classifies
each ``seq`` as first, in order, after a gap (how many frames were lost), duplicate, or a
sender restart, following docs/protocol.md ("Sequence numbers", "Timestamps and
wrap-around"). It does not map MCU time onto the host clock (offset and drift fit) and it
does not parse frames.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

__all__ = [
    "SEQ_HALF_RANGE",
    "SEQ_MODULUS",
    "T_US_HALF_RANGE",
    "T_US_MODULUS",
    "SeqEvent",
    "SeqObservation",
    "SequenceTracker",
    "TimestampUnwrapper",
    "seq_distance",
    "unwrap_t_us",
]

T_US_MODULUS: Final = 1 << 32
"""Period of the raw ``t_us`` field [µs] (4294.97 s)."""
T_US_HALF_RANGE: Final = 1 << 31
"""Largest forward step the unwrapper accepts [µs] (2147.5 s ≈ 35.8 min)."""
SEQ_MODULUS: Final = 1 << 16
"""Period of the ``seq`` field."""
SEQ_HALF_RANGE: Final = 1 << 15
"""Distances at or above this are "older than expected"."""


def unwrap_t_us(previous_us: int | None, raw_us: int) -> int:
    """Unwrap one raw u32 timestamp against the previous unwrapped one.

    With the previous unwrapped value ``T`` and a raw value ``r``,
    ``T' = T + ((r - T) mod 2^32)`` when that step is below 2^31, else ``r`` is a slightly
    older time: ``T' = T - ((T - r) mod 2^32)``.

    Parameters
    ----------
    previous_us : int or None
        Previous unwrapped timestamp [µs]; ``None`` for the first one.
    raw_us : int
        Raw ``t_us`` field [µs], 0..2^32-1.

    Returns
    -------
    int
        Unwrapped timestamp [µs]; equals ``raw_us`` for the first frame, may be negative
        only if a frame older than the very first one arrives.
    """
    if not 0 <= raw_us < T_US_MODULUS:
        raise ValueError(f"raw_us={raw_us} out of range 0..{T_US_MODULUS - 1}")
    if previous_us is None:
        return raw_us
    step = (raw_us - previous_us) % T_US_MODULUS
    if step < T_US_HALF_RANGE:
        return previous_us + step
    return previous_us - ((previous_us - raw_us) % T_US_MODULUS)


class TimestampUnwrapper:
    """Unwraps successive raw ``t_us`` values of one sender into a 64-bit count [µs].

    Each value is unwrapped against the previous unwrapped value (docs/protocol.md), so
    consecutive frames must be less than 2^31 µs (35.8 min) apart; the ≤ 1 s heartbeat
    guarantees that while the link is up.
    """

    __slots__ = ("_last_us", "_max_us", "_wraps_before")

    def __init__(self) -> None:
        self._last_us: int | None = None
        self._max_us = 0
        self._wraps_before = 0

    @property
    def last_us(self) -> int | None:
        """Last unwrapped timestamp [µs], ``None`` before the first frame."""
        return self._last_us

    @property
    def wraps(self) -> int:
        """Times the clock passed 2^32 → 0 (latest time seen, over every run since creation)."""
        return self._wraps_before + (0 if self._last_us is None else self._max_us // T_US_MODULUS)

    def peek(self, raw_us: int) -> int:
        """Unwrapped value of ``raw_us`` without updating the state [µs]."""
        return unwrap_t_us(self._last_us, raw_us)

    def unwrap(self, raw_us: int) -> int:
        """Unwrap ``raw_us`` and make it the reference for the next one [µs]."""
        value = unwrap_t_us(self._last_us, raw_us)
        if self._last_us is None or value > self._max_us:
            self._max_us = value
        self._last_us = value
        return value

    def reset(self) -> None:
        """Forget the reference: the next value is taken as is (sender restarted)."""
        self._wraps_before = self.wraps
        self._last_us = None
        self._max_us = 0


def seq_distance(seq: int, expected: int) -> int:
    """``(seq - expected) mod 65536``: 0 in order, 1..32767 frames lost, else older."""
    return (seq - expected) % SEQ_MODULUS


class SeqEvent(StrEnum):
    """How a received frame's ``seq`` relates to the ones before it."""

    FIRST = "first"
    """First frame seen: sets the expected sequence number, no gap counted."""
    IN_ORDER = "in_order"
    """``seq`` is the expected one."""
    GAP = "gap"
    """``seq`` is ahead by ``lost`` frames (1..32767); they were lost."""
    DUPLICATE = "duplicate"
    """Same ``seq`` and same bytes as a recently received frame: not delivered again."""
    RESTART = "restart"
    """The sender restarted its counter (older ``seq`` that is not a duplicate, or the
    caller saw a restart in the content): the frame is taken as a new first frame."""


@dataclass(frozen=True, slots=True)
class SeqObservation:
    """Classification of one received ``seq``.

    Parameters
    ----------
    event : SeqEvent
        The classification.
    lost : int
        Frames lost just before this one (non-zero only for :attr:`SeqEvent.GAP`).
    wrapped : bool
        Whether the counter passed 65535 → 0 between the previous frame and this one.
    """

    event: SeqEvent
    lost: int = 0
    wrapped: bool = False

    @property
    def deliver(self) -> bool:
        """Whether the frame is new (everything except a duplicate)."""
        return self.event != SeqEvent.DUPLICATE


class SequenceTracker:
    """Per-sender u16 sequence state (docs/protocol.md, "Sequence numbers").

    For every frame, ``d = (seq - expected) mod 65536``: ``d == 0`` in order,
    ``0 < d < 32768`` a gap of ``d`` lost frames, ``d >= 32768`` an older frame. Every link
    (BLE, USB CDC, UART) delivers bytes in order, so an older frame is either a duplicate
    — same ``seq`` and same bytes as one of the last ``history`` frames — or proof that
    the sender restarted its counter; a restart is taken as a new first frame, so that a
    probe reset never blocks delivery.

    Parameters
    ----------
    history : int
        Number of recent frames remembered for duplicate detection.
    """

    __slots__ = ("_expected", "_history", "_last_seq", "_order", "_recent")

    def __init__(self, history: int = 256) -> None:
        if history < 1:
            raise ValueError(f"history={history} must be at least 1")
        self._history = history
        self._expected: int | None = None
        self._last_seq = 0
        self._recent: dict[int, bytes | None] = {}
        self._order: deque[int] = deque()

    @property
    def expected(self) -> int | None:
        """Next expected ``seq``, ``None`` before the first frame."""
        return self._expected

    def reset(self) -> None:
        """Forget everything: the next frame is a first frame."""
        self._expected = None
        self._recent.clear()
        self._order.clear()

    def _remember(self, seq: int, fingerprint: bytes | None) -> None:
        if seq in self._recent:
            self._order.remove(seq)
        self._recent[seq] = fingerprint
        self._order.append(seq)
        if len(self._order) > self._history:
            del self._recent[self._order.popleft()]

    def classify(
        self, seq: int, fingerprint: bytes | None = None, *, restart: bool = False
    ) -> SeqObservation:
        """Classify ``seq`` without updating the state (see :meth:`observe`)."""
        expected = self._expected
        if expected is None:
            return SeqObservation(SeqEvent.FIRST)
        d = seq_distance(seq, expected)
        if d >= SEQ_HALF_RANGE and seq in self._recent:
            known = self._recent[seq]
            if fingerprint is None or known is None or known == fingerprint:
                return SeqObservation(SeqEvent.DUPLICATE)
        if restart or d >= SEQ_HALF_RANGE:
            return SeqObservation(SeqEvent.RESTART)
        wrapped = seq < self._last_seq
        if d == 0:
            return SeqObservation(SeqEvent.IN_ORDER, 0, wrapped)
        return SeqObservation(SeqEvent.GAP, d, wrapped)

    def observe(
        self, seq: int, fingerprint: bytes | None = None, *, restart: bool = False
    ) -> SeqObservation:
        """Classify ``seq`` and update the state.

        Parameters
        ----------
        seq : int
            Received sequence number, 0..65535.
        fingerprint : bytes or None
            The frame's bytes (or any identity of its content); an older ``seq`` counts as a
            duplicate only if its fingerprint equals the remembered one. ``None`` matches
            any.
        restart : bool
            The caller saw from the content that the sender restarted (e.g. SAMPLES
            ``first_index`` went backwards); overrides in-order and gap, not duplicate.

        Returns
        -------
        SeqObservation
            The classification.
        """
        if not 0 <= seq < SEQ_MODULUS:
            raise ValueError(f"seq={seq} out of range 0..{SEQ_MODULUS - 1}")
        obs = self.classify(seq, fingerprint, restart=restart)
        if obs.event == SeqEvent.DUPLICATE:
            return obs
        if obs.event == SeqEvent.RESTART:
            self._recent.clear()
            self._order.clear()
        self._expected = (seq + 1) % SEQ_MODULUS
        self._last_seq = seq
        self._remember(seq, fingerprint)
        return obs
