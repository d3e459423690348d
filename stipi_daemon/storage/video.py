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

import contextlib
import logging
import math
import os
import queue
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
#: How often a caller waiting for the encoder (``record(wait=True)``) looks whether recording
#: stopped meanwhile [s of wall time].
ENCODER_WAIT_POLL_S: Final = 0.1
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
#: FFmpeg threads of the FFV1 encoder [-] (1: it runs in the recorder's encoder thread only).
ENCODER_THREADS: Final = 1
#: Matroska tag naming the pixel layout the daemon counted on (``gray`` or ``bgr``).
TAG_IMAGE: Final = "STIPI_IMAGE"
#: Matroska tag holding the stored rectangle ``x0,y0,x1,y1`` of the camera frame [px].
TAG_CROP: Final = "STIPI_CROP"

Image = npt.NDArray[np.uint8]
Crop = tuple[int, int, int, int]


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
        self._queue: queue.Queue[tuple[int, float, Image] | None] | None = None
        self._thread: threading.Thread | None = None
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
        encoder instead (a source that can wait: a file, the simulator). FFV1 frames are
        encoded in that thread; a failure there stops recording and shows at the session
        writer's next call.

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
            if self._queue is not None:  # FFV1: encoded in the encoder thread
                if not self._enqueue(self._queue, (seq, t_capture_s, image), wait):
                    self.left_out += 1  # the encoder cannot keep up: leave this frame out
                    return False
                return self._failed is None
            self._store(seq, t_capture_s, image, packet)
        except SessionError as exc:  # the database failed: stop the video with the rows
            self._stop(str(exc), exc)
            return False
        except (OSError, ValueError) as exc:  # av.FFmpegError is an OSError or ValueError
            self._stop(f"{self.path}: video recording stopped: {exc}")
            return False
        return True

    def _enqueue(
        self,
        q: queue.Queue[tuple[int, float, Image] | None],
        item: tuple[int, float, Image],
        wait: bool,
    ) -> bool:
        """Hand a frame to the encoder thread: at once or not at all, or, with ``wait``, as
        soon as the encoder takes one (False: recording stopped meanwhile)."""
        while True:
            try:
                q.put(item, block=wait, timeout=ENCODER_WAIT_POLL_S if wait else None)
                return True
            except queue.Full:
                if not wait or self._failed is not None or self._closed:
                    return False

    def _store(self, seq: int, t_capture_s: float, image: Image, packet: bytes | None) -> None:
        """Mux one frame and add its ``video_frames`` row (raises on failure)."""
        pts = max(self._last_pts + 1, round((t_capture_s - self._t0_s) * 1000.0))
        self._mux(pts, image, packet)
        self._last_pts = pts
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

    def _encode_loop(self, q: queue.Queue[tuple[int, float, Image] | None]) -> None:
        """The FFV1 encoder thread (PyAV releases the GIL while FFmpeg encodes), at a lower CPU
        priority (Linux: the process's niceness + :data:`ENCODER_NICE` for this thread), so
        the measurement's threads come first."""
        with contextlib.suppress(OSError, AttributeError):
            base = os.getpriority(os.PRIO_PROCESS, 0)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(19, base + ENCODER_NICE))
        while (item := q.get()) is not None:
            if self._failed is not None:
                continue  # drain, so that record() never blocks on a dead encoder
            try:
                self._store(*item, None)
            except SessionError as exc:
                self._stop(str(exc), exc, join=False)
            except (OSError, ValueError) as exc:
                self._stop(f"{self.path}: video recording stopped: {exc}", join=False)

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
            q: queue.Queue[tuple[int, float, Image] | None] = queue.Queue(ENCODER_QUEUE_FRAMES)
            self._queue = q
            self._thread = threading.Thread(
                target=self._encode_loop, args=(q,), name=f"video encoder {self.path}", daemon=True
            )
            self._thread.start()
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

    def _mux(self, pts: int, image: Image, packet: bytes | None) -> None:
        if self._codec != "mjpeg" and self._crop is not None:
            x0, y0, x1, y1 = self._crop  # crop, then convert the crop (per pixel: the same)
            image = image[y0:y1, x0:x1]
            if self._to_gray is not None:
                image = self._to_gray(image)
        write_video_frame(self._container, self._stream, pts, image, packet)

    def _stop(self, reason: str, error: SessionError | None = None, *, join: bool = True) -> None:
        self._failed = reason
        _log.error("%s", reason)
        self._writer.fail(error if error is not None else SessionError(reason))
        if join:
            self._close_container()

    def _join_encoder(self) -> None:
        q, thread, self._queue, self._thread = self._queue, self._thread, None, None
        if q is not None and thread is not None:
            q.put(None)
            thread.join()

    def _close_container(self) -> None:
        self._join_encoder()
        container, self._container = self._container, None
        if container is None:
            return
        try:
            if self._codec == "ffv1" and self._failed is None:
                for out in self._stream.encode(None):
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
            stream = container.add_stream("ffv1", options={"level": "3", "slicecrc": "1"})
            stream.pix_fmt = "gray" if layout == "gray" else "bgr0"
            stream.codec_context.gop_size = 1
            # the encoder's own time base (PyAV's default is 1/24 s): frames are rebased
            # onto it before encoding, which would round 60 fps pts to 42 ms steps
            stream.codec_context.time_base = PTS_TIME_BASE
            # FFmpeg's own threads off: the recorder already encodes in a thread of its own
            # (at its niceness, which threads FFmpeg starts would not share), and FFV1's
            # slice threads cost CPU: 3.5 ms per 420x420 gray frame with them, 1.9 ms
            # without (docs/performance.md, "Demo speed").
            stream.codec_context.thread_count = ENCODER_THREADS
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


def write_video_frame(
    container: Any, stream: Any, pts: int, image: Image, packet: bytes | None
) -> None:
    """Store one frame at ``pts`` [ms] in a stream of :func:`open_video_file`.

    An ``mjpeg`` stream muxes ``packet`` (a complete JPEG) as it is, a keyframe, without
    decoding it; an ``ffv1`` stream encodes ``image`` (gray ``(H, W)`` or BGR ``(H, W, 3)``).
    FFmpeg errors propagate (``OSError`` or ``ValueError``).
    """
    import av

    if stream.codec_context.name == "mjpeg":
        if packet is None:
            raise ValueError("a frame without its JPEG packet in an MJPG recording")
        pkt = av.Packet(packet)
        pkt.stream = stream
        pkt.time_base = PTS_TIME_BASE
        pkt.pts = pkt.dts = pts
        pkt.is_keyframe = True
        container.mux_one(pkt)
        return
    fmt = "gray" if image.ndim == 2 else "bgr24"
    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format=fmt)
    frame.pts = pts
    frame.time_base = PTS_TIME_BASE
    for out in stream.encode(frame):
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


def _open_input(path: Path) -> Any:
    import av

    if not path.is_file():
        raise SessionError(f"{path}: video file is missing")
    try:
        container = av.open(str(path), "r")
    except (OSError, ValueError) as exc:
        raise SessionError(f"{path}: not a readable video ({exc})") from None
    if _decode_threads:
        for stream in container.streams.video:
            stream.codec_context.thread_count = _decode_threads
            if _decode_threads == 1:
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
    container = _open_input(p)
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
