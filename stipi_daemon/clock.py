"""The session clock: the one time base every daemon timestamp is taken on.

A session clock is monotonic seconds since the session started. Real devices run at
``speed = 1``; the demo and tests run simulated devices accelerated (``speed > 1``), and
every part of the daemon - simulated probe, simulated camera, watchdogs, the state
machine - reads the same clock, so an accelerated run is the same run, only faster.
This module owns no other state and does no I/O.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

__all__ = ["ScaledClock", "SessionClock", "wait_event"]


@runtime_checkable
class SessionClock(Protocol):
    """Monotonic session time [s] and a way to wait for it."""

    @property
    def speed(self) -> float:
        """Session seconds per wall-clock second [-]."""
        ...

    def now(self) -> float:
        """Current session time [s]."""
        ...

    async def sleep_until(self, t_s: float) -> None:
        """Return once ``now() >= t_s`` (at once if it already is)."""
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


async def wait_event(event: asyncio.Event, wall_s: float) -> bool:
    """Wait for ``event`` at most ``wall_s`` of wall time [s], >= 0; whether it was set.

    A cancel always ends the wait, also one that arrives in the same turn of the loop as
    the event: Python 3.11's ``asyncio.wait_for`` returns the inner result then and drops
    the cancel, so that a loop that waits on its wake-up event never ended (an emulated
    probe's task, and with it the daemon, hung after its measurement, about once in 15
    demo runs). ``asyncio.timeout`` turns only its own deadline into ``TimeoutError``.
    """
    try:
        async with asyncio.timeout(wall_s):
            await event.wait()
    except TimeoutError:
        return event.is_set()
    return True
