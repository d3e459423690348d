"""SimulatorCamera: the simulator's frames, paced on the session clock."""

from __future__ import annotations

import time

import numpy as np

from stipi_daemon.cameras import CameraFrame, SimulatorCameraConfig, open_camera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.sim.camera import SimulatorCamera
from stipi_daemon.sim.pipeline import Pipeline, frame_count
from tests.cameras._scenes import small_scene
from tests.conftest import REPO_ROOT


async def _all(cam: SimulatorCamera) -> list[tuple[CameraFrame, float]]:
    await cam.open()
    out = []
    try:
        async for f in cam.frames():
            out.append((f, cam._clock.now()))
    finally:
        await cam.close()
    return out


async def test_frames_equal_pipeline_frames_and_times() -> None:
    scene = small_scene()
    speed = 10.0
    clock = ScaledClock(speed=speed)
    cam = SimulatorCamera(scene, clock, seed=3)  # t0: the first open
    w0 = time.monotonic()
    got = await _all(cam)
    wall = time.monotonic() - w0
    ref = list(Pipeline(scene, 3).frames())
    t0 = cam.t0_s
    assert t0 is not None
    assert len(got) == len(ref) == frame_count(scene)
    for (f, now), r in zip(got, ref, strict=True):
        assert f.seq == r.index and f.dropped_before == 0
        assert f.t_capture_s == t0 + r.t_s
        np.testing.assert_array_equal(f.image, r.image)
        assert now >= f.t_capture_s - 1e-9  # paced: never early
    # the first frame's capture time, known before it is made (its lag before it comes)
    assert cam.first_frame_due_s() == got[0][0].t_capture_s
    duration_s = ref[-1].t_s
    assert wall > 0.9 * duration_s / speed  # paced at speed 10, not as fast as possible
    assert wall < duration_s / speed + 1.5
    assert abs(cam.stats.fps() - scene.camera.fps) < 0.05 * scene.camera.fps


async def test_dropped_frames_effect_shows_as_seq_gaps() -> None:
    scene = small_scene(effects=[{"name": "dropped_frames", "probability": 0.2}])
    cam = SimulatorCamera(scene, ScaledClock(speed=20.0), seed=5)
    got = [f for f, _ in await _all(cam)]
    ref = [r.index for r in Pipeline(scene, 5).frames()]
    assert [f.seq for f in got] == ref
    gaps = np.diff([-1, *ref]) - 1
    assert [f.dropped_before for f in got] == gaps.tolist()
    assert cam.stats.dropped == ref[-1] + 1 - len(ref) > 0  # gaps before delivered frames


async def test_open_camera_from_config_uses_scene_file() -> None:
    cfg = SimulatorCameraConfig(scene=REPO_ROOT / "configs" / "scenes" / "grade1.yaml", seed=2)
    cam = open_camera(cfg, ScaledClock(speed=50.0))  # t0: the first open
    assert isinstance(cam, SimulatorCamera) and cam.seed == 2
    assert cam.nominal_fps == 60.0
    await cam.open()
    it = cam.frames()
    first = [await anext(it) for _ in range(3)]
    await cam.close()
    assert [f.seq for f in first] == [0, 1, 2]
    assert first[0].image.shape == (480, 640, 3)
    assert cam.metadata()["scene"] == "grade1"
