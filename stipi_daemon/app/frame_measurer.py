"""The camera side of the acquisition: each frame measured and stored where it arrives.

:class:`FrameMeasurer` is the camera's ``frame_hook``
(:attr:`~stipi_daemon.cameras.threaded.ThreadedCamera.frame_hook`): in the camera's capture
thread, as a frame is delivered, it counts S_k (Eqs. 1-2), stores the frame in the session
video (:class:`~stipi_daemon.storage.video.VideoRecorder`) and adds its ``frames`` row,
committed at once (at most every :data:`COMMIT_SPACING_WALL_S` of wall time). A frame's row
and its video frame are thus made together, in one place, and on disk about a millisecond
after the frame is measured, whatever the event loop is doing; the loop receives a small
:class:`FrameResult` (S_k, flags, times) for the measurement and offers the image to the
representative-frame keeper (:mod:`stipi_daemon.measurement.representative_frames`).

A frame due more than ``skip_late_s`` ago when it is delivered is neither measured nor
stored: a :class:`LateFrame`, which the loop stores as a gap (reason ``processing_behind``).
A frame whose shape (size, gray or colour) is not the session's first frame's is neither
measured nor stored either: a :class:`ResizedFrame`, which ends the run with a fault (S_k
counts pixels, and the ROI, the threshold and the calibration are those of the first
frame's size; a video stream cannot change its frame size either). The first frame itself
must have the size the camera reported on opening (``frame_size_px``), which the ROI and
the calibration were checked against (:mod:`stipi_daemon.app.devices`): a driver or a file
header that states one size and delivers frames of another is a :class:`ResizedFrame` too.
Once the measurement has ended (:meth:`FrameMeasurer.stop_storing`) frames are no longer
stored, and once its end time is known (:meth:`FrameMeasurer.store_until`: the end of the
recovery window, known at the release; the end the analysis starts at) a frame captured
after it is not stored either, nor offered as a representative frame: the session's frames
are those of the measurement, however long the final analysis keeps the loop busy and
however far the capture thread runs ahead of the loop. When storing fails (a full disk: the
writer's or the video's error), nothing more is stored and the error travels with the
frame's result to the loop, which stops the run as for any storage failure. A video that
fails (any FFmpeg error) stops the same way: the recorder hands its error to the writer
(:meth:`~stipi_daemon.storage.video.VideoRecorder.record`), so the measurement never goes on
without its video; a frame's row is stored once, whatever fails after it.

All times are on the session clock [s] unless named ``_wall_``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, RectROI
from stipi_daemon.cameras import CameraFrame
from stipi_daemon.cameras.threaded import RawFrame
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import SessionError
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.storage.video import VideoRecorder
from stipi_daemon.storage.writer import SessionWriter

__all__ = [
    "COMMIT_SPACING_WALL_S",
    "FrameMeasurer",
    "FrameResult",
    "LateFrame",
    "ResizedFrame",
    "describe_shape",
]

#: Shortest wall time between two commits made for frame rows [s]. In real time (60 fps: a
#: frame every 16.7 ms) each frame's row is committed as soon as it is measured; faster (an
#: accelerated demo) the frames of up to this long share one commit. The writer's own commit
#: interval (``storage.commit_interval_s``) bounds every row anyway.
COMMIT_SPACING_WALL_S = 0.005


@dataclass(frozen=True, slots=True)
class FrameResult:
    """One frame's measurement, as the camera pump queues it (no image).

    Attributes
    ----------
    seq : int
        The camera's frame number.
    t_capture_s, t_processed_s : float
        Capture time and the time the frame was measured and stored, on the session
        clock [s].
    s_k : int
        S_k, Eq. (2) [px].
    flags : tuple of str
        The frame's imaging flags (e.g. saturation), sorted.
    dropped_before : int
        Frames the camera dropped just before this one.
    error : SessionError or None
        Storing failed (its row or video frame is missing): the loop stops the run.
    stored : bool
        Its row and video frame were stored (False: captured after the measurement's end).
    """

    seq: int
    t_capture_s: float
    t_processed_s: float
    s_k: int
    flags: tuple[str, ...]
    dropped_before: int
    error: SessionError | None = None
    stored: bool = True


@dataclass(frozen=True, slots=True)
class LateFrame:
    """A frame that arrived too late to be measured: stored as a gap, never fed.

    Attributes
    ----------
    seq : int
        The camera's frame number.
    t_capture_s : float
        Capture time on the session clock [s].
    lag_s : float
        Session time when it was delivered minus its capture time [s].
    dropped_before : int
        Frames the camera dropped just before this one.
    """

    seq: int
    t_capture_s: float
    lag_s: float
    dropped_before: int


@dataclass(frozen=True, slots=True)
class ResizedFrame:
    """A frame of another shape than the session's first frame: not measured, not stored;
    the acquisition ends the run with a fault (see the module docstring).

    Attributes
    ----------
    seq, t_capture_s, dropped_before
        As for a :class:`LateFrame`.
    shape, session_shape : tuple of int
        This frame's array shape and the session's (its first frame's): ``(H, W)`` gray or
        ``(H, W, C)`` [px].
    reported : bool
        The session has no frame yet and ``session_shape`` is ``(H, W)`` of the size the
        camera reported on opening, which this (first) frame does not have.
    """

    seq: int
    t_capture_s: float
    shape: tuple[int, ...]
    session_shape: tuple[int, ...]
    dropped_before: int
    reported: bool = False

    def fault_line(self) -> str:
        """The run's fault line: which frame, both sizes, and why the run stopped."""
        if self.reported:
            h, w = self.session_shape[:2]
            return (
                f"camera: frame {self.seq} is {describe_shape(self.shape)}, but the camera "
                f"reported {w}x{h} px frames on opening, the size the ROI and the calibration "
                "were checked against; the measurement stopped there"
            )
        return (
            f"camera: frame {self.seq} is {describe_shape(self.shape)}, the session's frames "
            f"are {describe_shape(self.session_shape)} (S_k, the ROI and the calibration are "
            "for that size); the measurement stopped there"
        )


def describe_shape(shape: tuple[int, ...]) -> str:
    """A frame's shape as a person reads it: ``640x480 gray``, ``640x480 BGR``."""
    layout = "gray" if len(shape) == 2 else {2: "YUYV", 3: "BGR", 4: "BGRA"}.get(shape[2], "")
    return f"{shape[1]}x{shape[0]} {layout or f'{shape[2]} channels'}"


@dataclass(frozen=True, slots=True)
class _Captured:
    """What :meth:`FrameMeasurer.on_capture` made of a frame: S_k [px] and its sorted flags
    (or, late, its lag [s] and no measurement; or, of another shape than the session's, the
    session's shape and no measurement), the session time it was done [s], why storing
    it failed, if it did, and whether it was stored (not after the measurement's end)."""

    s_k: int
    flags: tuple[str, ...]
    late_lag_s: float | None
    t_done_s: float
    error: SessionError | None = None
    resized_from: tuple[int, ...] | None = None
    stored: bool = False
    resized_reported: bool = False


class FrameMeasurer:
    """Measures and stores each frame where it arrives (see the module docstring).

    Parameters
    ----------
    clock : SessionClock
        Session clock (the processing time stamp).
    threshold_p : int
        Threshold p of Eq. (1) [8-bit intensity].
    roi : CircleROI or RectROI or None
        Where S_k is counted (None: the whole frame).
    saturation_limit_fraction : float
        Saturated fraction of the ROI above which a frame is flagged.
    keeper : RepresentativeFrames
        Chooses the raw frames the session keeps.
    pipeline : MeasurementPipeline
        The live measurement, whose phase and times the keeper's choice depends on.
    skip_late_s : float or None
        A frame delivered more than this after its capture [s of session time] is not
        measured: a :class:`LateFrame` instead (None: every frame is measured).
    writer : SessionWriter or None
        Receives each measured frame's ``frames`` row (None: rows are not stored).
    frame_size_px : tuple of int or None
        ``(width, height)`` the camera reported on opening [px], which the first frame
        must have (None: it reported none; the first frame sets the session's size).
    """

    #: Stores each measured frame in the session video (set by the daemon; None: no video).
    recorder: VideoRecorder | None = None
    #: The camera waits for the video's encoder instead of leaving a frame out of the video
    #: (set by the daemon for a source that waits for its consumer: a file, the simulator).
    wait_for_encoder: bool = False
    #: Given each measured frame ``(seq, t_capture_s, s_k, image)`` on the loop, the image
    #: by reference (the live view keeps the newest; None: no view).
    preview: Callable[[int, float, int, npt.NDArray[np.uint8]], None] | None = None

    def __init__(
        self,
        clock: SessionClock,
        threshold_p: int,
        roi: CircleROI | RectROI | None,
        saturation_limit_fraction: float,
        keeper: RepresentativeFrames,
        pipeline: MeasurementPipeline,
        skip_late_s: float | None = None,
        writer: SessionWriter | None = None,
        frame_size_px: tuple[int, int] | None = None,
    ) -> None:
        self._clock = clock
        self._reported_hw = None if frame_size_px is None else (frame_size_px[1], frame_size_px[0])
        self._threshold_p = threshold_p
        self._roi = roi
        self._saturation_limit_fraction = saturation_limit_fraction
        self._keeper = keeper
        self._pipeline = pipeline
        self._skip_late_s = skip_late_s
        self._writer = writer
        # the capture thread and the loop each have a processor (they keep scratch buffers)
        self._processors: dict[bool, FrameProcessor] = {}
        self._lock = threading.Lock()  # storing, against store_until
        self._store_until_s = math.inf  # frames captured after it are not stored [s]
        self._error: SessionError | None = None
        self._last_commit_wall_s = float("-inf")
        #: Shape of the session's frames: its first frame's (None before it).
        self.shape: tuple[int, ...] | None = None
        #: Frames whose rows were stored [-] (also those stored after the loop's last look).
        self.stored = 0

    def stop_storing(self) -> None:
        """Store no more frames (the measurement has ended); a frame being stored right
        now is stored before this returns."""
        self.store_until(-math.inf)

    def store_until(self, t_end_s: float) -> None:
        """Store no frame captured after session time ``t_end_s`` [s] (the measurement's
        end, once known; a later call can only bring it earlier): such a frame is measured
        for the loop, but neither stored nor offered as a representative frame. A frame
        being stored right now is stored before this returns."""
        with self._lock:
            self._store_until_s = min(self._store_until_s, t_end_s)

    def on_capture(self, raw: RawFrame) -> _Captured:
        """The camera's ``frame_hook``, run in its capture thread as a frame is delivered:
        S_k and flags measured, the frame stored (the camera waits for the video's encoder
        when :attr:`wait_for_encoder`)."""
        return self._measure(raw.seq, raw.t_capture_s, raw.image, raw.packet, in_thread=True)

    def __call__(self, ev: object) -> object:
        """A :class:`FrameResult` for a camera frame (a :class:`LateFrame` when it is too
        late to measure); other camera events as they are. A frame the capture thread did
        not measure (no hook, or the hook failed) is measured and stored here, on the loop
        (which never waits for the video's encoder)."""
        if not isinstance(ev, CameraFrame):
            return ev
        captured = ev.measured
        if not isinstance(captured, _Captured):
            captured = self._measure(ev.seq, ev.t_capture_s, ev.image, ev.packet, in_thread=False)
        if captured.resized_from is not None:
            shape = tuple(ev.image.shape)
            return ResizedFrame(
                ev.seq,
                ev.t_capture_s,
                shape,
                captured.resized_from,
                ev.dropped_before,
                captured.resized_reported,
            )
        if captured.late_lag_s is not None:
            return LateFrame(ev.seq, ev.t_capture_s, captured.late_lag_s, ev.dropped_before)
        s_k = captured.s_k
        st = self._pipeline.state
        if self.preview is not None:
            self.preview(ev.seq, ev.t_capture_s, s_k, ev.image)
        if captured.stored:  # a representative frame is one of the session's
            self._keeper.offer(
                ev.seq, ev.t_capture_s, ev.image, s_k, st.phase, st.t_pit_start_s, st.t_release_s
            )
        return FrameResult(
            ev.seq,
            ev.t_capture_s,
            captured.t_done_s,
            s_k,
            captured.flags,
            ev.dropped_before,
            captured.error,
            captured.stored,
        )

    def _measure(
        self,
        seq: int,
        t_capture_s: float,
        image: npt.NDArray[np.uint8],
        packet: bytes | None,
        *,
        in_thread: bool,
    ) -> _Captured:
        now = self._clock.now()
        if self.shape is None:
            hw = self._reported_hw
            if hw is not None and image.shape[:2] != hw:  # not the size the checks were for
                return _Captured(0, (), None, now, resized_from=hw, resized_reported=True)
            self.shape = image.shape
        elif image.shape != self.shape:  # S_k of another size: not the session's quantity
            return _Captured(0, (), None, now, resized_from=self.shape)
        lag_s = now - t_capture_s
        if self._skip_late_s is not None and lag_s > self._skip_late_s:
            return _Captured(0, (), lag_s, now)
        proc = self._processors.get(in_thread)
        if proc is None or proc.frame_shape != image.shape:
            proc = self._processors[in_thread] = FrameProcessor(
                image.shape,
                self._threshold_p,
                self._roi,
                saturation_limit_fraction=self._saturation_limit_fraction,
            )
        m = proc.measure(image)
        s_k, flags = int(m.s_k_px), tuple(sorted(m.flags))
        t_done = self._clock.now()
        error = None
        with self._lock:
            stored = t_capture_s <= self._store_until_s
            if stored:
                row = (seq, t_capture_s, t_done, s_k, flags)
                error = self._store(row, image, packet, in_thread)
        return _Captured(s_k, flags, None, t_done, error, stored=stored)

    def _store(
        self,
        row: tuple[int, float, float, int, tuple[str, ...]],
        image: npt.NDArray[np.uint8],
        packet: bytes | None,
        in_thread: bool,
    ) -> SessionError | None:
        """The frame into the session video and its ``frames`` row ``(seq, t_capture_s,
        t_host_s, s_k, flags)`` into the session, committed (at most every
        :data:`COMMIT_SPACING_WALL_S`); the storage error, if storing failed now or before
        (then nothing more is stored).

        Never raises: once the row is added, a failure of any kind is this frame's storage
        error (the run stops), so the frame is never measured and stored again (the camera
        measures a frame again on the loop when its hook raised: a second ``frames`` row of
        the same ``seq``). The video's own failures (any FFmpeg error) stop the recorder,
        which hands them to the writer: the commit below raises them."""
        if self._error is not None:
            return self._error
        try:
            # the row first: a writer that has failed (a full disk) takes neither
            if self._writer is not None:
                self._writer.add_frames([row])
                self.stored += 1
            if self.recorder is not None:  # the session video: the frame S_k was counted on
                wait = in_thread and self.wait_for_encoder
                self.recorder.record(row[0], row[1], image, packet, wait=wait)
            if self._writer is not None:
                now_wall = time.monotonic()
                # a recorder that stopped has handed its error to the writer: a commit now
                # raises it, so it travels with this very frame
                stopped = self.recorder is not None and self.recorder.failed is not None
                if stopped or now_wall - self._last_commit_wall_s >= COMMIT_SPACING_WALL_S:
                    self._writer.commit()
                    self._last_commit_wall_s = now_wall
        except SessionError as exc:
            self._error = exc
        except Exception as exc:  # a bug: stop the run rather than store the frame twice
            self._error = SessionError(
                f"storing frame {row[0]} failed: {type(exc).__name__}: {exc}"
            )
        return self._error
