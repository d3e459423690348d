"""Reading a session's stored video back: what it holds, whether it is whole, its frames.

The file is the one :mod:`stipi_daemon.storage.video` records (PyAV's Matroska muxer, one
frame per cluster, every cluster with its CRC-32). :func:`probe_video` (codec, size, frame
count; no check), :func:`check_video` (damage: every cluster's CRC-32, every packet demuxed,
optionally every frame decoded), :func:`iter_video_frames` (every frame in file order,
sound with its image or damaged with the reason: nothing skipped), :func:`iter_video_images`
(the images exactly as the daemon counted them: JPEG packets decoded by ``cv2.imdecode`` as
the camera did, FFV1 frames decoded to the recorded pixel layout; :class:`VideoDamageError`
at a damaged frame), :func:`read_video_image` (one frame; :func:`read_video_images`: a few
in one pass), :func:`count_video_frames` (the frames its structure holds, no frame read).
It computes nothing about the images.
"""

from __future__ import annotations

import mmap
import os
import zlib
from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import SessionError

__all__ = [
    "TAG_CROP",
    "TAG_FRAME_SIZE",
    "TAG_IMAGE",
    "StoredFrame",
    "VideoCheck",
    "VideoDamageError",
    "VideoInfo",
    "check_video",
    "count_video_frames",
    "crop_tag",
    "iter_video_frames",
    "iter_video_images",
    "probe_video",
    "read_video_image",
    "read_video_images",
    "set_decode_threads",
]

#: Matroska tag naming the pixel layout the daemon counted on (``gray`` or ``bgr``).
TAG_IMAGE: Final = "STIPI_IMAGE"
#: Matroska tag holding the stored rectangle ``x0,y0,x1,y1`` of the camera frame [px].
TAG_CROP: Final = "STIPI_CROP"
#: Matroska tag holding the camera frame's size ``WIDTHxHEIGHT`` [px] a cropped video was cut
#: from (only with :data:`TAG_CROP`; files recorded before it have none).
TAG_FRAME_SIZE: Final = "STIPI_FRAME_SIZE"

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
    frame_size : tuple of int or None
        The camera frame's ``(width, height)`` [px]: the stored size without a crop; with
        one, the :data:`TAG_FRAME_SIZE` tag (None where the file has none).
    """

    path: Path
    size_bytes: int
    codec: str
    frames: int
    width: int
    height: int
    image: str
    crop: tuple[int, int, int, int] | None
    frame_size: tuple[int, int] | None


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
    """What :func:`check_video` found in a stored video (``path`` and ``size_bytes`` as in
    :class:`VideoInfo`).

    Attributes
    ----------
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
    its padding byte (the recorder padded the BGR bytes: the same pixels), read from the
    frame's plane (:func:`~stipi_daemon.cameras.base.av_frame_pixels`); another layout
    converted by FFmpeg's scaler."""
    import cv2

    from stipi_daemon.cameras.base import av_frame_pixels

    fmt = frame.format.name
    if (fmt == "gray") == gray and fmt in ("gray", "bgr0"):
        pixels = av_frame_pixels(frame)
        return pixels.copy() if gray else np.asarray(cv2.cvtColor(pixels, cv2.COLOR_BGRA2BGR))
    return np.asarray(frame.to_ndarray(format="gray" if gray else "bgr24"))


