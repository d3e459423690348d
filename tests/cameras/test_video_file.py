"""VideoFileCamera on real MJPG AVI files written with OpenCV (and the simulator's video)."""

from __future__ import annotations

import asyncio
import csv
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.cameras import CameraFrame, VideoFileCameraConfig, open_camera
from stipi_daemon.cameras.video_file import DECODER_PYAV, VideoFileCamera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import CameraError
from stipi_daemon.sim.output import write_outputs
from tests.cameras._pyav_video import pyav_frames, write_pyav
from tests.cameras._scenes import small_scene
from tests.cameras._video import raw_packets, write_avi

FPS = 30.0


async def collect(cam: VideoFileCamera, limit: int | None = None) -> list[CameraFrame]:
    await cam.open()
    out: list[CameraFrame] = []
    try:
        async for f in cam.frames():
            out.append(f)
            if limit is not None and len(out) >= limit:
                break
    finally:
        await cam.close()
    return out


@pytest.fixture
def avi(tmp_path: Path) -> Path:
    p = tmp_path / "v.avi"
    write_avi(p, 24, fps=FPS)
    return p


async def test_unpaced_color_delivers_every_frame(avi: Path) -> None:
    clock = ScaledClock()
    cam = VideoFileCamera(avi, clock, pace=False, gray=False, t0_s=5.0)
    frames = await collect(cam)
    assert [f.seq for f in frames] == list(range(24))
    assert all(f.dropped_before == 0 for f in frames)
    np.testing.assert_allclose([f.t_capture_s for f in frames], 5.0 + np.arange(24) / FPS)
    # the first frame's capture time, known before it is made (its lag before it comes)
    assert cam.first_frame_due_s() == frames[0].t_capture_s == 5.0
    expected = [cv2.imdecode(p, cv2.IMREAD_COLOR) for p in raw_packets(avi)]
    for f, e in zip(frames, expected, strict=True):
        assert f.image.shape == (120, 160, 3) and f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, e)
    assert cam.stats.frames == 24 and cam.stats.dropped == 0
    assert cam.notes == []
    meta = cam.metadata()
    assert meta["fourcc"] == "MJPG" and meta["declared_frames"] == 24 and meta["fps"] == FPS


async def test_mjpg_frames_carry_their_jpeg_packet(avi: Path) -> None:
    frames = await collect(VideoFileCamera(avi, ScaledClock(), pace=False, gray=True))
    packets = raw_packets(avi)
    assert [f.packet for f in frames] == [p.tobytes() for p in packets]
    for f in frames:
        assert f.packet is not None
        decoded = cv2.imdecode(np.frombuffer(f.packet, np.uint8), cv2.IMREAD_GRAYSCALE)
        np.testing.assert_array_equal(f.image, decoded)


async def test_gray_matches_cvtcolor_of_color_frames(avi: Path) -> None:
    # Gray frames are the JPEG's luma plane; cvtColor of the BGR decode recomputes it from
    # upsampled chroma, so the two agree to a few levels at sharp colour edges only.
    clock = ScaledClock()
    gray = await collect(VideoFileCamera(avi, clock, pace=False, gray=True))
    color = await collect(VideoFileCamera(avi, clock, pace=False, gray=False))
    assert len(gray) == len(color) == 24
    for g, c in zip(gray, color, strict=True):
        assert g.image.shape == (120, 160)
        ref = cv2.cvtColor(c.image, cv2.COLOR_BGR2GRAY)
        diff = np.abs(g.image.astype(np.int16) - ref.astype(np.int16))
        assert diff.max() <= 4
        assert diff.mean() < 0.5


async def test_gray_file_gray_option_is_exact(tmp_path: Path) -> None:
    p = tmp_path / "g.avi"
    write_avi(p, 6, color=False)
    clock = ScaledClock()
    gray = await collect(VideoFileCamera(p, clock, pace=False, gray=True))
    color = await collect(VideoFileCamera(p, clock, pace=False, gray=False))
    for g, c in zip(gray, color, strict=True):
        np.testing.assert_array_equal(g.image, cv2.cvtColor(c.image, cv2.COLOR_BGR2GRAY))


