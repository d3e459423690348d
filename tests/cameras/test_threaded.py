"""FrameHandoff: the bounded thread-to-asyncio queue, driven by real threads."""

from __future__ import annotations

import asyncio
import threading

import pytest

from stipi_daemon.cameras.threaded import FrameHandoff


async def test_drop_oldest_keeps_newest_and_counts() -> None:
    h: FrameHandoff[int] = FrameHandoff(asyncio.get_running_loop(), 3, drop_oldest=True)
    t = threading.Thread(target=lambda: [h.put(i) for i in range(10)])
    t.start()
    t.join()
    assert [await h.get() for _ in range(3)] == [7, 8, 9]
    assert h.dropped == 7


async def test_block_policy_applies_back_pressure_without_loss() -> None:
    h: FrameHandoff[int] = FrameHandoff(asyncio.get_running_loop(), 2, drop_oldest=False)
    done = threading.Event()

    def produce() -> None:
        for i in range(50):
            assert h.put(i)
        done.set()

    t = threading.Thread(target=produce)
    t.start()
    await asyncio.sleep(0.05)
    assert not done.is_set()  # blocked: the queue holds 2
    got = [await h.get() for _ in range(50)]
    t.join(2.0)
    assert got == list(range(50)) and h.dropped == 0


async def test_close_unblocks_producer_and_ends_consumer() -> None:
    h: FrameHandoff[int] = FrameHandoff(asyncio.get_running_loop(), 1, drop_oldest=False)
    results: list[bool] = []
    t = threading.Thread(target=lambda: results.extend([h.put(1), h.put(2)]))
    t.start()
    await asyncio.sleep(0.05)
    h.close()
    t.join(2.0)
    assert not t.is_alive() and results == [True, False]
    assert await h.get() == 1
    assert await h.get() is None


async def test_consumer_wakes_on_put_from_thread() -> None:
    h: FrameHandoff[str] = FrameHandoff(asyncio.get_running_loop(), 4, drop_oldest=True)
    waiter = asyncio.ensure_future(h.get())
    await asyncio.sleep(0.01)
    assert not waiter.done()
    threading.Thread(target=h.put, args=("x",)).start()
    assert await asyncio.wait_for(waiter, 2.0) == "x"


async def test_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError, match="capacity"):
        FrameHandoff(asyncio.get_running_loop(), 0, drop_oldest=True)
