"""What the view costs the measurement: nothing without a viewer, little with some.

With nobody connected, publishing a frame keeps it by reference (no copy) and the view's
thread encodes nothing and stays asleep. A 720p frame's preview is subsampled, yet tints
exactly the camera pixels S_k counts. Viewers share one timer for their state and the
pushed frames' preview encodings (at most :data:`PREVIEW_RATE_HZ` a second, however many
watch).
"""

from __future__ import annotations

import asyncio
import json
import threading
import time

import aiohttp
import cv2
import numpy as np

from stipi_daemon.app.liveview.preview import preview_jpeg
from stipi_daemon.app.liveview.server import PREVIEW_RATE_HZ, STATE_RATE_HZ
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


async def test_viewers_share_the_state_timer_and_the_encodings() -> None:
    state = LiveState(view_info())
    stop = threading.Event()

    def daemon() -> None:  # frames at 60 fps, as the acquisition publishes them
        k = 0
        while not stop.is_set():
            publish(state, k)
            k += 1
            time.sleep(1 / 60.0)

    feeder = threading.Thread(target=daemon, daemon=True)
    feeder.start()
    wall_s = 1.5
    try:
        with served(state) as server:
            url = f"http://127.0.0.1:{server.port}/ws?token={server.token}"
            origin = f"http://127.0.0.1:{server.port}"
            t0 = time.monotonic()
            got = await asyncio.gather(*(_watch(url, origin, wall_s) for _ in range(5)))
            elapsed_s = time.monotonic() - t0
            encoded = server.previews_encoded
    finally:
        stop.set()
        feeder.join()
    for g in got:  # the first state at once, then one a tick
        assert 2 <= g["states"] <= STATE_RATE_HZ * elapsed_s + 2, g
        assert 5 <= g["frames"] <= PREVIEW_RATE_HZ * elapsed_s + 2, g  # pushed, unasked
    assert encoded <= PREVIEW_RATE_HZ * elapsed_s + 2
    assert sum(g["frames"] for g in got) > encoded  # a preview is shared by the viewers
