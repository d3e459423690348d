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
holds every frame. Every stored frame is tied to its ``frames`` row by a
``video_frames`` row (``seq, frame_index, pts_ms, t_capture_host_s``), made as the frame is
muxed and handed to the session writer in batches, once the oldest waiting row is
:data:`ROW_BATCH_FRACTION` of its commit interval old (a second table in every frame's
commit cost about 10 us per frame, docs/performance.md); a killed recording's video may
therefore hold a few frames more than rows, and :meth:`VideoRecorder.close` hands over the
rest. The muxer flushes its I/O after every packet (``flush_packets=1``),
so a process killed at any moment leaves a file that FFmpeg opens and plays up to the
newest frame but one (the muxer holds the newest block until the next arrives), within one
commit interval of the newest committed ``frames`` row. When writing fails (disk full), the
recorder stops, closes the file as far as it can and hands the error to the session
writer (:meth:`~.writer.SessionWriter.fail`), so rows and video stop together.

Reading: :func:`probe_video` (codec, size, frame count), :func:`iter_video_images` (the
images exactly as the daemon counted them: JPEG packets decoded by ``cv2.imdecode`` as the
camera did, FFV1 frames decoded to the recorded pixel layout), :func:`read_video_image`.
It computes nothing about the images.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
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
    "VIDEO_MODES",
    "VideoInfo",
    "VideoMode",
    "VideoRecorder",
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
#: Muxer options: flush the file after every packet (the crash-survival argument).
MUXER_OPTIONS: Final = {"flush_packets": "1"}
#: Frames waiting for the FFV1 encoder thread at most [-]. At 60 fps they span 133 ms, less
#: than the default commit interval. When it is full the frame is left out of the video
#: (counted): recording never slows the measurement down.
ENCODER_QUEUE_FRAMES: Final = 8
#: Longest a caller that can wait (``record(wait=True)``) waits for the encoders to take a
#: frame [s of wall time] before leaving it out: shorter than a camera stream's shortest stall
#: timeout (``cameras.stream.STALL_MIN_WALL_S``, 0.125 s), so that waiting for the encoders
#: never reads as a stalled camera; a machine that cannot keep up falls behind (the
#: acquisition's lag) and, past this, leaves frames out of the video, counted.
ENCODER_WAIT_MAX_S: Final = 0.1
#: ``video_frames`` rows are handed to the session writer once the oldest one waiting is this
#: fraction of its ``commit_interval_s`` old [-] (and when the recorder closes): the rows are
#: an index into the video, read after the run, so they need not be in every frame's commit.
ROW_BATCH_FRACTION: Final = 0.5

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
        import av  # noqa: F401  (loaded now, not at the first frame in the daemon's loop)

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
        try:
            if self._container is None:
                self._open(t_capture_s, image, packet)
            if self._encoders is not None:  # FFV1: encoded in the encoder threads
                return self._submit(seq, t_capture_s, image, wait)
            self._store(seq, t_capture_s, image, packet)
        except SessionError as exc:  # the database failed: stop the video with the rows
            self._stop(str(exc), exc)
            return False
        except (OSError, ValueError) as exc:  # av.FFmpegError is an OSError or ValueError
            self._stop(f"{self.path}: video recording stopped: {exc}")
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
        elif now - self._rows_since >= self._row_batch_s:
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
        """An encoder or the muxing failed (an FFmpeg error is an OSError or ValueError; a
        SessionError is the writer's): recording stops, with the rows."""
        if isinstance(exc, SessionError):
            self._stop(str(exc), exc, join=False)
            return
        what = str(exc) if isinstance(exc, (OSError, ValueError)) else repr(exc)
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
        self._writer.add_event(
            t_capture_s,
            "video_started",
            {
                "file": self.path.name,
                "mode": self.mode,
                "codec": self._codec,
                "image": layout,
                "size": [w, h],
                "crop": None if self._crop is None else list(self._crop),
                "t0_s": t_capture_s,
            },
        )

    def _stored_image(self, image: Image) -> Image:
        """What a lossless frame stores of ``image``: the crop (converted to gray where
        asked: crop, then convert, per pixel the same) or all of it."""
        if self._crop is None:
            return image
        x0, y0, x1, y1 = self._crop
        image = image[y0:y1, x0:x1]
        return self._to_gray(image) if self._to_gray is not None else image

    def _stop(self, reason: str, error: SessionError | None = None, *, join: bool = True) -> None:
        self._failed = reason
        _log.error("%s", reason)
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
        except (OSError, ValueError) as exc:
            if self._failed is None:
                self._failed = f"{self.path}: video could not be closed cleanly: {exc}"

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
    [ms] by the FFV1 encoder ``ctx``; FFmpeg errors propagate (``OSError``/``ValueError``)."""
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
    FFmpeg errors propagate (``OSError`` or ``ValueError``).
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


def _open_input(path: Path, threads: int | None = None) -> Any:
    """``path`` opened for reading, its decoder with ``threads`` threads (default: the
    :func:`set_decode_threads` setting; 0: FFmpeg's choice)."""
    import av

    if not path.is_file():
        raise SessionError(f"{path}: video file is missing")
    try:
        container = av.open(str(path), "r")
    except (OSError, ValueError) as exc:
        raise SessionError(f"{path}: not a readable video ({exc})") from None
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


def probe_video(path: Path | str) -> VideoInfo:
    """Codec, size and complete-frame count of a stored video (demuxes every packet).

    Raises
    ------
    SessionError
        The file is missing or FFmpeg cannot read it.
    """
    p = Path(path)
    container = _open_input(p)
    try:
        if not container.streams.video:
            raise SessionError(f"{p}: holds no video stream")
        stream = container.streams.video[0]
        frames = 0
        try:
            for pkt in container.demux(stream):
                if pkt.size:
                    frames += 1
        except (OSError, ValueError):  # a cut-off tail (kill -9): the frames before count
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


def iter_video_images(path: Path | str) -> Iterator[Image]:
    """The stored frames in file order, as the daemon counted them.

    A JPEG packet is decoded with ``cv2.imdecode`` (gray or colour, as the camera did), an
    FFV1 frame to ``gray`` or ``bgr24``; a cropped recording yields the stored rectangle.
    A packet that does not decode (the cut-off tail of a killed recording) ends the
    iteration.
    """
    import cv2

    p = Path(path)
    container = _open_input(p)
    try:
        stream = container.streams.video[0]
        gray = dict(container.metadata).get(TAG_IMAGE, "bgr") == "gray"
        jpeg = stream.codec_context.name == "mjpeg"
        flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
        try:
            for pkt in container.demux(stream):
                if not pkt.size:
                    continue
                if jpeg:
                    img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), flag)
                    if img is None:
                        return
                    yield np.asarray(img, dtype=np.uint8)
                    continue
                for frame in stream.codec_context.decode(pkt):
                    yield _frame_image(frame, gray)
        except (OSError, ValueError):
            return
    finally:
        container.close()


def read_video_image(path: Path | str, frame_index: int) -> Image:
    """The stored frame at ``frame_index`` (from 0), as :func:`iter_video_images` gives it.

    Only that frame is decoded (every stored frame is intra): the packets before it are
    demuxed and skipped.

    Raises
    ------
    SessionError
        The file is unreadable or holds fewer frames.
    """
    import cv2

    p = Path(path)
    container = _open_input(p, threads=1)  # one frame: no decoder threads to start
    try:
        stream = container.streams.video[0]
        gray = dict(container.metadata).get(TAG_IMAGE, "bgr") == "gray"
        k = 0
        try:
            for pkt in container.demux(stream):
                if not pkt.size:
                    continue
                if k < frame_index:
                    k += 1
                    continue
                if stream.codec_context.name == "mjpeg":
                    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
                    img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), flag)
                    if img is not None:
                        return np.asarray(img, dtype=np.uint8)
                for frame in stream.codec_context.decode(pkt):
                    return _frame_image(frame, gray)
                break
        except (OSError, ValueError):
            pass
    finally:
        container.close()
    raise SessionError(f"{p}: holds no frame {frame_index}")
