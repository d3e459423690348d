"""The daemon's devices and the session video: what a camera's metadata tells (frame size,
JPEG packets) and the config rules of ``storage.video`` (docs/storage.md, "Video").

The V4L2 camera is the real :class:`~stipi_daemon.cameras.v4l2.V4L2Camera`, its settings
read back by its own ``_configure`` from a real OpenCV capture (a MJPG file stands in for
the device: no V4L2 device exists here), as the driver's granted size is read at open.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import pytest
import yaml

from stipi_daemon.analysis.calibration import Calibration, load_calibration, save_calibration
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.config import load_config
from stipi_daemon.app.devices import _check_frame, delivers_jpeg_packets, frame_size
from stipi_daemon.cameras import (
    CameraStream,
    SimulatorCameraConfig,
    V4L2CameraConfig,
    VideoFileCameraConfig,
    open_camera,
)
from stipi_daemon.cameras.v4l2 import V4L2Camera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import ConfigError
from tests.cameras._video import frame_image, write_avi
from tests.conftest import REPO_ROOT

SCENES = REPO_ROOT / "configs" / "scenes"
#: A calibration that records no frame size (the paper's coefficients at 640x480).
_CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)


def _v4l2_camera(avi: Path) -> V4L2Camera:
    """A V4L2 camera whose settings were read back from a real capture of ``avi``.

    The file's capture grants its own size whatever is requested (as a driver may).
    """
    cam = V4L2Camera(
        V4L2CameraConfig(device="/dev/video0", width=640, height=480, exposure_ms=5.0),
        ScaledClock(),
    )
    cap = cv2.VideoCapture(str(avi), cv2.CAP_FFMPEG)
    assert cap.isOpened()
    try:
        cam._configure(cap)
    finally:
        cap.release()
    return cam


def _config(tmp_path: Path, **sections: object) -> Path:
    scene = str(SCENES / "grade1.yaml")
    doc: dict[str, object] = {
        "probe": {"transport": {"kind": "emulated", "scene": scene}},
        "camera": {"kind": "simulator", "scene": scene},
        **sections,
    }
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_frame_size_of_a_v4l2_camera_is_what_the_driver_granted(tmp_path: Path) -> None:
    avi = tmp_path / "granted.avi"
    write_avi(avi, 3, width=320, height=240)
    metadata = _v4l2_camera(avi).metadata()
    assert metadata["applied"]["width"] == 320  # granted, not the 640 requested
    assert frame_size(metadata) == (320, 240)


@pytest.mark.parametrize(
    ("roi", "where"),
    [
        (CircleROI(cx_px=319.5, cy_px=239.5, radius_px=200.0), "partly outside"),
        (RectROI(x_px=400, y_px=300, width_px=100, height_px=100), "outside"),
    ],
)
def test_roi_off_a_v4l2_cameras_frame_is_a_config_error(
    tmp_path: Path, roi: CircleROI | RectROI, where: str
) -> None:
    avi = tmp_path / "granted.avi"
    write_avi(avi, 3, width=320, height=240)
    stream = CameraStream(_v4l2_camera(avi), ScaledClock())
    config = load_config(_config(tmp_path, imaging={"roi": roi.model_dump(mode="json")}))
    with pytest.raises(ConfigError) as info:
        _check_frame(config, stream, roi, _CAL)
    line = str(info.value)
    assert line.startswith("field 'imaging.roi': ") and "\n" not in line
    assert f"lies {where} the 320x240 frame" in line
    fits = RectROI(x_px=0, y_px=0, width_px=320, height_px=240)
    assert _check_frame(config, stream, fits, _CAL) == (320, 240)


def test_a_calibration_made_at_another_size_than_the_driver_granted_is_a_config_error(
    tmp_path: Path,
) -> None:
    """The camera was asked for 640x480 and the driver granted 320x240: a calibration
    made at 640x480 would turn the smaller frames' S into a wrong D_p and F_r. One line
    naming the calibration file and both sizes; at the granted size it passes."""
    avi = tmp_path / "granted.avi"
    write_avi(avi, 3, width=320, height=240)
    stream = CameraStream(_v4l2_camera(avi), ScaledClock())
    path = save_calibration(tmp_path / "cal.json", replace(_CAL, frame_size_px=(640, 480)))
    config = load_config(_config(tmp_path, calibration=str(path)))
    with pytest.raises(ConfigError) as info:
        _check_frame(config, stream, None, load_calibration(path))
    line = str(info.value)
    assert "\n" not in line
    assert line.startswith(f"field 'calibration' ({path}): the camera has 320x240 px frames")
    assert "made at 640x480 px" in line and "set the camera to 640x480" in line
    granted = replace(_CAL, frame_size_px=(320, 240))
    assert _check_frame(config, stream, None, granted) == (320, 240)
    assert _check_frame(config, stream, None, _CAL) == (320, 240)  # no size recorded: passes


async def test_which_cameras_deliver_jpeg_packets(tmp_path: Path) -> None:
    """Simulator: an MJPG scene's camera, not a clean one's; a video file: MJPG read as
    raw packets, not FFV1; V4L2: MJPG taken raw (its JPEGs), not a format OpenCV decodes."""
    clock = ScaledClock()
    mjpg = open_camera(SimulatorCameraConfig(scene=SCENES / "demo_grade3_mjpg.yaml"), clock)
    clean = open_camera(SimulatorCameraConfig(scene=SCENES / "grade1.yaml"), clock)
    assert delivers_jpeg_packets(mjpg.metadata())
    assert not delivers_jpeg_packets(clean.metadata())

    avi = tmp_path / "mjpg.avi"
    write_avi(avi, 3)
    ffv1 = tmp_path / "ffv1.avi"
    writer = cv2.VideoWriter(str(ffv1), cv2.VideoWriter.fourcc(*"FFV1"), 30.0, (160, 120))
    assert writer.isOpened()
    for k in range(3):
        writer.write(frame_image(k, 160, 120, True))
    writer.release()
    for path, expected in ((avi, True), (ffv1, False)):
        cam = open_camera(VideoFileCameraConfig(path=path, pace=False), clock)
        await cam.open()
        try:
            assert delivers_jpeg_packets(cam.metadata()) is expected, cam.metadata()
        finally:
            await cam.close()

    assert delivers_jpeg_packets(_v4l2_camera(avi).metadata())  # MJPG: its JPEGs
    assert not delivers_jpeg_packets(_v4l2_camera(ffv1).metadata())  # decoded by OpenCV


def test_video_roi_only_without_video_is_a_config_error(tmp_path: Path) -> None:
    path = _config(tmp_path, storage={"video": "off", "video_roi_only": True})
    with pytest.raises(ConfigError) as info:
        load_config(path)
    line = str(info.value)
    assert "\n" not in line and str(path) in line
    assert "storage.video_roi_only" in line and "storage.video is off" in line
    # Set on the command line: the message names the --set item.
    path = _config(tmp_path, storage={"video": "lossless", "video_roi_only": True})
    with pytest.raises(ConfigError, match=r"^--set storage.video=off: .*storage.video_roi_only"):
        load_config(path, overrides=["storage.video=off"])
    assert load_config(path).storage.video_roi_only  # with a video: fine
    assert load_config(path, overrides=["storage.video=passthrough"]).storage.video_roi_only
