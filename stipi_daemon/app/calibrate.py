"""Calibration orchestration: points for Eqs. (4)-(5) from files or recordings, fit, write.

The library side of ``stipi-daemon calibrate`` (:mod:`stipi_daemon.commands.calibrate`
parses the command line into a :class:`CalibrateRequest` and calls :func:`calibrate`).
Each equation takes its points from one source: Eq. (4) from measured pairs
(``s0_px``, ``depth_change_mm``) or from a recording held at known displacements
(:func:`~stipi_daemon.analysis.calibration_procedure.displacement_points`); Eq. (5) from
measured pairs (``s_px``, ``force_n``) or from the force plateaus of a recording
(:func:`~stipi_daemon.analysis.calibration_procedure.find_force_plateaus`). A recording is a
session directory (stored S_k) or a directory holding ``video.mkv``, ``frames.csv`` and
``force.csv`` as ``stipi-daemon simulate`` writes them (S_k counted with the request's
threshold and ROI, :mod:`stipi_daemon.app.offline_io`). The fits and the file format are
:mod:`stipi_daemon.analysis.calibration`'s. Progress and the fit report go to ``emit``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.calibration import (
    DEFAULT_INDENTER_LENGTH_MM,
    Calibration,
    calibration_from_fits,
    fit_depth_calibration,
    fit_force_calibration,
    load_calibration,
    save_calibration,
)
from stipi_daemon.analysis.calibration_procedure import (
    DEFAULT_MIN_FORCE_N,
    DEFAULT_MIN_PLATEAU_S,
    DEFAULT_PLATEAU_TOLERANCE_N,
    DEFAULT_TRIM_S,
    DisplacementInterval,
    depth_domain_problem,
    displacement_points,
    find_force_plateaus,
    fit_domain_warnings,
    fit_report,
    force_domain_problem,
    force_points,
)
from stipi_daemon.analysis.imaging import (
    CircleROI,
    RectROI,
    describe_roi,
    roi_from_record,
    same_roi,
    whole_frame_roi,
)
from stipi_daemon.app.imaging import check_roi_fits
from stipi_daemon.app.offline_io import (
    CsvTable,
    count_video,
    match_frame_times,
    read_csv_table,
    read_force_csv,
    read_frame_times_csv,
    read_session,
)
from stipi_daemon.errors import CalibrationError, ConfigError, DataFileError, SessionError
from stipi_daemon.storage.export import check_export_target

__all__ = ["CalibrateRequest", "calibrate"]

FloatArray = npt.NDArray[np.float64]
_T = TypeVar("_T")
Emit = Callable[[str], None]


@dataclass(frozen=True)
class CalibrateRequest:
    """What to fit from and where to write (the ``calibrate`` command line, checked).

    Attributes
    ----------
    out : Path
        The calibration file to write.
    depth_pairs : Path or None
        Eq. (4) pairs CSV (exclusive with ``depth_recording``).
    depth_recording, displacements : Path or None
        A recording held at known displacements and its intervals CSV
        (``t_start_s``, ``t_end_s``, ``depth_change_mm``).
    force_pairs : Path or None
        Eq. (5) pairs CSV (exclusive with ``force_recording``).
    force_recording : Path or None
        A recording with force plateaus.
    indenter_length_mm : float
        Indenter length l of Eq. (3) [mm].
    threshold_p : int or None
        Threshold p of Eq. (1) the S values were counted with [8-bit intensity].
    roi : CircleROI or RectROI or None
        ROI to count S on a video [px] (None: the whole frame), and the ROI recorded in the
        file as the one the S values were counted in (a recording's own must agree).
    whole_frame : bool
        ``--roi full``: the S values were counted in the whole frame (``roi`` None), which
        the file records as the rect of the frame size (needs the frame size).
    probe_id : str or None
        Probe identifier recorded in the file.
    frame_size_px : tuple of int or None
        ``(width, height)`` of the camera frames the S values were counted in [px]
        (recorded in the file; a recording's own must agree).
    plateau_tolerance_n, plateau_min_s, min_force_n, trim_s : float
        Plateau search: force band [N], shortest plateau [s], lowest mean force [N],
        time cut from each end [s].
    """

    out: Path
    depth_pairs: Path | None = None
    depth_recording: Path | None = None
    displacements: Path | None = None
    force_pairs: Path | None = None
    force_recording: Path | None = None
    indenter_length_mm: float = DEFAULT_INDENTER_LENGTH_MM
    threshold_p: int | None = None
    roi: CircleROI | RectROI | None = None
    whole_frame: bool = False
    probe_id: str | None = None
    frame_size_px: tuple[int, int] | None = None
    plateau_tolerance_n: float = DEFAULT_PLATEAU_TOLERANCE_N
    plateau_min_s: float = DEFAULT_MIN_PLATEAU_S
    min_force_n: float = DEFAULT_MIN_FORCE_N
    trim_s: float = DEFAULT_TRIM_S


@dataclass(frozen=True)
class _Series:
    frame_t: FloatArray
    s_k: FloatArray
    force_t: FloatArray
    force_n: FloatArray
    threshold_p: int | None
    what: str
    frame_size_px: tuple[int, int] | None = None
    roi: CircleROI | RectROI | None = None
    """The ROI the S values were counted in (None: the whole frame, or not known)."""
    whole_frame: bool = False
    """Whether they were counted in the whole frame (``roi`` None)."""


@dataclass
class _Seen:
    """What the recordings say about how their S values were counted."""

    thresholds: list[int] = field(default_factory=list)
    sizes: list[tuple[tuple[int, int], str]] = field(default_factory=list)
    #: (ROI, which recording); None: the whole frame.
    rois: list[tuple[CircleROI | RectROI | None, str]] = field(default_factory=list)

    def add(self, rec: _Series) -> None:
        if rec.threshold_p is not None:
            self.thresholds.append(rec.threshold_p)
        if rec.frame_size_px is not None:
            self.sizes.append((rec.frame_size_px, rec.what))
        if rec.roi is not None or rec.whole_frame:
            self.rois.append((rec.roi, rec.what))


def _load_recording(
    path: Path, threshold: int | None, roi: CircleROI | RectROI | None, need_force: bool
) -> _Series:
    """S_k and force series of a session directory or a simulator-style directory."""
    if (path / "manifest.json").is_file():
        data = read_session(path)
        cal = data.manifest.get("calibration") or {}
        imaging = (data.manifest.get("config") or {}).get("imaging") or {}
        p = imaging.get("threshold_p", cal.get("threshold_p"))
        try:
            counted_in = roi_from_record(cal.get("roi"))
        except ValueError as exc:
            raise DataFileError(
                f"{path / 'manifest.json'}: field 'calibration.roi': {exc}"
            ) from None
        return _Series(
            data.frame_times_s,
            data.s_k_px,
            data.force_times_s,
            data.force_n,
            None if p is None else int(p),
            f"session {data.session_id}",
            data.frame_size_px(),
            counted_in,
            # a record with "roi": null counted in the whole frame; one without, before the
            # ROI was kept, says nothing
            whole_frame=counted_in is None and "roi" in cal,
        )
    video = path / "video.mkv"
    if not path.is_dir() or not video.is_file():
        raise DataFileError(
            f"{path}: not a recording (expected a session directory with manifest.json, or a "
            "directory with video.mkv, frames.csv and force.csv)"
        )
    if threshold is None:
        raise ConfigError(f"{path}: counting S on the video needs --threshold P")
    frame_times = None
    if (path / "frames.csv").is_file():
        frame_times, _ = read_frame_times_csv(path / "frames.csv")
    counted = count_video(video, threshold, roi)
    t, s, _notes = match_frame_times(counted, frame_times, str(path / "frames.csv"))
    if need_force:
        ft, fn, _ = read_force_csv(path / "force.csv")
    else:
        ft, fn = np.empty(0), np.empty(0)
    h, w = counted.frame_shape[:2]
    size = (int(w), int(h)) if counted.crop is None else None  # a crop's frame is unknown
    whole = roi is None and size is not None
    return _Series(t, s, ft, fn, threshold, f"video {video}", size, roi, whole_frame=whole)


def _check_domain(table: CsvTable, problem: tuple[int, str] | None, option: str | None) -> None:
    """Refuse a calibration point outside its equation's domain, naming file and line."""
    if problem is None:
        return
    i, why = problem
    hint = f"; check the column's unit, or {option}" if option else "; check the column's sign"
    raise CalibrationError(f"{table.path}: line {int(table.lines[i])}: {why}{hint}")


def _depth_points(
    request: CalibrateRequest, seen: _Seen, emit: Emit
) -> tuple[FloatArray, FloatArray]:
    """Eq. (4) points: S_0 [px] and depth change d_s [mm]."""
    if request.depth_pairs is not None:
        table = read_csv_table(request.depth_pairs, ["s0_px", "depth_change_mm"])
        _check_domain(
            table,
            depth_domain_problem(table.columns["depth_change_mm"], request.indenter_length_mm),
            "--indenter-length",
        )
        emit(f"Eq. (4): {len(table)} pairs from {request.depth_pairs}")
        return table.columns["s0_px"], table.columns["depth_change_mm"]
    assert request.depth_recording is not None and request.displacements is not None
    rec = _load_recording(request.depth_recording, request.threshold_p, request.roi, False)
    seen.add(rec)
    table = read_csv_table(request.displacements, ["t_start_s", "t_end_s", "depth_change_mm"])
    _check_domain(
        table,
        depth_domain_problem(table.columns["depth_change_mm"], request.indenter_length_mm),
        "--indenter-length",
    )
    intervals = [
        DisplacementInterval(float(a), float(b), float(d))
        for a, b, d in zip(
            table.columns["t_start_s"],
            table.columns["t_end_s"],
            table.columns["depth_change_mm"],
            strict=True,
        )
    ]
    try:
        points = displacement_points(rec.frame_t, rec.s_k, intervals)
    except CalibrationError as exc:
        raise CalibrationError(f"{request.displacements}: {exc}") from None
    emit(f"Eq. (4): {len(points)} displacement(s) from {rec.what}")
    emit("   t_start_s  t_end_s   d_s [mm]   S0 [px]  sd [px]  frames")
    for pt in points:
        iv = pt.interval
        emit(
            f"  {iv.t_start_s:9.3f} {iv.t_end_s:8.3f} {iv.depth_change_mm:10.4g}"
            f" {pt.s0_px:9.1f} {pt.s0_sd_px:8.1f} {pt.n_frames:7d}"
        )
    return (
        np.asarray([p.s0_px for p in points]),
        np.asarray([p.interval.depth_change_mm for p in points]),
    )


def _force_points(
    request: CalibrateRequest, seen: _Seen, emit: Emit
) -> tuple[FloatArray, FloatArray]:
    """Eq. (5) points: S [px] and force F [N]."""
    if request.force_pairs is not None:
        table = read_csv_table(request.force_pairs, ["s_px", "force_n"])
        _check_domain(table, force_domain_problem(table.columns["force_n"]), None)
        emit(f"Eq. (5): {len(table)} pairs from {request.force_pairs}")
        return table.columns["s_px"], table.columns["force_n"]
    assert request.force_recording is not None
    rec = _load_recording(request.force_recording, request.threshold_p, request.roi, True)
    seen.add(rec)
    plateaus = find_force_plateaus(
        rec.force_t,
        rec.force_n,
        tolerance_n=request.plateau_tolerance_n,
        min_duration_s=request.plateau_min_s,
        min_force_n=request.min_force_n,
    )
    fpoints = force_points(
        rec.force_t, rec.force_n, rec.frame_t, rec.s_k, plateaus, trim_s=request.trim_s
    )
    emit(f"Eq. (5): {len(fpoints)} force plateau(s) found in {rec.what}")
    emit("   t_start_s  t_end_s    F [N]  sd [N]     S [px]  sd [px]  frames")
    for fp in fpoints:
        emit(
            f"  {fp.t_start_s:9.3f} {fp.t_end_s:8.3f} {fp.force_n:8.3f} {fp.force_sd_n:7.3f}"
            f" {fp.s_px:10.1f} {fp.s_sd_px:8.1f} {fp.n_frames:7d}"
        )
    return np.asarray([p.s_px for p in fpoints]), np.asarray([p.force_n for p in fpoints])


def _threshold(given: int | None, thresholds: list[int]) -> int | None:
    """The threshold p to record: the given one, else the recordings' (which must agree)."""
    if given is None and thresholds:
        if len(set(thresholds)) > 1:
            raise CalibrationError(
                f"the recordings were counted with different thresholds p {sorted(set(thresholds))}"
                ": S values are not comparable"
            )
        return thresholds[0]
    if given is not None and any(p != given for p in thresholds):
        raise CalibrationError(
            f"--threshold {given} differs from the recordings' p {sorted(set(thresholds))}"
        )
    return given


def _agreed(
    option: str,
    given: _T | None,
    seen: list[tuple[_T, str]],
    describe: Callable[[_T], str],
    differ: str,
) -> _T | None:
    """The value to record: ``given`` (the ``option``'s), else the recordings' ``seen``
    (value, which recording), which must agree with each other (``differ`` ends "the
    recordings' ..." when they do not) and with the given one."""
    text = "; ".join(f"{describe(v)} in {what}" for v, what in seen)
    if len({v for v, _ in seen}) > 1:
        raise CalibrationError(f"the recordings' {differ} ({text}): S values are not comparable")
    if given is not None and any(v != given for v, _ in seen):
        raise CalibrationError(f"{option} {describe(given)} differs from {text}")
    return given if given is not None else (seen[0][0] if seen else None)


def _agreed_roi(
    request: CalibrateRequest,
    seen: list[tuple[CircleROI | RectROI | None, str]],
    frame_size: tuple[int, int] | None,
) -> tuple[CircleROI | RectROI | None, bool]:
    """The ROI to record and whether S was counted in the whole frame without a known
    frame size to record it with. The ROI is ``--roi`` (``--roi full``: the whole frame),
    else the recordings' ``seen`` (ROI or None for the whole frame, which recording); they
    must all count the same pixels (:func:`same_roi`). The whole frame is recorded as the
    rect of ``frame_size`` [px]."""
    text = "; ".join(f"{describe_roi(v)} in {what}" for v, what in seen)
    if any(not same_roi(v, seen[0][0], frame_size) for v, _ in seen[1:]):
        raise CalibrationError(f"the recordings' ROIs differ ({text}): S values are not comparable")
    given = request.roi is not None or request.whole_frame
    if given and any(not same_roi(request.roi, v, frame_size) for v, _ in seen):
        raise CalibrationError(f"--roi {describe_roi(request.roi)} differs from {text}")
    if not given and not seen:
        return None, False
    chosen = request.roi if given else seen[0][0]
    if chosen is None:
        return (None, True) if frame_size is None else (whole_frame_roi(frame_size), False)
    return chosen, False


def _size_text(size: tuple[int, int]) -> str:
    return f"{size[0]}x{size[1]} px"


def calibrate(request: CalibrateRequest, emit: Emit) -> tuple[Calibration, Path]:
    """Fit Eqs. (4)-(5) as ``request`` says, write the calibration file and read it back.

    Returns
    -------
    (Calibration, Path)
        The calibration and the file written.

    Raises
    ------
    CalibrationError
        A fit is refused, the recordings' thresholds, frame sizes or ROIs disagree (with
        each other or with the request's), or intervals are unusable.
    DataFileError, ConfigError
        An input cannot be read or lacks what it needs; ``--roi`` does not lie within the
        frame; ``out`` is in a session directory (checked before anything is read).
    """
    try:  # a calibration file never replaces a session's file (summary.json, ...)
        check_export_target(request.out, [], is_file=True, what="a calibration")
    except SessionError as exc:
        raise ConfigError(str(exc)) from None
    if request.out.is_dir():
        raise ConfigError(f"--out {request.out}: is a directory (give a file name, CAL.json)")
    seen = _Seen()
    s0, d_s = _depth_points(request, seen, emit)
    s_px, f_n = _force_points(request, seen, emit)
    threshold = _threshold(request.threshold_p, seen.thresholds)
    frame_size = _agreed(
        "--frame-size", request.frame_size_px, seen.sizes, _size_text, "frames differ in size"
    )
    roi, whole_unsized = _agreed_roi(request, seen.rois, frame_size)
    if request.roi is not None and frame_size is not None:  # (a rect holding the frame is it)
        if not same_roi(request.roi, None, frame_size):
            check_roi_fits(request.roi, *frame_size, "--roi")
    try:
        depth_fit = fit_depth_calibration(s0, d_s)
    except CalibrationError as exc:
        raise CalibrationError(f"Eq. (4) depth fit refused: {exc}") from None
    try:
        force_fit = fit_force_calibration(s_px, f_n)
    except CalibrationError as exc:
        raise CalibrationError(f"Eq. (5) force fit refused: {exc}") from None
    cal = calibration_from_fits(
        depth_fit,
        force_fit,
        indenter_length_mm=request.indenter_length_mm,
        threshold_p=threshold,
        probe_id=request.probe_id,
        frame_size_px=frame_size,
        roi=roi,
    )
    emit("")
    for line in fit_report(cal):
        emit(line)
    for line in fit_domain_warnings(cal):
        emit(f"warning: {line}")
    if threshold is None:
        emit(
            "warning: no threshold p recorded (--threshold): the daemon will need "
            "imaging.threshold_p, and S values counted with another p are not comparable"
        )
    if frame_size is None:
        emit(
            "warning: no frame size recorded (--frame-size WxH): the daemon cannot tell a "
            "camera at another resolution, whose S values are not comparable"
        )
    if whole_unsized:
        emit(
            "warning: no ROI recorded: S was counted in the whole frame, whose size is not "
            "known (--frame-size WxH records both); the daemon cannot tell S counted in "
            "another ROI, whose S values are not comparable"
        )
    elif roi is None:
        emit(
            "warning: no ROI recorded (--roi): the daemon cannot tell S counted in another "
            "ROI, whose S values are not comparable"
        )
    try:
        path = save_calibration(request.out, cal)
    except OSError as exc:  # a full disk, no permission: no partial file is left
        raise ConfigError(f"--out {request.out}: cannot write: {exc.strerror or exc}") from None
    load_calibration(path)  # what was written reads back
    emit(f"\ncalibration written to {path}")
    return cal, path
