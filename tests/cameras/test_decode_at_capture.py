"""A paced camera hands over the encoded frame at its capture time and decodes it after.

Issue 16 asks the latency path to start when the encoded frame is available, as with a
real MJPG camera: so a paced video file and the simulated camera must not decode a frame
before its capture time on the session clock. Each test wraps the real decoder
(``cv2.imdecode``, PyAV's ``VideoCodecContext.decode``) with a recorder that notes the
session time and calls through, and logs, in the capture thread, each frame as it reaches
the frame hook (right after it was read and decoded). Every decode is then checked against
the capture time of the frame it was made for: the next frame the hook sees. The clock
only orders events here; no wall-time bound is asserted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import av.video.codeccontext
import cv2
import numpy as np
import pytest

from stipi_daemon.cameras import CameraFrame
from stipi_daemon.cameras.threaded import RawFrame, ThreadedCamera
from stipi_daemon.cameras.video_file import DECODER_PYAV, VideoFileCamera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.sim.camera import SimulatorCamera
from stipi_daemon.sim.pipeline import Pipeline
from tests.cameras._pyav_video import has_b_frames, pyav_frames, write_pyav
from tests.cameras._scenes import small_scene
from tests.cameras._video import decode_all, write_avi

#: Frame rate of the test files [1/s] and clock speed [-]: frames 0.2 s of session time
#: (0.1 s of wall time) apart, so a decode made before the wait is made a whole period early.
FPS = 5
SPEED = 2.0

Log = list[tuple[str, float, int]]  # ("decode", session time, -1) | ("frame", t_capture, seq)


def _recorder(log: Log, clock: ScaledClock, real: Callable[..., Any]) -> Callable[..., Any]:
    def record(*args: Any, **kwargs: Any) -> Any:
        log.append(("decode", clock.now(), -1))
        return real(*args, **kwargs)

    return record


async def _run(cam: ThreadedCamera[Any], log: Log) -> list[CameraFrame]:
    def hook(raw: RawFrame) -> None:
        log.append(("frame", raw.t_capture_s, raw.seq))

    cam.frame_hook = hook
    await cam.open()
    try:
        return [f async for f in cam.frames()]
    finally:
        await cam.close()


def _decodes_per_frame(log: Log) -> dict[int, list[float]]:
    """The session times of the decodes made for each frame (those logged before it)."""
    out: dict[int, list[float]] = {}
    pending: list[float] = []
    for kind, t, seq in log:
        if kind == "decode":
            pending.append(t)
        else:
            out[seq], pending = pending, []
    return out


def _assert_decoded_at_or_after_capture(log: Log, frames: list[CameraFrame]) -> None:
    per_frame = _decodes_per_frame(log)
    assert sorted(per_frame) == [f.seq for f in frames]
    for f in frames:
        decodes = per_frame[f.seq]
        assert decodes, f"frame {f.seq}: no decode recorded"
        early = [t for t in decodes if t < f.t_capture_s]
        assert not early, (
            f"frame {f.seq} decoded {f.t_capture_s - min(early):.3f} s of session time before "
            "its capture time"
        )


@pytest.mark.parametrize("gray", [True, False], ids=["gray", "bgr"])
async def test_paced_mjpg_file_decodes_each_jpeg_after_its_capture_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, gray: bool
) -> None:
    path = tmp_path / "v.avi"
    write_avi(path, 8, fps=float(FPS))
    clock = ScaledClock(speed=SPEED)
    log: Log = []
    monkeypatch.setattr(cv2, "imdecode", _recorder(log, clock, cv2.imdecode))
    frames = await _run(VideoFileCamera(path, clock, pace=True, gray=gray), log)
    monkeypatch.undo()
    assert [f.seq for f in frames] == list(range(8))
    assert all(f.packet is not None for f in frames)  # passthrough as before
    _assert_decoded_at_or_after_capture(log, frames)


@pytest.mark.parametrize("color", [True, False], ids=["bgr0", "gray"])
async def test_paced_ffv1_file_decodes_each_packet_after_its_capture_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, color: bool
) -> None:
    path = tmp_path / "v.mkv"
    written = write_pyav(path, 8, codec="ffv1", fps=FPS, color=color)
    clock = ScaledClock(speed=SPEED)
    log: Log = []
    ctx_class = av.video.codeccontext.VideoCodecContext
    monkeypatch.setattr(ctx_class, "decode", _recorder(log, clock, ctx_class.decode))
    cam = VideoFileCamera(path, clock, pace=True, gray=False)
    frames = await _run(cam, log)
    monkeypatch.undo()
    assert cam.metadata()["decoder"] == DECODER_PYAV
    assert [f.seq for f in frames] == list(range(8))
    assert all(f.packet is None for f in frames)  # no JPEG: the video records it losslessly
    for f, img in zip(frames, written, strict=True):  # FFV1 is lossless
        want = img if color else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        np.testing.assert_array_equal(f.image, want)
    _assert_decoded_at_or_after_capture(log, frames)


@pytest.mark.parametrize("gray", [False, True], ids=["bgr", "gray"])
async def test_b_frames_are_decoded_after_capture_and_all_delivered_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, gray: bool
) -> None:
    path = tmp_path / "b.mkv"
    write_pyav(path, 14, codec="mpeg4", fps=FPS)
    assert has_b_frames(path)  # decode order != presentation order
    reference = decode_all(path)  # OpenCV's FFmpeg backend: every frame, as before
    assert len(reference) == 14
    np.testing.assert_array_equal(np.stack(reference), np.stack(pyav_frames(path)))
    clock = ScaledClock(speed=SPEED)
    log: Log = []
    ctx_class = av.video.codeccontext.VideoCodecContext
    monkeypatch.setattr(ctx_class, "decode", _recorder(log, clock, ctx_class.decode))
    frames = await _run(VideoFileCamera(path, clock, pace=True, gray=gray), log)
    monkeypatch.undo()
    # the held-back last frames come out of the decoder's flush: none is lost
    assert [f.seq for f in frames] == list(range(14))
    np.testing.assert_allclose(
        [f.t_capture_s - frames[0].t_capture_s for f in frames], [k / FPS for k in range(14)]
    )
    for f, ref in zip(frames, reference, strict=True):
        want = cv2.cvtColor(ref, cv2.COLOR_BGR2GRAY) if gray else ref
        np.testing.assert_array_equal(f.image, want)
    _assert_decoded_at_or_after_capture(log, frames)


async def test_simulated_mjpg_camera_decodes_each_jpeg_after_its_capture_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scene = small_scene(fps=10.0, recovery_s=0.4)
    scene = scene.model_copy(
        update={"camera": scene.camera.model_copy(update={"pixel_format": "mjpg"})}
    )
    ref = list(Pipeline(scene, 3, gray_decode=True).frames())  # decoded before the patch
    clock = ScaledClock(speed=SPEED)
    log: Log = []
    monkeypatch.setattr(cv2, "imdecode", _recorder(log, clock, cv2.imdecode))
    frames = await _run(SimulatorCamera(scene, clock, seed=3), log)
    monkeypatch.undo()
    assert [f.seq for f in frames] == [r.index for r in ref] and len(frames) > 5
    for f, r in zip(frames, ref, strict=True):  # the same JPEG and the same decode
        assert f.packet == r.packet and f.packet is not None
        np.testing.assert_array_equal(f.image, r.image)
    # A frame whose picture repeats the one before (the same JPEG) reuses its decode;
    # every decode that is made is made after the capture time of its frame.
    per_frame = _decodes_per_frame(log)
    assert sum(len(d) for d in per_frame.values()) >= len({f.packet for f in frames})
    for f in frames:
        assert all(t >= f.t_capture_s for t in per_frame[f.seq]), f"frame {f.seq} decoded early"
