"""``stipi-daemon analyze``: recompute a measurement's results offline.

Two inputs. ``analyze SESSION`` replays a stored session (its frames' S_k and its force
samples, read from ``session.sqlite``) through a fresh live pipeline with the settings
and calibration its manifest recorded (``--config``/``--calibration`` override them;
``--recompute-sk`` re-counts S_k on the session's video). ``analyze --video FILE --force
FILE.csv`` does the same from files: S_k counted on every decoded frame (Eqs. 1-2),
frame times from ``--frame-times`` (default: ``frames.csv`` next to the video, as the
simulator writes it), force samples from the CSV. The results are printed and written as
JSON (``--out``; default ``analysis-<UTC time>.json`` in the session directory or next to
the video; the session's own files are never overwritten). A simulator ground truth
(``ground_truth.json`` next to the video, or the one a simulated session's summary holds)
is compared parameter by parameter. This module is the shell: the replay and comparisons
are :mod:`stipi_daemon.measurement.replay`, file reading :mod:`stipi_daemon.app.offline_io`.
"""

from __future__ import annotations

import argparse
import dataclasses
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from stipi_daemon import __version__
from stipi_daemon.analysis.calibration import Calibration, load_calibration
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.app.config import DaemonConfig, ImagingSettings, load_config
from stipi_daemon.app.offline_io import (
    SessionData,
    count_video,
    load_ground_truth,
    match_frame_times,
    parse_roi,
    read_force_csv,
    read_frame_times_csv,
    read_session,
)
from stipi_daemon.errors import ConfigError, DataFileError, SessionError
from stipi_daemon.measurement.replay import (
    ParameterComparison,
    Recording,
    ReplayOutcome,
    ReplaySetup,
    calibration_from_mapping,
    compare_ground_truth,
    diff_results,
    replay,
)
from stipi_daemon.measurement.state_machine import MeasurementConfig
from stipi_daemon.storage import DEFAULT_ROOT, SessionState, layout

OUTPUT_FORMAT = "stipi-offline-analysis"
OUTPUT_VERSION = 1

#: Files of a session directory that ``--out`` may never replace.
_PROTECTED = (
    layout.MANIFEST_NAME,
    layout.SUMMARY_NAME,
    layout.DB_NAME,
    layout.DB_NAME + "-wal",
    layout.DB_NAME + "-shm",
    layout.LOCK_NAME,
    layout.VIDEO_NAME,
)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "analyze",
        help="recompute a measurement's results from a stored session or from files",
        description=(
            "Replay a recorded measurement through the live analysis and print/write the "
            "results: either a stored SESSION (id under --root, or a directory path), or "
            "a video with a force CSV (--video/--force), e.g. the output of "
            "`stipi-daemon simulate`."
        ),
    )
    parser.add_argument(
        "session", nargs="?", metavar="SESSION", help="session id or directory path"
    )
    parser.add_argument(
        "--root",
        type=Path,
        default=DEFAULT_ROOT,
        help=f"directory holding the sessions (default: ./{DEFAULT_ROOT})",
    )
    parser.add_argument("--video", type=Path, metavar="FILE", help="video to count S_k on")
    parser.add_argument(
        "--force",
        type=Path,
        metavar="FILE.csv",
        help="force samples: a time column (t_s, t_true_s or t_host_s) and force_n",
    )
    parser.add_argument(
        "--frame-times",
        type=Path,
        metavar="FILE.csv",
        help="frame times in video order (column t_s, t_capture_host_s or t_host_s); "
        "default: frames.csv next to the video, else the video's frame rate",
    )
    parser.add_argument(
        "--calibration", type=Path, metavar="CAL.json", help="calibration file to use"
    )
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="daemon config whose measurement/analysis/imaging settings (and calibration, "
        "if set) replace the recorded ones",
    )
    parser.add_argument("--threshold", type=int, metavar="P", help="threshold p of Eq. (1), 0..255")
    parser.add_argument(
        "--roi",
        metavar="ROI",
        help="region of interest: circle:CX,CY,R or rect:X,Y,W,H [px], or full",
    )
    parser.add_argument(
        "--recompute-sk",
        action="store_true",
        help="with SESSION: count S_k again on the session's video instead of using the stored S_k",
    )
    parser.add_argument(
        "--ground-truth",
        type=Path,
        metavar="FILE",
        help="simulator ground truth to compare with (default: ground_truth.json next to the "
        "video, or the one in a simulated session's summary)",
    )
    parser.add_argument(
        "--out", type=Path, metavar="FILE.json", help="where to write the results (JSON)"
    )
    parser.add_argument("--quiet", action="store_true", help="print only the output path")
    parser.set_defaults(handler=run)


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


