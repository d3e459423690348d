"""A session's video: the camera stream as received, in ``video.mkv``, and reading it back.

This module owns recording the frames the daemon measured into the session's Matroska file
with PyAV (FFmpeg's muxer and codecs) and reading them back. :class:`VideoRecorder` writes
one video stream in one of two ways:

* ``passthrough``: a frame that carries its encoded packet (an MJPG camera's JPEG, see
  :attr:`~stipi_daemon.cameras.base.CameraFrame.packet`) is muxed as it came, without
  decoding or re-encoding (codec ``mjpeg``, every frame a keyframe). Frames without a
  packet (raw, YUYV, gray cameras; the simulator) are recorded losslessly instead;
* ``lossless``: the decoded image the daemon counted S_k on is encoded with FFV1 (level 3,
  every frame intra, CRC per slice), gray as ``gray``, BGR as ``bgr0`` (the same bytes padded
  to 32 bits); optionally only a rectangle of it (the gray bounding box of the ROI).

FFV1 frames are encoded in a thread of their own (PyAV releases the GIL while FFmpeg
encodes; FFmpeg starts no threads of its own, :data:`ENCODER_THREADS`) at a lower CPU
priority (:data:`ENCODER_NICE`), at most :data:`ENCODER_QUEUE_FRAMES` behind. A frame
arriving when the encoder lags further is left out of the video and counted, so that
recording never slows a live camera's measurement; a source that can wait (a video file,
the simulator) waits for the encoder instead (``record(..., wait=True)``), so its video
holds every frame. Every stored frame is tied to its ``frames`` row by a ``video_frames``
row (``seq, frame_index, pts_ms, t_capture_host_s``), made as the frame is muxed and handed
to the session writer in batches, once the oldest waiting row is :data:`ROW_BATCH_FRACTION`
of its commit interval old or :data:`ROW_BATCH_MAX_FRAMES` wait (a second table in every
frame's commit cost about 10 us per frame, docs/performance.md); a killed recording's video
may therefore hold a few frames more than rows (at most :data:`UNINDEXED_FRAMES_MAX`), and
:meth:`VideoRecorder.close` hands over the rest. The muxer flushes its I/O after every
packet (``flush_packets=1``), so a process killed at any moment leaves a file that FFmpeg
opens and plays up to the newest frame but one (the muxer holds the newest block until the
next arrives), within one commit interval of the newest committed ``frames`` row. When
writing fails (disk full, or any other FFmpeg error), the recorder stops, closes the file
as far as it can, records a ``video_stopped`` event and hands the error to the session
writer (:meth:`~.writer.SessionWriter.fail`), so rows and video stop together.

Reading: :func:`probe_video` (codec, size, frame count; no check), :func:`check_video`
(damage: every cluster's CRC-32, every packet demuxed, optionally every frame decoded),
:func:`iter_video_frames` (every frame in file order, sound with its image or damaged
with the reason: nothing skipped), :func:`iter_video_images` (the images exactly as the
daemon counted them: JPEG packets decoded by ``cv2.imdecode`` as the camera did, FFV1
frames decoded to the recorded pixel layout; :class:`VideoDamageError` at a damaged
frame), :func:`read_video_image`. It computes nothing about the images.
"""

from __future__ import annotations

import logging
import math
import mmap
import os
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Literal

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import SessionError
from stipi_daemon.storage.ordered_workers import OrderedWorkers

if TYPE_CHECKING:
    from stipi_daemon.storage.writer import SessionWriter

__all__ = [
    "ROW_BATCH_MAX_FRAMES",
    "UNINDEXED_FRAMES_MAX",
    "VIDEO_MODES",
    "StoredFrame",
    "VideoCheck",
    "VideoDamageError",
    "VideoInfo",
    "VideoMode",
    "VideoRecorder",
    "check_video",
    "iter_video_frames",
    "iter_video_images",
    "open_video_file",
    "probe_video",
    "read_video_image",
    "write_video_frame",
]

_log = logging.getLogger(__name__)

VideoMode = Literal["passthrough", "lossless", "off"]
#: The ``storage.video`` settings.
VIDEO_MODES: Final[tuple[VideoMode, ...]] = ("passthrough", "lossless", "off")

#: Time base of the stored presentation times: milliseconds (Matroska's own unit).
PTS_TIME_BASE: Final = Fraction(1, 1000)
#: Muxer options: flush the file after every packet (the crash-survival argument), and a
#: cluster of its own for every frame (``cluster_size_limit`` 1 B: FFmpeg's muxer holds a
#: cluster in memory until it ends, by default after 4 kB, so a killed recording of small
#: frames lost several; and the CRC-32 it writes per cluster then names one frame, 20-odd
#: bytes per frame, :func:`check_video`).
MUXER_OPTIONS: Final = {"flush_packets": "1", "cluster_size_limit": "1"}
#: Frames waiting for the FFV1 encoder thread at most [-]. At 60 fps they span 133 ms, less
#: than the default commit interval. When it is full the frame is left out of the video
#: (counted): recording never slows the measurement down.
ENCODER_QUEUE_FRAMES: Final = 8
#: Longest a caller that can wait (``record(wait=True)``) waits for the encoders to take a
#: frame [s of wall time] before leaving it out. The wait is part of the frame's hand-over,
#: which never counts towards a camera stall (``ThreadedCamera.source_silent_s``); a machine
#: that cannot keep up falls behind (the acquisition's lag) and, past this, leaves frames
#: out of the video, counted.
ENCODER_WAIT_MAX_S: Final = 0.1
#: ``video_frames`` rows are handed to the session writer once the oldest one waiting is this
#: fraction of its ``commit_interval_s`` old [-] (and when the recorder closes): the rows are
#: an index into the video, read after the run, so they need not be in every frame's commit.
ROW_BATCH_FRACTION: Final = 0.5
#: ... or once this many rows wait [-], whichever comes first: at 60 fps in real time the
#: time does (6 frames), in an accelerated run (the demo, 1,200 frames per wall second) the
#: count, so a killed recording's file holds a bounded number of frames without rows.
ROW_BATCH_MAX_FRAMES: Final = 30
#: Frames a recording that did not end cleanly (killed, or stopped by a storage failure) may
#: hold beyond its ``video_frames`` rows [-]: the recorder's batch not handed yet (fewer than
#: :data:`ROW_BATCH_MAX_FRAMES`, and the frame being muxed) and one batch handed to the writer
#: but not committed (the daemon commits every 5 ms of wall time,
#: ``app.frame_measurer.COMMIT_SPACING_WALL_S``, so no second one waits). The integrity check
#: allows no more (:meth:`~.reader.SessionReader.integrity_check`).
UNINDEXED_FRAMES_MAX: Final = 2 * ROW_BATCH_MAX_FRAMES