async def test_paced_on_accelerated_clock(avi: Path) -> None:
    speed = 8.0
    clock = ScaledClock(speed=speed)
    cam = VideoFileCamera(avi, clock, pace=True)
    await cam.open()
    got: list[tuple[CameraFrame, float]] = []
    w0 = time.monotonic()
    async for f in cam.frames():
        got.append((f, clock.now()))
    wall = time.monotonic() - w0
    await cam.close()
    t0 = got[0][0].t_capture_s
    np.testing.assert_allclose([f.t_capture_s - t0 for f, _ in got], np.arange(24) / FPS)
    lags = np.array([now - f.t_capture_s for f, now in got])
    assert lags.min() >= -1e-9  # never before its capture time
    # and not held a frame period too long: a pacer that waits until the next frame's time
    # is late by at least a period on every frame. (The lag of most frames is a few ms of
    # wall time, but a loaded machine wakes the thread later: a median bound of 6 ms of
    # wall time failed beside a busy loop on every CPU.)
    assert lags.min() < 1.0 / FPS
    # Paced: the last frame is not delivered before 23 frame periods of session time have
    # passed since the first open; at speed 8 that is 23 / 30 / 8 = 0.096 s of wall time.
    assert got[-1][1] >= t0 + 23 / FPS
    assert wall < 23 / FPS / speed + 1.0


async def test_unpaced_runs_faster_than_real_time(tmp_path: Path) -> None:
    p = tmp_path / "long.avi"
    write_avi(p, 150, fps=FPS)  # 5 s of video
    w0 = time.monotonic()
    frames = await collect(VideoFileCamera(p, ScaledClock(), pace=False, t0_s=0.0))
    assert time.monotonic() - w0 < 2.5
    assert len(frames) == 150
    assert frames[-1].t_capture_s == pytest.approx(149 / FPS)


@pytest.mark.parametrize("cut_in_frame", [3, 12, 23])
async def test_truncated_file_ends_at_last_complete_frame(
    avi: Path, tmp_path: Path, cut_in_frame: int
) -> None:
    full = await collect(VideoFileCamera(avi, ScaledClock(), pace=False, gray=False))
    data = avi.read_bytes()
    packet = raw_packets(avi)[cut_in_frame]
    start = data.find(packet[-64:].tobytes()) - (packet.size - 64)  # headers repeat: match tails
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: start + packet.size // 2])  # half of the frame's JPEG survives
    cam = VideoFileCamera(cut, ScaledClock(), pace=False, gray=False)
    frames = await collect(cam)
    assert [f.seq for f in frames] == list(range(cut_in_frame))
    for f, ref in zip(frames, full, strict=False):
        np.testing.assert_array_equal(f.image, ref.image)
    assert len(cam.notes) == 1
    note = cam.notes[0]
    assert f"frame {cut_in_frame} is incomplete" in note and str(cut) in note
    assert "\n" not in note


async def test_file_missing_only_its_index_replays_every_frame(avi: Path, tmp_path: Path) -> None:
    data = avi.read_bytes()
    cut = tmp_path / "noindex.avi"
    cut.write_bytes(data[: data.rfind(b"idx1")])
    cam = VideoFileCamera(cut, ScaledClock(), pace=False)
    assert len(await collect(cam)) == 24
    assert cam.notes == []


def _zero_end_marker(data: bytearray, packet: np.ndarray) -> None:
    """Damage the JPEG ``packet`` where it lies in the file ``data``: its end marker zeroed."""
    start = bytes(data).find(packet[-64:].tobytes()) - (packet.size - 64)
    assert start > 0
    end = start + packet.size
    data[end - 2 : end] = b"\x00\x00"


async def test_damaged_frame_inside_file_is_skipped(avi: Path, tmp_path: Path) -> None:
    data = bytearray(avi.read_bytes())
    _zero_end_marker(data, raw_packets(avi)[5])
    bad = tmp_path / "bad.avi"
    bad.write_bytes(bytes(data))
    cam = VideoFileCamera(bad, ScaledClock(), pace=False)
    frames = await collect(cam)
    assert [f.seq for f in frames] == [k for k in range(24) if k != 5]
    assert frames[5].dropped_before == 1 and cam.stats.dropped == 1
    assert any("frame 5 is damaged" in n for n in cam.notes)