def _manifest_settings(
    data: SessionData,
) -> tuple[MeasurementConfig, AnalysisSettings, ImagingSettings]:
    cfg = data.manifest.get("config") or {}
    where = f"{data.directory / layout.MANIFEST_NAME}: field 'config"
    return (
        _validated(MeasurementConfig, cfg.get("measurement"), f"{where}.measurement"),
        _validated(AnalysisSettings, cfg.get("analysis"), f"{where}.analysis"),
        _validated(ImagingSettings, cfg.get("imaging"), f"{where}.imaging"),
    )


def _cal_dict(cal: Calibration, source: str) -> dict[str, Any]:
    return {
        "alpha1_mm_per_px2": cal.alpha1_mm_per_px2,
        "alpha2_mm_per_px": cal.alpha2_mm_per_px,
        "c1_px": cal.c1_px,
        "c2_px_per_n": cal.c2_px_per_n,
        "indenter_length_mm": cal.indenter_length_mm,
        "threshold_p": cal.threshold_p,
        "s0_valid_range_px": None if cal.s0_valid_range_px is None else list(cal.s0_valid_range_px),
        "force_valid_range_n": None
        if cal.force_valid_range_n is None
        else list(cal.force_valid_range_n),
        "source": source,
    }


def _roi_dict(roi: CircleROI | RectROI | None) -> dict[str, Any] | None:
    return None if roi is None else roi.model_dump(mode="json")


def _roi_from_truth(truth: dict[str, Any] | None) -> CircleROI | None:
    r = None if truth is None else truth.get("roi")
    if not isinstance(r, dict):
        return None
    try:
        return CircleROI(
            kind="circle", cx_px=r["cx_px"], cy_px=r["cy_px"], radius_px=r["radius_px"]
        )
    except (KeyError, ValidationError):
        return None


def _threshold(
    args: argparse.Namespace, candidates: list[tuple[int | None, str]]
) -> tuple[int, str]:
    if args.threshold is not None:
        if not 0 <= args.threshold <= 255:
            raise ConfigError(f"--threshold must be 0..255, got {args.threshold}")
        return int(args.threshold), "--threshold"
    for value, source in candidates:
        if value is not None:
            return int(value), source
    raise ConfigError(
        "no threshold p for Eq. (1): give --threshold P (or a calibration with threshold_p)"
    )


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


def _check_out(out: Path, protected: list[Path]) -> None:
    target = out.resolve()
    for p in protected:
        if target == p.resolve():
            raise ConfigError(f"--out {out}: refusing to overwrite the recorded file {p}")
    if out.exists() and out.is_dir():
        raise ConfigError(f"--out {out}: is a directory (give a file name ending in .json)")


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


def _report(
    outcome: ReplayOutcome,
    doc: dict[str, Any],
    header: list[str],
    truth_rows: list[ParameterComparison] | None,
) -> list[str]:
    from stipi_daemon.app.console import format_results

    lines = list(header)
    lines.append(
        f"replayed {outcome.frames_fed} frames and {outcome.force_samples_fed} force samples:"
        f" phase {outcome.phase} ({outcome.end_reason})"
    )
    for note in doc["notes"]:
        lines.append(f"note: {note}")
    for note in dict.fromkeys(doc["summary"]["notes"]):
        lines.append(f"analysis note: {note}")
    lines.extend(format_results(doc["summary"]))
    stored = doc["comparison"]["stored_summary"]
    if stored is not None:
        if stored["identical"]:
            lines.append("")
            lines.append("recorded summary: identical results")
        else:
            diffs = stored["differences"]
            lines.append("")
            lines.append(f"recorded summary: {len(diffs)} difference(s)")
            lines.extend(f"  {d}" for d in diffs[:10])
            if len(diffs) > 10:
                lines.append(f"  ... and {len(diffs) - 10} more (see the output file)")
    if truth_rows is not None:
        lines.extend(_truth_lines(truth_rows))
    return lines