#: The clock the row batches are timed on [s] (a name of its own, for tests).
_monotonic = time.monotonic
#: Niceness of the encoder thread above the process's own [-] (capped at 19): the
#: measurement's threads weigh about 3x as much, and the encoder still gets its share against
#: the daemon's own threads and other programs' ordinary (nice 0) load. At 19 that load
#: starved it; at 10, a 640x480 recording in real time left 104 of 1,127 frames out with
#: nothing else running and 630 beside one busy process per CPU; at 5, 0 and 0 (2 beside
#: three busy processes on the 2 CPUs). docs/performance.md, "Demo speed".
ENCODER_NICE: Final = 5
#: FFmpeg threads of an FFV1 encoder [-] (1: it runs in the recorder's encoder thread only).
ENCODER_THREADS: Final = 1
#: FFV1 encoders working at once, each in a thread of its own, on alternate frames (FFmpeg
#: threads FFV1 only by slices, at 1.8x the CPU; whole frames in parallel cost nothing more).
ENCODER_WORKERS: Final = max(1, min(2, os.cpu_count() or 1))
#: The FFV1 encoder's options: level 3 (a configuration record in the file), a CRC per slice.
FFV1_OPTIONS: Final = {"level": "3", "slicecrc": "1"}
#: Matroska tag naming the pixel layout the daemon counted on (``gray`` or ``bgr``).
TAG_IMAGE: Final = "STIPI_IMAGE"
#: Matroska tag holding the stored rectangle ``x0,y0,x1,y1`` of the camera frame [px].
TAG_CROP: Final = "STIPI_CROP"

Image = npt.NDArray[np.uint8]
Crop = tuple[int, int, int, int]


@dataclass(frozen=True, slots=True)
class _Lossless:
    """A frame on its way to an FFV1 encoder: its ``seq``, capture time [s], presentation
    time [ms], image (None: the previous frame's image again) and whether its packets are
    kept for a repeat that may follow (a read-only image)."""

    seq: int
    t_capture_s: float
    pts: int
    image: Image | None
    keep: bool


@dataclass(frozen=True)
class VideoInfo:
    """What a stored video holds.

    Attributes
    ----------
    path : Path
        The file.
    size_bytes : int
        File size [B].
    codec : str
        FFmpeg codec name (``mjpeg``, ``ffv1``).
    frames : int
        Complete frames (non-empty packets) in the file [-].
    width, height : int
        Stored frame size [px].
    image : str
        Pixel layout the frames decode to for counting (``gray`` or ``bgr``).
    crop : tuple of int or None
        ``(x0, y0, x1, y1)`` of the camera frame the file stores [px]; None: the whole frame.
    """

    path: Path
    size_bytes: int
    codec: str
    frames: int
    width: int
    height: int
    image: str
    crop: tuple[int, int, int, int] | None


