"""A recorded video replayed as a camera (the simulator's video.mkv, a session's stored video).

This module owns reading a video file in a capture thread (its JPEG packets with OpenCV's
FFmpeg backend, other codecs' packets with PyAV),
timestamping frame k at ``t0 + (k - k0) / fps`` on the session clock (k0 the first frame
read, t0 the session time of the first open), pacing delivery at the file's frame rate or
not at all, looping, and the end of a truncated file. It does not analyse frames.

Capture time. A paced replay behaves as a camera: the capture thread reads frame k's
encoded packet ahead, waits until its capture time ``t0 + (k - k0) / fps`` on the session
clock and only then decodes it, so the time from capture to a stored row includes the
decode, as with a real MJPG camera (whose JPEG is available when the frame is captured).
Unpaced, frames are decoded as fast as they can be.

Decoding. For Motion-JPEG files (``MJPG``: every frame an independent JPEG) the capture is
switched to raw packets (``CAP_PROP_FORMAT = -1``) and each JPEG is decoded with
``cv2.imdecode``: straight to gray with ``IMREAD_GRAYSCALE`` when ``gray`` is set (the
JPEG's luma plane, no colour conversion: the fastest route, docs/bench_camera_decode.md),
else to BGR; the JPEG itself travels with the decoded frame (``CameraFrame.packet``), so
the session video stores it without re-encoding. Raw packets also tell a complete JPEG
(ending in the EOI marker ``FF D9``) from the cut-off last frame of a truncated file,
which FFmpeg's own decoder would return half grey. Other codecs (FFV1, H.264, ...) are
demuxed with PyAV one packet ahead and each packet is decoded by PyAV's (FFmpeg's) decoder,
whose state is kept from packet to packet, after the wait; a decoder that holds frames back
(B-frames) hands them over one packet later, and at the end of the file it is flushed, so no
frame is lost. Those frames carry no packet (the session video records them losslessly);
BGR(0) and gray frames are taken as they are decoded (``cv2.cvtColor`` to gray when ``gray``
is set, as before), other pixel formats through FFmpeg's conversion to BGR. Their timestamps
and ``seq`` are as for JPEG files: frame k of the file in presentation order.

Truncated and damaged files. The replay ends cleanly after the last complete frame and
records a note (:meth:`VideoFileCamera.notes`); a damaged frame inside the file (a JPEG
without its end, a packet the decoder rejects or a frame it marks corrupt) is skipped (a
``seq`` gap, counted as dropped) and noted. A complete JPEG is delivered at the size it
decodes to, even when that is not the file's: a frame of another size than the session's
first is the consumer's to refuse (the daemon ends the run on it, naming both sizes), not a
damaged frame. A missing or unreadable file raises
:class:`~stipi_daemon.errors.CameraError` naming it.

Frames are never dropped by this source (the hand-off applies back-pressure); late delivery
when the consumer lags shows in ``stats.max_lag_s``. After a close and reopen the replay
resumes at the frame after the last one delivered.
"""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import numpy.typing as npt

from stipi_daemon.cameras.base import VideoFileCameraConfig, av_frame_pixels
from stipi_daemon.cameras.threaded import RawFrame, ThreadedCamera
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import CameraError

if TYPE_CHECKING:
    import av.container
    import av.packet
    import av.video.frame
    import av.video.stream

__all__ = ["VideoFileCamera", "fourcc_string", "not_a_video", "quiet_opencv"]

#: Decoded frames the capture thread holds ahead of the consumer [-] (paced: frames are
#: decoded at their capture time, so these only absorb the consumer's jitter).
PREFETCH_FRAMES = 8

_JPEG_FOURCCS = frozenset({"MJPG", "JPEG", "AVRN", "LJPG", "MJLS"})
_EOI = b"\xff\xd9"
#: ``metadata()["decoder"]`` of the two reading routes.
DECODER_JPEG = "imdecode (raw MJPG packets)"
DECODER_PYAV = "pyav (packets demuxed ahead, decoded at their capture time)"


@contextmanager
def quiet_opencv() -> Iterator[None]:
    """OpenCV's own log lines (``[ WARN ]``) off while a file is probed; restored after.

    Our error says what is wrong with the file in one line; OpenCV's backend chatter
    (e.g. "backend is generally available but can't be used to capture by name") would
    be a second, unhelpful one.
    """
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


