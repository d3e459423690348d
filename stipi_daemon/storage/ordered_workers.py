"""Work on several threads, results delivered in submission order (the video's FFV1 encoders).

:class:`OrderedWorkers` runs one thread per worker function, each at a lower CPU priority
than the process (Linux: its niceness + ``nice``), hands items to them round-robin through
bounded queues and delivers each item's result, in the order the items were submitted, from
whichever worker finished the item the next delivery waits for. The session video uses it to
encode FFV1 frames with several encoder instances at once (:mod:`.video`): FFmpeg threads
FFV1 only by slices, which costs 1.8x the CPU, while frames encoded by separate instances
with the same settings form one stream. A caller leaves an item out when its worker's queue is
full (a live camera, which must not wait) or waits a bounded time for room (:meth:`submit`).

A failure (a worker or the delivery raises) is handed to ``on_error`` once; later items are
taken and dropped, so that a caller never waits on a dead pipeline. It computes nothing
itself.
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

__all__ = ["OrderedWorkers"]

T = TypeVar("T")
R = TypeVar("R")

#: How often a submitter waiting for room looks whether the workers failed [s].
WAIT_POLL_S = 0.1


class OrderedWorkers(Generic[T, R]):
    """Items worked on by ``len(work)`` threads, results delivered in submission order.

    Parameters
    ----------
    work : list of callables
        One per thread: ``work[i](item)`` gives the item's result (thread i only calls it).
    deliver : callable
        ``deliver(item, result)``, called in submission order, never concurrently.
    on_error : callable
        Called once with the first exception ``work`` or ``deliver`` raised.
    capacity : int
        Items waiting at most, over all threads (at least one per thread).
    name : str
        Threads' name prefix.
    nice : int
        Niceness of the threads above the process's (capped at 19; Linux only).
    """

    def __init__(
        self,
        work: list[Callable[[T], R]],
        deliver: Callable[[T, R], None],
        on_error: Callable[[BaseException], None],
        *,
        capacity: int,
        name: str,
        nice: int = 0,
    ) -> None:
        if not work:
            raise ValueError("OrderedWorkers needs at least one worker")
        per = max(1, capacity // len(work))
        self._queues: list[queue.Queue[tuple[int, T] | None]] = [queue.Queue(per) for _ in work]
        self._deliver = deliver
        self._on_error = on_error
        self._nice = nice
        self._lock = threading.Lock()  # delivery in order
        self._fail_lock = threading.Lock()
        self._done: dict[int, tuple[T, R]] = {}
        self._next_submit = 0
        self._next_deliver = 0
        self.failed: BaseException | None = None
        self._threads = [
            threading.Thread(target=self._run, args=(fn, q), name=f"{name} {i}", daemon=True)
            for i, (fn, q) in enumerate(zip(work, self._queues, strict=True))
        ]
        for t in self._threads:
            t.start()

    @property
    def threads(self) -> tuple[threading.Thread, ...]:
        """The worker threads."""
        return tuple(self._threads)

    def submit(self, item: T, *, wait_s: float = 0.0) -> bool:
        """Queue ``item`` for its worker (round-robin), waiting for room at most ``wait_s``
        [s of wall time]; False when it was not taken: the worker's queue stayed full, or the
        workers have failed. Called from one thread at a time."""
        q = self._queues[self._next_submit % len(self._queues)]
        deadline = time.monotonic() + wait_s
        while self.failed is None:
            left = deadline - time.monotonic()
            try:
                if left > 0.0:
                    q.put((self._next_submit, item), timeout=min(left, WAIT_POLL_S))
                else:
                    q.put_nowait((self._next_submit, item))
            except queue.Full:
                if left <= 0.0:
                    return False
                continue
            self._next_submit += 1
            return True
        return False

    def close(self) -> None:
        """Work off and deliver what was submitted, then end the threads."""
        for q in self._queues:
            q.put(None)
        for t in self._threads:
            t.join()

    def _run(self, work: Callable[[T], R], q: queue.Queue[tuple[int, T] | None]) -> None:
        with contextlib.suppress(OSError, AttributeError):
            base = os.getpriority(os.PRIO_PROCESS, 0)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(19, base + self._nice))
        while (entry := q.get()) is not None:
            k, item = entry
            if self.failed is not None:
                continue  # drain, so that a submitter never waits on a failed pipeline
            try:
                result = work(item)
            except BaseException as exc:
                self._fail(exc)
                continue
            self._deliver_ready(k, item, result)

    def _deliver_ready(self, k: int, item: T, result: R) -> None:
        with self._lock:
            self._done[k] = (item, result)
            while self.failed is None and self._next_deliver in self._done:
                ready = self._done.pop(self._next_deliver)
                self._next_deliver += 1
                try:
                    self._deliver(*ready)
                except BaseException as exc:
                    self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        with self._fail_lock:
            if self.failed is not None:
                return
            self.failed = exc
        self._on_error(exc)
