from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Awaitable, Callable

import pytest

from stipi_daemon.clock import ScaledClock, SessionClock, VirtualClock, wait_event


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


# -- VirtualClock: session time that waits for the daemon ---------------------------------


async def test_virtual_clock_wakes_waiters_in_deadline_order_one_at_a_time() -> None:
    clock = VirtualClock()
    woken: list[tuple[str, float]] = []

    async def sleeper(name: str, t_s: float) -> None:
        await clock.sleep_until(t_s)
        woken.append((name, clock.now()))

    async with clock.running():
        await asyncio.gather(sleeper("c", 3.0), sleeper("a", 1.0), sleeper("b", 2.0))
    assert woken == [("a", 1.0), ("b", 2.0), ("c", 3.0)]


async def test_virtual_clock_does_not_advance_while_work_is_due() -> None:
    """A hold, a working participant thread and data in flight each stop session time;
    an unpaced clock otherwise jumps straight to the next deadline."""
    clock = VirtualClock()
    in_flight = [True]
    remove = clock.add_pending(lambda: in_flight[0])
    async with clock.running():
        sleeper = asyncio.create_task(clock.sleep_until(10.0))
        for _ in range(200):
            await asyncio.sleep(0)
        assert clock.now() == 0.0 and not sleeper.done()  # bytes in flight
        in_flight[0] = False
        with clock.hold():
            for _ in range(200):
                await asyncio.sleep(0)
            assert clock.now() == 0.0  # held
        await sleeper
        assert clock.now() == 10.0
    remove()


async def test_virtual_clock_waits_for_a_participant_thread() -> None:
    clock = VirtualClock()
    started, release = threading.Event(), threading.Event()
    seen: list[float] = []

    def work() -> None:
        with clock.participant():
            started.set()
            release.wait(5.0)  # working: session time must not move
            seen.append(clock.now())
            assert clock.wait_until_blocking(4.0, None)
            seen.append(clock.now())

    async with clock.running():
        sleeper = asyncio.create_task(clock.sleep_until(2.0))
        thread = threading.Thread(target=work)
        thread.start()
        await asyncio.get_running_loop().run_in_executor(None, started.wait, 5.0)
        for _ in range(100):
            await asyncio.sleep(0.001)
        assert clock.now() == 0.0 and not sleeper.done()
        release.set()
        await sleeper
        await asyncio.get_running_loop().run_in_executor(None, thread.join, 5.0)
    assert seen == [0.0, 4.0]


async def test_virtual_clock_timeout_fires_at_its_session_deadline() -> None:
    clock = VirtualClock()
    event = asyncio.Event()
    async with clock.running():
        assert await clock.wait_event(event, 5.0) is False
        assert clock.now() == 5.0
        with pytest.raises(TimeoutError):
            async with clock.timeout(2.5):
                await asyncio.Event().wait()
        assert clock.now() == 7.5
        event.set()
        assert await clock.wait_event(event, 5.0) is True
        assert clock.now() == 7.5


async def test_virtual_clock_paced_never_runs_ahead_of_the_wall() -> None:
    wall = _Wall()  # stands still: a paced clock may not pass pace * elapsed wall time
    clock = VirtualClock(pace=10.0, wall=wall)
    async with clock.running():
        sleeper = asyncio.create_task(clock.sleep_until(1.0))
        await asyncio.sleep(0.05)
        assert clock.now() == 0.0 and not sleeper.done()
        wall.t += 0.1  # 0.1 s of wall time at pace 10: 1 s of session time
        await sleeper
    assert clock.now() == 1.0


def test_virtual_clock_refuses_a_bad_pace() -> None:
    with pytest.raises(ValueError, match="pace"):
        VirtualClock(0.0)
    assert isinstance(VirtualClock(), SessionClock)
