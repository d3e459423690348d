"""``stipi-daemon sessions``: list, show and export recorded sessions, and tabulate them.

Thin shell over :mod:`stipi_daemon.storage` and :mod:`stipi_daemon.app.sessions_view`:
``list`` prints one line per session under the root (``--subject/--site/--operator``
keep exact matches), ``show`` prints a session's metadata, manifest, summary, row counts
and integrity (``--decode``: every video frame decoded too), ``export`` writes one
session to CSV, Parquet or MATLAB (default ``exports/<ID>`` next to the sessions
directory), and ``table`` writes one row per session
(metadata, verdict, every quantity's value and validity) to CSV or Parquet (default
``exports/results.csv`` next to the sessions directory). The root is ``--root``, else the
``storage.root`` of ``--config FILE`` (where that config's daemon records), else
``./sessions``. A session ``ID`` may also be given as a path to its directory (anything
containing a ``/``, or a directory in the current directory when the root holds no
session of that id). ``export`` refuses a session that fails its integrity check unless
``--allow-damaged``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from stipi_daemon.commands import add_sessions_root, out_path
from stipi_daemon.storage import (
    EXPORT_FORMATS,
    SessionReader,
    SessionState,
    export_session,
)
from stipi_daemon.storage.export import (
    default_export_dir,
    default_table_path,
    write_results_table,
)

#: Metadata fields ``list`` and ``table`` select on (exact match).
_SEARCHABLE = ("subject", "site", "operator")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "sessions",
        help="list, show, export and tabulate recorded sessions",
        description="List, inspect and export recorded sessions (one directory each).",
    )

    def show_help(_args: argparse.Namespace) -> int:
        parser.print_help()
        return 0

    parser.set_defaults(handler=show_help)
    sub = parser.add_subparsers(title="subcommands", metavar="SUBCOMMAND")

    add_root = add_sessions_root

    def add_where(p: argparse.ArgumentParser) -> None:
        for field in _SEARCHABLE:
            p.add_argument(
                f"--{field}",
                metavar="TEXT",
                help=f"only sessions whose {field} is TEXT, exactly",
            )

    p_list = sub.add_parser(
        "list",
        help="one line per session: id, created, status, subject, site, operator, label, "
        "validity, counts, severity",
        description="One line per session. LABEL is the first line of the session's note, "
        "else scene:<name> for simulated devices; VALIDITY is the summary's verdict.",
    )
    add_root(p_list)
    add_where(p_list)
    p_list.set_defaults(handler=_cmd_list)

    p_show = sub.add_parser("show", help="metadata, manifest, summary, row counts, integrity")
    p_show.add_argument("session_id", metavar="ID", help="session id or directory path")
    p_show.add_argument(
        "--decode",
        action="store_true",
        help="the integrity check also decodes every video frame (finds a frame whose bytes "
        "are whole but do not decode; seconds to minutes for a long session)",
    )
    add_root(p_show)
    p_show.set_defaults(handler=_cmd_show)

    p_export = sub.add_parser(
        "export",
        help="write a session to CSV or Parquet (one file per table) or MATLAB (.mat)",
        description="Write a session: csv/parquet give one file per table, validity.<fmt> "
        "(each quantity's validity), session.<fmt> (its results row) and copies of "
        "manifest.json, summary.json and video.mkv; mat gives <ID>.mat (force samples, "
        "frames with S_k, results, metadata; scipy.io.loadmat reads it) and the video "
        "beside it as <ID>.mkv. A session that fails its integrity check is not exported "
        "unless --allow-damaged. Never writes into a session directory.",
    )
    p_export.add_argument("session_id", metavar="ID", help="session id or directory path")
    add_root(p_export)
    p_export.add_argument(
        "--format", choices=EXPORT_FORMATS, default="csv", dest="fmt", help="default: csv"
    )
    p_export.add_argument(
        "--out",
        type=str,
        help="output directory (default: exports/ID next to the sessions directory, "
        "i.e. ROOT/../exports/ID)",
    )
    p_export.add_argument(
        "--overwrite", action="store_true", help="replace existing files in the output directory"
    )
    p_export.add_argument(
        "--allow-damaged",
        action="store_true",
        help="export a session that fails its integrity check (e.g. a truncated video) as "
        "it is; the export carries the problems (integrity.txt, or integrity_problems in "
        "the .mat) and a warning is printed. Without it such a session is not exported "
        "(exit 2)",
    )
    # Deprecated spelling of --overwrite, kept working (hidden from --help).
    p_export.add_argument("--force", action=_DeprecatedOverwrite, help=argparse.SUPPRESS)
    p_export.set_defaults(handler=_cmd_export)

    p_table = sub.add_parser(
        "table",
        help="one row per session (metadata, verdict, each quantity and its validity) "
        "to CSV or Parquet",
        description="Write one row per session: id, status, subject, site, operator, note, "
        "label, verdict, duration and counts, then for each quantity its value (unit in the "
        "column name: depth_mm, elasticity_kpa, ...; empty when invalid), _status, _flags "
        "and _reason. Unreadable sessions are rows with status 'error'. The format follows "
        "the --out suffix; Parquet also keeps each column's unit in its metadata.",
    )
    add_root(p_table)
    add_where(p_table)
    p_table.add_argument(
        "--out",
        type=str,
        help="results.csv or results.parquet (default: exports/results.csv next to the "
        "sessions directory, i.e. ROOT/../exports/results.csv)",
    )
    p_table.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p_table.set_defaults(handler=_cmd_table)


class _DeprecatedOverwrite(argparse.Action):
    """``--force``: the old name of ``--overwrite``; works, and says so on stderr."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, "overwrite", nargs=0, help=argparse.SUPPRESS)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[object] | None,
        option_string: str | None = None,
    ) -> None:
        print("stipi-daemon: note: --force is deprecated, use --overwrite", file=sys.stderr)
        namespace.overwrite = True


