"""``stipi-daemon calibrate``: fit Eqs. (4)-(5) from calibration measurements (Section IV.B).

Each equation takes its points from one source. Eq. (4) (S_0 against the depth change
d_s): ``--depth-pairs FILE.csv`` (columns ``s0_px``, ``depth_change_mm``) or
``--depth-recording PATH --displacements FILE.csv`` (intervals ``t_start_s``,
``t_end_s``, ``depth_change_mm`` during which the indenter was held at a known
displacement; S_0 is the mean S over each). Eq. (5) (S against the force F):
``--force-pairs FILE.csv`` (columns ``s_px``, ``force_n``) or ``--force-recording PATH``
(force plateaus found in the load-cell series; S and F averaged over each). A recording
PATH is a session directory (stored S_k) or a directory holding ``video.avi``,
``frames.csv`` and ``force.csv`` as ``stipi-daemon simulate`` writes them (S_k counted
with ``--threshold``/``--roi``). The fits, their refusals and the file format are
:mod:`stipi_daemon.analysis.calibration`'s; recordings are turned into points by
:mod:`stipi_daemon.analysis.calibration_procedure`. The procedure is in ``docs/calibration.md``.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.calibration import (
    DEFAULT_INDENTER_LENGTH_MM,
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
    displacement_points,
    find_force_plateaus,
    fit_report,
    force_points,
)
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.offline_io import (
    count_video,
    match_frame_times,
    parse_roi,
    read_csv_table,
    read_force_csv,
    read_frame_times_csv,
    read_session,
)
from stipi_daemon.errors import CalibrationError, ConfigError, DataFileError

FloatArray = npt.NDArray[np.float64]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="fit the probe calibration (Eqs. 4-5) and write a calibration file",
        description=(
            "Fit Eq. (4) (S_0 -> depth change d_s) and Eq. (5) (S -> force) from measured "
            "pairs or recorded calibration runs, print coefficients with standard errors, "
            "R^2 and residuals, and write the versioned calibration file. "
            "See docs/calibration.md."
        ),
    )
    depth = parser.add_mutually_exclusive_group(required=True)
    depth.add_argument(
        "--depth-pairs",
        type=Path,
        metavar="FILE.csv",
        help="Eq. (4) points: columns s0_px, depth_change_mm",
    )
    depth.add_argument(
        "--depth-recording",
        type=Path,
        metavar="PATH",
        help="session directory or simulator-style directory recorded at known displacements "
        "(needs --displacements)",
    )
    force = parser.add_mutually_exclusive_group(required=True)
    force.add_argument(
        "--force-pairs", type=Path, metavar="FILE.csv", help="Eq. (5) points: columns s_px, force_n"
    )
    force.add_argument(
        "--force-recording",
        type=Path,
        metavar="PATH",
        help="session directory or simulator-style directory with force plateaus",
    )
    parser.add_argument(
        "--displacements",
        type=Path,
        metavar="FILE.csv",
        help="with --depth-recording: columns t_start_s, t_end_s, depth_change_mm",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="CAL.json", help="output file")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing calibration file"
    )
    parser.add_argument(
        "--indenter-length",
        type=float,
        default=DEFAULT_INDENTER_LENGTH_MM,
        metavar="MM",
        help=f"indenter length l of Eq. (3) [mm] (default {DEFAULT_INDENTER_LENGTH_MM:g})",
    )
    parser.add_argument(
        "--threshold",
        type=int,
        metavar="P",
        help="threshold p of Eq. (1) the S values were counted with (recorded in the file; "
        "required to count S on a video)",
    )
    parser.add_argument(
        "--roi", metavar="ROI", help="ROI to count S on a video: circle:CX,CY,R, rect:X,Y,W,H, full"
    )
    parser.add_argument("--probe-id", metavar="ID", help="probe identifier recorded in the file")
    parser.add_argument(
        "--plateau-tolerance",
        type=float,
        default=DEFAULT_PLATEAU_TOLERANCE_N,
        metavar="N",
        help=f"force band of a plateau [N] (default {DEFAULT_PLATEAU_TOLERANCE_N:g})",
    )
    parser.add_argument(
        "--plateau-min",
        type=float,
        default=DEFAULT_MIN_PLATEAU_S,
        metavar="S",
        help=f"shortest plateau [s] (default {DEFAULT_MIN_PLATEAU_S:g})",
    )
    parser.add_argument(
        "--min-force",
        type=float,
        default=DEFAULT_MIN_FORCE_N,
        metavar="N",
        help=f"plateaus below this mean force are ignored [N] (default {DEFAULT_MIN_FORCE_N:g})",
    )
    parser.add_argument(
        "--trim",
        type=float,
        default=DEFAULT_TRIM_S,
        metavar="S",
        help=f"time cut from each end of a plateau [s] (default {DEFAULT_TRIM_S:g})",
    )
    parser.set_defaults(handler=run)


@dataclass(frozen=True)
class _Series:
    frame_t: FloatArray
    s_k: FloatArray
    force_t: FloatArray
    force_n: FloatArray
    threshold_p: int | None
    what: str


def _load_recording(
    path: Path, threshold: int | None, roi: CircleROI | RectROI | None, need_force: bool
) -> _Series:
    """S_k and force series of a session directory or a simulator-style directory."""
    if (path / "manifest.json").is_file():
        data = read_session(path)
        cal = data.manifest.get("calibration") or {}
        imaging = (data.manifest.get("config") or {}).get("imaging") or {}
        p = imaging.get("threshold_p", cal.get("threshold_p"))
        return _Series(
            data.frame_times_s,
            data.s_k_px,
            data.force_times_s,
            data.force_n,
            None if p is None else int(p),
            f"session {data.session_id}",
        )
    video = path / "video.avi"
    if not path.is_dir() or not video.is_file():
        raise DataFileError(
            f"{path}: not a recording (expected a session directory with manifest.json, or a "
            "directory with video.avi, frames.csv and force.csv)"
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
    return _Series(t, s, ft, fn, threshold, f"video {video}")


def run(args: argparse.Namespace) -> int:
    if args.out.exists() and not args.overwrite:
        raise ConfigError(f"{args.out}: exists already (give --overwrite to replace it)")
    if args.depth_recording is not None and args.displacements is None:
        raise ConfigError("--depth-recording needs --displacements FILE.csv")
    if args.depth_recording is None and args.displacements is not None:
        raise ConfigError("--displacements applies to --depth-recording")
    if args.threshold is not None and not 0 <= args.threshold <= 255:
        raise ConfigError(f"--threshold must be 0..255, got {args.threshold}")
    roi = parse_roi(args.roi) if args.roi is not None else None
    thresholds: list[int] = []

    # Eq. (4) points.
    if args.depth_pairs is not None:
        table = read_csv_table(args.depth_pairs, ["s0_px", "depth_change_mm"])
        s0, d_s = table.columns["s0_px"], table.columns["depth_change_mm"]
        print(f"Eq. (4): {len(table)} pairs from {args.depth_pairs}")
    else:
        rec = _load_recording(args.depth_recording, args.threshold, roi, need_force=False)
        if rec.threshold_p is not None:
            thresholds.append(rec.threshold_p)
        table = read_csv_table(args.displacements, ["t_start_s", "t_end_s", "depth_change_mm"])
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
            raise CalibrationError(f"{args.displacements}: {exc}") from None
        print(f"Eq. (4): {len(points)} displacement(s) from {rec.what}")
        print("   t_start_s  t_end_s   d_s [mm]   S0 [px]  sd [px]  frames")
        for pt in points:
            iv = pt.interval
            print(
                f"  {iv.t_start_s:9.3f} {iv.t_end_s:8.3f} {iv.depth_change_mm:10.4g}"
                f" {pt.s0_px:9.1f} {pt.s0_sd_px:8.1f} {pt.n_frames:7d}"
            )
        s0 = np.asarray([p.s0_px for p in points])
        d_s = np.asarray([p.interval.depth_change_mm for p in points])

    # Eq. (5) points.
    if args.force_pairs is not None:
        table = read_csv_table(args.force_pairs, ["s_px", "force_n"])
        s_px, f_n = table.columns["s_px"], table.columns["force_n"]
        print(f"Eq. (5): {len(table)} pairs from {args.force_pairs}")
    else:
        rec = _load_recording(args.force_recording, args.threshold, roi, need_force=True)
        if rec.threshold_p is not None:
            thresholds.append(rec.threshold_p)
        plateaus = find_force_plateaus(
            rec.force_t,
            rec.force_n,
            tolerance_n=args.plateau_tolerance,
            min_duration_s=args.plateau_min,
            min_force_n=args.min_force,
        )
        fpoints = force_points(
            rec.force_t, rec.force_n, rec.frame_t, rec.s_k, plateaus, trim_s=args.trim
        )
        print(f"Eq. (5): {len(fpoints)} force plateau(s) found in {rec.what}")
        print("   t_start_s  t_end_s    F [N]  sd [N]     S [px]  sd [px]  frames")
        for fp in fpoints:
            print(
                f"  {fp.t_start_s:9.3f} {fp.t_end_s:8.3f} {fp.force_n:8.3f} {fp.force_sd_n:7.3f}"
                f" {fp.s_px:10.1f} {fp.s_sd_px:8.1f} {fp.n_frames:7d}"
            )
        s_px = np.asarray([p.s_px for p in fpoints])
        f_n = np.asarray([p.force_n for p in fpoints])

    threshold = args.threshold
    if threshold is None and thresholds:
        if len(set(thresholds)) > 1:
            raise CalibrationError(
                f"the recordings were counted with different thresholds p {sorted(set(thresholds))}"
                ": S values are not comparable"
            )
        threshold = thresholds[0]
    elif threshold is not None and any(p != threshold for p in thresholds):
        raise CalibrationError(
            f"--threshold {threshold} differs from the recordings' p {sorted(set(thresholds))}"
        )

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
        indenter_length_mm=args.indenter_length,
        threshold_p=threshold,
        probe_id=args.probe_id,
    )
    print()
    for line in fit_report(cal):
        print(line)
    if threshold is None:
        print(
            "warning: no threshold p recorded (--threshold): the daemon will need "
            "imaging.threshold_p, and S values counted with another p are not comparable"
        )
    path = save_calibration(args.out, cal)
    load_calibration(path)  # what was written reads back
    print(f"\ncalibration written to {path}")
    return 0