class VideoRecorder:
    """Records the measured frames into a session's ``video.mkv``.

    The file is opened at the first frame (its size and pixel layout decide the stream).

    Parameters
    ----------
    path : Path
        The video file (``<session>/video.mkv``).
    writer : SessionWriter
        The session: receives a ``video_frames`` row per frame, a ``video_started`` event,
        and the error when writing fails.
    mode : {"passthrough", "lossless"}
        See the module docstring.
    crop : tuple of int or callable, optional
        ``(x0, y0, x1, y1)`` [px]: store only this rectangle (lossless frames only; a
        passthrough packet is always the whole frame); or a function of the first frame's
        shape giving it (or None).
    to_gray : callable, optional
        With ``crop``: store the rectangle of ``to_gray(image)`` (the gray image S_k is
        counted on, e.g. :func:`stipi_daemon.analysis.imaging.to_gray`) rather than of the
        image as delivered.
    frame_rate_hz : float, optional
        The camera's nominal frame rate [1/s], declared in the file (players and OpenCV
        read it; the frames' own times are their pts). None or not finite and > 0: none.
    """

    def __init__(
        self,
        path: Path,
        writer: SessionWriter,
        mode: VideoMode,
        *,
        crop: Crop | Callable[[tuple[int, ...]], Crop | None] | None = None,
        to_gray: Callable[[Image], Image] | None = None,
        frame_rate_hz: float | None = None,
    ) -> None:
        if mode not in ("passthrough", "lossless"):
            raise ValueError(f"video mode {mode!r}: a recorder records passthrough or lossless")
        import av  # loaded now, not at the first frame in the daemon's loop

        #: What a failure of the video itself raises: any FFmpeg error (``av.FFmpegError``:
        #: not all are OSError or ValueError, e.g. ``av.ExternalError``), an OSError of the
        #: file system, a ValueError of ours (a frame that does not fit the stream).
        self._video_errors: tuple[type[Exception], ...] = (av.FFmpegError, OSError, ValueError)

        self.path = Path(path)
        self.mode = mode
        self._writer = writer
        self._crop_for = crop
        self._to_gray = to_gray
        self._frame_rate: Fraction | None = None
        if frame_rate_hz is not None and math.isfinite(frame_rate_hz) and frame_rate_hz > 0:
            self._frame_rate = Fraction(frame_rate_hz).limit_denominator(1001)
        self._crop: Crop | None = None
        self._container: Any = None
        self._stream: Any = None
        self._codec = ""
        self._t0_s = 0.0
        self._last_pts = -1
        self._failed: str | None = None
        self._last_t_s = 0.0  # capture time of the newest frame handed to record [s]
        self._closed = False
        self._encoders: OrderedWorkers[_Lossless, list[Any]] | None = None
        self._extra_contexts: list[Any] = []  # encoders beside the stream's own
        self._last_image: Image | None = None  # the image last handed to the encoders
        self._last_payloads: list[bytes] = []  # and its packets' payload, once muxed
        self._rows: list[tuple[int, int, int, float]] = []  # video_frames rows not handed yet
        self._rows_since = 0.0  # time.monotonic() of the oldest of them [s]
        self._row_batch_s = ROW_BATCH_FRACTION * writer.options.commit_interval_s
        #: Frames stored [-].
        self.frames = 0
        #: Frames left out because the encoder could not keep up [-] (no row either).
        self.left_out = 0

    @property
    def failed(self) -> str | None:
        """Why recording stopped early, or None."""
        return self._failed

    def stats(self) -> dict[str, Any]:
        """Mode, codec, frames stored, file size and failure, for the run's statistics."""
        size = self.path.stat().st_size if self.path.exists() else 0
        return {
            "file": self.path.name,
            "mode": self.mode,
            "codec": self._codec or None,
            "frames": self.frames,
            "left_out": self.left_out,
            "size_bytes": size,
            "crop": None if self._crop is None else list(self._crop),
            "error": self._failed,
        }

    def record(
        self,
        seq: int,
        t_capture_s: float,
        image: Image,
        packet: bytes | None,
        *,
        wait: bool = False,
    ) -> bool:
        """Store one frame and its ``video_frames`` row.

        Returns False when the frame is not stored: recording has stopped, or the FFV1
        encoder thread lags :data:`ENCODER_QUEUE_FRAMES` behind and the frame is left out
        (counted in :attr:`left_out`) - unless ``wait``, where the caller waits for the
        encoders instead (a source that can wait: a file, the simulator), up to
        :data:`ENCODER_WAIT_MAX_S`. FFV1 frames are encoded in those threads; a failure
        there stops recording and shows at the session writer's next call.

        Parameters
        ----------
        seq : int
            The frame's sequence number (its ``frames`` row).
        t_capture_s : float
            Capture time on the session clock [s].
        image : numpy.ndarray
            The decoded frame the daemon counts S_k on (gray ``(H, W)`` or BGR ``(H, W, 3)``).
        packet : bytes or None
            The camera's encoded frame (a complete JPEG), if it has one.
        """
        if self._failed is not None or self._closed:
            return False
        self._last_t_s = t_capture_s
        try:
            if self._container is None:
                self._open(t_capture_s, image, packet)
            if self._encoders is not None:  # FFV1: encoded in the encoder threads
                return self._submit(seq, t_capture_s, image, wait)
            self._store(seq, t_capture_s, image, packet)
        except SessionError as exc:  # the database failed: stop the video with the rows
            self._stop(str(exc), exc)
            return False
        except self._video_errors as exc:  # FFmpeg's (any class), the file system's, ours
            self._stop(f"{self.path}: video recording stopped: {_error_text(exc)}")
            return False
        return True

    def _next_pts(self, t_capture_s: float) -> int:
        """The presentation time of the next frame [ms]: its capture time since the first
        frame's, and after the previous frame's."""
        return max(self._last_pts + 1, round((t_capture_s - self._t0_s) * 1000.0))

    def _store(self, seq: int, t_capture_s: float, image: Image, packet: bytes | None) -> None:
        """Mux one JPEG packet and add its ``video_frames`` row (raises on failure)."""
        pts = self._next_pts(t_capture_s)
        write_video_frame(self._container, self._stream, pts, image, packet)
        self._last_pts = pts
        self._add_row(seq, pts, t_capture_s)

    def _add_row(self, seq: int, pts: int, t_capture_s: float) -> None:
        """The stored frame's ``video_frames`` row, handed to the writer in batches."""
        rows = self._rows
        rows.append((seq, self.frames, pts, t_capture_s))
        self.frames += 1
        now = _monotonic()
        if len(rows) == 1:
            self._rows_since = now
        elif now - self._rows_since >= self._row_batch_s or len(rows) >= ROW_BATCH_MAX_FRAMES:
            self._hand_rows()

    def _hand_rows(self) -> None:
        """Give the ``video_frames`` rows made so far to the session writer (may raise
        :class:`SessionError` when the writer has failed)."""
        rows, self._rows = self._rows, []
        if rows:
            self._writer.add_video_frames(rows)

    def _submit(self, seq: int, t_capture_s: float, image: Image, wait: bool) -> bool:
        """Hand a frame to the FFV1 encoders (see :meth:`record`). A frame that is the very
        read-only image of the frame before it (a clean simulated scene repeats its picture
        while S_k stays on the same pixel count) is not encoded again: its packet is the
        previous frame's payload (FFV1 codes every frame on its own, so encoding it again
        would give the same bytes)."""
        assert self._encoders is not None
        read_only = not image.flags.writeable
        repeat = read_only and image is self._last_image
        pts = self._next_pts(t_capture_s)
        item = _Lossless(seq, t_capture_s, pts, None if repeat else image, read_only)
        if not self._encoders.submit(item, wait_s=ENCODER_WAIT_MAX_S if wait else 0.0):
            self.left_out += 1  # the encoders cannot keep up: leave this frame out
            self._last_image = None
            return False
        self._last_pts = pts
        self._last_image = image if read_only else None  # only a read-only image repeats
        return self._failed is None

    def _encoder(self, context: Any) -> Callable[[_Lossless], list[Any]]:
        """Work of one encoder thread: a frame (cropped, as gray where asked) encoded by
        ``context`` (PyAV releases the GIL while FFmpeg encodes); nothing for a repeat."""

        def encode(item: _Lossless) -> list[Any]:
            if item.image is None:
                return []
            return encode_video_frame(context, item.pts, self._stored_image(item.image))

        return encode

    def _deliver(self, item: _Lossless, packets: list[Any]) -> None:
        """Mux an encoded frame's packets (in frame order; a repeat: the previous frame's
        payload at this frame's time) and add its row."""
        if item.image is None:
            packets = [_packet(payload, item.pts) for payload in self._last_payloads]
        else:  # kept only where a repeat can follow: a read-only image (see _submit)
            self._last_payloads = [bytes(p) for p in packets] if item.keep else []
        for pkt in packets:
            pkt.stream = self._stream
            self._container.mux_one(pkt)
        self._add_row(item.seq, item.pts, item.t_capture_s)

    def _encoder_failed(self, exc: BaseException) -> None:
        """An encoder or the muxing failed (a SessionError is the writer's): recording
        stops, with the rows."""
        if isinstance(exc, SessionError):
            self._stop(str(exc), exc, join=False)
            return
        what = _error_text(exc) if isinstance(exc, self._video_errors) else repr(exc)
        self._stop(f"{self.path}: video recording stopped: {what}", join=False)

    def _start_encoders(self, layout: str, size: tuple[int, int]) -> None:
        """The FFV1 encoder threads: the stream's own encoder and up to
        :data:`ENCODER_WORKERS` - 1 more with the same settings, each kept only if its
        configuration record (the file's extradata) is the stream's byte for byte, so that
        its frames decode as part of the one stream."""
        self._container.start_encoding()
        own = self._stream.codec_context
        contexts = [own]
        for _ in range(ENCODER_WORKERS - 1):
            ctx = ffv1_encoder(layout, size, self._frame_rate)
            if bytes(ctx.extradata or b"") != bytes(own.extradata or b""):
                _log.info("%s: a second FFV1 encoder differs; encoding with one", self.path)
                break
            contexts.append(ctx)
        self._extra_contexts = contexts[1:]
        self._encoders = OrderedWorkers(
            [self._encoder(c) for c in contexts],
            self._deliver,
            self._encoder_failed,
            capacity=ENCODER_QUEUE_FRAMES,
            name=f"video encoder {self.path}",
            nice=ENCODER_NICE,
        )

    def _open(self, t_capture_s: float, image: Image, packet: bytes | None) -> None:
        passthrough = self.mode == "passthrough" and packet is not None
        crop = self._crop_for(image.shape) if callable(self._crop_for) else self._crop_for
        crop_ignored = passthrough and crop is not None
        crop = None if passthrough else crop
        if crop is not None and self._to_gray is not None:
            image = self._to_gray(image)
        layout = "gray" if image.ndim == 2 else "bgr"
        h, w = image.shape[:2]
        if crop is not None:
            x0, y0, x1, y1 = crop
            if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
                raise ValueError(f"video crop {crop} lies outside the {w}x{h} frame")
            w, h = x1 - x0, y1 - y0
        self._crop = crop
        codec: Literal["mjpeg", "ffv1"] = "mjpeg" if passthrough else "ffv1"
        container, stream = open_video_file(
            self.path, codec, layout, (w, h), crop=crop, frame_rate=self._frame_rate
        )
        self._container, self._stream = container, stream
        self._codec = "mjpeg" if passthrough else "ffv1"
        self._t0_s = t_capture_s
        if not passthrough:
            self._start_encoders(layout, (w, h))
        started: dict[str, Any] = {
            "file": self.path.name,
            "mode": self.mode,
            "codec": self._codec,
            "image": layout,
            "size": [w, h],
            "crop": None if self._crop is None else list(self._crop),
            "t0_s": t_capture_s,
        }
        if crop_ignored:  # the whole frame: a JPEG packet is not cropped without re-encoding
            started["crop_ignored"] = "passthrough stores the camera's JPEG packets whole"
        self._writer.add_event(t_capture_s, "video_started", started)

    def _stored_image(self, image: Image) -> Image:
        """What a lossless frame stores of ``image``: the crop (converted to gray where
        asked: crop, then convert, per pixel the same) or all of it."""
        if self._crop is None:
            return image
        x0, y0, x1, y1 = self._crop
        image = image[y0:y1, x0:x1]
        return self._to_gray(image) if self._to_gray is not None else image

    def _stop(self, reason: str, error: SessionError | None = None, *, join: bool = True) -> None:
        """Stop recording: the video's own failure (``error`` None) is recorded as a
        ``video_stopped`` event and handed to the session writer, whose next call raises it
        (the daemon then stops, rows and video together, and names it in its one error
        line); a failure of the writer (``error``) is the writer's already."""
        self._failed = reason
        _log.info("%s", reason)  # the daemon's error line says it: not a second line here
        if error is None:
            try:
                self._writer.add_event(
                    self._last_t_s, "video_stopped", {"file": self.path.name, "error": reason}
                )
            except SessionError as exc:  # the writer failed too: its error goes on
                error = exc
        self._writer.fail(error if error is not None else SessionError(reason))
        if join:
            self._close_container()

    def _close_container(self) -> None:
        encoders, self._encoders = self._encoders, None
        if encoders is not None and threading.current_thread() not in encoders.threads:
            encoders.close()  # every frame handed over is encoded and muxed
        container, self._container = self._container, None
        if container is None:
            return
        try:
            if self._codec == "ffv1" and self._failed is None:
                for ctx in [self._stream.codec_context, *self._extra_contexts]:
                    for out in ctx.encode(None):  # FFV1 holds no frames back; to be sure
                        out.stream = self._stream
                        container.mux_one(out)
            container.close()
        except self._video_errors as exc:
            if self._failed is None:
                self._failed = f"{self.path}: video could not be closed cleanly: {_error_text(exc)}"

    def close(self) -> None:
        """Finish the file (cues, duration). Idempotent; never raises."""
        if self._closed:
            return
        self._closed = True
        self._close_container()
        try:
            self._hand_rows()
        except SessionError as exc:  # the session failed first: its error is already reported
            _log.debug("video_frames rows not stored: %s", exc)
        if self.left_out:
            _log.warning(
                "%s: %d frames left out of the video (the encoder could not keep up)",
                self.path,
                self.left_out,
            )


