"""The simulated camera delivers what an MJPG or a raw camera delivers, and the video-file
camera replays both kinds of ``simulate`` output (docs/simulator.md, "Video").

An MJPG scene's frame carries the JPEG the simulator encoded (``CameraFrame.packet``) and
its image is ``cv2.imdecode`` of exactly that packet straight to gray, as the V4L2 and file
cameras decode an MJPG frame with ``gray: true``; a raw scene's frame carries no packet and
its image is the rendered frame. The video-file camera (OpenCV's
FFmpeg backend) replays the lossless file bit for bit and the MJPG file's packets byte for
byte, with the frame times of ``frames.csv``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.cameras.base import CameraFrame
from stipi_daemon.cameras.video_file import VideoFileCamera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.sim import Pipeline, write_outputs
from stipi_daemon.sim.camera import SimulatorCamera
from stipi_daemon.sim.scene import Scene
from tests.cameras._scenes import small_scene


def _mjpg(scene: Scene, quality: int | None = None) -> Scene:
    cam = scene.camera.model_copy(update={"pixel_format": "mjpg", "jpeg_quality": quality})
    return scene.model_copy(update={"camera": cam})


async def _collect(cam: SimulatorCamera | VideoFileCamera) -> list[CameraFrame]:
    await cam.open()
    out: list[CameraFrame] = []
    try:
        async for f in cam.frames():
            out.append(f)
    finally:
        await cam.close()
    return out


@pytest.mark.parametrize("mjpg", [True, False], ids=["mjpg", "raw"])
async def test_simulated_camera_delivers_the_jpeg_it_encoded(mjpg: bool) -> None:
    scene = _mjpg(small_scene(), 85) if mjpg else small_scene()
    cam = SimulatorCamera(scene, ScaledClock(speed=20.0), seed=3)
    got = await _collect(cam)
    ref = list(Pipeline(scene, 3).frames())
    assert [f.seq for f in got] == [r.index for r in ref] and len(got) > 50
    assert cam.metadata()["jpeg_quality"] == (85 if mjpg else None)
    for f, r in zip(got, ref, strict=True):
        assert f.packet == r.packet
        if f.packet is None:
            assert not mjpg
            np.testing.assert_array_equal(f.image, r.image)  # raw BGR, as rendered
            continue
        # The image the daemon measures is the decode of the very packet it stores.
        assert f.packet.startswith(b"\xff\xd8") and f.packet.endswith(b"\xff\xd9")
        decoded = cv2.imdecode(np.frombuffer(f.packet, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert f.image.ndim == 2
        np.testing.assert_array_equal(f.image, decoded)


async def test_jpeg_compression_effect_makes_the_camera_mjpg() -> None:
    scene = small_scene(effects=[{"name": "jpeg_compression", "quality": 50}])
    got = await _collect(SimulatorCamera(scene, ScaledClock(speed=20.0), seed=1))
    assert got and all(f.packet is not None for f in got)


@pytest.mark.parametrize("gray", [False, True], ids=["bgr", "gray"])
async def test_video_file_camera_replays_the_lossless_file_exactly(
    tmp_path: Path, gray: bool
) -> None:
    scene = small_scene(fps=20.0)
    out = write_outputs(scene, tmp_path / "sim")
    assert out.video_codec == "ffv1"
    cam = VideoFileCamera(out.video, ScaledClock(), pace=False, gray=gray, t0_s=0.0)
    got = await _collect(cam)
    ref = list(Pipeline(scene).frames())
    assert len(got) == len(ref) == out.frames_written
    assert cam.nominal_fps == pytest.approx(20.0)
    with out.frames_csv.open() as fcsv:
        times = [float(r["t_s"]) for r in csv.DictReader(fcsv)]
    np.testing.assert_allclose([f.t_capture_s for f in got], times, atol=1e-9)
    for f, r in zip(got, ref, strict=True):
        assert f.packet is None
        want = cv2.cvtColor(r.image, cv2.COLOR_BGR2GRAY) if gray else r.image
        np.testing.assert_array_equal(f.image, want)


async def test_video_file_camera_replays_the_mjpg_files_packets(tmp_path: Path) -> None:
    scene = _mjpg(small_scene(fps=20.0), 75)
    out = write_outputs(scene, tmp_path / "sim")
    assert out.video_codec == "mjpeg"
    cam = VideoFileCamera(out.video, ScaledClock(), pace=False, gray=False, t0_s=0.0)
    got = await _collect(cam)
    ref = list(Pipeline(scene).frames())
    assert len(got) == len(ref) == out.frames_written
    assert cam.metadata()["decoder"] == "imdecode (raw MJPG packets)"
    for f, r in zip(got, ref, strict=True):
        assert f.packet == r.packet  # the simulator's JPEG, passed on as it is
        np.testing.assert_array_equal(f.image, r.image)
