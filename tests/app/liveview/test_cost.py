"""What the view costs the measurement: nothing without a viewer, little with some.

With nobody connected, publishing a frame keeps it by reference (no copy) and the view's
thread encodes nothing and stays asleep. A 720p frame's preview is subsampled, yet tints
exactly the camera pixels S_k counts. Viewers share one timer for their state and the
pushed frames' preview encodings (at most :data:`PREVIEW_RATE_HZ` a second, however many
watch); viewers in step share each state message, and many viewers take turns for the
frames (at most :data:`FRAME_SENDS_RATE_HZ` sent a second in all).
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import aiohttp
import cv2
import numpy as np

from stipi_daemon.app.liveview.preview import preview_jpeg
from stipi_daemon.app.liveview.server import FRAME_SENDS_RATE_HZ, PREVIEW_RATE_HZ, STATE_RATE_HZ
from stipi_daemon.app.liveview.state import LiveState
from tests.app.liveview._view import THRESHOLD_P, frame_image, publish, served, view_info


def _view_thread_cpu_s() -> float:
    """CPU time of the view server's thread so far [s]."""
    (thread,) = (t for t in threading.enumerate() if t.name == "stipi-view")
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def test_without_a_viewer_frames_are_kept_by_reference_and_nothing_is_encoded() -> None:
    state = LiveState(view_info())
    with served(state) as server:
        cpu0_s = _view_thread_cpu_s()
        for k in range(60):
            img = frame_image(k)
            state.frame(k, k / 60.0, int((img <= THRESHOLD_P).sum()), img)
            time.sleep(1 / 60.0)
            latest = state.preview_frame(None)
            assert latest is not None and latest.image is img  # the frame itself, no copy
        cpu_s = _view_thread_cpu_s() - cpu0_s
        assert server.previews_encoded == 0 and server.viewers == 0
        assert cpu_s < 0.02, f"the idle view's thread used {cpu_s * 1e3:.1f} ms of CPU in 1 s"


def test_a_720p_preview_tints_exactly_the_counted_camera_pixels() -> None:
    rng = np.random.default_rng(3)
    blocks = rng.integers(0, 256, size=(720 // 40, 1280 // 40), dtype=np.uint8)
    image = np.kron(blocks, np.ones((40, 40), dtype=np.uint8))  # 10x10 px patches shown
    roi = {"kind": "rect", "x_px": 130, "y_px": 70, "width_px": 600, "height_px": 400}
    jpeg, step = preview_jpeg(image, THRESHOLD_P, roi)
    shown = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)
    assert step == 4 and shown.shape[:2] == (180, 320)
    inside = np.zeros(image.shape, dtype=bool)
    inside[70:470, 130:730] = True
    # pixel (i, j) shown is camera pixel (i * step, j * step)
    counted = (inside & (image <= THRESHOLD_P))[::step, ::step]
    redness = shown[..., 2] - shown[..., 0]
    calm = cv2.erode(counted.astype(np.uint8), np.ones((3, 3))) > 0
    lit = cv2.dilate(counted.astype(np.uint8), np.ones((3, 3))) == 0
    assert calm.sum() > 100 and lit.any()
    assert (redness[calm] > 40).mean() > 0.95
    assert (np.abs(redness[lit]) < 25).mean() > 0.95


async def _watch(url: str, origin: str, wall_s: float) -> dict[str, int]:
    """One page's traffic for ``wall_s``: the states and the pushed frames received."""
    got = {"states": 0, "frames": 0}
    until = time.monotonic() + wall_s
    async with aiohttp.ClientSession() as session, session.ws_connect(url, origin=origin) as ws:
        while (left := until - time.monotonic()) > 0:
            try:
                msg = await ws.receive(timeout=left)
            except TimeoutError:
                break
            if msg.type == aiohttp.WSMsgType.TEXT:
                got["states"] += "info" not in json.loads(msg.data)
            elif msg.type == aiohttp.WSMsgType.BINARY:
                got["frames"] += 1
    return got


class _CountedState(LiveState):
    """The live state, counting the snapshots the server asks of it."""

    snapshots = 0

    def snapshot(self, cursor: dict[str, int]) -> dict[str, Any]:
        self.snapshots += 1
        return super().snapshot(cursor)


@contextmanager
def _fed(state: LiveState) -> Iterator[None]:
    """Frames published at 60 fps, as the acquisition publishes them, while inside."""
    stop = threading.Event()

    def daemon() -> None:
        k = 0
        while not stop.is_set():
            publish(state, k)
            k += 1
            time.sleep(1 / 60.0)

    feeder = threading.Thread(target=daemon, daemon=True)
    feeder.start()
    try:
        yield
    finally:
        stop.set()
        feeder.join()


async def _watched(
    state: LiveState, viewers: int, wall_s: float
) -> tuple[list[dict[str, int]], float, int]:
    """``viewers`` pages watching ``state`` for ``wall_s``: what each got, the wall time
    they watched [s] and the previews the server encoded."""
    with _fed(state), served(state) as server:
        url = f"http://127.0.0.1:{server.port}/ws?token={server.token}"
        origin = f"http://127.0.0.1:{server.port}"
        t0 = time.monotonic()
        got = await asyncio.gather(*(_watch(url, origin, wall_s) for _ in range(viewers)))
        return list(got), time.monotonic() - t0, server.previews_encoded


async def test_viewers_share_the_state_timer_and_the_encodings() -> None:
    got, elapsed_s, encoded = await _watched(LiveState(view_info()), 4, 1.5)
    for g in got:  # the first state at once, then one a tick
        assert 2 <= g["states"] <= STATE_RATE_HZ * elapsed_s + 2, g
        assert 5 <= g["frames"] <= PREVIEW_RATE_HZ * elapsed_s + 2, g  # pushed, unasked
    assert encoded <= PREVIEW_RATE_HZ * elapsed_s + 2
    assert sum(g["frames"] for g in got) > encoded  # a preview is shared by the viewers


async def test_many_viewers_share_state_messages_and_take_turns_for_frames() -> None:
    state = _CountedState(view_info())
    viewers, wall_s = 12, 2.0
    got, elapsed_s, _ = await _watched(state, viewers, wall_s)
    frames = [g["frames"] for g in got]
    # every viewer is shown the measurement, none is starved ...
    assert min(frames) >= 1 and all(g["states"] >= 2 for g in got), got
    # ... but the frames sent in all stay at the cap, not 10 a second times 12
    assert sum(frames) <= FRAME_SENDS_RATE_HZ * elapsed_s + FRAME_SENDS_RATE_HZ / PREVIEW_RATE_HZ
    # one snapshot a tick for the viewers in step (and one per cursor for late joiners),
    # not one per viewer a tick
    states_sent = sum(g["states"] for g in got)
    assert state.snapshots <= STATE_RATE_HZ * elapsed_s * 2 + viewers, (
        state.snapshots,
        states_sent,
    )
    assert states_sent >= 3 * state.snapshots, (state.snapshots, states_sent)