def not_a_video(path: Path) -> str | None:
    """Why ``path`` is not a video FFmpeg can read (``None``: it has a video stream).

    Probed with PyAV, whose FFmpeg logging is off, before OpenCV opens the file:
    OpenCV's bundled FFmpeg prints its own errors ("moov atom not found") to stderr, and
    turning those off would also silence them for the rest of the process.
    """
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return "the file has no video stream"
    except (av.error.FFmpegError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        return str(reason).rstrip(".")
    return None


def fourcc_string(code: float) -> str:
    """The four characters of an OpenCV FOURCC code (``cap.get(CAP_PROP_FOURCC)``)."""
    c = int(code) & 0xFFFFFFFF
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


def _complete_jpeg(packet: npt.NDArray[np.uint8]) -> bool:
    """True if the packet ends with the JPEG end-of-image marker (allowing padding)."""
    tail = packet.reshape(-1)[-16:].tobytes()
    return _EOI in tail


class _Damaged:
    """A packet the decoder rejected, or a frame it marked corrupt."""


_DAMAGED = _Damaged()


class _PacketReader:
    """A video's packets demuxed with PyAV one ahead of their decode (codecs other than JPEG).

    :meth:`next_frame` takes the next packet from the demuxer, waits (the caller's capture
    time) and only then decodes it; the decoder keeps its state from packet to packet, and a
    decoder that holds frames back (B-frames: a packet in decode order may yield no frame,
    or an earlier one) is flushed at the end of the file, so every frame comes out, in
    presentation order.
    """

    def __init__(self, path: Path) -> None:
        self._path = path
        self._open()

    def _open(self) -> None:
        import av

        self._container: av.container.InputContainer = av.open(str(self._path))
        stream = self._container.streams.video[0]
        self._ctx = stream.codec_context
        self._demux = self._container.demux(stream)
        # a packet taken from the demuxer and not decoded yet (skip(), a close while waiting)
        self._ahead: av.packet.Packet[av.video.stream.VideoStream] | None = None
        self._decoded: deque[av.video.frame.VideoFrame] = deque()  # a flush gives several
        self._flushed = False
        #: Why the demuxer stopped early (a damaged container), else None.
        self.demux_error: str | None = None

    def close(self) -> None:
        self._container.close()

    def _next_packet(self) -> av.packet.Packet[av.video.stream.VideoStream] | None:
        """The next non-empty packet in decode order; None at the demuxer's end."""
        import av

        if self._ahead is not None:
            pkt, self._ahead = self._ahead, None
            return pkt
        try:
            for pkt in self._demux:
                if pkt.size:
                    return pkt
        except av.error.FFmpegError as exc:
            self.demux_error = str(getattr(exc, "strerror", None) or exc).rstrip(".")
        return None

    def next_frame(self, wait: Callable[[], bool]) -> av.video.frame.VideoFrame | _Damaged | bool:
        """The next frame in presentation order, its packets decoded only once ``wait()``
        has returned True; ``_DAMAGED`` for a packet the decoder rejects (one frame);
        False when ``wait()`` returned False (closed); True at the end of the file."""
        import av

        while not self._decoded:
            if self._flushed:
                return True
            packet = self._next_packet()  # demuxed ahead: encoded data, not yet decoded
            if not wait():
                if packet is not None:
                    self._ahead = packet
                return False
            try:
                frames = self._ctx.decode(packet)  # None: flush the held-back frames
            except av.error.FFmpegError:
                if packet is None:
                    self._flushed = True
                    continue
                return _DAMAGED
            self._flushed = packet is None
            self._decoded.extend(frames)
        frame = self._decoded.popleft()
        return _DAMAGED if frame.is_corrupt else frame

    def skip(self, n: int) -> int:
        """Skip ``n`` frames; the number skipped (fewer at the end). Packets are skipped
        undecoded while every one is a keyframe and so is the packet after them (intra-only
        video: one packet, one frame); otherwise the file is decoded from its start."""
        done = 0
        while done < n:
            pkt = self._next_packet()
            if pkt is None:
                return done
            if not pkt.is_keyframe:
                break
            done += 1
        else:
            nxt = self._next_packet()
            self._ahead = nxt
            if nxt is None or nxt.is_keyframe:
                return done
        self.close()  # an inter-coded video: decode the frames before the start
        self._open()
        done = 0
        while done < n and not isinstance(self.next_frame(_at_once), bool):
            done += 1
        return done


def _at_once() -> bool:
    return True


@dataclass
class _Handle:
    cap: cv2.VideoCapture | None  # raw JPEG packets through OpenCV
    reader: _PacketReader | None  # other codecs through PyAV
    pos: int  # index in the file of the next frame read
    bad_frames: list[int] = field(default_factory=list)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
        if self.reader is not None:
            self.reader.close()


class VideoFileCamera(ThreadedCamera[_Handle]):
    """Replays a video file as a camera.

    Parameters
    ----------
    path : str or Path
        Video file.
    clock : SessionClock
        Session clock.
    loop : bool
        Restart at ``start_s`` when the file ends; ``seq`` and times keep increasing.
    pace : bool
        Deliver frame k at its capture time on the session clock (the file's frame rate);
        ``False``: as fast as it decodes (same timestamps).
    start_s : float
        Start position in the file [s], >= 0.
    gray : bool
        Deliver ``(H, W)`` gray frames.
    t0_s : float, optional
        Session time [s] of the first frame; default: the session time of the first open.
    """

    def __init__(
        self,
        path: str | Path,
        clock: SessionClock,
        *,
        loop: bool = False,
        pace: bool = True,
        start_s: float = 0.0,
        gray: bool = True,
        t0_s: float | None = None,
    ) -> None:
        super().__init__(clock, capacity=PREFETCH_FRAMES, drop_oldest=False, paced=pace)
        if not (start_s >= 0.0 and math.isfinite(start_s)):
            raise ValueError(f"start_s must be a finite number >= 0, got {start_s}")
        self.path = Path(path)
        self.loop = loop
        self.pace = pace
        self.start_s = start_s
        self.gray = gray
        self._t0_s = t0_s
        self._fps = float("nan")
        self._size: tuple[int, int] | None = None
        self._fourcc = ""
        self._declared_frames = -1
        self._decoder = ""  # DECODER_JPEG or DECODER_PYAV, once opened
        self._k0 = 0
        self._pass_base_seq = [0]  # seq of the first frame of each pass (loop)
        self._seq_next = 0

    @classmethod
    def from_config(
        cls, config: VideoFileCameraConfig, clock: SessionClock, *, t0_s: float | None = None
    ) -> VideoFileCamera:
        """Build from a :class:`~.base.VideoFileCameraConfig`."""
        return cls(
            config.path,
            clock,
            loop=config.loop,
            pace=config.pace,
            start_s=config.start_s,
            gray=config.gray,
            t0_s=t0_s,
        )

    @property
    def name(self) -> str:
        return f"video file {self.path}"

    @property
    def nominal_fps(self) -> float:
        return self._fps

    @property
    def declared_frames(self) -> int:
        """Frame count in the file's header (-1 unknown; a truncated file has fewer)."""
        return self._declared_frames

    def _first_seq(self) -> int:
        return self._k0

    def _first_capture_s(self) -> float | None:
        return self._t0_s  # frame k0 is captured at t0 (None before the first open)

    def _metadata(self) -> dict[str, Any]:
        return {
            "kind": "file",
            "path": str(self.path),
            "fps": self._fps,
            "size": list(self._size) if self._size else None,
            "fourcc": self._fourcc,
            "declared_frames": self._declared_frames,
            "start_s": self.start_s,
            "loop": self.loop,
            "pace": self.pace,
            "gray": self.gray,
            "decoder": self._decoder or (DECODER_JPEG if self._raw_possible() else DECODER_PYAV),
        }

    def _raw_possible(self) -> bool:
        return self._fourcc.upper() in _JPEG_FOURCCS

    # -- source hooks -----------------------------------------------------------------------

    def _open_source(self) -> _Handle:
        p = self.path
        if not p.exists():
            raise CameraError(f"video file {p}: not found")
        if not p.is_file():
            raise CameraError(f"video file {p}: not a regular file")
        if not os.access(p, os.R_OK):
            raise CameraError(f"video file {p}: permission denied")
        problem = not_a_video(p)
        if problem is not None:
            raise CameraError(f"video file {p}: not a video OpenCV/FFmpeg can read ({problem})")
        with quiet_opencv():
            cap = cv2.VideoCapture(str(p), cv2.CAP_FFMPEG)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"video file {p}: not a video OpenCV/FFmpeg can read")
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if not (math.isfinite(fps) and fps > 0.0):
            cap.release()
            raise CameraError(f"video file {p}: no frame rate in the file (got {fps})")
        first_open = self._size is None
        self._fps = fps
        self._fourcc = fourcc_string(cap.get(cv2.CAP_PROP_FOURCC))
        self._size = (
            int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
        self._declared_frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if first_open:
            self._k0 = round(self.start_s * fps)
            self._seq_next = self._k0
            self._pass_base_seq = [self._k0]
            if self._t0_s is None:
                self._t0_s = self._clock.now()
            if self._declared_frames > 0 and self._k0 >= self._declared_frames:
                cap.release()
                raise CameraError(
                    f"video file {p}: start_s {self.start_s:g} s is past its end "
                    f"({self._declared_frames} frames at {fps:g} fps)"
                )
        # Resume after the last frame delivered (the first open: at k0).
        last = self._last_seq
        resume_seq = self._k0 if last is None else last + 1
        base = max(b for b in self._pass_base_seq if b <= resume_seq)
        self._seq_next = resume_seq
        handle = self._reader_handle(cap)
        self._skip_to(handle, self._k0 + (resume_seq - base))
        return handle

    def _reader_handle(self, cap: cv2.VideoCapture) -> _Handle:
        """The file's reading route: raw JPEG packets through ``cap``, else PyAV (``cap``
        released); at its first frame."""
        if self._raw_possible() and bool(cap.set(cv2.CAP_PROP_FORMAT, -1)):
            self._decoder = DECODER_JPEG
            return _Handle(cap, None, 0)
        cap.release()
        return self._pyav_handle()

    def _pyav_handle(self) -> _Handle:
        """The file opened with PyAV, at its first frame."""
        import av

        try:
            reader = _PacketReader(self.path)
        except (av.error.FFmpegError, IndexError) as exc:
            raise CameraError(f"video file {self.path}: PyAV cannot read it ({exc})") from exc
        self._decoder = DECODER_PYAV
        return _Handle(None, reader, 0)

    def _skip_to(self, h: _Handle, pos: int) -> None:
        """Advance to file frame ``pos``: JPEG packets by grabbing (no decode; works on
        truncated files, whose index is gone), other codecs by :meth:`_PacketReader.skip`."""
        if h.reader is not None:
            h.pos += h.reader.skip(pos - h.pos)
            return
        assert h.cap is not None
        while h.pos < pos:
            if not h.cap.grab():
                break
            h.pos += 1

    def _read(self, h: _Handle) -> RawFrame | None:
        while True:
            image = self._read_image(h, self._seq_next)
            stop = getattr(self._thread_state, "stop", None)
            if stop is not None and stop.is_set():
                return None  # closed while waiting for the capture time
            if image is None:
                if self.loop and h.pos > self._k0 and self._seq_next > self._pass_base_seq[-1]:
                    h.close()
                    fresh = self._reopen_for_loop()
                    h.cap, h.reader, h.pos = fresh.cap, fresh.reader, fresh.pos
                    self._pass_base_seq.append(self._seq_next)
                    continue
                return None
            if isinstance(image, int):  # damaged frame inside the file: skip it
                self._seq_next += 1
                continue
            seq = self._seq_next
            self._seq_next += 1
            img, packet = image
            return RawFrame(seq, self._t_capture(seq), img, packet)

    def _t_capture(self, seq: int) -> float:
        """Capture time of frame ``seq`` on the session clock [s]."""
        t0 = self._t0_s if self._t0_s is not None else 0.0
        return t0 + (seq - self._k0) / self._fps

    def _reopen_for_loop(self) -> _Handle:
        if self._decoder == DECODER_PYAV:
            h = self._pyav_handle()
        else:
            cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
            if not cap.isOpened():
                raise CameraError(f"video file {self.path}: cannot be reopened to loop")
            h = self._reader_handle(cap)
        self._skip_to(h, self._k0)
        return h

    def _captured(self, seq: int) -> bool:
        """Capture thread: wait for frame ``seq``'s capture time when paced (its encoded
        packet is read, not yet decoded); False when closed meanwhile."""
        return not self.pace or self._wait_until(self._t_capture(seq))

    def _read_image(
        self, h: _Handle, seq: int
    ) -> tuple[npt.NDArray[np.uint8], bytes | None] | int | None:
        """Frame ``seq``'s image and its JPEG packet (raw MJPG reading, else None); an int
        (its file index) for a damaged frame that is followed by more; None at the end
        (after noting a truncated last frame) or when the camera is closed while waiting.

        Paced, the encoded frame is read ahead and decoded once its capture time has come
        (see the module docstring)."""
        if h.reader is not None:
            return self._read_decoded(h, seq)
        assert h.cap is not None
        ok, data = h.cap.read()  # raw mode: the JPEG as stored, not decoded
        if not ok or data is None:
            self._note_short_end(h)
            return None
        index = h.pos
        h.pos += 1
        for k in h.bad_frames:  # followed by more data: damaged, not the truncated end
            self._note(f"video file {self.path}: frame {k} is damaged and was skipped")
        h.bad_frames.clear()
        if not self._captured(seq):
            return None
        packet = np.asarray(data, dtype=np.uint8)
        decoded = None
        if packet.size > 0 and _complete_jpeg(packet):
            flag = cv2.IMREAD_GRAYSCALE if self.gray else cv2.IMREAD_COLOR
            decoded = cv2.imdecode(packet.reshape(-1), flag)
        if decoded is not None:  # of any size: a JPEG of another size is a frame of it
            return np.asarray(decoded, dtype=np.uint8), packet.tobytes()
        h.bad_frames.append(index)
        return index

    def _read_decoded(
        self, h: _Handle, seq: int
    ) -> tuple[npt.NDArray[np.uint8], bytes | None] | int | None:
        """:meth:`_read_image` for a file PyAV decodes (no packet travels with the frame)."""
        assert h.reader is not None
        got = h.reader.next_frame(lambda: self._captured(seq))
        if got is False:
            return None  # closed while waiting
        if got is True:
            if h.reader.demux_error is not None:
                self._note(
                    f"video file {self.path}: unreadable after frame {h.pos - 1} "
                    f"({h.reader.demux_error}); the replay ended there"
                )
            else:
                self._note_short_end(h)
            return None
        index = h.pos
        h.pos += 1
        if isinstance(got, _Damaged):
            self._note(f"video file {self.path}: frame {index} is damaged and was skipped")
            return index
        return self._image(got), None

    def _image(self, frame: av.video.frame.VideoFrame) -> npt.NDArray[np.uint8]:
        """A decoded frame as the camera delivers it: gray ``(H, W)`` or BGR ``(H, W, 3)``."""
        pixels = av_frame_pixels(frame)
        if pixels.ndim == 2:
            return (
                pixels.copy() if self.gray else np.asarray(cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR))
            )
        if pixels.shape[2] == 4:  # FFV1's BGR: 4 bytes a pixel, read in place
            code = cv2.COLOR_BGRA2GRAY if self.gray else cv2.COLOR_BGRA2BGR
            return np.asarray(cv2.cvtColor(pixels, code), dtype=np.uint8)
        return np.asarray(cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)) if self.gray else pixels

    def _note_short_end(self, h: _Handle) -> None:
        if h.bad_frames and h.bad_frames[-1] == h.pos - 1:
            last_bad = h.bad_frames.pop()
            self._note(
                f"video file {self.path}: truncated: frame {last_bad} is incomplete; the replay "
                f"ended at frame {last_bad - 1}, the last complete one"
                + (
                    f" ({self._declared_frames} frames declared)"
                    if self._declared_frames > 0
                    else ""
                )
            )
        elif 0 < h.pos < self._declared_frames:
            self._note(
                f"video file {self.path}: ended after {h.pos} of the {self._declared_frames} "
                "frames its header declares (truncated?)"
            )

    def _close_source(self, h: _Handle) -> None:
        h.close()
