"""``stipi-daemon view SESSION``: a stored session as the view, frames and traces in step.

A short simulated session is recorded once (lossless video of the ROI's box, as the demo
stores it). The frame the view shows for a ``seq`` must be the frame S_k was counted on
(recounted, it gives the stored S_k, in camera coordinates under the ROI); the marked
frames must be those that set S_0, S_max and T_r by the summary; in Chromium, frame N of
the page must come with the traces' cursor at that frame's capture time.
"""

from __future__ import annotations

import io
import re
import threading
from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.analysis.imaging import FrameProcessor, roi_from_record
from stipi_daemon.app.liveview.replay import ReplaySource, result_marks, serve_session
from stipi_daemon.app.liveview.server import ViewServer
from stipi_daemon.storage import SessionReader
from tests.app.liveview._browser import chromium, screenshot, text, wait_for
from tests.app.liveview._view import get
from tests.daemon._support import short_session


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return short_session(
        tmp_path_factory.mktemp("replay"),
        {"video": "lossless", "video_roi_only": True},
        speed=50.0,
        measurement={"stop_when_settled": True},
    )


def _frames(session: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    with SessionReader(session) as r:
        f = r.frames()
        summary = r.summary
    assert summary is not None
    order = np.argsort(f["t_capture_host_s"], kind="stable")
    return f["seq"][order], f["t_capture_host_s"][order], f["s_k"][order], summary


def test_result_marks_on_a_known_series() -> None:
    t = np.arange(10, dtype=float)
    s = np.array([5, 5, 1, 2, 3, 9, 8, 9, 7, 7], dtype=float)
    marks = result_marks(t, s, {"t0_s": 1.5, "ts_s": 4.2})
    assert marks == {"s0": 2, "s_max": 5, "t_r": 5}
    assert result_marks(t, s, None) == {}
    assert result_marks(t, s, {"t0_s": None}) == {}


def test_the_marked_frames_set_s0_s_max_and_t_r(session: Path) -> None:
    seq, t, s_k, summary = _frames(session)
    pitting = summary["results"]["pitting"]
    marks = ReplaySource(session).marks()
    i0, imax, itr = marks["s0"]["index"], marks["s_max"]["index"], marks["t_r"]["index"]
    assert t[i0] >= pitting["t0_s"] > t[i0 - 1]
    assert s_k[imax] == s_k[i0:].max()
    assert t[itr] >= pitting["ts_s"] > t[itr - 1]
    assert marks["s_max"]["seq"] == int(seq[imax]) and marks["s0"]["t_s"] == float(t[i0])


def test_the_frame_shown_is_the_frame_s_k_was_counted_on(session: Path) -> None:
    source = ReplaySource(session)
    info = source.info()
    roi = roi_from_record(info["roi"])
    assert roi is not None
    seq, _, s_k, _ = _frames(session)
    for i in (0, len(seq) // 3, source.marks()["s_max"]["index"], len(seq) - 1):
        frame = source.preview_frame(int(seq[i]))
        assert frame is not None and frame.seq == int(seq[i])
        proc = FrameProcessor(frame.image.shape, info["threshold_p"], roi)
        assert int(proc.measure(frame.image).s_k_px) == int(s_k[i]) == frame.s_k
    assert source.preview_frame(10**9) is None


def test_view_session_serves_and_prints_its_address(session: Path) -> None:
    out, stop = io.StringIO(), threading.Event()
    runner = threading.Thread(
        target=serve_session, args=(session,), kwargs={"out": out, "until": stop}
    )
    runner.start()
    try:
        url = wait_for(lambda: re.search(r"(http://\S+)", out.getvalue()), why="the address").group(
            1
        )
        assert url.startswith("http://127.0.0.1:") and "token=" in url
    finally:
        stop.set()
        runner.join(timeout=10)
    assert not runner.is_alive()


def test_frame_n_comes_with_the_traces_at_its_time(session: Path, tmp_path: Path) -> None:
    seq, t, _, _ = _frames(session)
    source = ReplaySource(session)
    n = len(seq) // 2
    server = ViewServer(source)
    server.start()
    try:
        status, headers, _ = get(server, f"/frame.jpg?token={server.token}&seq={int(seq[n])}")
        assert status == 200 and float(headers["x-frame-t-s"]) == float(t[n])
        with chromium(tmp_path / "profile") as driver:
            driver.get(f"{server.url}&frame={n}")
            wait_for(lambda: text(driver, "frame-info").startswith(f"frame {int(seq[n])} "))
            for trace in ("trace-force", "trace-sk"):
                cursor = driver.execute_script(
                    f"return document.getElementById('{trace}').dataset.cursorT"
                )
                assert float(cursor) == float(t[n]), trace
            assert text(driver, "mode") == "replay"
            smax = source.marks()["s_max"]
            driver.find_element("css selector", 'button[data-mark="s_max"]').click()
            wait_for(lambda: text(driver, "frame-info").startswith(f"frame {smax['seq']} "))
            screenshot(driver, "liveview-replay.png", tmp_path)
    finally:
        server.stop()
