from __future__ import annotations

import asyncio
import sys
from collections.abc import Awaitable, Callable

import pytest

from stipi_daemon.clock import ScaledClock, SessionClock, wait_event


class _Wall:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_scaled_clock_runs_at_speed() -> None:
    wall = _Wall()
    clock = ScaledClock(4.0, wall)
    assert isinstance(clock, SessionClock)
    assert clock.now() == 0.0
    wall.t += 2.5
    assert clock.now() == pytest.approx(10.0)
    assert clock.wall_seconds(10.0) == pytest.approx(2.5)


def test_bad_speed() -> None:
    with pytest.raises(ValueError, match="speed"):
        ScaledClock(0.0)


async def test_sleep_until_waits_scaled_time() -> None:
    clock = ScaledClock(50.0)
    await clock.sleep_until(1.0)  # 1 session second = 20 ms of wall time
    assert clock.now() >= 1.0
    before = clock.now()
    await clock.sleep_until(0.0)  # already past: returns at once
    assert clock.now() - before < 0.5


async def _cancelled_as_it_wakes(wait: Callable[[asyncio.Event], Awaitable[object]]) -> str:
    """How a task waiting with ``wait`` ends when its event is set and the task cancelled
    in the same turn of the loop (a link closing, then ``stop()``)."""
    event = asyncio.Event()
    task = asyncio.create_task(wait(event))
    await asyncio.sleep(0)  # the task now waits
    event.set()
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        return "cancelled"
    return "returned"


async def test_wait_event_ends_on_a_cancel_that_comes_with_the_event() -> None:
    assert await _cancelled_as_it_wakes(lambda ev: wait_event(ev, 10.0)) == "cancelled"


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="Python 3.12 fixed asyncio.wait_for")
async def test_wait_for_drops_that_cancel_on_python_3_11() -> None:
    """Why wait_event exists: the same wait through asyncio.wait_for returns instead."""
    result = await _cancelled_as_it_wakes(lambda ev: asyncio.wait_for(ev.wait(), 10.0))
    assert result == "returned"


async def test_wait_event_times_out_and_reports_the_event() -> None:
    event = asyncio.Event()
    assert await wait_event(event, 0.0) is False
    assert await wait_event(event, 0.01) is False
    event.set()
    assert await wait_event(event, 0.0) is True