# ------------------------------------------------------------------------- writing frames


def _error_text(exc: BaseException) -> str:
    """An error as one line, its class named where the message alone may not say what
    failed (an FFmpeg error other than an OSError's errno, e.g. ``av.ExternalError``)."""
    text = str(exc) or repr(exc)
    return text if isinstance(exc, OSError) and exc.errno else f"{type(exc).__name__}: {text}"


def open_video_file(
    path: Path,
    codec: Literal["mjpeg", "ffv1"],
    layout: str,
    size: tuple[int, int],
    *,
    crop: Crop | None = None,
    frame_rate: Fraction | None = None,
    options: dict[str, str] | None = None,
) -> tuple[Any, Any]:
    """Open ``path`` as a Matroska file with one video stream, as a session video is stored.

    ``codec`` ``mjpeg``: JPEG packets muxed as they are (:func:`write_video_frame`);
    ``ffv1``: frames encoded losslessly (level 3, every frame intra, CRC per slice), ``gray``
    or ``bgr0`` by ``layout`` (``"gray"`` or ``"bgr"``, stored as the :data:`TAG_IMAGE` tag).
    Times are in :data:`PTS_TIME_BASE`. ``size`` is ``(width, height)`` [px]; ``crop``, if
    any, is stored as the :data:`TAG_CROP` tag; ``frame_rate`` [1/s], if known, is declared
    (players and OpenCV read it as the file's frame rate); ``options`` are the muxer's
    (default :data:`MUXER_OPTIONS`). Returns ``(container, stream)``; close the container.
    """
    import av

    opts = MUXER_OPTIONS if options is None else options
    container = av.open(str(path), "w", format="matroska", options=opts)
    try:
        if codec == "mjpeg":
            stream = container.add_stream("mjpeg")
            stream.pix_fmt = "yuvj420p"
        else:
            stream = container.add_stream("ffv1", options=dict(FFV1_OPTIONS))
            _set_ffv1(stream.codec_context, layout, size, frame_rate)
        if frame_rate is not None:
            stream.codec_context.framerate = frame_rate
        stream.width, stream.height = size
        stream.time_base = PTS_TIME_BASE
        container.metadata[TAG_IMAGE] = layout
        if crop is not None:
            container.metadata[TAG_CROP] = ",".join(str(v) for v in crop)
    except BaseException:
        container.close()
        raise
    return container, stream


def _set_ffv1(ctx: Any, layout: str, size: tuple[int, int], frame_rate: Fraction | None) -> None:
    """The session video's FFV1 encoder settings on codec context ``ctx`` (not yet open)."""
    ctx.pix_fmt = "gray" if layout == "gray" else "bgr0"
    ctx.width, ctx.height = size
    ctx.gop_size = 1  # every frame intra: any frame decodes alone, a killed file plays
    # the encoder's own time base (PyAV's default is 1/24 s): frames are rebased onto it
    # before encoding, which would round 60 fps pts to 42 ms steps
    ctx.time_base = PTS_TIME_BASE
    # FFmpeg's own threads off: the recorder encodes in threads of its own (at their
    # niceness, which threads FFmpeg starts would not share), and FFV1's slice threads cost
    # CPU: 3.5 ms per 420x420 gray frame with them, 1.9 ms without (docs/performance.md).
    ctx.thread_count = ENCODER_THREADS
    if frame_rate is not None:
        ctx.framerate = frame_rate


def ffv1_encoder(layout: str, size: tuple[int, int], frame_rate: Fraction | None) -> Any:
    """An open FFV1 encoder with the settings of a session video's stream
    (:func:`open_video_file`), beside the stream's own: its frames belong to that stream
    when its configuration record (``extradata``) is the stream encoder's."""
    import av

    ctx = av.CodecContext.create("ffv1", "w")
    _set_ffv1(ctx, layout, size, frame_rate)
    ctx.options = dict(FFV1_OPTIONS)
    ctx.open()
    return ctx


def encode_video_frame(ctx: Any, pts: int, image: Image) -> list[Any]:
    """The packets of ``image`` (gray ``(H, W)`` or BGR ``(H, W, 3)``) encoded at ``pts``
    [ms] by the FFV1 encoder ``ctx``; FFmpeg errors propagate (``av.FFmpegError``)."""
    import av

    fmt = "gray" if image.ndim == 2 else "bgr24"
    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format=fmt)
    frame.pts = pts
    frame.time_base = PTS_TIME_BASE
    return list(ctx.encode(frame))


def _packet(payload: bytes, pts: int) -> Any:
    """A keyframe packet of ``payload`` at ``pts`` [ms] (:data:`PTS_TIME_BASE`)."""
    import av

    pkt = av.Packet(payload)
    pkt.time_base = PTS_TIME_BASE
    pkt.pts = pkt.dts = pts
    pkt.is_keyframe = True
    return pkt


def write_video_frame(
    container: Any, stream: Any, pts: int, image: Image, packet: bytes | None
) -> None:
    """Store one frame at ``pts`` [ms] in a stream of :func:`open_video_file`.

    An ``mjpeg`` stream muxes ``packet`` (a complete JPEG) as it is, a keyframe, without
    decoding it; an ``ffv1`` stream encodes ``image`` (gray ``(H, W)`` or BGR ``(H, W, 3)``).
    FFmpeg errors propagate (``av.FFmpegError``, of many classes).
    """

    if stream.codec_context.name == "mjpeg":
        if packet is None:
            raise ValueError("a frame without its JPEG packet in an MJPG recording")
        pkt = _packet(packet, pts)
        pkt.stream = stream
        container.mux_one(pkt)
        return
    for out in encode_video_frame(stream.codec_context, pts, image):
        out.stream = stream
        container.mux_one(out)


