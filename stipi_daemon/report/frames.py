"""Representative camera frames of a measurement, kept as PNGs in the session.

The daemon chooses three raw frames while it records
(:class:`~stipi_daemon.measurement.representative_frames.RepresentativeFrames`: the middle
of the pitting hold, the deepest pit near S_0, the recovered tissue near S_max). This
module owns their storage in the session directory and reading them back:
``frames/representative_<kind>.png`` (lossless, the camera's pixels exactly) and
``frames/representative.json`` (frame number, capture time [s] and S_k [px] each), and the
kinds' captions (:data:`KINDS`). Reading takes each frame from the session's ``video.mkv``
by its ``seq`` (the primary data; a cropped recording's rectangle is placed at its offset
in the camera frame, the rest marked as not stored, :class:`FrameImage`); the PNG only
where the video cannot give the frame, and the frame says why. It does not choose
frames, threshold or count pixels (:mod:`stipi_daemon.analysis.imaging`) nor draw them
(:mod:`stipi_daemon.report.render`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import SessionError
from stipi_daemon.measurement.representative_frames import RepresentativeFrame

__all__ = [
    "FRAMES_DIR",
    "FRAMES_INDEX",
    "KINDS",
    "NOT_STORED_FILL",
    "FrameImage",
    "RepresentativeFrame",
    "read_representative_frames",
    "write_representative_frames",
]

#: Sub-directory of the session directory holding the representative frames.
FRAMES_DIR: Final = "frames"
#: Index file (JSON) of the representative frames, inside :data:`FRAMES_DIR`.
FRAMES_INDEX: Final = "representative.json"
#: The kinds of representative frame, in display order, with their captions.
KINDS: Final[dict[str, str]] = {
    "pitting": "middle of the hold",
    "recovery_start": "near S_0, deepest pit",
    "recovered": "largest S_k, recovered",
}


def write_representative_frames(
    session_dir: Path, frames: tuple[RepresentativeFrame, ...]
) -> list[Path]:
    """Store ``frames`` as lossless PNGs and an index in ``<session_dir>/frames/``.

    Returns
    -------
    list of Path
        The files written (PNGs, then the index); empty when there is no frame.

    Raises
    ------
    SessionError
        A file cannot be written (path and reason named).
    """
    if not frames:
        return []
    directory = Path(session_dir) / FRAMES_DIR
    try:
        directory.mkdir(exist_ok=True)
    except OSError as exc:
        raise SessionError(f"{directory}: cannot create frames directory: {exc}") from exc
    written: list[Path] = []
    index: dict[str, dict[str, Any]] = {}
    for f in frames:
        path = directory / f"representative_{f.kind}.png"
        try:
            ok = cv2.imwrite(str(path), f.image)
        except cv2.error as exc:
            raise SessionError(f"{path}: cannot write frame: {exc}") from exc
        if not ok:
            raise SessionError(f"{path}: cannot write frame (OpenCV imwrite failed)")
        written.append(path)
        index[f.kind] = {
            "file": path.name,
            "seq": f.seq,
            "t_capture_s": f.t_s,
            "s_k_px": f.s_k_px,
            "shape": list(f.image.shape),
        }
    index_path = directory / FRAMES_INDEX
    try:
        index_path.write_text(json.dumps(index, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise SessionError(f"{index_path}: cannot write: {exc}") from exc
    written.append(index_path)
    return written


#: A frame's pixels as the video stores them (gray, or BGR; a crop's rectangle only).
_Pixels = npt.NDArray[np.uint8]
#: A rectangle of the camera frame, ``(x0, y0, x1, y1)`` [px] (x1 and y1 exclusive).
Box = tuple[int, int, int, int]
#: Value of the pixels of a cropped recording's frame that the video does not store (white:
#: above every threshold p < 255, never counted; the figure hatches them).
NOT_STORED_FILL: Final = 255


class FrameImage(np.ndarray[Any, np.dtype[np.uint8]]):
    """A representative frame's pixels in camera coordinates, with where they come from.

    What :func:`read_representative_frames` gives as each frame's ``image``; views and
    arrays computed from it are plain (the class attributes' defaults).

    Attributes
    ----------
    source : str
        One line for the figure: the video frame the pixels were read from, or why the
        stored PNG is shown instead.
    stored_box : tuple of int or None
        ``(x0, y0, x1, y1)`` [px]: the only pixels the video stores (a cropped recording,
        ``storage.video_roi_only``: the ROI's bounding box, as gray); the rest of the frame
        is :data:`NOT_STORED_FILL`, not camera data. None: every pixel is the camera's.
    """

    source: str = ""
    stored_box: Box | None = None


def _frame_image(image: npt.NDArray[np.uint8], source: str, box: Box | None) -> FrameImage:
    out = np.ascontiguousarray(image, dtype=np.uint8).view(FrameImage)
    out.source = source
    out.stored_box = box
    return out


@dataclass(frozen=True)
class _Video:
    """The session's video and its frames' ``seq`` and index, read once for all the
    representative frames; ``crop``: the stored rectangle (None: whole frames)."""

    path: Path
    seqs: npt.NDArray[np.int64]
    frame_index: npt.NDArray[np.int64]
    crop: Box | None


def _open_video(session_dir: Path) -> _Video | str:
    """The session's video, or one line saying why its frames cannot be read from it."""
    from stipi_daemon.storage import SessionReader
    from stipi_daemon.storage.video_readback import probe_video

    try:
        with SessionReader(session_dir) as reader:
            video = reader.video_path
            if video is None:
                return "the session stores no video"
            rows = reader.video_frames()
    except SessionError as exc:
        return f"the session's video_frames are not readable ({exc})"
    if not video.is_file():
        return f"{video.name} is missing"
    try:
        crop = probe_video(video).crop
    except SessionError:
        return f"{video.name} is not readable"
    return _Video(video, np.asarray(rows["seq"]), np.asarray(rows["frame_index"]), crop)


def _video_images(video: _Video | str, seqs: Sequence[int]) -> dict[int, _Pixels | str]:
    """The stored images of the frames ``seqs`` from the session's video (the primary
    data), read in one pass, or for each one line saying why it cannot be read there."""
    from stipi_daemon.storage.video_readback import read_video_images

    if isinstance(video, str):
        return dict.fromkeys(seqs, video)
    name = video.path.name
    out: dict[int, _Pixels | str] = {}
    index: dict[int, int] = {}
    for seq in seqs:
        where = video.frame_index[video.seqs == seq]
        if where.size:
            index[seq] = int(where[0])
        else:
            out[seq] = f"{name} holds no frame {seq} (no video_frames row: left out of the video)"
    try:
        images = read_video_images(video.path, list(index.values()))
    except SessionError:
        images = [SessionError("unreadable")] * len(index)
    for (seq, k), image in zip(index.items(), images, strict=True):
        out[seq] = (
            f"{name} frame {k} (seq {seq}) is missing or does not decode"
            if isinstance(image, SessionError)
            else image
        )
    return out


def _video_image(
    video: _Video | str, seq: int, image: _Pixels | str, shape: Sequence[int]
) -> FrameImage | str:
    """Frame ``seq``'s stored ``image`` (:func:`_video_images`) in camera coordinates of
    the recorded ``shape`` (a crop placed at its offset, the rest :data:`NOT_STORED_FILL`),
    or one line saying why it cannot be shown from the video."""
    if isinstance(image, str):
        return image
    if isinstance(video, str):  # not reached: without a video every image is a line
        return video
    name = video.path.name
    k = int(video.frame_index[video.seqs == seq][0])
    if video.crop is None:
        if list(image.shape) != list(shape):
            return f"{name} frame {k} is {list(image.shape)}, the index says {list(shape)}"
        return _frame_image(image, f"from {name}, its stored frame {k}", None)
    x0, y0, x1, y1 = video.crop
    height, width = int(shape[0]), int(shape[1])
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height) or image.shape[:2] != (
        y1 - y0,
        x1 - x0,
    ):
        return f"{name} frame {k}: its crop {video.crop} does not fit the {width}x{height} frame"
    canvas = np.full((height, width, *image.shape[2:]), NOT_STORED_FILL, dtype=np.uint8)
    canvas[y0:y1, x0:x1] = image
    return _frame_image(canvas, f"from {name}, its stored frame {k}", video.crop)


def read_representative_frames(session_dir: Path) -> tuple[RepresentativeFrame, ...]:
    """Read the frames :func:`write_representative_frames` stored (none: empty tuple).

    Each frame is read from the session's video by its ``seq`` (a cropped recording's
    rectangle placed at its offset in the camera frame, see :class:`FrameImage`); where the
    video cannot give it (no video, the frame left out of it, not decodable) from the PNG,
    and the image's ``source`` says why.

    Raises
    ------
    SessionError
        The index is not valid JSON of the expected shape, or a frame the video cannot give
        has its PNG missing or unreadable, or not of the recorded shape.
    """
    index_path = Path(session_dir) / FRAMES_DIR / FRAMES_INDEX
    if not index_path.is_file():
        return ()
    try:
        index = json.loads(index_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SessionError(f"{index_path}: not readable JSON: {exc}") from exc
    if not isinstance(index, dict):
        raise SessionError(f"{index_path}: expected an object keyed by frame kind")
    entries: list[tuple[str, str, int, float, int, list[int]]] = []
    for kind in KINDS:
        entry = index.get(kind)
        if entry is None:
            continue
        try:
            name, seq = str(entry["file"]), int(entry["seq"])
            t_s, s_k, shape = float(entry["t_capture_s"]), int(entry["s_k_px"]), entry["shape"]
            entries.append((kind, name, seq, t_s, s_k, [int(v) for v in shape]))
        except (KeyError, TypeError, ValueError) as exc:
            raise SessionError(f"{index_path}: entry {kind!r} is malformed ({exc})") from exc
    video = _open_video(Path(session_dir)) if entries else ""
    stored = _video_images(video, [e[2] for e in entries])
    out: list[RepresentativeFrame] = []
    for kind, name, seq, t_s, s_k, shape in entries:
        image = _video_image(video, seq, stored[seq], shape)
        if isinstance(image, str):
            image = _png_image(index_path.parent / name, shape, image)
        out.append(RepresentativeFrame(kind, seq, t_s, s_k, image))
    return tuple(out)


def _png_image(path: Path, shape: list[int], why: str) -> FrameImage:
    """The stored PNG at ``path``, its ``source`` naming it and ``why`` not the video."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if image is None:
        raise SessionError(
            f"{path}: representative frame missing or not a readable PNG (and not in the "
            f"video: {why})"
        )
    if list(image.shape) != shape or image.dtype != np.uint8:
        raise SessionError(
            f"{path}: shape {list(image.shape)} {image.dtype}, index says {shape} uint8"
        )
    source = f"from {FRAMES_DIR}/{path.name}: not from the video, as {why}"
    return _frame_image(np.asarray(image, dtype=np.uint8), source, None)
