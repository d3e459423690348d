"""FrameHandoff (the bounded thread-to-asyncio queue) and the capture thread's hook, driven by
real threads."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from stipi_daemon.cameras.threaded import FrameHandoff, RawFrame, ThreadedCamera
from stipi_daemon.clock import ScaledClock


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


# ------------------------------------------------------------- the capture thread's hook


class _Counter(ThreadedCamera[list[int]]):
    """A source of ``n`` 4x4 frames, frame k captured at k / fps on the session clock."""

    def __init__(self, clock: ScaledClock, n: int, *, live: bool, paced: bool) -> None:
        super().__init__(clock, capacity=4, drop_oldest=live, paced=paced)
        self.n, self.fps = n, 100.0

    @property
    def name(self) -> str:
        return "counter"

    @property
    def nominal_fps(self) -> float:
        return self.fps

    def _open_source(self) -> list[int]:
        return [0]

    def _read(self, handle: list[int]) -> RawFrame | None:
        k = handle[0]
        if k >= self.n:
            return None
        handle[0] += 1
        return RawFrame(k, k / self.fps, np.full((4, 4), k % 256, np.uint8))

    def _close_source(self, handle: list[int]) -> None:
        pass


async def test_a_paced_frame_reaches_the_hook_at_its_capture_time() -> None:
    clock = ScaledClock(speed=5.0)
    cam = _Counter(clock, 20, live=False, paced=True)
    seen: list[tuple[int, float, float]] = []  # seq, capture time, session time at the hook
    cam.frame_hook = lambda raw: seen.append((raw.seq, raw.t_capture_s, clock.now()))
    await cam.open()
    got = [f async for f in cam.frames()]
    await cam.close()
    assert [f.seq for f in got] == [s for s, _, _ in seen] == list(range(20))
    assert all(now >= t - 1e-9 for _, t, now in seen)  # never before it is captured
    assert cam.waits_for_consumer


async def test_a_live_source_leaves_out_a_frame_before_its_hook_never_after() -> None:
    """A full hand-off of a hooked live source drops the newest frame before the hook: every
    frame the hook measured and stored reaches the consumer, and the others are counted."""
    clock = ScaledClock(speed=1.0)
    cam = _Counter(clock, 200, live=True, paced=False)  # as fast as the thread reads
    hooked: list[int] = []
    cam.frame_hook = lambda raw: hooked.append(raw.seq)
    await cam.open()
    got: list[int] = []
    async for f in cam.frames():
        got.append(f.seq)
        await asyncio.sleep(0.002)  # a slow consumer: the hand-off of 4 fills up
    await cam.close()
    assert got == hooked  # nothing the hook saw was dropped afterwards
    assert len(got) < 200 and cam.stats.queue_dropped == 200 - len(got)
    assert not cam.waits_for_consumer


async def test_an_injected_stall_swallows_frames_before_the_hook() -> None:
    clock = ScaledClock(speed=4.0)
    cam = _Counter(clock, 60, live=False, paced=True)
    hooked: list[int] = []
    cam.frame_hook = lambda raw: hooked.append(raw.seq)
    await cam.open()
    got: list[int] = []
    t_stall = 0.0
    async for f in cam.frames():
        got.append(f.seq)
        if f.seq == 10:
            t_stall = clock.now()
            cam.stall(0.2)  # 20 frame periods of session time
    await cam.close()
    assert got == hooked and 10 in got and len(got) < 60
    missing = sorted(set(range(60)) - set(got))
    # after frame 10, and captured before the stall's end (delivered during it, or captured
    # while frozen)
    assert missing and all(10 < k < (t_stall + 0.2) * cam.fps for k in missing)


def test_the_first_frame_is_due_from_its_known_capture_time_unless_live() -> None:
    """A source that waits for its consumer knows its first frame's capture time before
    it is made (the daemon's lag until that frame comes); a live camera's frames are not
    captured before they come (its silence is a stall, not a lag)."""

    class Known(_Counter):
        def _first_capture_s(self) -> float | None:
            return 2.5

    clock = ScaledClock(speed=1.0)
    cam = Known(clock, 3, live=False, paced=True)
    assert cam.first_frame_due_s() == 2.5
    assert Known(clock, 3, live=True, paced=False).first_frame_due_s() is None
    assert _Counter(clock, 3, live=False, paced=True).first_frame_due_s() is None
    t_stall = clock.now()
    cam.stall(10.0)  # the frames until its end are lost, not late: none is due before it
    due = cam.first_frame_due_s()
    assert due is not None and due >= t_stall + 10.0