# ------------------------------------------------------------------------------ reading

#: Threads FFmpeg's decoder may use per video read (0: FFmpeg's choice, one per CPU).
_decode_threads = 0


def set_decode_threads(threads: int) -> None:
    """Threads FFmpeg may use to decode a stored video (0: one per CPU, the default).

    A process that is one of several sharing the CPUs (a study's Dask worker) sets 1: the
    slice threads of each of its decodes would otherwise contend with the other processes
    and hand each frame between threads (thousands of context switches per session)."""
    global _decode_threads
    if threads < 0:
        raise ValueError(f"decode threads must be >= 0, not {threads}")
    _decode_threads = threads


class VideoDamageError(SessionError):
    """A stored video is damaged where it is read: a frame whose bytes fail their Matroska
    CRC-32 or that does not decode, a damaged header, or a file structure that breaks off.
    The message names the file, the frame (index from 0) and the byte offset.

    Attributes
    ----------
    path : Path or None
        The video file.
    frame_index : int or None
        The damaged frame, from 0 (None: no single frame, e.g. the header or a break).
    pos_bytes : int or None
        Byte offset in the file of the frame's data or of the damage.
    """

    def __init__(
        self,
        message: str,
        path: Path | None = None,
        frame_index: int | None = None,
        pos_bytes: int | None = None,
    ) -> None:
        super().__init__(message)
        self.path = path
        self.frame_index = frame_index
        self.pos_bytes = pos_bytes

    def __reduce__(self) -> tuple[Any, ...]:  # pickled whole (a study's Dask workers)
        return (type(self), (str(self), self.path, self.frame_index, self.pos_bytes))


@dataclass(frozen=True, slots=True)
class StoredFrame:
    """One frame of a stored video as :func:`iter_video_frames` reads it: sound (``image``)
    or damaged (``damage`` says why, ``image`` is None).

    Attributes
    ----------
    frame_index : int
        Position in the file, from 0 (a ``video_frames`` row's ``frame_index``).
    pos_bytes : int
        Byte offset of the frame's data (its Matroska block) in the file.
    pts_ms : int or None
        Presentation time [ms] (a row's ``pts_ms``); None when FFmpeg's demuxer did not read
        the frame.
    image : numpy.ndarray or None
        The image as the daemon counted it; None when damaged or not decoded
        (``decode=False``).
    damage : str or None
        Why the frame is unusable (its cluster fails its CRC-32, it does not decode, the
        demuxer skipped it); None for a sound frame.
    """

    frame_index: int
    pos_bytes: int
    pts_ms: int | None
    image: Image | None
    damage: str | None


@dataclass(frozen=True)
class VideoCheck:
    """What :func:`check_video` found in a stored video.

    Attributes
    ----------
    path : Path
        The file.
    size_bytes : int
        File size [B].
    frames : int
        Complete frames (Matroska blocks) in the file [-].
    pts_ms : tuple of (int or None)
        Each frame's presentation time [ms] as FFmpeg's demuxer reads it (None: not read).
    damaged : tuple of StoredFrame
        The damaged frames (``damage`` says why; no image), in file order.
    problems : tuple of str
        File-level damage, one line each: not readable, header damaged, the structure
        breaking off at a byte (frames after it unknown).
    cut_at : int or None
        The file ends inside the element that starts at this byte [B]: the cut-off tail a
        killed recording leaves (FFmpeg's demuxer leaves it out); None: it ends whole.
    decoded : bool
        Every frame was decoded too (``decode=True``), not only its bytes checked.
    """

    path: Path
    size_bytes: int
    frames: int
    pts_ms: tuple[int | None, ...]
    damaged: tuple[StoredFrame, ...]
    problems: tuple[str, ...]
    cut_at: int | None
    decoded: bool

    @property
    def ok(self) -> bool:
        """No damage found (a cut-off tail is not damage: whether it is allowed depends on
        how the recording ended, which the session knows)."""
        return not self.damaged and not self.problems


def _open_input(path: Path, threads: int | None = None) -> Any:
    """``path`` opened for reading, its decoder with ``threads`` threads (default: the
    :func:`set_decode_threads` setting; 0: FFmpeg's choice)."""
    import av

    if not path.is_file():
        raise SessionError(f"{path}: video file is missing")
    try:
        container = av.open(str(path), "r")
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise SessionError(f"{path}: not a readable video ({exc})") from None
    if not container.streams.video:
        container.close()
        raise SessionError(f"{path}: holds no video stream")
    threads = _decode_threads if threads is None else threads
    if threads:
        for stream in container.streams.video:
            stream.codec_context.thread_count = threads
            if threads == 1:
                stream.codec_context.thread_type = "NONE"
    return container


def _frame_image(frame: Any, gray: bool) -> Image:
    """A decoded FFV1 frame as the daemon counted it: ``gray`` as stored, ``bgr0`` without
    its padding byte (the recorder padded the BGR bytes: the same pixels). Read from the
    frame's plane directly: PyAV's ``to_ndarray(format=...)`` makes a scaler per frame,
    which cost more than the decode (0.6 ms per 160x120 frame, two threads started each)."""
    import cv2

    fmt = frame.format.name
    if (fmt == "gray") == gray and fmt in ("gray", "bgr0"):
        plane = frame.planes[0]
        h, w, c = frame.height, frame.width, 1 if gray else 4
        rows = np.frombuffer(plane, np.uint8).reshape(h, plane.line_size)[:, : w * c]
        if gray:
            return rows.copy()
        return np.asarray(cv2.cvtColor(rows.reshape(h, w, 4), cv2.COLOR_BGRA2BGR))
    return np.asarray(frame.to_ndarray(format="gray" if gray else "bgr24"))


def _crop_tag(text: str | None) -> tuple[int, int, int, int] | None:
    if not text:
        return None
    x0, y0, x1, y1 = (int(v) for v in text.split(","))
    return x0, y0, x1, y1


# ---------------------------------------------------------- the file's structure and CRC-32
#
# FFmpeg's Matroska muxer writes a CRC-32 element first in every level-1 element (its
# ``write_crc32`` default), and with ``flush_packets=1`` every frame in a cluster of its own;
# FFmpeg's demuxer does not verify them, and FFmpeg's FFV1 decoder only logs a slice CRC
# mismatch (it conceals the slice from the previous frame and reports no error, whatever
# ``err_detect`` says: measured with FFmpeg 8.1). So the file's element headers are walked
# here (no payload is read) and each cluster's CRC-32 is checked: every byte of every frame.

#: EBML element IDs (Matroska, RFC 9559).
_ID_EBML: Final = 0x1A45DFA3
_ID_SEGMENT: Final = 0x18538067
_ID_CLUSTER: Final = 0x1F43B675
_ID_CRC32: Final = 0xBF
_ID_VOID: Final = 0xEC
_ID_SIMPLE_BLOCK: Final = 0xA3
_ID_BLOCK_GROUP: Final = 0xA0
_ID_BLOCK: Final = 0xA1
_CLUSTER_ID_BYTES: Final = _ID_CLUSTER.to_bytes(4, "big")
#: The Segment's children (level 1) by name, for messages.
_LEVEL1: Final = {
    0x114D9B74: "SeekHead",
    0x1549A966: "Info",
    0x1654AE6B: "Tracks",
    0x1254C367: "Tags",
    _ID_CLUSTER: "Cluster",
    0x1C53BB6B: "Cues",
    0x1043A770: "Chapters",
    0x1941A469: "Attachments",
    _ID_VOID: "Void",
}