# --------------------------------------------------------------------------------------------
# run
# --------------------------------------------------------------------------------------------


def _session_dir(args: argparse.Namespace) -> Path:
    text: str = args.session
    if "/" in text or Path(text).is_dir():
        return Path(text)
    directory = Path(args.root) / text
    if not directory.is_dir():
        raise SessionError(f"{directory}: no such session (list them: stipi-daemon sessions list)")
    return directory


def run(args: argparse.Namespace) -> int:
    if args.session is not None and args.video is not None:
        raise ConfigError("give either SESSION or --video/--force, not both")
    if args.session is None and args.video is None:
        raise ConfigError("nothing to analyse: give SESSION, or --video FILE --force FILE.csv")
    if args.session is None and args.force is None:
        raise ConfigError("--video needs --force FILE.csv (the force samples)")
    if args.session is None and args.recompute_sk:
        raise ConfigError(
            "--recompute-sk applies to a SESSION (with --video S_k is always counted)"
        )
    if args.session is not None and (args.force is not None or args.frame_times is not None):
        raise ConfigError("--force/--frame-times apply to --video; a SESSION has its own samples")
    roi_override = parse_roi(args.roi) if args.roi is not None else None
    cfg: DaemonConfig | None = load_config(args.config) if args.config is not None else None
    if args.session is not None:
        return _run_session(args, cfg, roi_override)
    return _run_files(args, cfg, roi_override)


def _calibration(
    args: argparse.Namespace, cfg: DaemonConfig | None, fallback: tuple[Calibration, str] | None
) -> tuple[Calibration, str]:
    if args.calibration is not None:
        return load_calibration(args.calibration), str(args.calibration)
    if cfg is not None and cfg.calibration is not None:
        return load_calibration(cfg.calibration), str(cfg.calibration)
    if fallback is None:
        raise ConfigError("no calibration: give --calibration CAL.json")
    return fallback


