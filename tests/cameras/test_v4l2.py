"""V4L2Camera: error paths and the MJPG read path here, and an opt-in test on a real camera.

The hardware test runs only with ``pytest --camera-device=/dev/video0`` (no V4L2 device
exists in CI): it opens the camera with locked exposure and white balance, checks what the
driver applied and reads about 2 s of frames.

Without a device, the camera's own configure-and-read code runs on the closest real
substitutes OpenCV offers: its FFmpeg backend in raw-packet mode (``CAP_PROP_FORMAT = -1``)
on an MJPG AVI hands over each JPEG as a ``1 x N`` byte array, as the V4L2 backend hands
over a raw MJPG buffer with ``CAP_PROP_CONVERT_RGB`` off, and accepts that setting; its own
MJPEG reader (``CAP_OPENCV_MJPEG``) reports ``MJPG``, refuses raw frames and decodes to BGR,
as a driver without raw mode does.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.cameras import CameraConfig, CameraFrame, V4L2CameraConfig, open_camera
from stipi_daemon.cameras.threaded import RawFrame
from stipi_daemon.cameras.v4l2 import V4L2Camera, _Handle, decode_mode, device_path
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import CameraError
from tests.cameras._video import raw_packets, write_avi


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
# MJPG: the camera's JPEGs travel with the frames, in colour as in gray
# --------------------------------------------------------------------------------------------


def test_decode_mode_takes_mjpg_raw_in_colour_too() -> None:
    asked: list[str] = []

    def driver(accepts: bool, fourcc: str) -> bool:
        asked.append(fourcc)
        return accepts

    table = {
        ("MJPG", True, True): "jpeg_gray",
        ("MJPG", False, True): "jpeg_bgr",
        ("JPEG", False, True): "jpeg_bgr",
        ("MJPG", True, False): "bgr_to_gray",
        ("MJPG", False, False): "bgr",
        ("YUYV", True, True): "yuyv_gray",
        ("YUYV", False, True): "bgr",  # not asked: OpenCV's BGR is what colour needs
        ("GREY", True, True): "bgr_to_gray",
    }
    for (fourcc, gray, accepts), want in table.items():
        asked.clear()
        assert decode_mode(fourcc, gray, lambda a=accepts, f=fourcc: driver(a, f)) == want
        assert asked == ([] if (fourcc, gray) in (("YUYV", False), ("GREY", True)) else [fourcc])


def _read_all(cam: V4L2Camera, cap: cv2.VideoCapture, n: int) -> list[RawFrame]:
    mode = cam._configure(cap)  # the camera's own settings, read-back and decode choice
    handle = _Handle(cap, mode, cam.nominal_fps)
    try:
        return [cam._read(handle) or pytest.fail("no frame") for _ in range(n)]
    finally:
        cap.release()


@pytest.mark.parametrize("gray", [False, True], ids=["colour", "gray"])
def test_mjpg_frames_carry_the_cameras_jpeg(tmp_path: Path, gray: bool) -> None:
    path = tmp_path / "mjpg.avi"
    write_avi(path, 6, width=160, height=120)
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    assert cap.set(cv2.CAP_PROP_FORMAT, -1)  # raw packets, as the V4L2 backend's raw MJPG
    config = V4L2CameraConfig(device=str(path), width=160, height=120, exposure_ms=5.0, gray=gray)
    cam = V4L2Camera(config, ScaledClock())
    frames = _read_all(cam, cap, 6)
    applied = cam.applied_settings()
    assert applied["decode"] == ("jpeg_gray" if gray else "jpeg_bgr")
    assert applied["jpeg_packets"] is True
    assert not any("refused raw MJPG" in n for n in cam.notes)
    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    for f, jpeg in zip(frames, [p.tobytes() for p in raw_packets(path)], strict=True):
        assert f.packet == jpeg  # the JPEG as the camera sent it: passthrough recording
        assert f.image.shape == ((120, 160) if gray else (120, 160, 3))
        np.testing.assert_array_equal(f.image, cv2.imdecode(np.frombuffer(jpeg, np.uint8), flag))
    assert [f.seq for f in frames] == list(range(6))


@pytest.mark.parametrize("gray", [False, True], ids=["colour", "gray"])
def test_a_driver_refusing_raw_mjpg_is_noted_and_frames_carry_no_jpeg(
    tmp_path: Path, gray: bool
) -> None:
    path = tmp_path / "mjpg.avi"
    write_avi(path, 4, width=160, height=120)
    reference = cv2.VideoCapture(str(path), cv2.CAP_OPENCV_MJPEG)
    expected = [reference.read()[1] for _ in range(4)]
    reference.release()
    cap = cv2.VideoCapture(str(path), cv2.CAP_OPENCV_MJPEG)  # MJPG, no raw mode
    assert cap.isOpened()
    config = V4L2CameraConfig(device=str(path), width=160, height=120, exposure_ms=5.0, gray=gray)
    cam = V4L2Camera(config, ScaledClock())
    frames = _read_all(cam, cap, 4)
    applied = cam.applied_settings()
    assert applied["fourcc"] == "MJPG" and applied["jpeg_packets"] is False
    assert cam.metadata()["applied"]["jpeg_packets"] is False  # stored with the session
    notes = [n for n in cam.notes if "refused raw MJPG" in n]
    assert len(notes) == 1 and str(path) in notes[0] and "losslessly" in notes[0]
    for f, bgr in zip(frames, expected, strict=True):
        assert f.packet is None
        want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if gray else bgr
        np.testing.assert_array_equal(f.image, want)


# --------------------------------------------------------------------------------------------
# Opt-in hardware test
# --------------------------------------------------------------------------------------------


@pytest.fixture
def camera_device(request: pytest.FixtureRequest) -> str:
    device = request.config.getoption("--camera-device")
    if device is None:
        pytest.skip("no camera: pass --camera-device=/dev/videoN to run")
    return str(device)


@pytest.mark.parametrize("gray", [True, False], ids=["gray", "colour"])
async def test_real_camera_settings_and_frames(camera_device: str, gray: bool) -> None:
    config = V4L2CameraConfig(
        device=camera_device, width=640, height=480, fps=30.0, exposure_ms=10.0, gray=gray
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
    shape = (applied["height"], applied["width"])
    assert frames[0].image.shape == (shape if gray else (*shape, 3))
    # an MJPG camera's JPEGs travel with its frames (passthrough), unless the driver refused
    jpegs = applied["fourcc"] == "MJPG" and applied["jpeg_packets"]
    assert all((f.packet is not None) == jpegs for f in frames)
    seqs = [f.seq for f in frames]
    times = [f.t_capture_s for f in frames]
    assert seqs == sorted(seqs) and times == sorted(times)
    assert all(t <= clock.now() for t in times)
    assert math.isfinite(cam.stats.fps()) and cam.stats.fps() > 0.5 * applied["fps"]
