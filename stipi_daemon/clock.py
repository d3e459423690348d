"""The session clock: the one time base every daemon timestamp is taken on.

A session clock is monotonic seconds since the session started, in one of two kinds:

* :class:`ScaledClock`: wall time times ``speed``. Real devices run on it at speed 1: a
  camera or a probe cannot wait, so whatever the machine does is part of the data.
* :class:`VirtualClock`: a run whose every device is simulated in this process. Session
  time advances only when the daemon has handled everything due so far (discrete events:
  from one waiter's deadline to the next), so a busy machine slows such a run down but
  never changes what it records; ``run.speed`` only caps how far it may run ahead of
  real time.

Both give the same waits: :meth:`sleep_until`, :meth:`timeout` and :meth:`wait_event` in
the event loop, :meth:`wait_until_blocking` in a thread. This module owns no other state
and does no I/O.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Protocol, runtime_checkable

__all__ = ["ScaledClock", "SessionClock", "VirtualClock", "wait_event"]

#: Polling period [s of wall time] of a thread waiting on a virtual clock for its stop event.
_THREAD_POLL_WALL_S = 0.05
#: Turns of the event loop a virtual clock spins before it waits for a poke instead [-].
_SPINS = 20
#: Longest wait for a poke [s of wall time] before a virtual clock looks again.
_POKE_WAIT_WALL_S = 0.001


@runtime_checkable
class SessionClock(Protocol):
    """Monotonic session time [s] and the ways to wait for it."""

    @property
    def speed(self) -> float:
        """Session seconds per wall second of a :class:`ScaledClock` [-] (1 for a
        :class:`VirtualClock`, whose waits are all in session time)."""
        ...

    @property
    def waits_for_daemon(self) -> bool:
        """True when session time advances only as fast as the daemon handles it."""
        ...

    def now(self) -> float:
        """Current session time [s]."""
        ...

    async def sleep_until(self, t_s: float) -> None:
        """Return once ``now() >= t_s`` (at once if it already is)."""
        ...

    def timeout(self, session_s: float | None) -> contextlib.AbstractAsyncContextManager[None]:
        """Context manager raising ``TimeoutError`` after ``session_s`` of session time [s]
        (None: never)."""
        ...

    async def wait_event(self, event: asyncio.Event, session_s: float) -> bool:
        """Wait for ``event`` at most ``session_s`` of session time [s]; whether it was set."""
        ...

    def wait_until_blocking(self, t_s: float, stop: threading.Event | None) -> bool:
        """In a thread: block until ``now() >= t_s``; False when ``stop`` was set first."""
        ...

    def hold(self) -> contextlib.AbstractContextManager[None]:
        """While held, session time does not advance (work the daemon waits for off the
        event loop: a device opening in an executor, a computation on a worker thread)."""
        ...

    def participant(self) -> contextlib.AbstractContextManager[None]:
        """A thread that produces or handles data: session time waits for it except while
        it waits in :meth:`wait_until_blocking`."""
        ...

    def add_pending(self, pending: Callable[[], bool]) -> Callable[[], None]:
        """Session time waits while ``pending()`` is true (data in flight between two
        parts, e.g. bytes on a pty); returns the function that removes it."""
        ...


class ScaledClock:
    """Session time = (monotonic wall time - start) * ``speed``.

    Parameters
    ----------
    speed : float
        Session seconds per wall second, > 0 (1 for real devices).
    wall : callable
        The wall clock [s] (default ``time.monotonic``).
    """

    waits_for_daemon = False

    def __init__(self, speed: float = 1.0, wall: Callable[[], float] = time.monotonic) -> None:
        if not speed > 0.0:
            raise ValueError(f"clock speed must be > 0, got {speed}")
        self._speed = float(speed)
        self._wall = wall
        self._start = wall()

    @property
    def speed(self) -> float:
        return self._speed

    def now(self) -> float:
        return (self._wall() - self._start) * self._speed

    def wall_seconds(self, session_s: float) -> float:
        """Wall-clock duration [s] of a session-time duration ``session_s`` [s]."""
        return session_s / self._speed

    async def sleep_until(self, t_s: float) -> None:
        delay = (t_s - self.now()) / self._speed
        if delay > 0.0:
            await asyncio.sleep(delay)

    @contextlib.asynccontextmanager
    async def timeout(self, session_s: float | None) -> AsyncIterator[None]:
        async with asyncio.timeout(None if session_s is None else session_s / self._speed):
            yield

    async def wait_event(self, event: asyncio.Event, session_s: float) -> bool:
        return await wait_event(event, session_s / self._speed)

    def wait_until_blocking(self, t_s: float, stop: threading.Event | None) -> bool:
        while True:
            wall_s = (t_s - self.now()) / self._speed
            if wall_s <= 0.0:
                return stop is None or not stop.is_set()
            if stop is None:
                time.sleep(wall_s)
            elif stop.wait(wall_s):
                return False

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        yield  # wall time does not wait

    def participant(self) -> contextlib.AbstractContextManager[None]:
        return self.hold()

    def add_pending(self, pending: Callable[[], bool]) -> Callable[[], None]:
        return lambda: None


class VirtualClock:
    """Session time of a run whose every device is simulated in this process.

    Time stands still while anything is due. It moves to the next waiter's deadline
    (:meth:`sleep_until`, :meth:`timeout`, :meth:`wait_until_blocking`), one waiter at a
    time, only when the event loop has nothing ready, no participant thread is working
    (:meth:`participant`), nothing is held (:meth:`hold`) and no data is in flight
    (:meth:`add_pending`). Waiters due at the same instant are woken in a fixed order
    (threads first, then the loop's in the order they began to wait), each once the one
    before has been handled. Everything stamped with :meth:`now` is therefore the same on
    any machine, at any load and at any pace. :meth:`running` moves it.

    Parameters
    ----------
    pace : float or None
        At most this many session seconds per wall second, > 0 (``run.speed``; 1: real
        time); None: as fast as the daemon goes.
    wall : callable
        The wall clock [s] the pace is kept on (default ``time.monotonic``).
    """

    waits_for_daemon = True
    speed = 1.0

    def __init__(
        self, pace: float | None = None, wall: Callable[[], float] = time.monotonic
    ) -> None:
        if pace is not None and not pace > 0.0:
            raise ValueError(f"clock pace must be > 0, got {pace}")
        self.pace = pace
        self._wall = wall
        self._t = 0.0
        self._cond = threading.Condition()
        self._busy = 0  # participant threads working + holds
        # waiters: (deadline [s], 0 thread / 1 loop, order, waiter)
        self._waiters: list[tuple[float, int, int, _Waiter]] = []
        self._order = itertools.count()
        self._pending: list[Callable[[], bool]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Event | None = None
        #: Waiters woken so far [-] (each a settled instant of the run).
        self.steps = 0

    def now(self) -> float:
        return self._t

    def _wait(self, t_s: float, waiter: _Waiter) -> None:
        with self._cond:
            heapq.heappush(self._waiters, (t_s, waiter.rank, next(self._order), waiter))

    # -- waits in the event loop ------------------------------------------------------------

    def _at(self, t_s: float, callback: Callable[[], None]) -> _Waiter:
        """Call ``callback`` in the loop once session time reaches ``t_s``."""
        waiter = _Waiter(1, callback)
        self._wait(t_s, waiter)
        self._poke()
        return waiter

    async def sleep_until(self, t_s: float) -> None:
        if t_s <= self._t:
            await asyncio.sleep(0)
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def wake() -> None:
            if not fut.done():
                fut.set_result(None)

        waiter = self._at(t_s, wake)
        try:
            await fut
        finally:
            waiter.cancelled = True

    @contextlib.asynccontextmanager
    async def timeout(self, session_s: float | None) -> AsyncIterator[None]:
        if session_s is None:
            yield
            return
        async with asyncio.timeout(None) as cm:
            loop = asyncio.get_running_loop()
            waiter = self._at(self._t + session_s, lambda: cm.reschedule(loop.time()))
            try:
                yield
            finally:
                waiter.cancelled = True

    async def wait_event(self, event: asyncio.Event, session_s: float) -> bool:
        return await _wait_within(event, self.timeout(session_s))

    # -- threads, holds, data in flight -----------------------------------------------------

    def wait_until_blocking(self, t_s: float, stop: threading.Event | None) -> bool:
        """In a :meth:`participant` thread: block until ``now() >= t_s``; False when
        ``stop`` was set first."""
        with self._cond:
            if self._t < t_s:
                waiter = _Waiter(0, None)
                heapq.heappush(self._waiters, (t_s, 0, next(self._order), waiter))
                self._busy -= 1  # waiting on the clock: not working
                self._poke_threadsafe()
                while not waiter.woken:
                    if stop is not None and stop.is_set():
                        waiter.cancelled = True
                        self._busy += 1
                        return False
                    self._cond.wait(_THREAD_POLL_WALL_S)
        return stop is None or not stop.is_set()

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        with self._cond:
            self._busy += 1
        try:
            yield
        finally:
            with self._cond:
                self._busy -= 1
            self._poke_threadsafe()

    def participant(self) -> contextlib.AbstractContextManager[None]:
        return self.hold()

    def add_pending(self, pending: Callable[[], bool]) -> Callable[[], None]:
        self._pending.append(pending)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self._pending.remove(pending)
            self._poke_threadsafe()

        return remove

    # -- the task that moves time -----------------------------------------------------------

    def _poke(self) -> None:
        if self._changed is not None:
            self._changed.set()

    def _poke_threadsafe(self) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            loop.call_soon_threadsafe(self._poke)

    def _quiet(self, loop: asyncio.AbstractEventLoop) -> bool:
        """Whether nothing is due: no participant working, nothing held, no data in
        flight, and no callback ready in the event loop besides this task's."""
        with self._cond:
            if self._busy > 0:
                return False
        if any(p() for p in self._pending):
            return False
        return loop_idle(loop)

    async def _settle(self, loop: asyncio.AbstractEventLoop) -> None:
        """Return once :meth:`_quiet` holds."""
        changed = self._changed
        assert changed is not None
        spins = 0
        while True:
            await asyncio.sleep(0)
            if self._quiet(loop):
                return
            spins += 1
            if spins < _SPINS:
                continue
            # a thread works, a device opens, bytes cross a pty: wait for a poke, briefly
            changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(_POKE_WAIT_WALL_S):
                    await changed.wait()

    def _next(self) -> tuple[float, _Waiter] | None:
        """The next waiter (cancelled ones dropped), not removed; None: none waits."""
        with self._cond:
            while self._waiters and self._waiters[0][3].cancelled:
                heapq.heappop(self._waiters)
            if not self._waiters:
                return None
            t_s, *_, waiter = self._waiters[0]
            return t_s, waiter

    def _wake(self, t_s: float) -> None:
        """Move to ``t_s`` and wake the first waiter due then."""
        with self._cond:
            *_, waiter = heapq.heappop(self._waiters)
            self._t = max(self._t, t_s)
            self.steps += 1
            if waiter.callback is None:  # a thread: it works from now on, until it waits
                if waiter.cancelled:  # it stopped waiting meanwhile (counted itself busy)
                    return
                waiter.woken = True
                self._busy += 1
                self._cond.notify_all()
                return
        if not waiter.cancelled:
            waiter.callback()

    async def run(self) -> None:
        """Move session time for as long as the run lasts (cancel it to stop)."""
        loop = self._loop = asyncio.get_running_loop()
        changed = self._changed = asyncio.Event()
        wall0 = self._wall() - (0.0 if self.pace is None else self._t / self.pace)
        while True:
            await self._settle(loop)
            nxt = self._next()
            if nxt is None:  # nothing scheduled: wait for a waiter
                changed.clear()
                await changed.wait()
                continue
            t_s, _ = nxt
            if self.pace is not None and t_s > self._t:
                wall_s = wall0 + t_s / self.pace - self._wall()
                if wall_s > 0.0:
                    changed.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(wall_s):
                            await changed.wait()
                    continue  # settle again: an earlier waiter may have come
            self._wake(t_s)

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[VirtualClock]:
        """Move session time while the block runs."""
        task = asyncio.create_task(self.run(), name="virtual clock")
        try:
            yield self
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            self._loop = self._changed = None


class _Waiter:
    """One wait on a :class:`VirtualClock`: a thread's (``callback`` None) or the loop's."""

    __slots__ = ("callback", "cancelled", "rank", "woken")

    def __init__(self, rank: int, callback: Callable[[], None] | None) -> None:
        self.rank = rank
        self.callback = callback
        self.cancelled = False
        self.woken = False

    def __lt__(self, other: _Waiter) -> bool:  # never reached: (t, rank, order) are unique
        return False


def loop_idle(loop: asyncio.AbstractEventLoop) -> bool:
    """Whether ``loop`` has no callback ready to run and no timer due (asyncio's base event
    loop keeps them in ``_ready`` and ``_scheduled``; a loop without them counts as busy)."""
    ready = getattr(loop, "_ready", None)
    scheduled = getattr(loop, "_scheduled", None)
    if ready is None or scheduled is None:
        return False
    if ready:
        return False
    return not (scheduled and scheduled[0].when() <= loop.time())


async def wait_event(event: asyncio.Event, wall_s: float) -> bool:
    """Wait for ``event`` at most ``wall_s`` of wall time [s], >= 0; whether it was set.

    A cancel always ends the wait, also one that arrives in the same turn of the loop as
    the event: Python 3.11's ``asyncio.wait_for`` returns the inner result then and drops
    the cancel. ``asyncio.timeout`` turns only its own deadline into ``TimeoutError``.
    """
    return await _wait_within(event, asyncio.timeout(wall_s))


async def _wait_within(
    event: asyncio.Event, timeout: contextlib.AbstractAsyncContextManager[object]
) -> bool:
    """Wait for ``event`` inside ``timeout``; whether it was set."""
    try:
        async with timeout:
            await event.wait()
    except TimeoutError:
        return event.is_set()
    return True
