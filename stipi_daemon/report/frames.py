"""Representative camera frames of a measurement, kept as PNGs in the session.

The daemon chooses three raw frames while it records
(:class:`~stipi_daemon.measurement.representative_frames.RepresentativeFrames`: the middle
of the pitting hold, the deepest pit near S_0, the recovered tissue near S_max). This
module owns their storage in the session directory and reading them back:
``frames/representative_<kind>.png`` (lossless, the camera's pixels exactly) and
``frames/representative.json`` (frame number, capture time [s] and S_k [px] each), and the
kinds' captions (:data:`KINDS`). Reading takes each frame from the session's ``video.mkv``
by its ``seq`` when the video holds it whole (the PNG otherwise). It does not choose
frames, threshold or count pixels (:mod:`stipi_daemon.analysis.imaging`) nor draw them
(:mod:`stipi_daemon.report.render`).
"""

from __future__ import annotations

import json
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


#: The session video's frame numbers: (path, ``seq`` of each stored frame, its index).
_VideoIndex = tuple[Path, npt.NDArray[np.int64], npt.NDArray[np.int64]]


def _video_index(session_dir: Path) -> _VideoIndex | None:
    """The session's ``video.mkv`` and its frames' ``seq`` and index, read once for all
    the representative frames; None when there is no video, it holds a crop rather than
    whole frames, or it cannot be read (the PNGs are used then)."""
    from stipi_daemon.storage import VIDEO_NAME, SessionReader
    from stipi_daemon.storage.video import probe_video

    video = session_dir / VIDEO_NAME
    if not video.is_file():
        return None
    try:
        if probe_video(video).crop is not None:
            return None
        with SessionReader(session_dir) as reader:
            rows = reader.video_frames()
    except SessionError:
        return None
    return video, np.asarray(rows["seq"]), np.asarray(rows["frame_index"])


def _video_image(index: _VideoIndex | None, seq: int, shape: Any) -> npt.NDArray[np.uint8] | None:
    """Frame ``seq`` from the session's video (the primary data) when it holds that frame
    whole with the recorded shape; None otherwise (the PNG is used then)."""
    from stipi_daemon.storage.video import read_video_image

    if index is None:
        return None
    video, seqs, frame_index = index
    where = frame_index[seqs == seq]
    if not where.size:
        return None
    try:
        image = read_video_image(video, int(where[0]))
    except SessionError:
        return None
    return image if list(image.shape) == list(shape) else None


def read_representative_frames(session_dir: Path) -> tuple[RepresentativeFrame, ...]:
    """Read the frames :func:`write_representative_frames` stored (none: empty tuple).

    Raises
    ------
    SessionError
        The index is not valid JSON of the expected shape, or a PNG named in it is missing
        or unreadable, or does not have the recorded shape.
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
    out: list[RepresentativeFrame] = []
    video = _video_index(Path(session_dir)) if index else None
    for kind in KINDS:
        entry = index.get(kind)
        if entry is None:
            continue
        try:
            name, seq = str(entry["file"]), int(entry["seq"])
            t_s, s_k, shape = float(entry["t_capture_s"]), int(entry["s_k_px"]), entry["shape"]
        except (KeyError, TypeError, ValueError) as exc:
            raise SessionError(f"{index_path}: entry {kind!r} is malformed ({exc})") from exc
        path = index_path.parent / name
        image: Any = _video_image(video, seq, shape)
        if image is None:
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
        if image is None:
            raise SessionError(f"{path}: representative frame missing or not a readable PNG")
        if list(image.shape) != list(shape) or image.dtype != np.uint8:
            raise SessionError(
                f"{path}: shape {list(image.shape)} {image.dtype}, index says {shape} uint8"
            )
        out.append(RepresentativeFrame(kind, seq, t_s, s_k, np.asarray(image, dtype=np.uint8)))
    return tuple(out)
