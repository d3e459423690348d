"""Exact accounting of load-cell samples sent by the probe and received by the host.

This module owns :class:`SampleAccounting`: fed the ``first_index`` and ``count`` of every
delivered SAMPLES message, it knows how many samples the probe took since the first one
received (``sent``), how many arrived (``received``), and which were lost
(:class:`SampleGap`: first missing index and count), so that ``sent == received + lost``
holds exactly. Indices are u32 and handled modulo 2^32 (a forward step below 2^31 is a
gap; a backward step means the probe restarted and opens a new run). It does not decide
where samples were lost: each gap records how many link frames were lost just before it
(from :class:`~stipi_daemon.protocol.decoder.DecodedFrame`), and STATUS ``dropped`` tells
the probe-side losses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from stipi_daemon.errors import ProtocolError
from stipi_daemon.protocol.decoder import DecodedFrame
from stipi_daemon.protocol.messages import MAX_SAMPLES_PER_BATCH, Samples
from stipi_daemon.protocol.timestamps import SeqEvent

__all__ = ["SampleAccounting", "SampleGap"]

_U32: Final = 1 << 32
_HALF_U32: Final = 1 << 31


@dataclass(frozen=True, slots=True)
class SampleGap:
    """A run of samples the host never received.

    Parameters
    ----------
    start_index : int
        ``first_index`` numbering (u32) of the first missing sample.
    count : int
        Number of missing samples.
    run : int
        Sender run (0 for the first; +1 at every probe restart) the gap belongs to.
    link_frames_lost : int
        Frames lost on the link since the previous SAMPLES (from sequence gaps); 0 means
        the samples were dropped in the probe.
    """

    start_index: int
    count: int
    run: int
    link_frames_lost: int


class SampleAccounting:
    """Counts samples sent, received and lost, from SAMPLES ``first_index`` and ``count``.

    ``sent`` counts from the first sample of the first batch received in each run (samples
    taken before the host started listening are not known to exist) to the end of the
    last batch received; losses after the last received batch are only known once a later
    batch arrives.
    """

    __slots__ = ("_frames_lost", "_gaps", "_lost", "_next", "_received", "_run", "_sent_done")

    def __init__(self) -> None:
        self._next: int | None = None
        self._run = -1
        self._received = 0
        self._lost = 0
        self._sent_done = 0
        self._gaps: list[SampleGap] = []
        self._frames_lost = 0

    @property
    def received(self) -> int:
        """Samples received."""
        return self._received

    @property
    def lost(self) -> int:
        """Samples lost between received batches."""
        return self._lost

    @property
    def sent(self) -> int:
        """Samples the probe took, from the first received to the last received (all runs)."""
        return self._received + self._lost

    @property
    def gaps(self) -> tuple[SampleGap, ...]:
        """Every gap, in order."""
        return tuple(self._gaps)

    @property
    def runs(self) -> int:
        """Sender runs seen (1 + probe restarts), 0 before the first batch."""
        return self._run + 1

    @property
    def next_index(self) -> int | None:
        """``first_index`` the next batch should have, ``None`` before the first batch."""
        return self._next

    def note_link_loss(self, frames: int) -> None:
        """Record ``frames`` frames lost on the link (attributed to the next gap)."""
        if frames < 0:
            raise ProtocolError(f"frames={frames} must not be negative")
        self._frames_lost += frames

    def observe(self, first_index: int, count: int, *, restart: bool = False) -> SampleGap | None:
        """Account for one received batch.

        Parameters
        ----------
        first_index : int
            SAMPLES ``first_index``, 0..2^32-1.
        count : int
            SAMPLES ``count``, 1..24.
        restart : bool
            The probe restarted before this batch (its indices start afresh).

        Returns
        -------
        SampleGap or None
            The gap just before this batch, if any.
        """
        if not 0 <= first_index < _U32:
            raise ProtocolError(f"first_index={first_index} out of range 0..{_U32 - 1}")
        if not 1 <= count <= MAX_SAMPLES_PER_BATCH:
            raise ProtocolError(f"count={count} out of range 1..{MAX_SAMPLES_PER_BATCH}")
        gap: SampleGap | None = None
        nxt = self._next
        if nxt is None or restart or (first_index - nxt) % _U32 >= _HALF_U32:
            self._run += 1
        else:
            missing = (first_index - nxt) % _U32
            if missing:
                gap = SampleGap(nxt, missing, self._run, self._frames_lost)
                self._gaps.append(gap)
                self._lost += missing
        self._frames_lost = 0
        self._received += count
        self._next = (first_index + count) % _U32
        return gap

    def observe_frame(self, frame: DecodedFrame) -> SampleGap | None:
        """Account for any delivered frame: link losses from every frame, samples from SAMPLES.

        Parameters
        ----------
        frame : DecodedFrame
            A frame returned by :meth:`FrameDecoder.feed`; duplicates are ignored.

        Returns
        -------
        SampleGap or None
            The gap just before this batch, if ``frame`` is SAMPLES and one was found.
        """
        if frame.event == SeqEvent.DUPLICATE:
            return None
        if frame.event == SeqEvent.RESTART:
            self._frames_lost = 0
        self._frames_lost += frame.lost_before
        msg = frame.message
        if not isinstance(msg, Samples):
            return None
        return self.observe(msg.first_index, len(msg.adc), restart=frame.event == SeqEvent.RESTART)
