"""V4L2Camera: error paths here, and an opt-in test on a real camera.

The hardware test runs only with ``pytest --camera-device=/dev/video0`` (no V4L2 device
exists in CI): it opens the camera with locked exposure and white balance, checks what the
driver applied and reads about 2 s of frames.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.cameras import CameraConfig, CameraFrame, V4L2CameraConfig, open_camera
from stipi_daemon.cameras.v4l2 import V4L2Camera, device_path
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import CameraError


@pytest.mark.parametrize("device", ["/dev/video99", 99])
async def test_missing_device_is_one_line_camera_error(device: str | int) -> None:
    cam = open_camera(V4L2CameraConfig(device=device, exposure_ms=5.0), ScaledClock())
    assert isinstance(cam, V4L2Camera)
    with pytest.raises(CameraError) as info:
        await cam.open()
    msg = str(info.value)
    assert msg == "camera /dev/video99: no such device"


async def test_non_camera_file_is_camera_error(tmp_path: Path) -> None:
    fake = tmp_path / "video0"
    fake.write_bytes(b"\0" * 64)
    cam = V4L2Camera(V4L2CameraConfig(device=str(fake), exposure_ms=5.0), ScaledClock())
    with pytest.raises(CameraError, match="cannot be opened as a V4L2 capture device") as info:
        await cam.open()
    assert str(fake) in str(info.value) and "\n" not in str(info.value)
    assert not cam.is_open


def test_device_path() -> None:
    assert device_path(2) == "/dev/video2"
    assert device_path("/dev/v4l/by-id/usb-cam") == "/dev/v4l/by-id/usb-cam"


def test_config_union_and_validation() -> None:
    adapter: TypeAdapter[object] = TypeAdapter(CameraConfig)
    cfg = adapter.validate_python({"kind": "v4l2", "device": 1, "exposure_ms": 8.0})
    assert isinstance(cfg, V4L2CameraConfig)
    assert cfg.fourcc == "MJPG" and cfg.gray and cfg.white_balance_k == 4600
    with pytest.raises(ValidationError, match="exposure_ms"):
        adapter.validate_python({"kind": "v4l2"})  # exposure must be chosen, never auto
    with pytest.raises(ValidationError, match="fourcc"):
        adapter.validate_python({"kind": "v4l2", "exposure_ms": 8.0, "fourcc": "MJPEG"})
    with pytest.raises(ValidationError, match="extra"):
        adapter.validate_python({"kind": "file", "path": "v.avi", "speed": 2})


# --------------------------------------------------------------------------------------------
# Opt-in hardware test
# --------------------------------------------------------------------------------------------


@pytest.fixture
def camera_device(request: pytest.FixtureRequest) -> str:
    device = request.config.getoption("--camera-device")
    if device is None:
        pytest.skip("no camera: pass --camera-device=/dev/videoN to run")
    return str(device)


async def test_real_camera_settings_and_frames(camera_device: str) -> None:
    config = V4L2CameraConfig(
        device=camera_device, width=640, height=480, fps=30.0, exposure_ms=10.0, gray=True
    )
    clock = ScaledClock()
    cam = V4L2Camera(config, clock)
    await cam.open()
    frames: list[CameraFrame] = []
    try:
        applied = cam.applied_settings()
        assert applied["auto_exposure"] == 1.0, f"auto exposure still on: {applied}"
        assert applied["width"] > 0 and applied["height"] > 0 and applied["fps"] > 0
        w0 = time.monotonic()
        async for f in cam.frames():
            frames.append(f)
            if time.monotonic() - w0 > 2.0:
                break
    finally:
        await cam.close()
    print("applied:", applied, "notes:", cam.notes, "stats:", cam.stats.as_dict())
    assert len(frames) >= 0.5 * 2.0 * applied["fps"]
    assert frames[0].image.shape == (applied["height"], applied["width"])
    seqs = [f.seq for f in frames]
    times = [f.t_capture_s for f in frames]
    assert seqs == sorted(seqs) and times == sorted(times)
    assert all(t <= clock.now() for t in times)
    assert math.isfinite(cam.stats.fps()) and cam.stats.fps() > 0.5 * applied["fps"]
