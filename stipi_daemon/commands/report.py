"""``stipi-daemon report``: a session's report page and figures, or a comparison of sessions.

Thin shell over :mod:`stipi_daemon.report.write`. ``report SESSION`` writes
``<session>/report/report.html`` (self-contained) and the figures as PNGs next to it (or
into ``--out``); ``report --compare S1 S2 ...`` overlays several sessions and tabulates
mean and spread per parameter into ``--out``. A session is an id under ``--root`` (default:
the ``storage.root`` of ``--config``, else ``./sessions``) or a path to its directory. A
session is only read, never changed; its report directory is replaced.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from stipi_daemon.commands import add_sessions_root
from stipi_daemon.errors import ConfigError

#: Default output directory of ``--compare`` (relative to the working directory).
DEFAULT_COMPARE_OUT = Path("compare-report")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "report",
        help="write a session's HTML report and figures, or compare sessions",
        description=(
            "Write a self-contained HTML report with its figures as PNGs: force and S_k over "
            "time with the phases, the recovery fit with residuals, the VPR curves against "
            "the reference grades with the severity window and threshold (the paper's "
            "Figs. 10-12), the recovery models side by side (weights, 95 % intervals, the "
            "Kelvin-Voigt decision; also printed), the parameter table and representative "
            "frames. With --compare, "
            "overlay several sessions and tabulate mean and spread per parameter."
        ),
    )
    parser.add_argument(
        "session",
        nargs="?",
        metavar="SESSION",
        help="session id under --root, or a session directory",
    )
    parser.add_argument(
        "--compare",
        nargs="+",
        metavar="S",
        help="compare these sessions (ids under --root or directories; at least two)",
    )
    parser.add_argument(
        "--labels",
        nargs="+",
        metavar="LABEL",
        help="with --compare: one label per session (e.g. the grade); equal labels are "
        "grouped as repeated trials",
    )
    add_sessions_root(parser)
    parser.add_argument(
        "--out",
        type=Path,
        help="output directory (default: <session>/report; with --compare: "
        f"./{DEFAULT_COMPARE_OUT})",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from stipi_daemon.app.config import find_session, sessions_root
    from stipi_daemon.report.write import write_compare_report, write_session_report

    if args.session is not None and args.compare:
        raise ConfigError("give either SESSION or --compare S1 S2 ..., not both")
    if args.session is None and not args.compare:
        raise ConfigError("nothing to report: give SESSION, or --compare S1 S2 ...")
    if args.labels and not args.compare:
        raise ConfigError("--labels applies to --compare")
    if args.compare:
        if len(args.compare) < 2:
            raise ConfigError(f"--compare needs at least two sessions, got {len(args.compare)}")
        if args.labels and len(args.labels) != len(args.compare):
            raise ConfigError(
                f"--labels: {len(args.labels)} labels for {len(args.compare)} sessions"
            )
        root = sessions_root(args.root, getattr(args, "config", None))
        dirs = [find_session(root, s) for s in args.compare]
        written = write_compare_report(dirs, args.out or DEFAULT_COMPARE_OUT, args.labels)
    else:
        root = sessions_root(args.root, getattr(args, "config", None))
        written = write_session_report(find_session(root, args.session), args.out)
    print(f"report: {written.html_path}")
    if written.verdict:
        print(f"verdict: {written.verdict}")
    if written.recovery_models:
        print(written.recovery_models)
    print(f"figures: {len(written.figures)} PNG(s) in {written.html_path.parent}")
    for name, reason in written.missing.items():
        print(f"not drawn: {name}: {reason}")
    return 0
