"""``stipi-daemon calibrate``: fit Eqs. (4)-(5) from calibration measurements (Section IV.B).

Each equation takes its points from one source. Eq. (4) (S_0 against the depth change
d_s): ``--depth-pairs FILE.csv`` (columns ``s0_px``, ``depth_change_mm``) or
``--depth-recording PATH --displacements FILE.csv`` (intervals ``t_start_s``,
``t_end_s``, ``depth_change_mm`` during which the indenter was held at a known
displacement; S_0 is the mean S over each). Eq. (5) (S against the force F):
``--force-pairs FILE.csv`` (columns ``s_px``, ``force_n``) or ``--force-recording PATH``
(force plateaus found in the load-cell series; S and F averaged over each). A recording
PATH is a session directory (stored S_k) or a directory holding ``video.mkv``,
``frames.csv`` and ``force.csv`` as ``stipi-daemon simulate`` writes them (S_k counted
with ``--threshold``/``--roi``). The fits, their refusals and the file format are
:mod:`stipi_daemon.analysis.calibration`'s; recordings are turned into points by
:mod:`stipi_daemon.analysis.calibration_procedure`; the orchestration is
:func:`stipi_daemon.app.calibrate.calibrate`. This module parses the command line. The
procedure is in ``docs/calibration.md``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from stipi_daemon.analysis.calibration import DEFAULT_INDENTER_LENGTH_MM
from stipi_daemon.analysis.calibration_procedure import (
    DEFAULT_MIN_FORCE_N,
    DEFAULT_MIN_PLATEAU_S,
    DEFAULT_PLATEAU_TOLERANCE_N,
    DEFAULT_TRIM_S,
)
from stipi_daemon.commands import frame_size_arg, given_path
from stipi_daemon.errors import ConfigError


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
    parser.add_argument("--out", type=str, required=True, metavar="CAL.json", help="output file")
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
        "--roi",
        metavar="ROI",
        help="ROI the S values were counted in, and to count S on a video in: circle:CX,CY,R, "
        "rect:X,Y,W,H, full (recorded in the file, full as the rect of the frame size; the "
        "daemon refuses another ROI; a recording's own must agree)",
    )
    parser.add_argument("--probe-id", metavar="ID", help="probe identifier recorded in the file")
    parser.add_argument(
        "--frame-size",
        type=frame_size_arg,
        metavar="WxH",
        help="camera frame size the S values were counted at [px] (recorded in the file; the "
        "daemon refuses a camera of another size; a recording's own must agree)",
    )
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


def _check_values(args: argparse.Namespace) -> None:
    """Refuse option values out of their domain, naming the option (one line each)."""
    if args.threshold is not None and not 0 <= args.threshold <= 255:
        raise ConfigError(
            f"--threshold {args.threshold}: out of range, threshold p of Eq. (1) is a gray "
            "level 0..255"
        )
    positive = (
        ("--indenter-length", args.indenter_length, "mm", "the indenter length l of Eq. (3)"),
        ("--plateau-tolerance", args.plateau_tolerance, "N", "a plateau's force band"),
        ("--plateau-min", args.plateau_min, "s", "the shortest plateau"),
    )
    for option, value, unit, what in positive:
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"{option} {value:g}: must be > 0 {unit} ({what})")
    for option, value, unit in (("--min-force", args.min_force, "N"), ("--trim", args.trim, "s")):
        if not (math.isfinite(value) and value >= 0.0):
            raise ConfigError(f"{option} {value:g}: must be >= 0 {unit}")


def run(args: argparse.Namespace) -> int:
    # the fits and the readers are imported when the command runs, not at every start-up
    from stipi_daemon.app.calibrate import CalibrateRequest, calibrate
    from stipi_daemon.app.offline_io import parse_roi

    out = given_path(args.out)
    if out.exists() and not out.is_dir() and not args.overwrite:
        raise ConfigError(f"{out}: exists already (give --overwrite to replace it)")
    if args.depth_recording is not None and args.displacements is None:
        raise ConfigError("--depth-recording needs --displacements FILE.csv")
    if args.depth_recording is None and args.displacements is not None:
        raise ConfigError("--displacements applies to --depth-recording")
    _check_values(args)
    roi = parse_roi(args.roi) if args.roi is not None else None
    request = CalibrateRequest(
        out=out,
        depth_pairs=args.depth_pairs,
        depth_recording=args.depth_recording,
        displacements=args.displacements,
        force_pairs=args.force_pairs,
        force_recording=args.force_recording,
        indenter_length_mm=args.indenter_length,
        threshold_p=args.threshold,
        roi=roi,
        whole_frame=args.roi is not None and roi is None,
        probe_id=args.probe_id,
        frame_size_px=args.frame_size,
        plateau_tolerance_n=args.plateau_tolerance,
        plateau_min_s=args.plateau_min,
        min_force_n=args.min_force,
        trim_s=args.trim,
    )
    calibrate(request, emit=print)
    return 0