_Buf = bytes | mmap.mmap


class _Break(Exception):
    """No element where one must be, at byte ``pos`` (damage); ``cut``: the file ends
    inside the element starting at ``pos`` instead."""

    def __init__(self, pos: int, *, cut: bool = False) -> None:
        super().__init__(pos)
        self.pos = pos
        self.cut = cut


@dataclass
class _Layout:
    """A video file's Matroska structure as :func:`_walk` finds it.

    ``blocks``: the data offset of every frame's block, in file order (PyAV's
    ``Packet.pos``); ``cluster_of``: each block's cluster, an index into ``clusters``:
    ``(offset of its stored CRC-32 or -1 for none, first byte covered, end)``;
    ``header_damage``: other level-1 elements failing their CRC-32; ``broken_at``: where
    the structure breaks off (damage); ``cut_at``: the file ends inside the element
    starting there (a killed recording's tail)."""

    size_bytes: int
    blocks: list[int] = field(default_factory=list)
    cluster_of: list[int] = field(default_factory=list)
    clusters: list[tuple[int, int, int]] = field(default_factory=list)
    header_damage: list[str] = field(default_factory=list)
    broken_at: int | None = None
    cut_at: int | None = None

    def beyond(self, pos: int) -> bool:
        """Whether a packet at byte ``pos`` lies where the walk found no frame and none can
        be: after a break, in or after the cut-off tail, or written since the walk."""
        if self.broken_at is not None and pos >= self.broken_at:
            return True
        return pos >= (self.size_bytes if self.cut_at is None else self.cut_at)


def _vint(buf: _Buf, p: int, end: int, max_len: int) -> tuple[int, int, int]:
    """The EBML variable-length integer at ``p``: raw value (marker bit kept), length [B]
    and the offset after it; :class:`_Break` (cut at ``end``) when it does not fit."""
    if p >= end:
        raise _Break(p, cut=True)
    n = 9 - buf[p].bit_length()
    if n > max_len:
        raise _Break(p)
    if p + n > end:
        raise _Break(p, cut=True)
    return int.from_bytes(buf[p : p + n], "big"), n, p + n


def _element(buf: _Buf, p: int, end: int) -> tuple[int, int, int | None]:
    """ID, data offset and data size (None: unknown) of the element starting at ``p``;
    :class:`_Break` at ``p`` when its header is no EBML or does not end before ``end``."""
    try:
        kind, _, q = _vint(buf, p, end, 4)
        raw, n, data = _vint(buf, q, end, 8)
    except _Break as brk:
        raise _Break(p, cut=brk.cut) from None
    unknown = (1 << (7 * n)) - 1
    size = raw & unknown
    return kind, data, None if size == unknown else size


def _crc_ok(buf: _Buf, cluster: tuple[int, int, int]) -> bool | None:
    """Whether an element's bytes match its stored CRC-32 (None: it has none)."""
    crc_at, start, end = cluster
    if crc_at < 0:
        return None
    stored = int.from_bytes(buf[crc_at : crc_at + 4], "little")
    with memoryview(buf) as whole, whole[start:end] as covered:
        return zlib.crc32(covered) == stored


def _first_crc(buf: _Buf, data: int, end: int) -> tuple[int, int, int]:
    """``(offset of the stored CRC-32, first byte covered, end)`` of an element whose data
    runs from ``data`` to ``end`` (offset -1: its first child is no CRC-32)."""
    if data < end:
        kind, at, size = _element(buf, data, end)
        if kind == _ID_CRC32 and size == 4:
            return at, at + 4, end
    return -1, data, end


def _walk_cluster(buf: _Buf, data: int, end: int, lay: _Layout, *, cut: bool = False) -> None:
    """The blocks of a cluster whose data runs from ``data`` to ``end``; ``cut``: the file
    ends at ``end`` inside the cluster: its whole blocks (FFmpeg's demuxer reads them), with
    no CRC-32 to check them by."""
    index = len(lay.clusters)
    lay.clusters.append((-1, data, end) if cut else _first_crc(buf, data, end))
    q = data
    while q < end:
        try:
            kind, at, size = _element(buf, q, end)
        except _Break:
            if cut:
                return
            raise _Break(q) from None
        if size is None or at + size > end:
            if cut:
                return
            raise _Break(q)
        if kind == _ID_SIMPLE_BLOCK:
            lay.blocks.append(at)
            lay.cluster_of.append(index)
        elif kind == _ID_BLOCK_GROUP:
            g = at
            while g < at + size:
                child, c_at, c_size = _element(buf, g, at + size)
                if c_size is None or c_at + c_size > at + size:
                    raise _Break(g)
                if child == _ID_BLOCK:
                    lay.blocks.append(c_at)
                    lay.cluster_of.append(index)
                g = c_at + c_size
        q = at + size


def _walk_segment(buf: _Buf, p: int, end: int, lay: _Layout) -> None:
    """The Segment's children from ``p`` to ``end``: clusters walked, the other elements'
    CRC-32 checked."""
    released = 0
    while p < end:
        released = _release(buf, p, released)
        kind, data, size = _element(buf, p, end)
        name = _LEVEL1.get(kind)
        if name is None or size is None:
            raise _Break(p)
        stop = data + size
        if stop > end:
            # the file ends inside it (a killed recording), unless a cluster follows inside
            # it: then its size is damaged
            tail = end == len(buf) and buf.find(_CLUSTER_ID_BYTES, data, end) < 0
            if tail and kind == _ID_CLUSTER:
                _walk_cluster(buf, data, end, lay, cut=True)
            raise _Break(p, cut=tail)
        if kind == _ID_CLUSTER:
            _walk_cluster(buf, data, stop, lay)
        elif kind != _ID_VOID and _crc_ok(buf, _first_crc(buf, data, stop)) is False:
            lay.header_damage.append(f"its {name} element (byte {p}) fails its CRC-32")
        p = stop


def _walk(buf: _Buf) -> _Layout:
    """The Matroska structure of a session video: element headers only, no payload read
    (CRC-32s of clusters are checked by the reader, :func:`_crc_ok`)."""
    size = len(buf)
    lay = _Layout(size)
    p = 0
    try:
        kind, data, length = _element(buf, 0, size)
        if kind != _ID_EBML or length is None:
            raise _Break(0)
        p = data + length
        if p > size:
            raise _Break(0, cut=True)
        kind, data, length = _element(buf, p, size)
        if kind != _ID_SEGMENT:
            raise _Break(p)
        _walk_segment(buf, data, size if length is None else min(size, data + length), lay)
    except _Break as brk:
        if brk.cut:
            lay.cut_at = brk.pos
        else:
            lay.broken_at = brk.pos
    return lay


@contextmanager
def _mapped(path: Path) -> Iterator[_Buf]:
    """The file's bytes, mapped read-only (an empty file: ``b""``)."""
    if not path.is_file():
        raise SessionError(f"{path}: video file is missing")
    try:
        fh = open(path, "rb")  # closed below, around the yield
    except OSError as exc:
        raise SessionError(f"{path}: video file cannot be read ({exc})") from None
    with fh:
        try:
            size = os.fstat(fh.fileno()).st_size
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else None
        except OSError as exc:
            raise SessionError(f"{path}: video file cannot be read ({exc})") from None
        if mm is None:
            yield b""
            return
        with mm:
            yield mm