def _run_session(
    args: argparse.Namespace,
    cfg: DaemonConfig | None,
    roi_override: CircleROI | RectROI | None,
) -> int:
    directory = _session_dir(args)
    data = read_session(directory)
    m_meas, m_analysis, m_imaging = _manifest_settings(data)
    measurement = cfg.measurement if cfg is not None else m_meas
    analysis = cfg.analysis if cfg is not None else m_analysis
    imaging = cfg.imaging if cfg is not None else m_imaging
    manifest_cal = data.manifest.get("calibration") or {}
    calibration, cal_source = _calibration(
        args,
        cfg,
        (
            calibration_from_mapping(manifest_cal, f"{directory / layout.MANIFEST_NAME}"),
            "session manifest",
        ),
    )
    summary = data.summary
    truth: dict[str, Any] | None = None
    if args.ground_truth is not None:
        truth = load_ground_truth(args.ground_truth)
    elif summary is not None and isinstance(summary.get("ground_truth"), dict):
        truth = summary["ground_truth"]

    notes: list[str] = []
    status = data.status
    if status is SessionState.INTERRUPTED:
        notes.append(
            "session interrupted (the recorder stopped before finishing): analysed the "
            "samples that were kept"
        )
    elif status is SessionState.RECORDING:
        notes.append("session still recording: analysed the samples committed so far")
    elif summary is None:
        notes.append(f"session status {status} but no summary.json")

    s_k = None
    imaging_out: dict[str, Any] = {"s_k_source": "session"}
    if args.recompute_sk:
        if data.video_path is None:
            raise SessionError(f"{directory}: --recompute-sk: the session has no video file")
        threshold, t_source = _threshold(
            args,
            [
                (imaging.threshold_p, "config imaging.threshold_p"),
                (manifest_cal.get("threshold_p"), "session manifest calibration"),
                (calibration.threshold_p, "calibration"),
            ],
        )
        roi = roi_override if args.roi is not None else imaging.roi
        if args.roi is None and roi is None:
            roi = _roi_from_truth(truth)
            if roi is not None:
                notes.append("ROI: the simulator's waveguide disc (ground truth)")
            else:
                notes.append("ROI: none recorded, the whole frame is counted")
        video = count_video(
            data.video_path,
            threshold,
            roi,
            saturation_limit_fraction=imaging.saturation_limit_fraction,
        )
        n_rows, n_video = data.frame_times_s.size, video.s_k_px.size
        if n_video < n_rows:
            notes.append(
                f"the video holds {n_video} of the {n_rows} stored frames: the first "
                f"{n_video} are analysed"
            )
        elif n_video > n_rows:
            notes.append(
                f"the video holds {n_video - n_rows} frame(s) more than the database "
                f"({n_rows}): frames without a stored time are not used"
            )
        n = min(n_rows, n_video)
        data = dataclasses.replace(
            data, frame_times_s=data.frame_times_s[:n], s_k_px=data.s_k_px[:n]
        )
        s_k = video.s_k_px[:n]
        imaging_out = {
            "s_k_source": f"video {data.video_path}",
            "threshold_p": threshold,
            "threshold_source": t_source,
            "roi": _roi_dict(roi),
            "saturated_frames": video.saturated_frames,
        }
    recording = data.recording(s_k)
    setup = ReplaySetup(measurement, analysis, calibration, load_reference())
    partial = status in (SessionState.INTERRUPTED, SessionState.RECORDING)
    # A complete session whose recorder ended the recovery before these settings would
    # (an older, shorter settling rule - docs/settling.md - or a shorter hold) is analysed
    # on the recovery it kept, as an interrupted one is.
    outcome = replay(recording, setup, partial_recovery=partial or status is SessionState.COMPLETE)
    if status is SessionState.COMPLETE and outcome.partial:
        notes.append(
            "the recorder ended the recovery before these settings would have (an older "
            "settling rule, docs/settling.md): analysed the recovery it kept; T_r and F_r "
            "may read low"
        )
    recomputed = outcome.summary()

    stored_cmp: dict[str, Any] | None = None
    if summary is not None and "phase" in summary:
        keys = [k for k in recomputed if k in summary]
        diffs = diff_results(
            {k: summary[k] for k in keys},
            _json_roundtrip({k: recomputed[k] for k in keys}),
            "summary",
        )
        stored_cmp = {"identical": not diffs, "differences": diffs}
    truth_rows = compare_ground_truth(recomputed, truth) if truth is not None else None
    doc = _document(
        {
            "kind": "session",
            "session_dir": str(data.directory),
            "session_id": data.session_id,
            "status": str(status),
            "frames": int(data.frame_times_s.size),
            "force_samples": int(data.force_times_s.size),
            "t_arm_s": data.t_arm_s,
        },
        measurement,
        analysis,
        _cal_dict(calibration, cal_source),
        imaging_out,
        outcome,
        notes,
        stored_cmp,
        truth_rows,
    )
    out = args.out if args.out is not None else _default_out(data.directory)
    _check_out(out, [data.directory / name for name in _PROTECTED])
    header = [f"session {data.session_id} ({status}), {data.directory}"]
    return _finish(args, out, doc, outcome, header, truth_rows)


