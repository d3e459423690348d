"""A session's video: the camera stream as received, recorded into ``video.mkv``.

This module owns recording the frames the daemon measured into the session's Matroska file
with PyAV (FFmpeg's muxer and codecs). :class:`VideoRecorder` writes
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

Reading the file back (what it holds, whether it is whole, its frames) is
:mod:`stipi_daemon.storage.video_readback`.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Literal

import numpy as np

from stipi_daemon.errors import SessionError
from stipi_daemon.storage.ordered_workers import OrderedWorkers
from stipi_daemon.storage.video_readback import TAG_CROP, TAG_FRAME_SIZE, TAG_IMAGE, Crop, Image

if TYPE_CHECKING:
    from stipi_daemon.storage.writer import SessionWriter

__all__ = [
    "ROW_BATCH_MAX_FRAMES",
    "UNINDEXED_FRAMES_MAX",
    "VIDEO_MODES",
    "VideoError",
    "VideoMode",
    "VideoRecorder",
    "open_video_file",
    "write_video_frame",
]

_log = logging.getLogger(__name__)


class VideoError(SessionError):
    """The session video's own failure (FFmpeg could not write it: a full disk, any muxer
    or encoder error), as the recorder hands it to the session writer
    (:meth:`~.writer.SessionWriter.fail`): the writer's next call raises a
    :class:`SessionError` caused by it, so the daemon can say that the video failed."""


VideoMode = Literal["passthrough", "lossless", "off"]
#: The ``storage.video`` settings.
VIDEO_MODES: Final[tuple[VideoMode, ...]] = ("passthrough", "lossless", "off")

#: Time base of the stored presentation times: milliseconds (Matroska's own unit).
PTS_TIME_BASE: Final = Fraction(1, 1000)
#: Muxer options: flush the file after every packet (the crash-survival argument), and a
#: cluster of its own for every frame (``cluster_size_limit`` 1 B: FFmpeg's muxer holds a
#: cluster in memory until it ends, by default after 4 kB, so a killed recording of small
#: frames lost several; and the CRC-32 it writes per cluster then names one frame, 20-odd
#: bytes per frame, :func:`~.video_readback.check_video`).
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
        self._shape: tuple[int, ...] = ()  # of the frames handed to record (the first's)
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
        #: Longest a caller that can wait waits for the encoders [s of wall time]; inf on
        #: a simulated run's clock, which waits for the daemon: no frame is left out there.
        self.wait_max_s = ENCODER_WAIT_MAX_S
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
            The decoded frame the daemon counts S_k on (gray ``(H, W)`` or BGR ``(H, W, 3)``);
            every frame of the shape of the first (another one stops the recording: FFmpeg
            encodes an FFV1 frame of another size at the stream's size without an error).
        packet : bytes or None
            The camera's encoded frame (a complete JPEG), if it has one.
        """
        if self._failed is not None or self._closed:
            return False
        self._last_t_s = t_capture_s
        try:
            if self._container is None:
                self._open(t_capture_s, image, packet)
                self._shape = image.shape
            elif image.shape != self._shape:  # FFmpeg would encode or mux it regardless
                raise ValueError(
                    f"frame {seq} has shape {image.shape}, the video's frames {self._shape} "
                    "(a stream keeps its frame size)"
                )
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
        if not self._encoders.submit(item, wait_s=self.wait_max_s if wait else 0.0):
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
        frame_size = (w, h)
        if crop is not None:
            x0, y0, x1, y1 = crop
            if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
                raise ValueError(f"video crop {crop} lies outside the {w}x{h} frame")
            w, h = x1 - x0, y1 - y0
        self._crop = crop
        codec: Literal["mjpeg", "ffv1"] = "mjpeg" if passthrough else "ffv1"
        container, stream = open_video_file(
            self.path,
            codec,
            layout,
            (w, h),
            crop=crop,
            frame_size=frame_size,
            frame_rate=self._frame_rate,
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
        self._writer.fail(error if error is not None else VideoError(reason))
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
    frame_size: tuple[int, int] | None = None,
    frame_rate: Fraction | None = None,
    options: dict[str, str] | None = None,
) -> tuple[Any, Any]:
    """Open ``path`` as a Matroska file with one video stream, as a session video is stored.

    ``codec`` ``mjpeg``: JPEG packets muxed as they are (:func:`write_video_frame`);
    ``ffv1``: frames encoded losslessly (level 3, every frame intra, CRC per slice), ``gray``
    or ``bgr0`` by ``layout`` (``"gray"`` or ``"bgr"``, stored as the :data:`TAG_IMAGE` tag).
    Times are in :data:`PTS_TIME_BASE`. ``size`` is ``(width, height)`` [px]; ``crop``, if
    any, is stored as the :data:`TAG_CROP` tag, with the camera frame's ``frame_size``
    ``(width, height)`` [px] it was cut from as :data:`TAG_FRAME_SIZE`; ``frame_rate``
    [1/s], if known, is declared (players and OpenCV read it as the file's frame rate);
    ``options`` are the muxer's (default :data:`MUXER_OPTIONS`). Returns ``(container,
    stream)``; close the container.
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
            if frame_size is not None:
                container.metadata[TAG_FRAME_SIZE] = f"{frame_size[0]}x{frame_size[1]}"
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
