"""Offline analysis orchestration: recompute a measurement's results from a session or files.

The library side of ``stipi-daemon analyze`` (:mod:`stipi_daemon.commands.analyze` parses
the command line into an :class:`AnalyzeRequest` and calls :func:`analyze`). Two inputs:

* a stored session (:func:`analyze_session`): its frames' S_k and force samples, read from
  ``session.sqlite``, replayed with the settings its manifest recorded (a ``--config``
  replaces them); with ``recompute_sk`` S_k is counted again on the session's video, each
  stored frame paired with its video frame by ``seq`` (``video_frames``), and compared with
  the stored S_k: a recount that does not reproduce them (with the recorded threshold and
  ROI) or lacks stored frames flags the results (:data:`EXIT_S_K_NOT_REPRODUCED`);
* files (:func:`analyze_files`): a video whose S_k is counted on every decoded frame
  (Eqs. 1-2), frame times (``frames.csv`` next to the video by default, else the video's
  frame rate) and a force CSV.

Which calibration, threshold and ROI apply is :func:`stipi_daemon.app.imaging.choose_imaging`'s
rule, the same the daemon follows. The replay is :mod:`stipi_daemon.measurement.replay`, the
comparisons with the stored summary and with a simulator's ground truth
:mod:`stipi_daemon.analysis.summary_diff` and :mod:`stipi_daemon.analysis.truth_comparison`,
file reading :mod:`stipi_daemon.app.offline_io`. This module builds the output document
(format ``stipi-offline-analysis``), writes it (never over a recorded file) and the lines
the command prints.

Sessions that ended early (aborted, fault, interrupted, still recording) are analysed
for what their recording allows (:func:`rescue`): the recovery that was kept, and when
the replay re-enacts the fault that ended the session (a lost link, a session closed in
the recovery), the recording up to that fault. Such an analysis is written beside the
session like any other (``analysis-<UTC time>.json``, never over ``summary.json``); its
verdict is ``incomplete`` and its line says how the session ended.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from stipi_daemon import __version__
from stipi_daemon.analysis.calibration import Calibration, load_calibration
from stipi_daemon.analysis.imaging import CircleROI, RectROI, describe_roi
from stipi_daemon.analysis.results import AnalysisSettings, force_full_scale_n
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.summary_diff import diff_results
from stipi_daemon.analysis.truth_comparison import ParameterComparison, compare_ground_truth
from stipi_daemon.analysis.validity import FROM_SK
from stipi_daemon.app.config import DaemonConfig, ImagingSettings
from stipi_daemon.app.console import format_results
from stipi_daemon.app.imaging import (
    Choice,
    Imaging,
    ImagingSource,
    choose_imaging,
    recorded_source,
    settings_source,
    truth_source,
)
from stipi_daemon.app.offline_io import (
    SessionData,
    VideoCount,
    count_session_video,
    count_video,
    load_ground_truth,
    match_frame_times,
    read_force_csv,
    read_frame_times_csv,
    read_session,
)
from stipi_daemon.errors import EXIT_S_K_NOT_REPRODUCED, ConfigError, DataFileError, SessionError
from stipi_daemon.measurement.replay import Recording, ReplayOutcome, ReplaySetup, replay
from stipi_daemon.measurement.state_machine import FAULT_PHASES, MeasurementConfig, Phase
from stipi_daemon.storage import SessionState, layout
from stipi_daemon.storage.export import check_export_target
from stipi_daemon.storage.metadata import metadata_of

__all__ = [
    "EXIT_S_K_NOT_REPRODUCED",
    "OUTPUT_FORMAT",
    "OUTPUT_VERSION",
    "ROI_NOT_CALIBRATED",
    "S_K_NOT_REPRODUCED",
    "THRESHOLD_NOT_CALIBRATED",
    "AnalysisRun",
    "AnalyzeRequest",
    "analyze",
    "analyze_files",
    "analyze_session",
    "replay_session",
]

OUTPUT_FORMAT = "stipi-offline-analysis"
OUTPUT_VERSION = 1

#: Validity flag of the quantities computed from S_k when the recount does not reproduce
#: or cover the stored S_k (``settings.imaging.s_k_vs_stored.problem`` says how).
S_K_NOT_REPRODUCED = "s_k_not_reproduced"
#: Validity flag of every quantity computed from S_k (D_p, F_r by Eqs. 4-5, T_r by Eq. 6,
#: tau, and E, eta and the severity from them) when S_k were counted with another threshold
#: p than the one the calibration was made with (``analyze --threshold`` exploring another
#: p, or a ``--calibration`` made with another p than the session counted with): the S
#: values of Eqs. 4-5 and these S_k do not compare, and T_r's settling level (a fraction of
#: S_max) moves with them (1.5 % at p 90 instead of 128 on a simulated grade I).
THRESHOLD_NOT_CALIBRATED = "threshold_not_calibrated"
#: Validity flag of the same quantities when S_k were counted in another ROI than the one
#: the calibration was made in (``analyze --roi``, a study's ``imaging.roi``, or a
#: ``--calibration`` made in another ROI than the session counted in): S counts the occluded
#: pixels within the ROI, so the S values of Eqs. 4-5 and these S_k do not compare (a disc
#: 20 px wider than the lit one: D_p 12 mm instead of 1.82, T_r 27 % short).
ROI_NOT_CALIBRATED = "roi_not_calibrated"
#: What either flag's reason says follows.
_NOT_CALIBRATED = (
    "S_k are not the calibration's S, so D_p, F_r, T_r, tau and what follows from them do not hold"
)

_NO_THRESHOLD = "no threshold p for Eq. (1): give --threshold P (or a calibration with threshold_p)"


@dataclass(frozen=True)
class AnalyzeRequest:
    """What to analyse and how (the ``analyze`` command line, checked).

    Attributes
    ----------
    session_dir : Path or None
        A stored session's directory (exclusive with ``video``).
    video, force, frame_times : Path or None
        A video, its force CSV and frame-times CSV.
    calibration : Path or None
        A calibration file overriding every other source.
    config : DaemonConfig or None
        A config whose measurement/analysis/imaging settings (and calibration, if set)
        replace the recorded ones.
    threshold_p : int or None
        Threshold p of Eq. (1) overriding every other source [8-bit intensity, 0..255].
    roi : CircleROI or RectROI or None
        ROI overriding every other source [px], when ``roi_given`` (None: the whole frame).
    roi_given : bool
        Whether an ROI was given.
    recompute_sk : bool
        With a session: count S_k again on its video.
    ground_truth : Path or None
        A simulator ground truth to compare with.
    out : Path or None
        Output file (default ``analysis-<UTC time>.json`` next to the input).
    sections : mapping or None
        With a session: fields of the ``measurement``, ``analysis`` and ``imaging``
        sections (section -> field -> value) set over those the session recorded (or
        ``config``'s); the merged sections are validated as the config's are.
    """

    session_dir: Path | None = None
    video: Path | None = None
    force: Path | None = None
    frame_times: Path | None = None
    calibration: Path | None = None
    config: DaemonConfig | None = None
    threshold_p: int | None = None
    roi: CircleROI | RectROI | None = None
    roi_given: bool = False
    recompute_sk: bool = False
    ground_truth: Path | None = None
    out: Path | None = None
    sections: Mapping[str, Mapping[str, Any]] | None = None

    def override(self) -> ImagingSource:
        """The command line's imaging source (``--calibration``, ``--threshold``, ``--roi``)."""
        p = self.threshold_p
        if p is not None and not 0 <= p <= 255:
            raise ConfigError(f"--threshold must be 0..255, got {p}")
        cal = self.calibration
        return ImagingSource(
            calibration=None if cal is None else Choice(load_calibration(cal), str(cal)),
            threshold_p=None if p is None else Choice(int(p), "--threshold"),
            roi=Choice(self.roi, "--roi") if self.roi_given else None,
        )


@dataclass(frozen=True)
class AnalysisRun:
    """One analysis done and written.

    Attributes
    ----------
    out : Path
        The output file written.
    document : dict
        Its content.
    outcome : ReplayOutcome
        The replay.
    header : list of str
        The input, in one line.
    truth_rows : list of ParameterComparison or None
        The comparison with a simulator's ground truth, if there is one.
    """

    out: Path
    document: dict[str, Any]
    outcome: ReplayOutcome
    header: list[str]
    truth_rows: list[ParameterComparison] | None

    @property
    def recount(self) -> Mapping[str, Any] | None:
        """With ``--recompute-sk``: the recounted S_k against the stored ones
        (``settings.imaging.s_k_vs_stored``); None otherwise."""
        check = self.document["settings"]["imaging"].get("s_k_vs_stored")
        return check if isinstance(check, dict) else None

    @property
    def exit_code(self) -> int:
        """0 when the replay produced results, 1 when it produced none,
        :data:`EXIT_S_K_NOT_REPRODUCED` (3) when it did but the S_k recount did not
        reproduce or cover the stored S_k (the results are flagged)."""
        if self.outcome.result is None:
            return 1
        check = self.recount
        return EXIT_S_K_NOT_REPRODUCED if check is not None and check["problem"] else 0

    def lines(self) -> list[str]:
        """The report printed for the operator."""
        outcome, doc = self.outcome, self.document
        lines = list(self.header)
        if self.recount is not None:
            lines.append(_recount_line(self.recount))
        lines.append(
            f"replayed {outcome.frames_fed} frames and {outcome.force_samples_fed} force "
            f"samples: phase {outcome.phase} ({outcome.end_reason})"
        )
        lines.extend(f"note: {note}" for note in doc["notes"])
        lines.extend(f"analysis note: {note}" for note in dict.fromkeys(doc["summary"]["notes"]))
        lines.extend(format_results(doc["summary"]))
        stored = doc["comparison"]["stored_summary"]
        if stored is not None:
            lines.append("")
            if stored["identical"]:
                lines.append("recorded summary: identical results")
            else:
                diffs = stored["differences"]
                lines.append(f"recorded summary: {len(diffs)} difference(s)")
                lines.extend(f"  {d}" for d in diffs[:10])
                if len(diffs) > 10:
                    lines.append(f"  ... and {len(diffs) - 10} more (see the output file)")
        if self.truth_rows is not None:
            lines.extend(_truth_lines(self.truth_rows))
        return lines


def analyze(request: AnalyzeRequest) -> AnalysisRun:
    """Analyse a session or files as ``request`` says and write the output document."""
    if request.session_dir is not None:
        return analyze_session(request)
    return analyze_files(request)


# --------------------------------------------------------------------------------------------
# settings
# --------------------------------------------------------------------------------------------


_M = TypeVar("_M", bound=BaseModel)


def _validated(model: type[_M], data: Any, where: str) -> _M:
    try:
        return model.model_validate(data if data is not None else {})
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        raise SessionError(f"{where}.{loc}: {err['msg']}") from None


def _session_settings(
    data: SessionData,
    config: DaemonConfig | None,
    sections: Mapping[str, Mapping[str, Any]] | None = None,
) -> tuple[MeasurementConfig, AnalysisSettings, ImagingSettings]:
    """The config's settings if one is given, else those the manifest recorded; then
    the fields of ``sections`` set over them (:attr:`AnalyzeRequest.sections`)."""
    sections = sections or {}
    names = ("measurement", "analysis", "imaging")
    if config is None:
        cfg = data.manifest.get("config") or {}
        where = f"{data.directory / layout.MANIFEST_NAME}: field 'config."
    elif not sections:
        return config.measurement, config.analysis, config.imaging
    else:
        cfg = {name: getattr(config, name).model_dump(mode="json") for name in names}
        where = "the config's field '"
    if sections:
        where = f"(with the settings given) {where}"
    merged = {name: cfg.get(name) for name in names}
    for name, fields in sections.items():
        recorded = merged.get(name) or {}
        if isinstance(recorded, dict):  # else the recorded section's own error is reported
            merged[name] = {**recorded, **fields}
    return (
        _validated(MeasurementConfig, merged["measurement"], f"{where}measurement"),
        _validated(AnalysisSettings, merged["analysis"], f"{where}analysis"),
        _validated(ImagingSettings, merged["imaging"], f"{where}imaging"),
    )


def _cal_dict(cal: Calibration, source: str) -> dict[str, Any]:
    def pair(v: tuple[float, float] | None) -> list[float] | None:
        return None if v is None else list(v)

    return {
        "alpha1_mm_per_px2": cal.alpha1_mm_per_px2,
        "alpha2_mm_per_px": cal.alpha2_mm_per_px,
        "c1_px": cal.c1_px,
        "c2_px_per_n": cal.c2_px_per_n,
        "indenter_length_mm": cal.indenter_length_mm,
        "threshold_p": cal.threshold_p,
        "s0_valid_range_px": pair(cal.s0_valid_range_px),
        "force_valid_range_n": pair(cal.force_valid_range_n),
        "frame_size_px": None if cal.frame_size_px is None else list(cal.frame_size_px),
        "roi": _roi_dict(cal.roi),
        "source": source,
    }


def _roi_dict(roi: CircleROI | RectROI | None) -> dict[str, Any] | None:
    return None if roi is None else roi.model_dump(mode="json")


# --------------------------------------------------------------------------------------------
# a session
# --------------------------------------------------------------------------------------------


def _session_truth(request: AnalyzeRequest, data: SessionData) -> dict[str, Any] | None:
    if request.ground_truth is not None:
        return load_ground_truth(request.ground_truth)
    summary = data.summary
    if summary is not None and isinstance(summary.get("ground_truth"), dict):
        truth: dict[str, Any] = summary["ground_truth"]
        return truth
    return None


def _status_notes(data: SessionData) -> list[str]:
    status = data.status
    if status is SessionState.INTERRUPTED:
        return [
            "session interrupted (the recorder stopped before finishing): analysed the "
            "samples that were kept"
        ]
    if status is SessionState.RECORDING:
        return ["session still recording: analysed the samples committed so far"]
    if data.summary is None:
        return [f"session status {status} but no summary.json"]
    return []


def _check_calibration_size(
    calibration: Choice[Calibration], size: tuple[int, int] | None, where: str
) -> None:
    """:class:`ConfigError` when the calibration was made at another frame size than
    ``size`` [px] (None: not known), naming where the calibration came from."""
    if size is None:
        return
    problem = calibration.value.frame_size_problem(size[0], size[1], where)
    if problem is not None:
        raise ConfigError(
            f"calibration ({calibration.source}): {problem}; give one made at "
            f"{size[0]}x{size[1]} px"
        )


def _roi_field(source: str) -> str:
    """How an ROI error names what set the ROI (``--roi``, a config field, a file)."""
    if source in ("--roi",):
        return source
    if source == "config imaging.roi":
        return "field 'imaging.roi'"
    return f"the ROI ({source})"


def _settings_change(
    data: SessionData, threshold: Choice[int], imaging: Imaging, roi_given: bool
) -> str | None:
    """How the threshold and ROI of a recount differ from those the session counted its
    S_k with live (its manifest's calibration record: ``threshold_p``, ``roi``), or None
    when they are the same (the recount must then reproduce every stored S_k)."""
    cal = data.manifest.get("calibration")
    cal = cal if isinstance(cal, dict) else {}
    changes: list[str] = []
    recorded_p = cal.get("threshold_p")
    if (recorded_p is not None and threshold.value != recorded_p) or (
        recorded_p is None and threshold.source == "--threshold"
    ):
        changes.append(f"threshold {threshold.value} from {threshold.source}")
    roi = imaging.roi_value
    if ("roi" in cal and _roi_dict(roi) != cal["roi"]) or ("roi" not in cal and roi_given):
        where = "no ROI source" if imaging.roi is None else imaging.roi.source
        changes.append(f"ROI {'full frame' if roi is None else _roi_text(roi)} from {where}")
    return "; ".join(changes) or None


def _roi_text(roi: CircleROI | RectROI) -> str:
    if isinstance(roi, CircleROI):
        return f"circle:{roi.cx_px:g},{roi.cy_px:g},{roi.radius_px:g}"
    return f"rect:{roi.x_px},{roi.y_px},{roi.width_px},{roi.height_px}"


_IntArray = np.ndarray[Any, np.dtype[np.int64]]


def _first_repeat(values: _IntArray) -> int | None:
    """A value that occurs more than once in ``values``, or None."""
    uniq, counts = np.unique(values, return_counts=True)
    repeated = uniq[counts > 1]
    return int(repeated[0]) if repeated.size else None


def _pair_rows(data: SessionData, video: Path, frames_in_file: int) -> tuple[_IntArray, list[str]]:
    """The file index (``video_frames`` ``frame_index``) of the video frame of each stored
    ``frames`` row, by ``seq`` (-1: none), and notes. Without ``video_frames`` rows the
    frames are paired by position only when the video holds exactly as many frames as
    the ``frames`` table.

    Raises
    ------
    SessionError
        The pairing would not be one to one: a ``seq`` twice in ``frames`` or in
        ``video_frames``, a ``frame_index`` twice, or no ``video_frames`` rows and another
        number of frames in the video than rows in ``frames``.
    """
    db = data.directory / layout.DB_NAME
    seq = data.frame_seq if data.frame_seq is not None else np.zeros(0, np.int64)
    n_rows = int(data.frame_times_s.size)
    vseq, vindex = data.video_seq, data.video_frame_index
    if vseq is None or vindex is None or not vseq.size:
        if frames_in_file != n_rows:
            raise SessionError(
                f"{video}: --recompute-sk: the video holds {frames_in_file} frames, the "
                f"session {n_rows} frame rows, and no video_frames rows tie them together: "
                "the stored frames cannot be paired with the video's frames one to one"
            )
        note = (
            f"no video_frames rows: the {n_rows} stored frames are paired with the video's "
            f"{frames_in_file} frames by position"
        )
        return np.arange(n_rows, dtype=np.int64), [note]
    for table, column, values in (
        ("frames", "seq", seq),
        ("video_frames", "seq", vseq),
        ("video_frames", "frame_index", vindex),
    ):
        twice = _first_repeat(values)
        if twice is not None:
            raise SessionError(
                f"{db}: table {table}: {column} {twice} occurs more than once: the stored "
                "frames cannot be paired with the video's frames one to one"
            )
    notes: list[str] = []
    by_seq = dict(zip(vseq.tolist(), vindex.tolist(), strict=True))
    index = np.array([by_seq.get(int(s), -1) for s in seq], dtype=np.int64)
    orphans = len(by_seq) - int(np.count_nonzero(index >= 0))
    if orphans:
        notes.append(f"{orphans} video_frames row(s) name a seq no frames row has: not used")
    unlisted = frames_in_file - int(np.count_nonzero((vindex >= 0) & (vindex < frames_in_file)))
    if unlisted > 0:
        notes.append(
            f"the video holds {unlisted} frame(s) more than its video_frames rows "
            f"({vseq.size}; an interrupted recording whose last rows were not committed): "
            "those frames are not tied to a stored frame and are not used"
        )
    return index, notes


def _recount(
    data: SessionData,
    imaging: Imaging,
    settings: ImagingSettings,
    notes: list[str],
    *,
    roi_given: bool = False,
    frame_size: tuple[int, int] | None = None,
) -> tuple[SessionData, np.ndarray[Any, np.dtype[np.float64]], dict[str, Any]]:
    """Count S_k again on the session's video: the data cut to the stored frames whose video
    frame decoded (paired by ``seq`` through ``video_frames``, :func:`_pair_rows`), their
    new S_k and the output's imaging record, whose ``s_k_vs_stored`` compares them with the
    stored S_k and says (``problem``) why the results must be flagged: with the recorded
    threshold and ROI any S_k not reproduced; always, stored frames missing from the video
    or undecodable there. ``notes`` gets what the reader should know; ``frame_size`` is the
    camera's ``(width, height)`` [px] when known."""
    from stipi_daemon.storage.video_readback import count_video_frames

    if data.video_path is None:
        raise SessionError(f"{data.directory}: --recompute-sk: the session has no video file")
    threshold = imaging.need_threshold(_NO_THRESHOLD)
    roi = imaging.roi_value
    if imaging.roi is None:
        notes.append("ROI: none recorded, the whole frame is counted")
    elif imaging.roi.source == "simulator ground truth":
        notes.append("ROI: the simulator's waveguide disc (ground truth)")
    field = "the ROI (none recorded)" if imaging.roi is None else _roi_field(imaging.roi.source)
    if roi is None and field == "--roi":
        field = "--roi full"
    # the frames (Matroska blocks) the file holds, from its structure before anything is
    # counted: a pairing that cannot be made is refused at once
    index, more = _pair_rows(data, data.video_path, count_video_frames(data.video_path))
    video = count_session_video(
        data.video_path,
        threshold.value,
        roi,
        saturation_limit_fraction=settings.saturation_limit_fraction,
        roi_field=field,
        frame_size=frame_size,
    )
    notes.extend(more)
    notes.extend(_damage_notes(video))
    in_file = (index >= 0) & (index < video.s_k_px.size)
    counted = np.full(index.size, np.nan)
    counted[in_file] = video.s_k_px[index[in_file]]
    keep = np.isfinite(counted)
    # rows whose frame lies past a break in the file's structure are damaged, not absent
    absent = (index < 0) | (~in_file & (index >= 0) & (not video.broken))
    s_k, stored = counted[keep], data.s_k_px[keep]
    check = _comparison(
        s_k,
        stored,
        missing=int(np.count_nonzero(absent)),
        undecodable=int(np.count_nonzero(~keep & ~absent)),
        change=_settings_change(data, threshold, imaging, roi_given),
    )
    if not keep.all():
        notes.append(
            f"{int((~keep).sum())} of the {keep.size} stored frames have no decodable frame "
            "in the video: they are left out"
        )
    data = dataclasses.replace(
        data,
        frame_times_s=data.frame_times_s[keep],
        s_k_px=stored,
        frame_seq=None if data.frame_seq is None else data.frame_seq[keep],
    )
    record = {
        "s_k_source": f"video {data.video_path}",
        "threshold_p": threshold.value,
        "threshold_source": threshold.source,
        "roi": _roi_dict(roi),
        "video_crop": None if video.crop is None else list(video.crop),
        "saturated_frames": video.saturated_frames,
        "s_k_vs_stored": check,
    }
    return data, s_k, record


def _damage_notes(video: VideoCount, shown: int = 5) -> list[str]:
    """What the readback reported damaged in the video (the first ``shown`` frames, and a
    structure that breaks off)."""
    frames = [d for d in video.damage if d.startswith("frame ")]
    notes = [f"video damaged: {d}" for d in frames[:shown]]
    if len(frames) > shown:
        notes.append(f"video damaged: {len(frames) - shown} more frame(s)")
    notes.extend(f"video damaged: {d}" for d in video.damage if not d.startswith("frame "))
    return notes


def _comparison(
    s_k: np.ndarray[Any, np.dtype[np.float64]],
    stored: np.ndarray[Any, np.dtype[np.float64]],
    *,
    missing: int,
    undecodable: int,
    change: str | None,
) -> dict[str, Any]:
    """The ``s_k_vs_stored`` record: recounted S_k against the stored ones [px] (paired),
    stored frames not in the video and undecodable there, the settings (None: the
    recorded ones) and the problem that flags the results (None: none)."""
    differ = int(np.count_nonzero(s_k != stored))
    n_stored = int(s_k.size) + missing + undecodable
    parts = []
    if differ and change is None:
        parts.append(f"{differ} differ from the stored S_k")
    if missing:
        parts.append(f"{missing} not in the video")
    if undecodable:
        parts.append(f"{undecodable} undecodable in the video")
    problem = None
    if parts:
        problem = f"S_k recount from the video: of the {n_stored} stored frames, {', '.join(parts)}"
    return {
        "stored_frames": n_stored,
        "frames": int(s_k.size),
        "differing": differ,
        "max_abs_difference_px": float(np.max(np.abs(s_k - stored))) if s_k.size else 0.0,
        "frames_without_video": missing,
        "undecodable_frames": undecodable,
        "settings": "recorded" if change is None else change,
        "problem": problem,
    }


def _recount_line(check: Mapping[str, Any]) -> str:
    """The operator's line on whether the recount reproduced the stored S_k."""
    n, total = check["frames"], check["stored_frames"]
    changed = check["settings"] != "recorded"
    head = f"S_k recounted from the video: {n} of {total} stored frames"
    if changed:
        head += f" ({check['settings']})"
    differ, missing, bad = (
        check["differing"],
        check["frames_without_video"],
        check["undecodable_frames"],
    )
    if not (differ or missing or bad):
        return f"{head}, all equal"
    line = f"{head}: {differ} differ"
    if differ:
        line += f" (up to {check['max_abs_difference_px']:g} px)"
    line += f", {missing} not in the video, {bad} undecodable"
    if check["problem"] is None:
        return f"{line} (differences expected with other settings)"
    return f"{line}: the results are flagged"


def _flag_quantities(
    summary: dict[str, Any],
    problem: str,
    flag: str = S_K_NOT_REPRODUCED,
    quantities: tuple[str, ...] = FROM_SK,
) -> None:
    """Flag ``quantities`` and the verdict of ``summary`` (in place) with ``flag`` and
    ``problem``: by default the quantities computed from S_k, for a recount that did not
    reproduce or cover the stored S_k."""
    validity = summary.get("validity")
    for q in quantities:
        v = validity.get(q) if isinstance(validity, dict) else None
        if not isinstance(v, dict):
            continue
        v["flags"] = sorted({*v.get("flags", []), flag})
        if v.get("status") == "valid":
            v["status"], v["reason"] = "flagged", problem
        elif v.get("status") == "flagged":
            v["reason"] = "; ".join(r for r in (v.get("reason"), problem) if r)
    verdict = summary.get("verdict")
    verdict = verdict if isinstance(verdict, dict) else {}
    if verdict.get("status") in (None, "complete"):
        summary["verdict"] = {"status": "flagged", "line": f"Complete with caveats: {problem}."}
    else:
        summary["verdict"] = {**verdict, "line": f"{verdict.get('line', '')} {problem}.".strip()}


def _threshold_problem(counted_p: Any, calibration: Choice[Calibration]) -> str | None:
    """Why the calibrated quantities do not hold for S_k counted with ``counted_p`` (None:
    not known), or None when the calibration was made with that p or records none."""
    own = calibration.value.threshold_p
    if own is None or counted_p is None or int(counted_p) == own:
        return None
    return (
        f"S_k counted with threshold p {int(counted_p)}, the calibration ({calibration.source}) "
        f"made with p {own}: {_NOT_CALIBRATED}"
    )


def _roi_problem(
    counted: CircleROI | RectROI | None, calibration: Choice[Calibration]
) -> str | None:
    """Why the calibrated quantities do not hold for S_k counted in ``counted`` [px] (None:
    the whole frame), or None when the calibration was made in that ROI (or in the whole
    frame, as ``counted``) or records none."""
    if calibration.value.holds_in_roi(counted):
        return None
    return (
        f"S_k counted in {describe_roi(counted)}, the calibration ({calibration.source}) made "
        f"in {describe_roi(calibration.value.roi)}: {_NOT_CALIBRATED}"
    )


def _flag_uncalibrated(
    summary: dict[str, Any], problems: Mapping[str, str | None], notes: list[str]
) -> None:
    """Flag the S_k quantities of ``summary`` with each flag of ``problems`` whose problem
    is not None, and note the problem."""
    for flag, problem in problems.items():
        if problem is not None:
            notes.append(problem)
            _flag_quantities(summary, problem, flag)


def _json_roundtrip(value: Any) -> Any:
    from stipi_daemon.storage.schema import to_jsonable

    return json.loads(json.dumps(to_jsonable(value, "summary"), allow_nan=False))


def _stored_comparison(
    stored: dict[str, Any] | None, recomputed: dict[str, Any]
) -> dict[str, Any] | None:
    """The recomputed summary against the recorded one (keys both hold), as JSON stores it."""
    if stored is None or "phase" not in stored:
        return None
    keys = [k for k in recomputed if k in stored]
    diffs = diff_results(
        {k: stored[k] for k in keys},
        _json_roundtrip({k: recomputed[k] for k in keys}),
        "summary",
    )
    return {"identical": not diffs, "differences": diffs}


#: Session states of a session that did not end DONE (analysed for what the data allow).
ENDED_EARLY = (
    SessionState.ABORTED,
    SessionState.FAULT,
    SessionState.INTERRUPTED,
    SessionState.RECORDING,
)


def _cut(rec: Recording, t_end_s: float) -> Recording | None:
    """The recording strictly before ``t_end_s`` [s] (None when no frame is left)."""
    frames = rec.frame_times_s < t_end_s
    if not frames.any():
        return None
    force = rec.force_times_s < t_end_s
    return dataclasses.replace(
        rec,
        frame_times_s=rec.frame_times_s[frames],
        s_k_px=rec.s_k_px[frames],
        force_times_s=rec.force_times_s[force],
        force_n=rec.force_n[force],
        link_events=tuple(e for e in rec.link_events if e.t_s < t_end_s),
    )


def rescue(
    rec: Recording, setup: ReplaySetup, outcome: ReplayOutcome
) -> tuple[ReplayOutcome, float | None]:
    """What the recording of a session that ended early allows.

    When the replay ends in a fault or an abort without results (it re-enacted what ended
    the session), the recording before that end is replayed again and its recovery, if
    any, analysed (``partial_recovery``). Returns the outcome to report and the time the
    recording was cut at [s] (None when ``outcome`` is kept).
    """
    terminal = FAULT_PHASES | {Phase.ABORTED}
    if outcome.result is not None or outcome.phase not in terminal:
        return outcome, None
    ends = [t.t_s for t in outcome.transitions if t.new in terminal]
    cut = _cut(rec, ends[-1]) if ends else None
    if cut is None:
        return outcome, None
    rescued = replay(cut, setup, partial_recovery=True)
    if rescued.result is None:
        return outcome, None
    return rescued, ends[-1]


def _incomplete_verdict(
    data: SessionData, outcome: ReplayOutcome, cut_at_s: float | None
) -> dict[str, str]:
    """The verdict of an analysis of a session that ended early: incomplete, and why."""
    stored = data.summary or {}
    why = stored.get("end_reason") or stored.get("storage_error") or f"session {data.status}"
    if outcome.result is None:
        shown = "no results: the recording holds no recovery to analyse"
    elif cut_at_s is not None:
        shown = f"results rescued from the recording before {cut_at_s:.2f} s"
    else:
        shown = "results computed from the recovery that was recorded"
    return {"status": "incomplete", "line": f"Session {data.status} ({why}): {shown}."}


def analyze_session(request: AnalyzeRequest) -> AnalysisRun:
    """Replay a stored session (:class:`AnalyzeRequest` ``session_dir``) and write the results."""
    assert request.session_dir is not None
    if request.out is not None:  # before anything is read or counted
        _check_out(request.out, [], session=request.session_dir)
    doc, outcome, header, truth_rows, directory = replay_session(request)
    out = request.out if request.out is not None else _default_out(directory)
    return _write(out, doc, outcome, header, truth_rows)


def replay_session(
    request: AnalyzeRequest,
) -> tuple[dict[str, Any], ReplayOutcome, list[str], list[ParameterComparison] | None, Path]:
    """Replay a stored session as :func:`analyze_session` does, writing nothing.

    Returns the output document, the replay, the header line, the comparison with a
    ground truth (None: none) and the session's directory.
    """
    assert request.session_dir is not None
    data = read_session(request.session_dir)
    measurement, analysis, settings = _session_settings(data, request.config, request.sections)
    truth = _session_truth(request, data)
    recorded = recorded_source(
        data.manifest.get("calibration") or {}, f"{data.directory / layout.MANIFEST_NAME}"
    )
    imaging = choose_imaging(
        override=request.override(),
        config=settings_source(
            settings, request.config.calibration if request.config is not None else None
        ),
        recorded=recorded,
        scene=None if truth is None else truth_source(truth, "ground truth", "ground truth"),
    )
    calibration = imaging.need_calibration("no calibration: give --calibration CAL.json")
    _check_calibration_size(calibration, data.frame_size_px(), f"session {data.session_id}")
    notes = _status_notes(data)
    s_k = None
    imaging_out: dict[str, Any] = {"s_k_source": "session"}
    if request.recompute_sk:
        data, s_k, imaging_out = _recount(
            data,
            imaging,
            settings,
            notes,
            roi_given=request.roi_given,
            frame_size=_frame_size(truth),
        )
    status = data.status
    setup = ReplaySetup(
        measurement,
        analysis,
        calibration.value,
        load_reference(),
        force_full_scale_n=force_full_scale_n(data.manifest.get("firmware")),
    )
    # A complete session whose recorder ended the recovery before these settings would
    # (an older, shorter settling rule - docs/settling.md - or a shorter hold) is analysed
    # on the recovery it kept, as an interrupted one is.
    rec = data.recording(s_k)
    outcome = replay(rec, setup, partial_recovery=True)
    cut_at_s: float | None = None
    if status in ENDED_EARLY:
        ended_in = outcome.phase
        outcome, cut_at_s = rescue(rec, setup, outcome)
        if cut_at_s is not None:
            notes.append(
                f"the replay ends as the session did (phase {ended_in}); analysed the "
                f"recording before {cut_at_s:.2f} s, where the session ended"
            )
    if status is SessionState.COMPLETE and outcome.partial:
        notes.append(
            "the recorder ended the recovery before these settings would have (an older "
            "settling rule, docs/settling.md): analysed the recovery it kept; T_r and F_r "
            "may read low"
        )
    recomputed = outcome.summary()
    if status in ENDED_EARLY:
        recomputed["verdict"] = _incomplete_verdict(data, outcome, cut_at_s)
    problem = imaging_out.get("s_k_vs_stored", {}).get("problem")
    if problem:
        _flag_quantities(recomputed, problem)
    counted_p = imaging_out.get(
        "threshold_p", (data.manifest.get("calibration") or {}).get("threshold_p")
    )
    # the ROI S_k were counted in: the recount's, else the live run's (None: not recorded)
    counted_roi = Choice(imaging.roi_value, "recount") if request.recompute_sk else recorded.roi
    _flag_uncalibrated(
        recomputed,
        {
            THRESHOLD_NOT_CALIBRATED: _threshold_problem(counted_p, calibration),
            ROI_NOT_CALIBRATED: None
            if counted_roi is None
            else _roi_problem(counted_roi.value, calibration),
        },
        notes,
    )
    truth_rows = compare_ground_truth(recomputed, truth) if truth is not None else None
    inputs = {
        "kind": "session",
        "session_dir": str(data.directory),
        "session_id": data.session_id,
        "status": str(status),
        "frames": int(data.frame_times_s.size),
        "force_samples": int(data.force_times_s.size),
        "t_arm_s": data.t_arm_s,
    }
    doc = _document(
        inputs,
        (measurement, analysis, _cal_dict(calibration.value, calibration.source), imaging_out),
        outcome,
        notes,
        _stored_comparison(data.summary, recomputed),
        truth_rows,
    )
    doc["summary"] = recomputed
    # Who and what the session is of (subject, site, operator, note), as recorded.
    doc["metadata"] = metadata_of(data.manifest, data.directory / layout.MANIFEST_NAME)
    header = [f"session {data.session_id} ({status}), {data.directory}"]
    return doc, outcome, header, truth_rows, data.directory


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


def _files_imaging(request: AnalyzeRequest, truth_path: Path | None) -> Imaging:
    cfg = request.config
    truth = None if truth_path is None else load_ground_truth(truth_path)
    return choose_imaging(
        override=request.override(),
        config=settings_source(
            cfg.imaging if cfg is not None else ImagingSettings(),
            cfg.calibration if cfg is not None else None,
        ),
        scene=None
        if truth is None
        else truth_source(truth, str(truth_path), f"simulator ground truth {truth_path}"),
    )


def analyze_files(request: AnalyzeRequest) -> AnalysisRun:
    """Count S_k on a video, replay it with its force CSV and write the results."""
    video_path, force_path = request.video, request.force
    assert video_path is not None and force_path is not None
    if not video_path.is_file():
        raise DataFileError(f"{video_path}: no such video file")
    vdir = video_path.parent
    truth_path = request.ground_truth
    if truth_path is None and (vdir / "ground_truth.json").is_file():
        truth_path = vdir / "ground_truth.json"
    cfg = request.config
    settings = cfg.imaging if cfg is not None else ImagingSettings()
    imaging = _files_imaging(request, truth_path)
    calibration = imaging.need_calibration("no calibration: give --calibration CAL.json")
    notes: list[str] = []
    if calibration.source == f"simulator ground truth {truth_path}":
        notes.append(f"calibration: the scene's, from {truth_path}")
    threshold = imaging.need_threshold(_NO_THRESHOLD)
    roi = imaging.roi_value
    if imaging.roi is None:
        notes.append("ROI: none given, the whole frame is counted (give --roi)")
    force_t, force_n, force_col = read_force_csv(force_path)
    times_path = request.frame_times
    if times_path is None and (vdir / "frames.csv").is_file():
        times_path = vdir / "frames.csv"
    frame_times = None if times_path is None else read_frame_times_csv(times_path)[0]
    video = count_video(
        video_path,
        threshold.value,
        roi,
        saturation_limit_fraction=settings.saturation_limit_fraction,
        roi_field=None if imaging.roi is None else _roi_field(imaging.roi.source),
        check_size=lambda w, h: _check_calibration_size(calibration, (w, h), f"video {video_path}"),
    )
    t, s_k, more = match_frame_times(video, frame_times, str(times_path))
    notes.extend(more)
    if video.saturated_frames:
        notes.append(f"{video.saturated_frames} frame(s) saturated (see the flags)")
    measurement = cfg.measurement if cfg is not None else MeasurementConfig()
    analysis = cfg.analysis if cfg is not None else AnalysisSettings()
    setup = ReplaySetup(measurement, analysis, calibration.value, load_reference())
    outcome = replay(Recording(t, s_k, force_t, force_n), setup, partial_recovery=True)
    truth = imaging.truth
    truth_rows = compare_ground_truth(outcome.summary(), truth) if truth is not None else None
    inputs = {
        "kind": "files",
        "video": str(video_path),
        "force_csv": str(force_path),
        "force_time_column": force_col,
        "frame_times": None if times_path is None else str(times_path),
        "ground_truth": None if truth_path is None else str(truth_path),
        "frames": int(s_k.size),
        "force_samples": int(force_t.size),
        "frame_shape": list(video.frame_shape),
        "video_fps": video.fps,
    }
    imaging_out = {
        "s_k_source": f"video {video_path}",
        "threshold_p": threshold.value,
        "threshold_source": threshold.source,
        "roi": _roi_dict(roi),
        "video_crop": None if video.crop is None else list(video.crop),
        "saturated_frames": video.saturated_frames,
        "s_k_range_px": [float(np.min(s_k)), float(np.max(s_k))],
    }
    settings_out = (measurement, analysis, _cal_dict(calibration.value, calibration.source))
    doc = _document(inputs, (*settings_out, imaging_out), outcome, notes, None, truth_rows)
    _flag_uncalibrated(
        doc["summary"],
        {
            THRESHOLD_NOT_CALIBRATED: _threshold_problem(threshold.value, calibration),
            ROI_NOT_CALIBRATED: _roi_problem(roi, calibration),
        },
        doc["notes"],
    )
    out = request.out if request.out is not None else _default_out(vdir)
    protected = [p for p in (video_path, force_path, times_path, truth_path) if p is not None]
    _check_out(out, protected, explicit=request.out is not None)
    header = [f"video {video_path} ({s_k.size} frames), force {force_path}"]
    return _write(out, doc, outcome, header, truth_rows)


# --------------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------------


def _default_out(directory: Path) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    path = directory / f"analysis-{stamp}.json"
    n = 2
    while path.exists():
        path = directory / f"analysis-{stamp}-{n}.json"
        n += 1
    return path


def _check_out(
    out: Path, protected: list[Path], *, session: Path | None = None, explicit: bool = True
) -> None:
    """Refuse an output file that is one of the ``protected`` input files, a directory,
    or (``explicit``: given as ``--out``) inside any session directory: the analysed
    ``session``, a session of its sessions directory, or any directory holding a
    session's manifest (:func:`~stipi_daemon.storage.export.check_export_target`,
    as ``sessions export`` does), at any depth (``frames/`` too)."""
    target = out.resolve()
    for p in protected:
        if target == p.resolve():
            raise ConfigError(f"--out {out}: refusing to overwrite the recorded file {p}")
    if out.exists() and out.is_dir():
        raise ConfigError(f"--out {out}: is a directory (give a file name ending in .json)")
    if not explicit:
        return
    roots = [] if session is None else [session.parent]
    try:
        check_export_target(
            out, roots, [] if session is None else [session], is_file=True, what="an analysis"
        )
    except SessionError as exc:
        raise ConfigError(str(exc)) from None


def _frame_size(truth: Mapping[str, Any] | None) -> tuple[int, int] | None:
    """The camera's frame ``(width, height)`` [px] a simulator's ground truth records
    (``frame.width_px``, ``frame.height_px``), or None."""
    frame = None if truth is None else truth.get("frame")
    if not isinstance(frame, dict):
        return None
    w, h = frame.get("width_px"), frame.get("height_px")
    return (w, h) if isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0 else None


def _fmt(v: float | None, digits: int = 4) -> str:
    return "-" if v is None else f"{v:.{digits}g}"


def _truth_lines(rows: list[ParameterComparison]) -> list[str]:
    lines = ["", "ground truth (simulator)       truth       measured    error"]
    for r in rows:
        err = "-" if r.error_percent is None else f"{r.error_percent:+.3f} %"
        mark = ""
        if r.within_tolerance is not None:
            ok = "ok" if r.within_tolerance else "OUTSIDE"
            mark = f"  ({ok}, tolerance {r.tolerance_percent:g} %)"
        lines.append(f"  {r.label:<26} {_fmt(r.truth):>10}  {_fmt(r.measured):>10}  {err}{mark}")
    return lines


def _document(
    inputs: dict[str, Any],
    settings: tuple[MeasurementConfig, AnalysisSettings, dict[str, Any], dict[str, Any]],
    outcome: ReplayOutcome,
    notes: list[str],
    stored: dict[str, Any] | None,
    truth_rows: list[ParameterComparison] | None,
) -> dict[str, Any]:
    """The output document: inputs, settings (measurement, analysis, calibration, imaging),
    the replay, notes, the recomputed summary and the comparisons."""
    measurement, analysis, calibration, imaging = settings
    return {
        "format": OUTPUT_FORMAT,
        "version": OUTPUT_VERSION,
        "created_utc": layout.utc_now_iso(),
        "software": {"stipi_daemon": __version__},
        "input": inputs,
        "settings": {
            "measurement": measurement.model_dump(mode="json"),
            "analysis": analysis.model_dump(mode="json"),
            "calibration": calibration,
            "imaging": imaging,
        },
        "replay": {
            "frames_fed": outcome.frames_fed,
            "force_samples_fed": outcome.force_samples_fed,
            "partial_recovery": outcome.partial,
            "transitions": [
                {"t_s": t.t_s, "old": str(t.old), "new": str(t.new), "reason": t.reason}
                for t in outcome.transitions
            ],
        },
        "notes": [*notes, *outcome.notes],
        "summary": outcome.summary(),
        "comparison": {
            "stored_summary": stored,
            "ground_truth": None
            if truth_rows is None
            else [
                dataclasses.asdict(r) | {"within_tolerance": r.within_tolerance} for r in truth_rows
            ],
        },
    }


def _write(
    out: Path,
    doc: dict[str, Any],
    outcome: ReplayOutcome,
    header: list[str],
    truth_rows: list[ParameterComparison] | None,
) -> AnalysisRun:
    layout.write_json_atomic(out, doc, what="analysis results")
    return AnalysisRun(out, doc, outcome, header, truth_rows)