#: Bytes of a mapped video read before the pages behind are let go [B]: a walk over a whole
#: video (every cluster's CRC-32) would otherwise keep the file's pages resident in this
#: process (its RSS: 114 MB for the demo's video), though the kernel keeps them cached.
RELEASE_STEP_BYTES: Final = 8 << 20


def _release(buf: _Buf, upto: int, released: int) -> int:
    """Let go of the mapped pages of ``buf`` before byte ``upto`` once it has passed
    ``released`` by :data:`RELEASE_STEP_BYTES` (``madvise(MADV_DONTNEED)``: a read-only file
    mapping reads them again from the page cache if touched); returns the new mark [B]."""
    if not isinstance(buf, mmap.mmap) or upto - released < RELEASE_STEP_BYTES:
        return released
    mark = upto - upto % mmap.PAGESIZE
    buf.madvise(mmap.MADV_DONTNEED, 0, mark)
    return mark


# ---------------------------------------------------------------------- reading the frames


@dataclass(slots=True)
class _Slot:
    """A frame on its way through :class:`_FrameReader`."""

    index: int
    pos: int
    pts: int | None
    image: Image | None = None
    damage: str | None = None
    done: bool = False


def _jpeg_whole(payload: bytes) -> bool:
    """A JPEG's SOI and EOI markers are where they belong (trailing zero padding allowed,
    as UVC cameras send it): the check of a packet whose cluster holds no CRC-32."""
    return payload[:2] == b"\xff\xd8" and payload.rstrip(b"\0")[-2:] == b"\xff\xd9"


class _FrameReader:
    """Turns the demuxed packets of a session video into :class:`StoredFrame`, in file
    order: each checked against its cluster's CRC-32, then decoded (``decode``) as the
    daemon counted it. FFV1 pictures are matched to their packets by pts (FFmpeg's frame
    threads hand them out later)."""

    def __init__(self, path: Path, buf: _Buf, lay: _Layout, ctx: Any, gray: bool, decode: bool):
        import cv2

        self._path, self._buf, self._lay, self._ctx = path, buf, lay, ctx
        self._released = 0  # mapped bytes let go of (:func:`_release`) [B]
        self._jpeg = ctx.name == "mjpeg"
        self._gray = gray
        self._flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
        self._decode = decode
        self._index = {pos: i for i, pos in enumerate(lay.blocks)}
        self._next = 0  # the next block the demuxer should give
        self._slots: deque[_Slot] = deque()
        self._crc: dict[int, bool | None] = {}  # each cluster's CRC-32 check, once
        self._error = "no error given"  # FFmpeg's last decoding error

    def known(self, pos: int | None) -> bool:
        """Whether a frame's block starts its data at byte ``pos``."""
        return pos in self._index

    def packet(self, pkt: Any) -> None:
        """Take one demuxed packet (non-empty)."""
        i = self._index.get(pkt.pos, -1)
        if i < self._next:
            raise VideoDamageError(
                f"{self._path}: frame data at byte {pkt.pos} lies in no block of the file: "
                "its Matroska structure is damaged",
                self._path,
                None,
                pkt.pos,
            )
        self._missed(i, "FFmpeg's demuxer skipped it")
        self._next = i + 1
        slot = _Slot(i, pkt.pos, None if pkt.pts is None else int(pkt.pts))
        self._slots.append(slot)
        slot.damage = self._check(i, pkt)
        if slot.damage is not None or not self._decode:
            slot.done = True
        elif self._jpeg:  # decoded as the camera did
            import cv2

            img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), self._flag)
            if img is None:
                slot.damage = "its JPEG does not decode"
            else:
                slot.image = np.asarray(img, dtype=np.uint8)
            slot.done = True
        else:
            self._feed(pkt)

    def _check(self, i: int, pkt: Any) -> str | None:
        cluster = self._lay.cluster_of[i]
        if cluster not in self._crc:  # once per cluster (older files: several frames each)
            self._crc[cluster] = _crc_ok(self._buf, self._lay.clusters[cluster])
            self._released = _release(self._buf, self._lay.clusters[cluster][2], self._released)
        crc = self._crc[cluster]
        if crc is False:
            return "its Matroska cluster fails its CRC-32"
        if crc is None and self._jpeg and not _jpeg_whole(bytes(pkt)):
            return "its JPEG lacks the SOI or EOI marker"
        return None

    def _missed(self, upto: int, why: str) -> None:
        for k in range(self._next, upto):
            self._slots.append(_Slot(k, self._lay.blocks[k], None, None, why, True))

    def _feed(self, pkt: Any) -> None:
        import av

        try:
            pictures = self._ctx.decode(pkt)
        except av.FFmpegError as exc:
            self._error = str(exc)
            return
        for picture in pictures:
            self._picture(picture)

    def _picture(self, picture: Any) -> None:
        """A decoded picture: the frame waiting with its pts (those waiting before it gave
        none)."""
        for slot in self._slots:
            if slot.done:
                continue
            slot.done = True
            if picture.pts is None or picture.pts == slot.pts:
                if picture.is_corrupt:
                    slot.damage = "FFmpeg's decoder flagged its picture corrupt"
                else:
                    slot.image = _frame_image(picture, self._gray)
                return
            slot.damage = f"FFmpeg's decoder gave no picture for it ({self._error})"

    def ready(self) -> Iterator[StoredFrame]:
        """The frames read completely so far, in file order."""
        slots = self._slots
        while slots and slots[0].done:
            s = slots.popleft()
            yield StoredFrame(s.index, s.pos, s.pts, s.image, s.damage)

    def finish(self, demux_error: str | None) -> Iterator[StoredFrame]:
        """The rest, once the demuxer has ended (``demux_error``: why, if it failed)."""
        import av

        if self._decode and not self._jpeg:
            try:
                for picture in self._ctx.decode(None):
                    self._picture(picture)
            except av.FFmpegError as exc:
                self._error = str(exc)
            for slot in self._slots:
                if not slot.done:
                    slot.damage = f"FFmpeg's decoder gave no picture for it ({self._error})"
                    slot.done = True
        why = "FFmpeg's demuxer did not read it"
        self._missed(len(self._lay.blocks), why + (f" ({demux_error})" if demux_error else ""))
        self._next = len(self._lay.blocks)
        yield from self.ready()


def _read_frames(path: Path, buf: _Buf, lay: _Layout, *, decode: bool) -> Iterator[StoredFrame]:
    """Every frame of the file (walked as ``lay``) in order; raises
    :class:`VideoDamageError` where its structure breaks off, after the frames before."""
    import av

    if lay.blocks:
        container = _open_input(path)
        try:
            stream = container.streams.video[0]
            gray = dict(container.metadata).get(TAG_IMAGE, "bgr") == "gray"
            reader = _FrameReader(path, buf, lay, stream.codec_context, gray, decode)
            error = None
            try:
                for pkt in container.demux(stream):
                    if not pkt.size:
                        continue
                    pos = -1 if pkt.pos is None else int(pkt.pos)
                    if not reader.known(pos) and lay.beyond(pos):
                        break  # the cut-off tail, a break (below), or written since the walk
                    reader.packet(pkt)
                    yield from reader.ready()
            except av.FFmpegError as exc:
                error = str(exc)
            yield from reader.finish(error)
        finally:
            container.close()
    if lay.broken_at is not None:
        raise VideoDamageError(
            f"{path}: its Matroska structure breaks off at byte {lay.broken_at} (after "
            f"{len(lay.blocks)} frames; the frames after it cannot be located)",
            path,
            None,
            lay.broken_at,
        )


