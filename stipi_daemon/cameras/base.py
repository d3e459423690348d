"""What every camera gives the daemon: frames on the session clock, events, stats, config.

This module owns the camera-facing types shared by all sources: :class:`CameraFrame` (one
image with its sequence number and session-clock capture time), the stream events
:class:`CameraStalled` and :class:`CameraRecovered`, :class:`CameraStats` (counters and the
measured frame rate over a sliding window), the :class:`Camera` protocol every source
implements, and the pydantic config models of the three sources (``kind`` = ``v4l2``,
``file``, ``simulator``). It does no I/O: opening devices and files is the job of the
source modules (:mod:`.v4l2`, :mod:`.video_file`, :mod:`.simulator`), stall detection and
reopening that of :mod:`.stream`.

Sequence numbers and drops
--------------------------
``seq`` is the source's own frame number (file: frame index in the file; simulator: the
scene's frame index; V4L2: frames the driver delivered, plus frames inferred missing from
gaps in the driver's timestamps). Consecutive frames of the source have consecutive
``seq``; ``dropped_before`` is the number of frames lost just before this one, whatever lost
them (the source, the bounded hand-off queue when the consumer lags, a stall).
"""

from __future__ import annotations

from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "DEFAULT_FPS_WINDOW_S",
    "Camera",
    "CameraEvent",
    "CameraFrame",
    "CameraRecovered",
    "CameraStalled",
    "CameraStats",
    "SimulatorCameraConfig",
    "V4L2CameraConfig",
    "VideoFileCameraConfig",
    "av_frame_pixels",
]

#: Length of the sliding window over which :class:`CameraStats` measures the frame rate,
#: in session time [s].
DEFAULT_FPS_WINDOW_S = 2.0


# --------------------------------------------------------------------------------------------
# Frames and events
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """One camera frame.

    Attributes
    ----------
    seq : int
        The source's frame number (see the module docstring), >= 0, increasing.
    t_capture_s : float
        Capture time on the session clock [s].
    image : numpy.ndarray
        ``uint8`` image, gray ``(H, W)`` or BGR ``(H, W, 3)``; owned by the receiver.
    dropped_before : int
        Frames lost between the previous delivered frame and this one [-], >= 0.
    packet : bytes or None
        The frame as the source encoded it (an MJPG camera's or file's complete JPEG),
        which ``image`` was decoded from; None for raw sources. The session video stores
        it as it is (:mod:`stipi_daemon.storage.video`, passthrough).
    measured : object
        What the camera's ``frame_hook`` computed from ``image`` in the capture thread
        (the daemon's S_k), or None.
    """

    seq: int
    t_capture_s: float
    image: npt.NDArray[np.uint8]
    dropped_before: int
    packet: bytes | None = None
    measured: object = None


@dataclass(frozen=True, slots=True)
class CameraStalled:
    """No frame arrived within the stall timeout; the stream is about to reopen the camera.

    Attributes
    ----------
    t_s : float
        Session time at which the stall was detected [s].
    last_seq : int
        ``seq`` of the last frame delivered before the stall (-1: none yet).
    silent_s : float
        Session time since the last frame (or since the camera was opened) [s].
    reason : str
        ``"timeout"`` or the one-line error the source raised.
    """

    t_s: float
    last_seq: int
    silent_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class CameraRecovered:
    """The camera delivers again after a stall; the next event is its first frame.

    Attributes
    ----------
    t_s : float
        Session time of recovery [s].
    attempts : int
        Reopen attempts it took (1 = the first reopen worked).
    outage_s : float
        Session time from the last frame before the stall to this recovery [s].
    """

    t_s: float
    attempts: int
    outage_s: float


CameraEvent = CameraFrame | CameraStalled | CameraRecovered
"""What :class:`~stipi_daemon.cameras.stream.CameraStream` yields."""


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------


@dataclass
class CameraStats:
    """Counters of one camera over its lifetime (they survive close and reopen).

    Attributes
    ----------
    frames : int
        Frames delivered to the consumer.
    dropped : int
        Frames lost (sum of ``dropped_before``), whatever the cause.
    queue_dropped : int
        Of ``dropped``: frames discarded by the bounded hand-off queue because the consumer
        lagged (drop-oldest policy).
    stalls : int
        Stalls detected by the stream.
    reopens : int
        Successful reopens after a stall.
    max_lag_s : float
        Largest delay between a frame's capture time and its delivery, in session time [s].
    window_s : float
        Sliding window of :meth:`fps` [s].
    """

    frames: int = 0
    dropped: int = 0
    queue_dropped: int = 0
    stalls: int = 0
    reopens: int = 0
    max_lag_s: float = 0.0
    window_s: float = DEFAULT_FPS_WINDOW_S
    _times: deque[float] = field(default_factory=deque, repr=False)

    def record(self, frame: CameraFrame, delivered_at_s: float) -> None:
        """Count a delivered frame (capture and delivery times on the session clock [s])."""
        self.frames += 1
        self.dropped += frame.dropped_before
        self.max_lag_s = max(self.max_lag_s, delivered_at_s - frame.t_capture_s)
        self._times.append(frame.t_capture_s)
        while self._times and self._times[0] < frame.t_capture_s - self.window_s:
            self._times.popleft()

    def fps(self) -> float:
        """Measured frame rate over the last ``window_s`` of capture times [1/s].

        NaN until two frames are in the window.
        """
        if len(self._times) < 2 or self._times[-1] <= self._times[0]:
            return float("nan")
        return (len(self._times) - 1) / (self._times[-1] - self._times[0])

    def as_dict(self) -> dict[str, Any]:
        """The counters and the measured fps, for logs and session metadata."""
        return {
            "frames": self.frames,
            "dropped": self.dropped,
            "queue_dropped": self.queue_dropped,
            "stalls": self.stalls,
            "reopens": self.reopens,
            "max_lag_s": self.max_lag_s,
            "fps": self.fps(),
        }


