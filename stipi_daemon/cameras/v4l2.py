"""A UVC/V4L2 camera read through OpenCV, with exposure and white balance locked.

This module owns opening ``/dev/videoN`` with ``cv2.VideoCapture(path, cv2.CAP_V4L2)``,
requesting pixel format, size and frame rate, switching auto exposure and auto white
balance off and setting absolute values, reading back what the driver accepted
(:meth:`V4L2Camera.applied_settings`; each mismatch is logged and kept as a note), and the
capture thread (``grab`` blocks until the driver has a frame). Frames go through a
drop-oldest hand-off: when the consumer lags, the oldest frames are discarded and counted.
It does not analyse frames.

Property values, as OpenCV's V4L2 backend passes them to the driver (not normalised):
``CAP_PROP_AUTO_EXPOSURE`` is ``V4L2_CID_EXPOSURE_AUTO`` (1 = manual),
``CAP_PROP_EXPOSURE`` is ``V4L2_CID_EXPOSURE_ABSOLUTE`` in units of 100 us,
``CAP_PROP_AUTO_WB`` is ``V4L2_CID_AUTO_WHITE_BALANCE`` and ``CAP_PROP_WB_TEMPERATURE``
``V4L2_CID_WHITE_BALANCE_TEMPERATURE`` [K].

Timestamps. OpenCV exposes the driver's buffer timestamp as ``CAP_PROP_POS_MSEC``. UVC
drivers stamp buffers on ``CLOCK_MONOTONIC`` (Python's ``time.monotonic``) when the frame
starts arriving, which is closer to the exposure than the moment ``grab`` returns (after
USB transfer and queueing). So when that timestamp is plausible (0 to 1 s before the
grab returned), the capture time is the session time at grab minus the frame's age;
otherwise it is the session time at grab. With driver timestamps, gaps longer than 1.5
frame periods reveal frames the driver lost; they are added to ``seq`` (so they show in
``dropped_before``). Without them no such inference is made (``metadata()["timestamps"]``).

Decoding. With ``MJPG`` the driver's JPEG is taken raw (``CAP_PROP_CONVERT_RGB`` off) and
decoded by ``cv2.imdecode`` once grabbed: straight to gray (``IMREAD_GRAYSCALE``) with
``gray``, else to BGR (``IMREAD_COLOR``). The raw JPEG travels with its decoded frame
(``CameraFrame.packet``), so the session video stores it without re-encoding
(passthrough). A driver that refuses raw frames leaves the decode to OpenCV (BGR,
converted with ``cv2.cvtColor`` with ``gray``): then no JPEG is available, which is noted
and recorded (``applied["jpeg_packets"]`` false in the camera's metadata), and the session
video is recorded losslessly instead. With ``gray`` and ``YUYV`` the luma plane is taken;
otherwise BGR is converted with ``cv2.cvtColor``.

A stuck driver: ``grab`` returns after OpenCV's 10 s select timeout at the latest (then the
thread ends with a :class:`~stipi_daemon.errors.CameraError`); :meth:`close` waits at most
:data:`~.threaded.JOIN_TIMEOUT_S` for it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from stipi_daemon.cameras.base import V4L2CameraConfig
from stipi_daemon.cameras.threaded import RawFrame, ThreadedCamera
from stipi_daemon.cameras.video_file import fourcc_string
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import CameraError

__all__ = ["V4L2Camera", "decode_mode", "device_path"]

#: ``V4L2_EXPOSURE_MANUAL``, the menu value of ``V4L2_CID_EXPOSURE_AUTO`` for manual exposure.
V4L2_EXPOSURE_MANUAL = 1
#: Largest age of a driver timestamp at grab time accepted as on CLOCK_MONOTONIC [s].
MAX_DRIVER_TIMESTAMP_AGE_S = 1.0

_Mode = Literal["bgr", "bgr_to_gray", "jpeg_gray", "jpeg_bgr", "yuyv_gray"]
#: Modes that take the driver's JPEG raw (it travels with the frame as its packet).
_JPEG_MODES: frozenset[_Mode] = frozenset({"jpeg_gray", "jpeg_bgr"})


def decode_mode(fourcc: str, gray: bool, raw_accepted: Callable[[], bool]) -> _Mode:
    """How frames of pixel format ``fourcc`` are decoded (see the module docstring).

    ``raw_accepted`` asks the driver for raw frames (``CAP_PROP_CONVERT_RGB`` off) and says
    whether it agreed; it is asked only where raw frames are used: MJPG always (its JPEGs
    are the session video), YUYV with ``gray``.
    """
    if fourcc in ("MJPG", "JPEG"):
        if raw_accepted():
            return "jpeg_gray" if gray else "jpeg_bgr"
    elif fourcc == "YUYV" and gray and raw_accepted():
        return "yuyv_gray"
    return "bgr_to_gray" if gray else "bgr"


def device_path(device: str | int) -> str:
    """``/dev/videoN`` for an index, the path itself otherwise."""
    return f"/dev/video{device}" if isinstance(device, int) else device


@dataclass
class _Handle:
    cap: cv2.VideoCapture
    mode: _Mode
    fps: float


class V4L2Camera(ThreadedCamera[_Handle]):
    """A V4L2 camera with locked exposure and white balance.

    Parameters
    ----------
    config : V4L2CameraConfig
        Device and requested settings.
    clock : SessionClock
        Session clock (speed 1 for a real camera).
    """

    def __init__(self, config: V4L2CameraConfig, clock: SessionClock) -> None:
        super().__init__(clock, capacity=config.queue_frames, drop_oldest=True, paced=False)
        self.config = config
        self.path = device_path(config.device)
        self._applied: dict[str, Any] = {}
        self._seq_next = 0
        self._prev_t_s: float | None = None
        self._driver_timestamps: bool | None = None

    @classmethod
    def from_config(cls, config: V4L2CameraConfig, clock: SessionClock) -> V4L2Camera:
        return cls(config, clock)

    @property
    def name(self) -> str:
        return f"V4L2 camera {self.path}"

    @property
    def nominal_fps(self) -> float:
        fps = self._applied.get("fps")
        return float(fps) if isinstance(fps, float) and fps > 0 else self.config.fps

    def applied_settings(self) -> dict[str, Any]:
        """What the driver accepted at the last open (keys as in the config, plus
        ``auto_exposure`` and ``auto_wb`` as read back); empty before the first open."""
        return dict(self._applied)

    def _metadata(self) -> dict[str, Any]:
        ts = {None: "unknown", True: "driver (CLOCK_MONOTONIC)", False: "session clock at grab"}
        return {
            "kind": "v4l2",
            "device": self.path,
            "requested": self.config.model_dump(mode="json"),
            "applied": self.applied_settings(),
            "timestamps": ts[self._driver_timestamps],
        }

    # -- source hooks -----------------------------------------------------------------------

    def _open_source(self) -> _Handle:
        path = self.path
        if not Path(path).exists():
            raise CameraError(f"camera {path}: no such device")
        if not os.access(path, os.R_OK | os.W_OK):
            raise CameraError(f"camera {path}: permission denied (is the user in group 'video'?)")
        cap = cv2.VideoCapture(path, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"camera {path}: cannot be opened as a V4L2 capture device")
        try:
            mode = self._configure(cap)
        except BaseException:
            cap.release()
            raise
        return _Handle(cap, mode, self.nominal_fps)

    def _configure(self, cap: cv2.VideoCapture) -> _Mode:
        c = self.config
        cap.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*c.fourcc)))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(c.width))
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(c.height))
        cap.set(cv2.CAP_PROP_FPS, float(c.fps))
        cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, float(V4L2_EXPOSURE_MANUAL))
        cap.set(cv2.CAP_PROP_EXPOSURE, c.exposure_ms * 10.0)  # unit 100 us
        if c.white_balance_k is not None:
            cap.set(cv2.CAP_PROP_AUTO_WB, 0.0)
            cap.set(cv2.CAP_PROP_WB_TEMPERATURE, float(c.white_balance_k))
        fourcc = fourcc_string(cap.get(cv2.CAP_PROP_FOURCC))
        mode = decode_mode(fourcc, c.gray, lambda: bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0.0)))
        if fourcc in ("MJPG", "JPEG") and mode not in _JPEG_MODES:
            self._note(
                f"camera {self.path}: the driver refused raw MJPG frames (CAP_PROP_CONVERT_RGB "
                "off); OpenCV decodes them, so the camera's JPEGs are not available and the "
                "session video is recorded losslessly"
            )
        applied: dict[str, Any] = {
            "fourcc": fourcc,
            "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": float(cap.get(cv2.CAP_PROP_FPS)),
            "auto_exposure": cap.get(cv2.CAP_PROP_AUTO_EXPOSURE),
            "exposure_ms": cap.get(cv2.CAP_PROP_EXPOSURE) / 10.0,
        }
        if c.white_balance_k is not None:
            applied["auto_wb"] = cap.get(cv2.CAP_PROP_AUTO_WB)
            applied["white_balance_k"] = int(cap.get(cv2.CAP_PROP_WB_TEMPERATURE))
        applied["decode"] = mode
        applied["jpeg_packets"] = mode in _JPEG_MODES  # the camera's JPEGs travel with frames
        self._applied = applied
        for key, want, tol in (
            ("fourcc", c.fourcc, None),
            ("width", c.width, None),
            ("height", c.height, None),
            ("fps", c.fps, 0.01 * c.fps),
            ("auto_exposure", float(V4L2_EXPOSURE_MANUAL), None),
            ("exposure_ms", c.exposure_ms, 0.1),
            ("auto_wb", 0.0, None),
            ("white_balance_k", c.white_balance_k, 50),
        ):
            if key not in applied:
                continue
            got = applied[key]
            if tol is None or not isinstance(want, int | float):
                same = got == want
            else:
                same = abs(float(got) - want) <= tol
            if not same:
                self._note(f"camera {self.path}: {key} requested {want}, driver applied {got}")
        return mode

    def _read(self, h: _Handle) -> RawFrame | None:
        while True:
            frame = self._read_one(h)
            if frame is not None:
                return frame

    def _read_one(self, h: _Handle) -> RawFrame | None:
        """One grabbed frame; None for a corrupt one (skipped: its ``seq`` is lost)."""
        if not h.cap.grab():
            raise CameraError(f"camera {self.path}: stopped delivering frames (grab failed)")
        wall_s = time.monotonic()
        now_s = self._clock.now()
        ok, data = h.cap.retrieve()
        if not ok or data is None:
            raise CameraError(f"camera {self.path}: frame could not be retrieved")
        ts_ms = float(h.cap.get(cv2.CAP_PROP_POS_MSEC))
        age_s = wall_s - ts_ms / 1000.0
        driver_ts = ts_ms > 0.0 and 0.0 <= age_s <= MAX_DRIVER_TIMESTAMP_AGE_S
        self._driver_timestamps = driver_ts
        t_s = now_s - age_s * self._clock.speed if driver_ts else now_s
        raw = np.asarray(data, dtype=np.uint8)
        image = self._decode(h.mode, raw)
        missing = 0
        if driver_ts and self._prev_t_s is not None and h.fps > 0.0:
            period_s = self._clock.speed / h.fps  # one frame period in session time
            missing = max(0, round((t_s - self._prev_t_s) / period_s) - 1)
        self._prev_t_s = t_s
        seq = self._seq_next + missing
        self._seq_next = seq + 1
        if image is None:
            self._note(f"camera {self.path}: corrupt frames from the driver were skipped")
            return None
        packet = raw.tobytes() if h.mode in _JPEG_MODES else None  # the JPEG as received
        return RawFrame(seq, t_s, image, packet)

    def _decode(self, mode: _Mode, data: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8] | None:
        if mode in _JPEG_MODES:
            flag = cv2.IMREAD_GRAYSCALE if mode == "jpeg_gray" else cv2.IMREAD_COLOR
            img = cv2.imdecode(data.reshape(-1), flag)
            return None if img is None else np.asarray(img, dtype=np.uint8)
        if mode == "yuyv_gray":
            return np.ascontiguousarray(data[:, :, 0]) if data.ndim == 3 else data
        if mode == "bgr_to_gray" and data.ndim == 3:
            return np.asarray(cv2.cvtColor(data, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        return data

    def _close_source(self, h: _Handle) -> None:
        h.cap.release()
