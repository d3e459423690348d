"""``stipi-daemon analyze``: recompute a measurement's results offline.

Two inputs. ``analyze SESSION`` replays a stored session (its frames' S_k and its force
samples, read from ``session.sqlite``) through a fresh live pipeline with the settings
and calibration its manifest recorded (``--config``/``--calibration`` override them;
``--recompute-sk`` re-counts S_k on the session's video). ``analyze --video FILE --force
FILE.csv`` does the same from files: S_k counted on every decoded frame (Eqs. 1-2),
frame times from ``--frame-times`` (default: ``frames.csv`` next to the video, as the
simulator writes it), force samples from the CSV. The results are printed and written as
JSON (``--out``; default ``analysis-<UTC time>.json`` in the session directory or next to
the video; an explicit ``--out`` inside any session directory is refused, so nothing
recorded is ever overwritten). A simulator ground truth (``ground_truth.json`` next to the
video, or the one a simulated session's summary holds) is compared parameter by parameter.
``--roi`` is in camera-frame coordinates, also on a video that stores only the ROI's box.
This module parses the command line; the analysis is
:func:`stipi_daemon.app.analyze.analyze`.

Exit status: 0 results written; 1 written without results (the line says why); 2 refused
(one line on stderr, nothing written); 3 written, but ``--recompute-sk`` did not reproduce
the stored S_k with the recorded threshold and ROI, or lacks stored frames (missing from
the video or undecodable): the results are flagged (docs/storage.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from stipi_daemon.errors import ConfigError
from stipi_daemon.storage import DEFAULT_ROOT


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
        epilog=(
            "Exit status: 0 results written; 1 written without results; 2 refused, nothing "
            "written; 3 written, but --recompute-sk did not reproduce every stored S_k (or "
            "stored frames are missing from the video or undecodable): results flagged."
        ),
    )
    parser.add_argument(
        "session", nargs="?", metavar="SESSION", help="session id or directory path"
    )
    parser.add_argument(
        "--root",
        type=Path,
        default=None,
        help="directory holding the sessions (default: the storage.root of --config, else "
        f"./{DEFAULT_ROOT})",
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
        "if set) replace the recorded ones; its storage.root holds the sessions",
    )
    parser.add_argument("--threshold", type=int, metavar="P", help="threshold p of Eq. (1), 0..255")
    parser.add_argument(
        "--roi",
        metavar="ROI",
        help="region of interest in camera-frame coordinates: circle:CX,CY,R or "
        "rect:X,Y,W,H [px], or full (refused on a video that stores only the ROI's box)",
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
        "--out",
        type=Path,
        metavar="FILE.json",
        help="where to write the results (JSON); never inside a session directory",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    parser.add_argument("--quiet", action="store_true", help="print only the output path")
    parser.set_defaults(handler=run)


def _check_values(args: argparse.Namespace) -> None:
    """Refuse option values out of their domain, naming the option (one line each)."""
    if args.threshold is not None and not 0 <= args.threshold <= 255:
        raise ConfigError(
            f"--threshold {args.threshold}: out of range, threshold p of Eq. (1) is a gray "
            "level 0..255"
        )
    if args.out is not None:
        if args.out.is_dir():
            raise ConfigError(f"--out {args.out}: is a directory; give a file name (FILE.json)")
        if not args.out.parent.is_dir():
            raise ConfigError(f"--out {args.out}: directory {args.out.parent} does not exist")
        if args.out.exists() and not args.overwrite:
            raise ConfigError(f"--out {args.out}: exists already (give --overwrite to replace it)")
    if args.overwrite and args.out is None:
        raise ConfigError("--overwrite applies to --out (the default output name is new)")


def _check(args: argparse.Namespace) -> None:
    """Refuse contradictory or incomplete inputs (one line each)."""
    _check_values(args)
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
    if args.session is not None and args.roi is not None and not args.recompute_sk:
        raise ConfigError(
            "--roi applies where S_k is counted (--video, or SESSION with --recompute-sk); "
            "the session's S_k was counted live with its recorded ROI"
        )
    if args.session is not None and args.threshold is not None and not args.recompute_sk:
        raise ConfigError(
            "--threshold applies where S_k is counted (--video, or SESSION with "
            "--recompute-sk); the session's S_k was counted live with its recorded threshold"
        )
    if args.session is not None and (args.force is not None or args.frame_times is not None):
        raise ConfigError("--force/--frame-times apply to --video; a SESSION has its own samples")


def _session_dir(args: argparse.Namespace) -> Path:
    """SESSION as a directory: a path, or an id under the sessions root (one rule for every
    command, :func:`~stipi_daemon.app.config.find_session`)."""
    from stipi_daemon.app.config import find_session, sessions_root

    return find_session(sessions_root(args.root, args.config), args.session)


def run(args: argparse.Namespace) -> int:
    # the analysis is imported when it runs, not by every command's start-up
    from stipi_daemon.app.analyze import AnalyzeRequest, analyze
    from stipi_daemon.app.config import load_config
    from stipi_daemon.app.offline_io import parse_roi

    _check(args)
    roi_given = args.roi is not None
    request = AnalyzeRequest(
        session_dir=_session_dir(args) if args.session is not None else None,
        video=args.video,
        force=args.force,
        frame_times=args.frame_times,
        calibration=args.calibration,
        config=load_config(args.config) if args.config is not None else None,
        threshold_p=args.threshold,
        roi=parse_roi(args.roi) if roi_given else None,
        roi_given=roi_given,
        recompute_sk=args.recompute_sk,
        ground_truth=args.ground_truth,
        out=args.out,
    )
    done = analyze(request)
    if args.quiet:
        print(done.out)
    else:
        for line in done.lines():
            print(line)
        print(f"\nresults written to {done.out}")
    return done.exit_code