def check_video(path: Path | str, *, decode: bool = False) -> VideoCheck:
    """Check a stored video for damage; never raises (what is wrong is in the result).

    Always (cheap: reads every byte once, no decoding; 0.3-1.0 s for 114 MB of FFV1 here,
    docs/storage.md): the Matroska structure is walked, every cluster's CRC-32 checked
    (every byte of every frame: FFmpeg's muxer writes one per cluster, one frame per
    cluster), every packet demuxed by FFmpeg (its pts, and whether the demuxer reads every
    block), a JPEG in a cluster without CRC-32 checked for its SOI/EOI markers. With
    ``decode``, every frame is also decoded as :func:`iter_video_images` gives it (about
    2 ms per 420x420 FFV1 frame here): what the bytes alone cannot show (a decoder
    error).
    """
    p = Path(path)
    problems: list[str] = []
    pts: list[int | None] = []
    damaged: list[StoredFrame] = []
    lay = _Layout(0)
    try:
        with _mapped(p) as buf:
            lay = _walk(buf)
            problems += [f"{p}: {m}" for m in lay.header_damage]
            try:
                for frame in _read_frames(p, buf, lay, decode=decode):
                    pts.append(frame.pts_ms)
                    if frame.damage is not None:
                        damaged.append(frame)
            except SessionError as exc:
                problems.append(str(exc))
    except SessionError as exc:
        problems.append(str(exc))
    return VideoCheck(
        path=p,
        size_bytes=lay.size_bytes,
        frames=len(lay.blocks),
        pts_ms=tuple(pts),
        damaged=tuple(damaged),
        problems=tuple(problems),
        cut_at=lay.cut_at,
        decoded=decode,
    )


def probe_video(path: Path | str) -> VideoInfo:
    """Codec, size and frame count of a stored video (demuxes every packet; checks nothing:
    :func:`check_video` does).

    Raises
    ------
    SessionError
        The file is missing, holds no frame (a recording stopped before its first frame
        reached the file), or FFmpeg cannot read it.
    """
    import av

    p = Path(path)
    try:
        container = _open_input(p)
    except SessionError:
        with _mapped(p) as buf:
            lay = _walk(buf)
        if not lay.blocks and lay.broken_at is None and not lay.header_damage:
            raise SessionError(
                f"{p}: holds no frame (the recording stopped before its first frame "
                "reached the file)"
            ) from None
        raise
    try:
        stream = container.streams.video[0]
        frames = 0
        try:
            for pkt in container.demux(stream):
                if pkt.size:
                    frames += 1
        except av.FFmpegError:  # damage: counted up to there (check_video names it)
            pass
        tags = dict(container.metadata)
        return VideoInfo(
            path=p,
            size_bytes=p.stat().st_size,
            codec=str(stream.codec_context.name),
            frames=frames,
            width=int(stream.codec_context.width),
            height=int(stream.codec_context.height),
            image=str(tags.get(TAG_IMAGE, "bgr")),
            crop=_crop_tag(tags.get(TAG_CROP)),
        )
    finally:
        container.close()


def iter_video_frames(path: Path | str, *, decode: bool = True) -> Iterator[StoredFrame]:
    """Every frame of a stored video in file order, sound or damaged: nothing is skipped.

    A sound frame carries its image exactly as the daemon counted it (JPEG packets decoded
    by ``cv2.imdecode`` as the camera did, FFV1 bit-exact, a cropped recording's stored
    rectangle); a damaged one carries ``damage`` (its cluster fails its CRC-32, it does not
    decode, FFmpeg's demuxer skipped it) and no image, so that a caller can go on and count
    what it could not read. ``decode=False``: no images, the bytes checked only. A killed
    recording's cut-off tail is no frame (it never was whole).

    Raises
    ------
    SessionError
        The file is missing or FFmpeg cannot open it.
    VideoDamageError
        Its header is damaged (before any frame), or its structure breaks off (after the
        frames before the break: later frames cannot be located).
    """
    p = Path(path)
    with _mapped(p) as buf:
        lay = _walk(buf)
        if lay.header_damage:
            raise VideoDamageError(f"{p}: {lay.header_damage[0]}", p, None, None)
        yield from _read_frames(p, buf, lay, decode=decode)


def iter_video_images(path: Path | str) -> Iterator[Image]:
    """The stored frames' images in file order, as the daemon counted them
    (:func:`iter_video_frames`).

    Raises
    ------
    VideoDamageError
        At the first damaged frame (naming its index and byte offset), after the images
        before it: readback never ends early or skips a frame silently. A caller that
        wants to go on past damaged frames uses :func:`iter_video_frames`.
    SessionError
        The file is missing or FFmpeg cannot open it.
    """
    p = Path(path)
    for frame in iter_video_frames(p):
        if frame.image is None:
            raise VideoDamageError(
                f"{p}: frame {frame.frame_index} (byte {frame.pos_bytes}) is damaged: "
                f"{frame.damage}",
                p,
                frame.frame_index,
                frame.pos_bytes,
            )
        yield frame.image


def read_video_image(path: Path | str, frame_index: int) -> Image:
    """The stored frame at ``frame_index`` (from 0), as :func:`iter_video_images` gives it.

    Only that frame's bytes are checked (its cluster's CRC-32) and decoded (every stored
    frame is intra): the packets before it are demuxed and skipped.

    Raises
    ------
    SessionError
        The file is unreadable or holds fewer frames.
    VideoDamageError
        That frame is damaged.
    """
    p = Path(path)
    with _mapped(p) as buf:
        lay = _walk(buf)
        if not 0 <= frame_index < len(lay.blocks):
            raise SessionError(f"{p}: holds no frame {frame_index}")
        pos = lay.blocks[frame_index]
        if lay.header_damage or _crc_ok(buf, lay.clusters[lay.cluster_of[frame_index]]) is False:
            why = lay.header_damage[0] if lay.header_damage else "fails its CRC-32"
            raise VideoDamageError(
                f"{p}: frame {frame_index} (byte {pos}) is damaged: {why}", p, frame_index, pos
            )
    image = _decode_one(p, pos)
    if image is None:
        raise VideoDamageError(
            f"{p}: frame {frame_index} (byte {pos}) is damaged: it does not decode",
            p,
            frame_index,
            pos,
        )
    return image


def _decode_one(path: Path, pos: int) -> Image | None:
    """The image of the frame whose block data starts at byte ``pos``, as the daemon
    counted it; None when it does not decode or the demuxer does not reach it."""
    import av
    import cv2

    container = _open_input(path, threads=1)  # one frame: no decoder threads to start
    try:
        stream = container.streams.video[0]
        gray = dict(container.metadata).get(TAG_IMAGE, "bgr") == "gray"
        for pkt in container.demux(stream):
            if not pkt.size or pkt.pos is None or pkt.pos < pos:
                continue
            if pkt.pos > pos:
                return None
            if stream.codec_context.name == "mjpeg":
                flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
                img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), flag)
                return None if img is None else np.asarray(img, dtype=np.uint8)
            for frame in [*stream.codec_context.decode(pkt), *stream.codec_context.decode(None)]:
                return None if frame.is_corrupt else _frame_image(frame, gray)
            return None
    except av.FFmpegError:
        return None
    finally:
        container.close()
    return None