def _root(args: argparse.Namespace) -> Path:
    from stipi_daemon.app.config import sessions_root

    return sessions_root(args.root, getattr(args, "config", None))


def _session_dir(root: Path, text: str) -> Path:
    from stipi_daemon.app.config import find_session

    return find_session(root, text)


def _where(args: argparse.Namespace) -> dict[str, str | None]:
    return {field: getattr(args, field) for field in _SEARCHABLE}


def _cmd_list(args: argparse.Namespace) -> int:
    from stipi_daemon.app.sessions_view import list_text

    print(list_text(_root(args), _where(args)))
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from stipi_daemon.app.sessions_view import show_text

    text, status = show_text(_session_dir(_root(args), args.session_id), decode=args.decode)
    print(text)
    return status


def _cmd_export(args: argparse.Namespace) -> int:
    root = _root(args)
    directory = _session_dir(root, args.session_id)
    given = out_path(args.out)
    out = given if given is not None else default_export_dir(directory)
    with SessionReader(directory) as reader:
        live = reader.status is SessionState.RECORDING
        integrity = reader.integrity_check()
        written = export_session(
            reader,
            out,
            args.fmt,
            overwrite=args.overwrite,
            roots=[root],
            allow_damaged=args.allow_damaged,
            integrity=integrity,
        )
    if integrity.problems:
        print(
            f"stipi-daemon: warning: {directory}: integrity check failed, exported as it is "
            f"(--allow-damaged): {'; '.join(integrity.problems)}",
            file=sys.stderr,
        )
    if live:
        print(
            f"stipi-daemon: warning: {directory}: the session is still recording: exported "
            "what was stored so far, without its results",
            file=sys.stderr,
        )
    for path in written:
        print(path)
    return 0


def _cmd_table(args: argparse.Namespace) -> int:
    root = _root(args)
    given = out_path(args.out)
    out = given if given is not None else default_table_path(root)
    path, n = write_results_table(root, out, _where(args), overwrite=args.overwrite)
    print(f"{path} ({n} session{'s' if n != 1 else ''})")
    return 0