def _run_files(
    args: argparse.Namespace,
    cfg: DaemonConfig | None,
    roi_override: CircleROI | RectROI | None,
) -> int:
    video_path: Path = args.video
    if not video_path.is_file():
        raise DataFileError(f"{video_path}: no such video file")
    vdir = video_path.parent
    notes: list[str] = []
    truth: dict[str, Any] | None = None
    truth_path = args.ground_truth
    if truth_path is None and (vdir / "ground_truth.json").is_file():
        truth_path = vdir / "ground_truth.json"
    if truth_path is not None:
        truth = load_ground_truth(truth_path)
    measurement = cfg.measurement if cfg is not None else MeasurementConfig()
    analysis = cfg.analysis if cfg is not None else AnalysisSettings()
    imaging = cfg.imaging if cfg is not None else ImagingSettings()
    fallback: tuple[Calibration, str] | None = None
    if truth is not None and isinstance(truth.get("calibration"), dict):
        fallback = (
            calibration_from_mapping(truth["calibration"], str(truth_path)),
            f"simulator ground truth {truth_path}",
        )
    calibration, cal_source = _calibration(args, cfg, fallback)
    if args.calibration is None and cfg is None and fallback is not None:
        notes.append(f"calibration: the scene's, from {truth_path}")
    truth_frame = truth.get("frame") if truth is not None else None
    threshold, t_source = _threshold(
        args,
        [
            (imaging.threshold_p, "config imaging.threshold_p"),
            (calibration.threshold_p, f"calibration ({cal_source})"),
            (
                truth_frame.get("threshold_p") if isinstance(truth_frame, dict) else None,
                f"simulator ground truth {truth_path}",
            ),
        ],
    )
    roi = roi_override if args.roi is not None else imaging.roi
    if args.roi is None and roi is None:
        roi = _roi_from_truth(truth)
        if roi is None:
            notes.append("ROI: none given, the whole frame is counted (give --roi)")
    force_t, force_n, force_col = read_force_csv(args.force)
    times_path: Path | None = args.frame_times
    if times_path is None and (vdir / "frames.csv").is_file():
        times_path = vdir / "frames.csv"
    frame_times = None
    if times_path is not None:
        frame_times, _ = read_frame_times_csv(times_path)
    video = count_video(
        video_path, threshold, roi, saturation_limit_fraction=imaging.saturation_limit_fraction
    )
    t, s_k, more = match_frame_times(video, frame_times, str(times_path))
    notes.extend(more)
    if video.saturated_frames:
        notes.append(f"{video.saturated_frames} frame(s) saturated (see the flags)")
    recording = Recording(t, s_k, force_t, force_n)
    setup = ReplaySetup(measurement, analysis, calibration, load_reference())
    outcome = replay(recording, setup, partial_recovery=True)
    truth_rows = compare_ground_truth(outcome.summary(), truth) if truth is not None else None
    doc = _document(
        {
            "kind": "files",
            "video": str(video_path),
            "force_csv": str(args.force),
            "force_time_column": force_col,
            "frame_times": None if times_path is None else str(times_path),
            "ground_truth": None if truth_path is None else str(truth_path),
            "frames": int(s_k.size),
            "force_samples": int(force_t.size),
            "frame_shape": list(video.frame_shape),
            "video_fps": video.fps,
        },
        measurement,
        analysis,
        _cal_dict(calibration, cal_source),
        {
            "s_k_source": f"video {video_path}",
            "threshold_p": threshold,
            "threshold_source": t_source,
            "roi": _roi_dict(roi),
            "saturated_frames": video.saturated_frames,
            "s_k_range_px": [float(np.min(s_k)), float(np.max(s_k))],
        },
        outcome,
        notes,
        None,
        truth_rows,
    )
    out = args.out if args.out is not None else _default_out(vdir)
    protected = [video_path, args.force]
    if times_path is not None:
        protected.append(times_path)
    if truth_path is not None:
        protected.append(truth_path)
    _check_out(out, protected)
    header = [f"video {video_path} ({s_k.size} frames), force {args.force}"]
    return _finish(args, out, doc, outcome, header, truth_rows)


def _json_roundtrip(value: Any) -> Any:
    import json

    from stipi_daemon.storage.schema import to_jsonable

    return json.loads(json.dumps(to_jsonable(value, "summary"), allow_nan=False))


def _document(
    inputs: dict[str, Any],
    measurement: MeasurementConfig,
    analysis: AnalysisSettings,
    calibration: dict[str, Any],
    imaging: dict[str, Any],
    outcome: ReplayOutcome,
    notes: list[str],
    stored: dict[str, Any] | None,
    truth_rows: list[ParameterComparison] | None,
) -> dict[str, Any]:
    all_notes = [*notes, *outcome.notes]
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
        "notes": all_notes,
        "summary": outcome.summary(),
        "comparison": {
            "stored_summary": stored,
            "ground_truth": None
            if truth_rows is None
            else [
                {
                    "name": r.name,
                    "label": r.label,
                    "truth": r.truth,
                    "measured": r.measured,
                    "error_percent": r.error_percent,
                    "tolerance_percent": r.tolerance_percent,
                    "within_tolerance": r.within_tolerance,
                }
                for r in truth_rows
            ],
        },
    }


def _finish(
    args: argparse.Namespace,
    out: Path,
    doc: dict[str, Any],
    outcome: ReplayOutcome,
    header: list[str],
    truth_rows: list[ParameterComparison] | None,
) -> int:
    layout.write_json_atomic(out, doc, what="analysis results")
    if args.quiet:
        print(out)
    else:
        for line in _report(outcome, doc, header, truth_rows):
            print(line)
        print(f"\nresults written to {out}")
    return 0 if outcome.result is not None else 1
