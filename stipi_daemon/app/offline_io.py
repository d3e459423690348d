"""Reading recorded measurements from disk for the offline commands (``analyze``, ``calibrate``).

This module owns the file side of offline analysis: numeric CSV files (sample series,
calibration pairs) with errors naming file, line and column; videos decoded with OpenCV
and counted into S_k (Eqs. 1-2) with :class:`~stipi_daemon.analysis.imaging.FrameProcessor`;
a stored session's frames, force samples and arm time read through
:class:`~stipi_daemon.storage.SessionReader`; a simulator's ``ground_truth.json``. It turns
them into :class:`~stipi_daemon.measurement.replay.Recording` values and does no analysis itself
(:mod:`stipi_daemon.measurement.replay`).

CSV conventions: a header row of column names (units in the names), comma separated,
lines starting with ``#`` and blank lines ignored, extra columns ignored. Numbers in any
form Python's ``float`` reads; an empty field is a missing value (NaN) only where a column
allows it (a force sample lost by the probe).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, RectROI, describe_roi
from stipi_daemon.app.imaging import check_roi_fits, roi_placement
from stipi_daemon.errors import ConfigError, DataFileError
from stipi_daemon.measurement.replay import Recording
from stipi_daemon.measurement.state_machine import (
    CameraRecovered,
    CameraStalled,
    Event,
    LinkLost,
    LinkRestored,
)
from stipi_daemon.storage import SessionReader, SessionState
from stipi_daemon.yamlfile import decode_utf8

__all__ = [
    "FORCE_TIME_COLUMNS",
    "FRAME_TIME_COLUMNS",
    "CsvTable",
    "SessionData",
    "VideoCount",
    "count_session_video",
    "count_video",
    "load_ground_truth",
    "match_frame_times",
    "parse_roi",
    "read_csv_table",
    "read_force_csv",
    "read_frame_times_csv",
    "read_session",
    "roi_in_video",
    "video_crop",
]

FloatArray = npt.NDArray[np.float64]

#: Accepted time columns of a frame-times CSV, in order of preference: the simulator's
#: ``frames.csv`` (``t_s``), a session export's ``frames.csv`` (capture time first).
FRAME_TIME_COLUMNS: tuple[str, ...] = ("t_s", "t_capture_host_s", "t_host_s")
#: Accepted time columns of a force CSV: plain ``t_s``, the simulator's ``force.csv``
#: (``t_true_s``), a session export's ``force_samples.csv`` (``t_host_s``).
FORCE_TIME_COLUMNS: tuple[str, ...] = ("t_s", "t_true_s", "t_host_s")


# --------------------------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CsvTable:
    """Numeric columns read from a CSV file.

    Attributes
    ----------
    path : Path
        The file.
    columns : dict of str to numpy.ndarray
        Requested columns (key: the name as found in the file), float64.
    lines : numpy.ndarray
        1-based file line of every row (for messages about a row).
    """

    path: Path
    columns: dict[str, FloatArray]
    lines: npt.NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.lines.size)


def _read_text(p: Path) -> str:
    """The text of ``p``; :class:`DataFileError` when it is missing or unreadable."""
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise DataFileError(f"{p}: no such file") from None
    except OSError as exc:
        raise DataFileError(f"{p}: cannot read: {exc}") from None
    return decode_utf8(data, str(p), DataFileError)


def read_csv_table(
    path: str | Path,
    required: Sequence[str | Sequence[str]],
    *,
    optional: Sequence[str] = (),
    nullable: Sequence[str] = (),
) -> CsvTable:
    """Read numeric columns of a CSV file.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    required : sequence of str or of alternatives
        Columns that must be present. An entry that is a sequence of names is satisfied by
        the first of them present in the header.
    optional : sequence of str
        Columns read when present.
    nullable : sequence of str
        Columns where an empty field is allowed (read as NaN).

    Returns
    -------
    CsvTable

    Raises
    ------
    DataFileError
        The file is missing or unreadable, has no header, lacks a required column (named,
        with the header's line), has a row with too few fields or a value that is not a
        number (file, line and column named), or holds no data row.
    """
    p = Path(path)
    text = _read_text(p)
    rows = [
        (n, row)
        for n, row in enumerate(csv.reader(text.splitlines()), start=1)
        if row and any(c.strip() for c in row) and not row[0].lstrip().startswith("#")
    ]
    if not rows:
        raise DataFileError(f"{p}: empty file (expected a header row of column names)")
    header_line, header = rows[0]
    names = [h.strip() for h in header]
    chosen: list[str] = []
    for entry in required:
        alternatives = (entry,) if isinstance(entry, str) else tuple(entry)
        found = next((a for a in alternatives if a in names), None)
        if found is None:
            want = " or ".join(f"'{a}'" for a in alternatives)
            raise DataFileError(
                f"{p}: line {header_line}: missing column {want} (header has: {', '.join(names)})"
            )
        chosen.append(found)
    chosen.extend(o for o in optional if o in names and o not in chosen)
    index = {name: names.index(name) for name in chosen}
    values: dict[str, list[float]] = {name: [] for name in chosen}
    lines: list[int] = []
    for n, row in rows[1:]:
        for name, i in index.items():
            if i >= len(row):
                raise DataFileError(
                    f"{p}: line {n}: {len(row)} fields, column '{name}' (field {i + 1}) missing"
                )
            field = row[i].strip()
            if field == "" and name in nullable:
                values[name].append(math.nan)
                continue
            try:
                v = float(field)
            except ValueError:
                raise DataFileError(
                    f"{p}: line {n}: column '{name}': {field!r} is not a number"
                ) from None
            if math.isinf(v) or (math.isnan(v) and name not in nullable):
                raise DataFileError(f"{p}: line {n}: column '{name}': {field!r} is not finite")
            values[name].append(v)
        lines.append(n)
    if not lines:
        raise DataFileError(f"{p}: no data rows after the header (line {header_line})")
    return CsvTable(
        path=p,
        columns={k: np.asarray(v, dtype=np.float64) for k, v in values.items()},
        lines=np.asarray(lines, dtype=np.int64),
    )


def _check_increasing(table: CsvTable, column: str) -> None:
    t = table.columns[column]
    bad = np.flatnonzero(np.diff(t) <= 0.0)
    if bad.size:
        i = int(bad[0]) + 1
        raise DataFileError(
            f"{table.path}: line {int(table.lines[i])}: column '{column}': time {float(t[i])!r} "
            f"does not increase (previous row: {float(t[i - 1])!r})"
        )


def read_force_csv(path: str | Path) -> tuple[FloatArray, FloatArray, str]:
    """Force samples: times [s], forces [N] (NaN where empty) and the time column used.

    Accepts a time column from :data:`FORCE_TIME_COLUMNS` and ``force_n``; times must
    increase strictly.
    """
    table = read_csv_table(path, [FORCE_TIME_COLUMNS, "force_n"], nullable=["force_n"])
    time_col = next(c for c in FORCE_TIME_COLUMNS if c in table.columns)
    _check_increasing(table, time_col)
    return table.columns[time_col], table.columns["force_n"], time_col


def read_frame_times_csv(path: str | Path) -> tuple[FloatArray, str]:
    """Frame times [s] in video order and the column used (:data:`FRAME_TIME_COLUMNS`)."""
    table = read_csv_table(path, [FRAME_TIME_COLUMNS])
    time_col = next(c for c in FRAME_TIME_COLUMNS if c in table.columns)
    _check_increasing(table, time_col)
    return table.columns[time_col], time_col


# --------------------------------------------------------------------------------------------
# ROI, video
# --------------------------------------------------------------------------------------------


def parse_roi(text: str) -> CircleROI | RectROI | None:
    """Parse an ROI given on the command line.

    Forms: ``circle:CX,CY,R`` (centre and radius [px]), ``rect:X,Y,W,H`` (top-left corner,
    width and height [px]), ``full`` (the whole frame, None).

    Raises
    ------
    DataFileError
        The text is not one of these forms.
    """
    t = text.strip()
    if t == "full":
        return None
    kind, _, rest = t.partition(":")
    parts = [x.strip() for x in rest.split(",")] if rest else []
    try:
        if kind == "circle" and len(parts) == 3:
            cx, cy, r = (float(x) for x in parts)
            return CircleROI(kind="circle", cx_px=cx, cy_px=cy, radius_px=r)
        if kind == "rect" and len(parts) == 4:
            x, y, w, h = (int(x) for x in parts)
            return RectROI(kind="rect", x_px=x, y_px=y, width_px=w, height_px=h)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(part) for part in err["loc"])
        raise DataFileError(f"--roi {text!r}: {field}: {err['msg']}") from None
    except ValueError as exc:  # float()/int() of a part
        raise DataFileError(f"--roi {text!r}: {exc}") from None
    raise DataFileError(f"--roi {text!r}: expected circle:CX,CY,R or rect:X,Y,W,H (pixels) or full")


#: A stored rectangle ``(x0, y0, x1, y1)`` of the camera frame, half-open [px].
Crop = tuple[int, int, int, int]


@dataclass(frozen=True)
class VideoCount:
    """S_k of every decoded frame of a video.

    Attributes
    ----------
    path : Path
        The video.
    s_k_px : numpy.ndarray
        S_k per frame, Eq. (2) [px], in file order. For a session video
        (:func:`count_session_video`) index i is the stored frame i (``video_frames``
        ``frame_index``) and NaN where that frame did not decode.
    flags : tuple of frozenset of Flag
        Quality flags per frame (saturated frame, ROI clipped or empty).
    fps : float
        Frame rate the container declares [1/s] (0 when unknown).
    frame_shape : tuple of int
        Decoded frame shape.
    threshold_p : int
        Threshold used [8-bit intensity].
    roi : CircleROI or RectROI or None
        ROI used, in camera-frame coordinates [px].
    crop : tuple of int or None
        ``(x0, y0, x1, y1)`` of the camera frame the video stores [px] (its ``STIPI_CROP``
        tag); None: the whole frame.
    frames_in_file : int or None
        Frames the readback found in the file [-] (session videos; None: not read so).
    undecodable : tuple of int
        File indices of stored frames the readback reports damaged (their S_k is NaN).
    damage : tuple of str
        The readback's reason for each of them (``frame I (byte B): why``), and the line of
        a structure that breaks off (frames after it cannot be located).
    broken : bool
        The file's structure breaks off after its last frame read: frames after it, if
        any, are damaged rather than absent.
    """

    path: Path
    s_k_px: FloatArray
    flags: tuple[frozenset[Flag], ...]
    fps: float
    frame_shape: tuple[int, ...]
    threshold_p: int
    roi: CircleROI | RectROI | None
    crop: Crop | None = None
    frames_in_file: int | None = None
    undecodable: tuple[int, ...] = ()
    damage: tuple[str, ...] = ()
    broken: bool = False

    @property
    def saturated_frames(self) -> int:
        """Number of frames flagged saturated."""
        return sum(1 for f in self.flags if Flag.SATURATED_FRAME in f)


def video_crop(path: Path) -> Crop | None:
    """The ``STIPI_CROP`` tag of a video (a session video that stores only the ROI's
    bounding box, or its export): ``(x0, y0, x1, y1)`` of the camera frame [px]; None when
    the file has no such tag or PyAV cannot open it.

    Raises
    ------
    DataFileError
        The tag is present but not four integers ``x0 < x1``, ``y0 < y1``, ``x0, y0 >= 0``.
    """
    import av

    from stipi_daemon.storage.video_readback import TAG_CROP, crop_tag

    try:
        with av.open(str(path), "r") as container:
            text = dict(container.metadata).get(TAG_CROP)
    except (OSError, ValueError):
        return None
    if not text:
        return None
    try:
        x0, y0, x1, y1 = crop_tag(str(text)) or (0, 0, 0, 0)
    except ValueError:
        raise DataFileError(f"{path}: tag {TAG_CROP} {text!r} is not x0,y0,x1,y1 [px]") from None
    if not (0 <= x0 < x1 and 0 <= y0 < y1):
        raise DataFileError(f"{path}: tag {TAG_CROP} {text!r} is not a rectangle x0,y0,x1,y1")
    return x0, y0, x1, y1


def roi_in_video(
    roi: CircleROI | RectROI | None,
    video_size: tuple[int, int],
    crop: Crop | None,
    field: str,
    path: Path,
    frame_size: tuple[int, int] | None = None,
) -> CircleROI | RectROI | None:
    """The ROI (camera-frame coordinates [px]) in the coordinates of a video's frames.

    A video that stores the whole frame (``crop`` None, ``video_size`` = ``(width,
    height)`` [px]) takes the ROI as it is; it must lie within the frame. A video that
    stores only ``crop`` = ``(x0, y0, x1, y1)`` of the camera frame takes the ROI moved by
    ``(-x0, -y0)`` (exact: integer offsets); it must lie within the camera frame
    (``frame_size``, when known) and within the stored box (pixels beyond it were never
    recorded), and the whole frame (``roi`` None) cannot be counted on it.

    Raises
    ------
    ConfigError
        One line naming ``field`` (what set the ROI, e.g. ``--roi``), the ROI and the frame
        or stored box it does not fit.
    """
    if crop is None:
        check_roi_fits(roi, video_size[0], video_size[1], field)
        return roi
    x0, y0, x1, y1 = crop
    frame = "" if frame_size is None else f" of the {frame_size[0]}x{frame_size[1]} camera frame"
    box = f"the box {x0},{y0},{x1},{y1} [px]{frame}"
    if roi is None:
        raise ConfigError(
            f"{field}: the whole frame cannot be counted: the video {path} holds only {box} "
            "(give an ROI inside that box, in camera-frame coordinates)"
        )
    if frame_size is not None:
        check_roi_fits(roi, frame_size[0], frame_size[1], field)
    local = _shifted_roi(roi, crop)
    assert local is not None
    placement = roi_placement(local, x1 - x0, y1 - y0)
    if placement != "inside":
        where = "outside" if placement == "outside" else "partly outside"
        raise ConfigError(
            f"{field}: {describe_roi(roi)} lies {where} {box}, all the video {path} holds "
            "(pixels beyond it were not recorded; the ROI must lie within that box)"
        )
    return local


def _processor_for(
    processor: FrameProcessor | None,
    frame: Any,
    settings: tuple[int, CircleROI | RectROI | None, float],
    path: Path,
    index: int,
) -> FrameProcessor:
    """The frame processor for a video's frame ``index``: made for the first frame with
    ``settings`` (threshold p, ROI in the video's pixels, saturation limit [-]); a later
    frame of another shape is refused (:class:`DataFileError` naming the file and frame)."""
    if processor is None:
        threshold_p, roi, saturation = settings
        return FrameProcessor(frame.shape, threshold_p, roi, saturation_limit_fraction=saturation)
    if frame.shape != processor.frame_shape:
        raise DataFileError(
            f"{path}: frame {index} has shape {frame.shape}, the first frame "
            f"{processor.frame_shape}"
        )
    return processor


def count_video(
    path: str | Path,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    *,
    saturation_limit_fraction: float = 0.01,
    max_frames: int | None = None,
    roi_field: str | None = None,
    check_size: Callable[[int, int], None] | None = None,
) -> VideoCount:
    """Decode a video with OpenCV and count S_k on every frame (Eqs. 1-2).

    Frames are decoded as 8-bit BGR and converted to gray inside the ROI by
    :class:`~stipi_daemon.analysis.imaging.FrameProcessor`. With ``roi_field`` (what set
    the ROI, e.g. ``"--roi"``), an ROI that does not lie within the first frame is refused
    before anything is counted (:func:`~stipi_daemon.app.imaging.check_roi_fits`). A video
    exported from a session that stored only the ROI's bounding box (its ``STIPI_CROP``
    tag, :func:`video_crop`) is counted with ``roi``, in camera-frame coordinates, moved
    into that box (:func:`roi_in_video`; an ROI not inside the box, or none, is refused).
    ``check_size`` is called with the first frame's width and height [px] before anything
    is counted, when the video stores whole camera frames (it raises to refuse them).

    Raises
    ------
    ConfigError
        ``roi_field`` is given and the ROI lies (partly) outside the frame, or the video
        stores a box of the frame and the ROI is none or not inside it.
    DataFileError
        The file is missing, OpenCV cannot open it, it holds no decodable frame, or a
        frame's size differs from the first one's (frame number named).
    AnalysisError
        Bad threshold or frame layout (from the frame processor).
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise DataFileError(f"{p}: no such video file")
    from stipi_daemon.cameras.video_file import not_a_video, quiet_opencv

    problem = not_a_video(p)
    if problem is not None:
        raise DataFileError(f"{p}: OpenCV cannot open this video ({problem})")
    crop = video_crop(p)
    with quiet_opencv():
        cap = cv2.VideoCapture(str(p))
    try:
        if not cap.isOpened():
            raise DataFileError(f"{p}: OpenCV cannot open this video (unsupported or corrupt)")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        processor: FrameProcessor | None = None
        counts: list[int] = []
        flags: list[frozenset[Flag]] = []
        while max_frames is None or len(counts) < max_frames:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            if processor is None:
                size = (int(frame.shape[1]), int(frame.shape[0]))
                if check_size is not None and crop is None:
                    check_size(*size)
                local_roi = roi
                if crop is not None or roi_field is not None:
                    local_roi = roi_in_video(roi, size, crop, roi_field or "the ROI", p)
            processor = _processor_for(
                processor,
                frame,
                (threshold_p, local_roi, saturation_limit_fraction),
                p,
                len(counts),
            )
            m = processor.measure(frame)
            counts.append(m.s_k_px)
            flags.append(m.flags)
    finally:
        cap.release()
    if processor is None:
        raise DataFileError(f"{p}: the video holds no decodable frame")
    return VideoCount(
        path=p,
        s_k_px=np.asarray(counts, dtype=np.float64),
        flags=tuple(flags),
        fps=fps if math.isfinite(fps) and fps > 0.0 else 0.0,
        frame_shape=tuple(processor.frame_shape),
        threshold_p=processor.p,
        roi=roi,
        crop=crop,
    )


def _shifted_roi(roi: CircleROI | RectROI | None, crop: Crop | None) -> CircleROI | RectROI | None:
    """The ROI in the coordinates of a video that stores only ``crop`` = ``(x0, y0, x1, y1)``
    of the camera frame (the shift is exact: integer offsets)."""
    if roi is None or crop is None:
        return roi
    x0, y0 = crop[0], crop[1]
    if isinstance(roi, RectROI):
        return roi.model_copy(update={"x_px": roi.x_px - x0, "y_px": roi.y_px - y0})
    return roi.model_copy(update={"cx_px": roi.cx_px - x0, "cy_px": roi.cy_px - y0})


def count_session_video(
    path: str | Path,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    *,
    saturation_limit_fraction: float = 0.01,
    roi_field: str = "the ROI",
    frame_size: tuple[int, int] | None = None,
) -> VideoCount:
    """Count S_k (Eqs. 1-2) on a session's ``video.mkv``, on the images as the daemon counted
    them (:func:`stipi_daemon.storage.video_readback.iter_video_frames`: the JPEGs decoded as the
    camera decoded them, FFV1 bit-exact). ``roi`` is in camera-frame coordinates; a video
    of the ROI's bounding box is counted with the ROI moved into it (:func:`roi_in_video`,
    which refuses an ROI outside the frame or the stored box, naming ``roi_field``, before
    anything is counted; the camera frame's size is the video's own record of it, else
    ``frame_size`` ``(width, height)`` [px] when known).

    The result has one S_k per stored frame (file index), NaN for a frame the readback
    reports damaged (listed in :attr:`VideoCount.undecodable`, with the readback's reasons
    in :attr:`VideoCount.damage`); a file whose structure breaks off ends there (the
    readback's line in :attr:`VideoCount.damage`, :attr:`VideoCount.broken` True).

    Raises
    ------
    ConfigError
        The ROI does not fit the frame or the stored box (one line naming ``roi_field``).
    SessionError
        The video is missing, unreadable, or its header is damaged.
    DataFileError
        It holds no decodable frame, or frames of different sizes.
    """
    from stipi_daemon.storage.video_readback import VideoDamageError, iter_video_frames, probe_video

    p = Path(path)
    info = probe_video(p)
    camera = info.frame_size if info.frame_size is not None else frame_size  # the file's own
    local_roi = roi_in_video(roi, (info.width, info.height), info.crop, roi_field, p, camera)
    processor: FrameProcessor | None = None
    counts: list[float] = []
    flags: list[frozenset[Flag]] = []
    undecodable: list[int] = []
    damage: list[str] = []
    broken = False
    try:
        for stored in iter_video_frames(p):
            frame = stored.image
            if frame is None:
                damage.append(f"frame {len(counts)} (byte {stored.pos_bytes}): {stored.damage}")
                undecodable.append(len(counts))
                counts.append(math.nan)
                flags.append(frozenset())
                continue
            processor = _processor_for(
                processor,
                frame,
                (threshold_p, local_roi, saturation_limit_fraction),
                p,
                stored.frame_index,
            )
            m = processor.measure(frame)
            counts.append(float(m.s_k_px))
            flags.append(m.flags)
    except VideoDamageError as exc:
        if exc.frame_index is None and not counts:
            raise
        damage.append(str(exc))
        broken = True
    if processor is None:
        raise DataFileError(f"{p}: the video holds no decodable frame")
    return VideoCount(
        path=p,
        s_k_px=np.asarray(counts, dtype=np.float64),
        flags=tuple(flags),
        fps=0.0,
        frame_shape=tuple(processor.frame_shape),
        threshold_p=processor.p,
        roi=roi,
        crop=info.crop,
        frames_in_file=len(counts),
        undecodable=tuple(undecodable),
        damage=tuple(damage),
        broken=broken,
    )


def match_frame_times(
    video: VideoCount, times_s: FloatArray | None, source: str
) -> tuple[FloatArray, FloatArray, list[str]]:
    """Pair a video's S_k with frame times; returns times, S_k and notes.

    Without times, frame k is at ``k / fps``. With more times than frames (a video cut
    short) the first ones are used; with fewer, :class:`DataFileError`.
    """
    n = video.s_k_px.size
    notes: list[str] = []
    if times_s is None:
        if video.fps <= 0.0:
            raise DataFileError(
                f"{video.path}: the video declares no frame rate; give --frame-times FILE.csv"
            )
        notes.append(
            f"frame times from the video's frame rate ({video.fps:g} fps), starting at 0 s: "
            "give --frame-times for the recorded capture times"
        )
        return np.arange(n, dtype=np.float64) / video.fps, video.s_k_px, notes
    if times_s.size < n:
        raise DataFileError(
            f"{source}: {times_s.size} frame times but the video {video.path.name} has {n} frames"
        )
    if times_s.size > n:
        notes.append(
            f"{source} lists {times_s.size} frames, the video {video.path.name} decodes {n}: "
            f"the last {times_s.size - n} frame(s) are missing from the video (cut short?)"
        )
    return times_s[:n], video.s_k_px, notes


# --------------------------------------------------------------------------------------------
# Sessions, ground truth
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SessionData:
    """What a stored session holds for offline analysis.

    Attributes
    ----------
    directory : Path
        The session directory.
    session_id : str
    status : SessionState
        ``complete``, ``fault``, ``aborted``, ``interrupted`` or ``recording``.
    manifest : dict
        ``manifest.json``.
    summary : dict or None
        ``summary.json`` if it was written.
    frame_times_s, s_k_px : numpy.ndarray
        Frame capture times [s] and stored S_k [px], in storage order.
    force_times_s, force_n : numpy.ndarray
        Force sample times [s] and forces [N] (NaN where NULL).
    t_arm_s : float or None
        Time of the ``idle -> armed`` transition, if recorded.
    link_events : tuple of Event
        The watchdog events the daemon recorded (``link_down``, ``link_up``,
        ``camera_stalled``, ``camera_recovered``) as state-machine events.
    video_path : Path or None
        The session's video if the file exists.
    frame_seq : numpy.ndarray or None
        Each frame row's camera ``seq``.
    video_seq : numpy.ndarray or None
        ``seq`` of each frame stored in the video (``video_frames``, in row order; empty
        for a session recorded without video or before schema version 2).
    video_frame_index : numpy.ndarray or None
        The file index (``frame_index``, from 0) of each of those frames, row by row.
    """

    directory: Path
    session_id: str
    status: SessionState
    manifest: dict[str, Any]
    summary: dict[str, Any] | None
    frame_times_s: FloatArray
    s_k_px: FloatArray
    force_times_s: FloatArray
    force_n: FloatArray
    t_arm_s: float | None
    video_path: Path | None
    link_events: tuple[Event, ...] = ()
    frame_seq: npt.NDArray[np.int64] | None = None
    video_seq: npt.NDArray[np.int64] | None = None
    video_frame_index: npt.NDArray[np.int64] | None = None

    def recording(self, s_k_px: FloatArray | None = None) -> Recording:
        """The session's samples as a :class:`Recording` (optionally with new S_k)."""
        return Recording(
            frame_times_s=self.frame_times_s,
            s_k_px=self.s_k_px if s_k_px is None else s_k_px,
            force_times_s=self.force_times_s,
            force_n=self.force_n,
            t_arm_s=self.t_arm_s,
            link_events=self.link_events,
        )

    def frame_size_px(self) -> tuple[int, int] | None:
        """``(width, height)`` [px] of the frames the session counted its S_k in: its
        manifest's calibration record, else (sessions recorded before it was kept there)
        its summary's camera; None when neither says.

        Raises
        ------
        DataFileError
            The recorded size is not ``[width, height]``, two integers > 0.
        """
        size = (self.manifest.get("calibration") or {}).get("frame_size_px")
        where = f"{self.directory / 'manifest.json'}: field 'calibration.frame_size_px'"
        if size is None and self.summary is not None:
            camera = ((self.summary.get("run") or {}).get("camera") or {}).get("source") or {}
            size = camera.get("size")
            where = f"{self.directory / 'summary.json'}: field 'run.camera.source.size'"
        if size is None:
            return None
        if not (
            isinstance(size, list)
            and len(size) == 2
            and all(type(v) is int and v > 0 for v in size)
        ):
            raise DataFileError(f"{where}: expected [width, height] in px, got {size!r}")
        return (size[0], size[1])


def read_session(directory: str | Path) -> SessionData:
    """Read a session's samples, arm time, manifest and summary (one database snapshot).

    Frames are timed by their capture time (``t_capture_host_s``), the time the live
    shell feeds the pipeline. The arm time is the first ``idle -> armed`` transition.

    Raises
    ------
    SessionError
        The directory is not a readable session (see :class:`SessionReader`).
    """
    with SessionReader(directory) as reader:
        status = reader.status
        with reader.snapshot():
            frames = reader.frames()
            video_frames = reader.video_frames()
            force = reader.force_samples()
            transitions = reader.transitions()
            events = reader.events()
        summary = reader.summary
        video = reader.video_path
        manifest = reader.manifest
        session_id = reader.session_id
        path = reader.directory
    watchdog: dict[str, type[LinkLost | LinkRestored | CameraStalled | CameraRecovered]] = {
        "link_down": LinkLost,
        "link_up": LinkRestored,
        "camera_stalled": CameraStalled,
        "camera_recovered": CameraRecovered,
    }
    link_events: tuple[Event, ...] = tuple(
        watchdog[e.kind](float(e.t_host_s)) for e in events if e.kind in watchdog
    )
    arms = [t.t_host_s for t in transitions if (t.old_state, t.new_state) == ("idle", "armed")]
    t_arm = float(arms[0]) if arms else None
    return SessionData(
        directory=path,
        session_id=session_id,
        status=status,
        manifest=manifest,
        summary=summary,
        frame_times_s=np.asarray(frames["t_capture_host_s"], dtype=np.float64),
        s_k_px=np.asarray(frames["s_k"], dtype=np.float64),
        force_times_s=np.asarray(force["t_host_s"], dtype=np.float64),
        force_n=np.asarray(force["force_n"], dtype=np.float64),
        t_arm_s=t_arm,
        video_path=video if video is not None and video.is_file() else None,
        link_events=link_events,
        frame_seq=np.asarray(frames["seq"], dtype=np.int64),
        video_seq=np.asarray(video_frames["seq"], dtype=np.int64),
        video_frame_index=np.asarray(video_frames["frame_index"], dtype=np.int64),
    )


def load_ground_truth(path: str | Path) -> dict[str, Any]:
    """Read a simulator's ``ground_truth.json``.

    Raises
    ------
    DataFileError
        Unreadable, not JSON, or not a ``stipi-sim-ground-truth`` document.
    """
    p = Path(path)
    text = _read_text(p)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFileError(
            f"{p}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})"
        ) from None
    if not isinstance(doc, dict) or not str(doc.get("format", "")).startswith(
        "stipi-sim-ground-truth"
    ):
        raise DataFileError(f"{p}: not a simulator ground truth (format stipi-sim-ground-truth)")
    return doc