# --------------------------------------------------------------------------------------------
# The protocol every source implements
# --------------------------------------------------------------------------------------------


@runtime_checkable
class Camera(Protocol):
    """A source of :class:`CameraFrame`.

    ``open()`` raises :class:`~stipi_daemon.errors.CameraError` (one line naming the device
    or file) when the source cannot be used. ``frames()`` yields frames until the source
    ends (a video file without ``loop``) and raises ``CameraError`` when a live source fails;
    it may be called again after a close and reopen. ``close()`` is idempotent and never
    waits for a stuck driver longer than a bounded time.
    """

    @property
    def name(self) -> str:
        """The device or file, for messages (e.g. ``"V4L2 camera /dev/video0"``)."""
        ...

    @property
    def nominal_fps(self) -> float:
        """The frame rate the source is set to deliver [1/s] (known once opened)."""
        ...

    @property
    def stats(self) -> CameraStats:
        """Counters over the camera's lifetime."""
        ...

    def metadata(self) -> dict[str, Any]:
        """Settings requested and applied, notes (truncation, mismatches), for the session."""
        ...

    async def open(self) -> None:
        """Open (or reopen) the source and start capturing."""
        ...

    async def close(self) -> None:
        """Stop capturing and release the source."""
        ...

    def frames(self) -> AsyncIterator[CameraFrame]:
        """The frames, in capture order."""
        ...


# --------------------------------------------------------------------------------------------
# Config models
# --------------------------------------------------------------------------------------------


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class V4L2CameraConfig(_Model):
    """A UVC/V4L2 camera read through OpenCV, with exposure and white balance locked.

    Attributes
    ----------
    kind : "v4l2"
    device : str or int
        Device path (``/dev/video0``) or index (0 = ``/dev/video0``).
    width, height : int
        Requested frame size [px].
    fps : float
        Requested frame rate [1/s].
    fourcc : str
        Requested pixel format, four characters (``MJPG``, ``YUYV``, ``GREY``).
    exposure_ms : float
        Exposure time [ms]; auto exposure is switched off. Required: a probe's images
        (and Eq. (1)'s threshold p) are only comparable at a fixed exposure.
    white_balance_k : int or None
        White-balance temperature [K]; auto white balance is switched off. ``None``: leave
        white balance alone (monochrome cameras have none).
    gray : bool
        Deliver ``(H, W)`` gray frames (MJPG decoded straight to gray, YUYV's luma plane).
    queue_frames : int
        Capacity of the hand-off queue between the capture thread and the consumer; when
        full, the oldest frame is dropped (and counted).
    """

    kind: Literal["v4l2"] = "v4l2"
    device: str | int = "/dev/video0"
    width: int = Field(640, ge=16, le=7680)
    height: int = Field(480, ge=16, le=4320)
    fps: float = Field(30.0, gt=0.0, le=1000.0)
    fourcc: str = Field("MJPG", pattern=r"^[ -~]{4}$")
    exposure_ms: float = Field(gt=0.0, le=10_000.0)
    white_balance_k: int | None = Field(4600, ge=1000, le=15000)
    gray: bool = True
    queue_frames: int = Field(4, ge=1, le=256)


class VideoFileCameraConfig(_Model):
    """A recorded video (the simulator's video.mkv, a session's stored video) as a camera.

    Attributes
    ----------
    kind : "file"
    path : Path
        Video file.
    loop : bool
        Start again at ``start_s`` when the file ends (frame numbers keep increasing).
    pace : bool
        Deliver frame k at session time ``t0 + k / fps - start_s`` (the file's frame rate on
        the session clock); ``False``: as fast as they decode, with the same timestamps.
    start_s : float
        Position in the file to start at [s] (frame ``round(start_s * fps)``).
    gray : bool
        Deliver ``(H, W)`` gray frames (an MJPG file is decoded straight to gray).
    """

    kind: Literal["file"] = "file"
    path: Path
    loop: bool = False
    pace: bool = True
    start_s: float = Field(0.0, ge=0.0)
    gray: bool = True


class SimulatorCameraConfig(_Model):
    """The scene simulator's rendered frames as a camera, paced on the session clock.

    Attributes
    ----------
    kind : "simulator"
    scene : Path
        Scene YAML file.
    seed : int or None
        Random seed; ``None`` uses the scene's.
    """

    kind: Literal["simulator"] = "simulator"
    scene: Path
    seed: int | None = None


def av_frame_pixels(frame: Any) -> npt.NDArray[np.uint8]:
    """A decoded PyAV video frame's pixels: ``gray`` as ``(H, W)``, FFV1's BGR (``bgr0``,
    ``bgra``: 4 bytes a pixel) as ``(H, W, 4)``, both views of the frame's plane without
    its row padding; any other format converted to BGR ``(H, W, 3)`` by PyAV. Read in place
    because PyAV's ``to_ndarray(format=...)`` makes a scaler per frame, which cost more than
    the decode (0.6 ms per 160x120 frame, two threads started each). The views share the
    frame's buffer: copy what outlives it."""
    fmt = frame.format.name
    if fmt not in ("gray", "bgr0", "bgra"):
        return np.asarray(frame.to_ndarray(format="bgr24"), dtype=np.uint8)
    plane, h, w = frame.planes[0], frame.height, frame.width
    rows = np.frombuffer(memoryview(plane), np.uint8).reshape(-1, plane.line_size)[:h]
    return rows[:, :w] if fmt == "gray" else rows[:, : 4 * w].reshape(h, w, 4)