async def test_skipping_damaged_frames_at_the_start_is_waiting_not_lagging(
    tmp_path: Path,
) -> None:
    """A paced file whose first 2 s of frames are damaged waits through them (each one's
    capture time) before its first good frame: that frame is not late, so the first frame
    is never due more than a frame or two before now (it was due from the file's t0, 2 s
    early: the daemon's first-frame lag then passed run.max_lag_s on a file that kept up)."""
    avi = tmp_path / "v.avi"
    write_avi(avi, 90, fps=FPS)
    data = bytearray(avi.read_bytes())
    for packet in raw_packets(avi)[:60]:
        _zero_end_marker(data, packet)
    bad = tmp_path / "bad.avi"
    bad.write_bytes(bytes(data))
    clock = ScaledClock(speed=2.0)
    cam = VideoFileCamera(bad, clock, pace=True, t0_s=clock.now())
    await cam.open()
    overdue: list[float] = []

    async def watch() -> None:
        while True:
            due = cam.first_frame_due_s()
            assert due is not None
            overdue.append(clock.now() - due)
            await asyncio.sleep(0.005)

    watcher = asyncio.create_task(watch())
    frames = cam.frames()
    first = await anext(frames)
    watcher.cancel()
    await cam.close()
    assert first.seq == 60 and first.dropped_before == 60
    assert len(overdue) > 20  # watched through the 1 s of wall time
    # a frame period is 33 ms; the thread's wake-ups on a loaded machine come on top
    assert max(overdue) < 1.0, max(overdue)
    assert cam.first_frame_due_s() == first.t_capture_s


@pytest.mark.parametrize(
    ("make", "problem"),
    [
        (lambda d: d / "missing.avi", "not found"),
        (lambda d: d, "not a regular file"),
        (lambda d: _text_file(d / "notes.avi"), "not a video"),
    ],
)
async def test_unusable_file_is_one_line_camera_error(
    tmp_path: Path, make: object, problem: str
) -> None:
    path = make(tmp_path)  # type: ignore[operator]
    cam = VideoFileCamera(path, ScaledClock())
    with pytest.raises(CameraError) as info:
        await cam.open()
    msg = str(info.value)
    assert problem in msg and str(path) in msg and "\n" not in msg
    assert not cam.is_open


def _text_file(p: Path) -> Path:
    p.write_text("this is not a video\n" * 100)
    return p


async def test_start_position_and_loop(avi: Path) -> None:
    clock = ScaledClock()
    cam = VideoFileCamera(avi, clock, pace=False, gray=False, loop=True, start_s=0.5, t0_s=1.0)
    frames = await collect(cam, limit=30)
    k0 = 15  # round(0.5 s * 30 fps)
    assert [f.seq for f in frames] == list(range(k0, k0 + 30))
    np.testing.assert_allclose([f.t_capture_s for f in frames], 1.0 + np.arange(30) / FPS)
    # 9 frames per pass (15..23): frame 9 of the stream is file frame 15 again.
    np.testing.assert_array_equal(frames[9].image, frames[0].image)
    np.testing.assert_array_equal(frames[20].image, frames[2].image)
    assert not np.array_equal(frames[1].image, frames[0].image)


async def test_start_past_end_is_camera_error(avi: Path) -> None:
    with pytest.raises(CameraError, match="past its end"):
        await VideoFileCamera(avi, ScaledClock(), start_s=10.0).open()


async def test_reopen_resumes_after_last_delivered_frame(avi: Path) -> None:
    cam = VideoFileCamera(avi, ScaledClock(), pace=False, gray=False)
    first = await collect(cam, limit=7)
    rest = await collect(cam)
    assert [f.seq for f in first + rest] == list(range(24))
    assert rest[0].dropped_before == 0


async def test_config_and_open_camera(avi: Path) -> None:
    cfg = VideoFileCameraConfig(path=avi, pace=False)
    cam = open_camera(cfg, ScaledClock(), t0_s=0.0)
    assert isinstance(cam, VideoFileCamera) and cam.gray
    await cam.open()
    n = 0
    async for _ in cam.frames():
        n += 1
    await cam.close()
    await cam.close()  # idempotent
    assert n == 24


