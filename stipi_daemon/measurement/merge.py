"""Merge timestamped streams into one time-ordered stream, live, with a bounded wait.

Force samples arrive in batches (tens of ms late, after clock sync) while frames arrive
one by one; fed to the state machine in arrival order, the same recording could yield
slightly different phase timings live and on replay. :class:`TimeOrderedMerger` releases
items in timestamp order: an item is released once every stream has delivered something
at or after its time (the *watermark*), or once it has waited ``max_hold_s`` of session
time, so that a stalled or lost stream delays the others by at most that much. Offline
replay (:mod:`stipi_daemon.measurement.replay`) feeds the stored rows in the same order, so a replay
reproduces the live run exactly unless the hold expired (the merger counts those
releases). Ties keep the streams' declared order (force before frame). Pure; no clock
is read: callers pass the current session time.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Sequence
from typing import Generic, TypeVar

__all__ = ["TimeOrderedMerger"]

T = TypeVar("T")


class TimeOrderedMerger(Generic[T]):
    """Time-ordered release of items from several streams.

    Parameters
    ----------
    streams : sequence of str
        Stream names, in tie-breaking order (earlier wins at equal times).
    max_hold_s : float
        Longest an item waits for the other streams [s of session time], >= 0.
    """

    def __init__(self, streams: Sequence[str], max_hold_s: float = 0.5) -> None:
        if not streams:
            raise ValueError("at least one stream is needed")
        if not max_hold_s >= 0.0:
            raise ValueError(f"max_hold_s must be >= 0, got {max_hold_s}")
        self._rank = {name: i for i, name in enumerate(streams)}
        self._last: dict[str, float] = {}
        self._closed: set[str] = set()
        self._heap: list[tuple[float, int, int, float, str, T]] = []
        self._counter = itertools.count()
        self.max_hold_s = max_hold_s
        #: Items released by the hold rather than by the watermark.
        self.released_by_timeout = 0

    def push(self, stream: str, t_s: float, item: T, now_s: float) -> None:
        """Add ``item`` of ``stream`` with timestamp ``t_s``, received at ``now_s`` [s]."""
        rank = self._rank[stream]
        prev = self._last.get(stream)
        self._last[stream] = t_s if prev is None else max(prev, t_s)
        heapq.heappush(self._heap, (t_s, rank, next(self._counter), now_s, stream, item))

    def close(self, stream: str) -> None:
        """``stream`` delivers no more: it no longer holds the others back."""
        self._closed.add(stream)

    def reopen(self, stream: str) -> None:
        """``stream`` delivers again after :meth:`close`."""
        self._closed.discard(stream)

    def _ready(self, t_s: float, rank: int) -> bool:
        """Whether no open stream can still deliver an item that sorts before (t_s, rank).

        A stream ranked before this item must have delivered something strictly later
        (it may send more items at ``t_s``, which sort first); one ranked after it needs
        only to have reached ``t_s``.
        """
        for name, r in self._rank.items():
            if name in self._closed or r == rank:
                continue
            last = self._last.get(name)
            if last is None or last < t_s or (last == t_s and r < rank):
                return False
        return True

    def pop_ready(self, now_s: float) -> list[tuple[str, T]]:
        """Items that may be released at session time ``now_s``, in time order."""
        out: list[tuple[str, T]] = []
        while self._heap:
            t, rank, _, received, stream, item = self._heap[0]
            if self._ready(t, rank):
                pass
            elif now_s - received >= self.max_hold_s:
                self.released_by_timeout += 1
            else:
                break
            heapq.heappop(self._heap)
            out.append((stream, item))
        return out

    def oldest_pending_s(self) -> float | None:
        """Timestamp of the oldest item still held [s], or None."""
        return self._heap[0][0] if self._heap else None

    def drain(self) -> list[tuple[str, T]]:
        """Every item still held, in time order (at the end of a run)."""
        out = []
        while self._heap:
            *_, stream, item = heapq.heappop(self._heap)
            out.append((stream, item))
        return out

    def __len__(self) -> int:
        return len(self._heap)