def _size_tag(text: str | None) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` as ``(width, height)``; None when absent or not two positive integers
    (a tag someone else wrote: the size is then unknown, not guessed)."""
    parts = (text or "").split("x")
    if len(parts) != 2 or not all(v.isdigit() and int(v) > 0 for v in parts):
        return None
    return int(parts[0]), int(parts[1])


def crop_tag(text: str | None) -> tuple[int, int, int, int] | None:
    """A :data:`TAG_CROP` value ``x0,y0,x1,y1`` as integers [px]; None when empty.

    Raises
    ------
    ValueError
        Not four comma-separated integers.
    """
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


def _is_gray(container: Any) -> bool:
    """Whether the daemon counted the file's frames as gray (its :data:`TAG_IMAGE`)."""
    return bool(dict(container.metadata).get(TAG_IMAGE, "bgr") == "gray")


def _jpeg_image(pkt: Any, gray: bool) -> Image | None:
    """A JPEG packet decoded as the camera decoded it (``cv2.imdecode``); None: it does not."""
    import cv2

    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), flag)
    return None if img is None else np.asarray(img, dtype=np.uint8)


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
        self._path, self._buf, self._lay, self._ctx = path, buf, lay, ctx
        self._released = 0  # mapped bytes let go of (:func:`_release`) [B]
        self._jpeg = ctx.name == "mjpeg"
        self._gray = gray
        self._decode = decode
        self._index = {pos: i for i, pos in enumerate(lay.blocks)}
        self._next = 0  # the next block the demuxer should give
        self._slots: deque[_Slot] = deque()
        # The last cluster's CRC-32 check (blocks come in file order: a cluster's are
        # consecutive, so each cluster is checked once; older files hold several frames each)
        self._crc_cluster = -1
        self._crc_last: bool | None = None
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
            slot.image = _jpeg_image(pkt, self._gray)
            if slot.image is None:
                slot.damage = "its JPEG does not decode"
            slot.done = True
        else:
            self._feed(pkt)

    def _check(self, i: int, pkt: Any) -> str | None:
        cluster = self._lay.cluster_of[i]
        if cluster != self._crc_cluster:
            self._crc_cluster = cluster
            self._crc_last = _crc_ok(self._buf, self._lay.clusters[cluster])
            self._released = _release(self._buf, self._lay.clusters[cluster][2], self._released)
        crc = self._crc_last
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
            reader = _FrameReader(path, buf, lay, stream.codec_context, _is_gray(container), decode)
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


def count_video_frames(path: Path | str) -> int:
    """The number of frames (Matroska blocks) in a stored video, as :func:`check_video`
    counts them (``frames``), from its element headers alone: no frame's bytes read, none
    checked, nothing demuxed (a damaged file: the blocks before the break).

    Raises
    ------
    SessionError
        The file is missing or cannot be read.
    """
    with _mapped(Path(path)) as buf:
        return len(_walk(buf).blocks)


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
        width, height = int(stream.codec_context.width), int(stream.codec_context.height)
        crop = crop_tag(tags.get(TAG_CROP))
        return VideoInfo(
            path=p,
            size_bytes=p.stat().st_size,
            codec=str(stream.codec_context.name),
            frames=frames,
            width=width,
            height=height,
            image=str(tags.get(TAG_IMAGE, "bgr")),
            crop=crop,
            frame_size=(width, height) if crop is None else _size_tag(tags.get(TAG_FRAME_SIZE)),
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
    (image,) = read_video_images(path, [frame_index])
    if isinstance(image, SessionError):
        raise image
    return image


def read_video_images(path: Path | str, frame_indices: Sequence[int]) -> list[Image | SessionError]:
    """The stored frames at ``frame_indices``, each as :func:`read_video_image` gives it or
    the error it would raise (:class:`SessionError`: no such frame; :class:`VideoDamageError`:
    that frame is damaged), in the order asked: one walk and one demux pass for all (a
    report's few frames), each frame's bytes checked and decoded alone.

    Raises
    ------
    SessionError
        The file is missing or cannot be read.
    """
    p = Path(path)
    out: dict[int, Image | SessionError] = {}
    wanted: dict[int, int] = {}  # block data offset [B] -> frame index
    with _mapped(p) as buf:
        lay = _walk(buf)
        for i in frame_indices:
            if not 0 <= i < len(lay.blocks):
                out[i] = SessionError(f"{p}: holds no frame {i}")
                continue
            pos = lay.blocks[i]
            if lay.header_damage or _crc_ok(buf, lay.clusters[lay.cluster_of[i]]) is False:
                why = lay.header_damage[0] if lay.header_damage else "fails its CRC-32"
                out[i] = VideoDamageError(
                    f"{p}: frame {i} (byte {pos}) is damaged: {why}", p, i, pos
                )
            else:
                wanted[pos] = i
    images = _decode_at(p, set(wanted))
    for pos, i in wanted.items():
        image = images.get(pos)
        out[i] = (
            image
            if image is not None
            else VideoDamageError(
                f"{p}: frame {i} (byte {pos}) is damaged: it does not decode", p, i, pos
            )
        )
    return [out[i] for i in frame_indices]


def _decode_at(path: Path, positions: set[int]) -> dict[int, Image | None]:
    """The images of the frames whose block data start at the byte offsets ``positions``,
    as the daemon counted them, in one demux pass up to the last; None for one that does not
    decode, none for one the demuxer does not reach."""
    import av

    out: dict[int, Image | None] = {}
    if not positions:
        return out
    last = max(positions)
    container = _open_input(path, threads=1)  # a few frames: no decoder threads to start
    try:
        stream = container.streams.video[0]
        gray = _is_gray(container)
        for pkt in container.demux(stream):
            if not pkt.size or pkt.pos is None or pkt.pos not in positions:
                if pkt.pos is not None and pkt.pos > last:
                    break
                continue
            out[int(pkt.pos)] = _packet_image(stream.codec_context, pkt, gray)
            if pkt.pos == last:
                break
    except av.FFmpegError:
        pass  # the frames not reached are absent: damaged where they are asked for
    finally:
        container.close()
    return out


def _packet_image(ctx: Any, pkt: Any, gray: bool) -> Image | None:
    """One packet's image as the daemon counted it (None: it does not decode); the decoder
    is drained and reset after it (every stored frame is intra)."""
    import av

    if ctx.name == "mjpeg":
        return _jpeg_image(pkt, gray)
    try:
        frames = [*ctx.decode(pkt), *ctx.decode(None)]
    except av.FFmpegError:
        frames = []
    ctx.flush_buffers()
    if not frames or frames[0].is_corrupt:
        return None
    return _frame_image(frames[0], gray)