async def test_simulator_video_replays_with_its_frame_times(tmp_path: Path) -> None:
    scene = small_scene(recovery_s=0.6)
    out = write_outputs(scene, tmp_path / "sim")
    with out.frames_csv.open() as f:
        rows = list(csv.DictReader(f))
    cam = VideoFileCamera(out.video, ScaledClock(), pace=False, gray=True, t0_s=0.0)
    frames = await collect(cam)
    assert len(frames) == out.frames_written == len(rows)
    np.testing.assert_allclose(
        [f.t_capture_s for f in frames], [float(r["t_s"]) for r in rows], atol=1e-9
    )
    # S_k of Eq. (2) from the straight-to-gray decode matches the colour decode + cvtColor.
    color = await collect(VideoFileCamera(out.video, ScaledClock(), pace=False, gray=False))
    roi = CircleROI(cx_px=32.0, cy_px=24.0, radius_px=20.0)
    pg = FrameProcessor((48, 64), scene.probe.threshold, roi)
    pc = FrameProcessor((48, 64, 3), scene.probe.threshold, roi)
    for g, c in zip(frames, color, strict=True):
        sg, sc = pg.count(g.image), pc.count(c.image)
        assert abs(sg - sc) <= max(2, 0.01 * sc)


async def test_consumer_cancel_then_close_does_not_hang(avi: Path) -> None:
    cam = VideoFileCamera(avi, ScaledClock(speed=0.5), pace=True)
    await cam.open()
    it = cam.frames()
    await anext(it)
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(anext(it), 0.01)
    w0 = time.monotonic()
    await cam.close()
    assert time.monotonic() - w0 < 1.0


# ------------------------------------------------- other codecs: PyAV, decoded at capture time


@pytest.mark.parametrize("codec", ["ffv1", "mpeg4"])
async def test_pyav_file_start_loop_and_reopen(tmp_path: Path, codec: str) -> None:
    """FFV1 (every packet a keyframe: skipped undecoded) and MPEG-4 with B-frames (decoded
    from the start to reach ``start_s``) replay from ``start_s``, loop and resume after a
    reopen with the frames PyAV's own decoder gives, at the same times as MJPG files."""
    path = tmp_path / f"{codec}.mkv"
    write_pyav(path, 12, codec=codec, fps=10)
    reference = pyav_frames(path)
    assert len(reference) == 12
    cam = VideoFileCamera(path, ScaledClock(), pace=False, gray=False, loop=True, start_s=0.5)
    cam_t0 = VideoFileCamera(path, ScaledClock(), pace=False, gray=False, t0_s=1.0)
    first = await collect(cam, limit=4)
    rest = await collect(cam, limit=6)  # reopened: resumes after frame 8
    frames = first + rest
    assert cam.metadata()["decoder"] == DECODER_PYAV
    assert [f.seq for f in frames] == list(range(5, 15))
    assert rest[0].dropped_before == 0
    file_index = [5, 6, 7, 8, 9, 10, 11, 5, 6, 7]  # 7 frames a pass from frame 5
    for f, k in zip(frames, file_index, strict=True):
        assert f.packet is None
        np.testing.assert_array_equal(f.image, reference[k])
    whole = await collect(cam_t0)
    np.testing.assert_allclose([f.t_capture_s for f in whole], 1.0 + np.arange(12) / 10.0)


async def test_pyav_truncated_file_ends_at_its_last_complete_frame(tmp_path: Path) -> None:
    import av

    path = tmp_path / "v.mkv"
    write_pyav(path, 10, codec="ffv1", fps=10)
    with av.open(str(path)) as container:
        packets = [(p.pos, p.size) for p in container.demux(video=0) if p.size]
    pos, size = packets[6]
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(path.read_bytes()[: pos + size // 2])  # half of frame 6's packet
    cam = VideoFileCamera(cut, ScaledClock(), pace=False, gray=False)
    frames = await collect(cam)
    assert [f.seq for f in frames] == list(range(6))
    for f, ref in zip(frames, pyav_frames(path), strict=False):
        np.testing.assert_array_equal(f.image, ref)
    assert cam.notes == [
        f"video file {cut}: ended after 6 of the 10 frames its header declares (truncated?)"
    ]
