"""``stipi-daemon sessions``: list, show and export recorded sessions.

Thin shell over :mod:`stipi_daemon.storage`: ``list`` prints one line per session under
the root, ``show`` prints a session's manifest, summary, row counts and integrity, and
``export`` writes its tables to CSV or Parquet. The root is ``--root``, else the
``storage.root`` of ``--config FILE`` (where that config's daemon records), else
``./sessions``. A session ``ID`` may
also be given as a path to its directory (anything containing a ``/``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import (
    DEFAULT_ROOT,
    EXPORT_FORMATS,
    SessionReader,
    export_session,
    list_sessions,
)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "sessions",
        help="list, show and export recorded sessions",
        description="List, inspect and export recorded sessions (one directory each).",
    )

    def show_help(_args: argparse.Namespace) -> int:
        parser.print_help()
        return 0

    parser.set_defaults(handler=show_help)
    sub = parser.add_subparsers(title="subcommands", metavar="SUBCOMMAND")

    def add_root(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--root",
            type=Path,
            default=None,
            help="directory holding the sessions (default: the storage.root of --config, "
            f"else ./{DEFAULT_ROOT})",
        )
        p.add_argument(
            "--config",
            type=Path,
            default=argparse.SUPPRESS,
            metavar="FILE",
            help="daemon config whose storage.root holds the sessions",
        )

    p_list = sub.add_parser("list", help="one line per session: id, created, status, counts")
    add_root(p_list)
    p_list.set_defaults(handler=_cmd_list)

    p_show = sub.add_parser("show", help="manifest, summary, row counts and integrity")
    p_show.add_argument("session_id", metavar="ID", help="session id or directory path")
    add_root(p_show)
    p_show.set_defaults(handler=_cmd_show)

    p_export = sub.add_parser("export", help="write every table to CSV or Parquet")
    p_export.add_argument("session_id", metavar="ID", help="session id or directory path")
    add_root(p_export)
    p_export.add_argument("--format", choices=EXPORT_FORMATS, required=True, dest="fmt")
    p_export.add_argument("--out", type=Path, required=True, help="output directory")
    p_export.add_argument(
        "--overwrite", action="store_true", help="replace existing files in the output directory"
    )
    # Deprecated spelling of --overwrite, kept working (hidden from --help).
    p_export.add_argument("--force", action=_DeprecatedOverwrite, help=argparse.SUPPRESS)
    p_export.set_defaults(handler=_cmd_export)


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


def _session_dir(root: Path, session_id: str) -> Path:
    if "/" in session_id:
        return Path(session_id)
    directory = root / session_id
    if not directory.is_dir():
        raise SessionError(f"{directory}: no such session (list them: stipi-daemon sessions list)")
    return directory


def _fmt_optional(value: object, fmt: str = "{}") -> str:
    return "-" if value is None else fmt.format(value)


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Left-aligned text table with two spaces between columns."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]
    lines = [header, *rows]
    return "\n".join(
        "  ".join(str(cell).ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
        for line in lines
    )


def _cmd_list(args: argparse.Namespace) -> int:
    listings = list_sessions(root := _root(args))
    if not listings:
        print(f"no sessions in {root}")
        return 0
    rows = [
        [
            s.session_id,
            s.created_utc or "-",
            s.status,
            s.validity,
            _fmt_optional(s.duration_s, "{:.1f} s"),
            _fmt_optional(s.n_frames),
            _fmt_optional(s.n_samples),
            s.severity or "-",
        ]
        for s in listings
    ]
    print(
        format_table(
            [
                "ID",
                "CREATED (UTC)",
                "STATUS",
                "VALIDITY",
                "DURATION",
                "FRAMES",
                "SAMPLES",
                "SEVERITY",
            ],
            rows,
        )
    )
    for s in listings:
        if s.error is not None:
            print(f"{s.session_id}: {s.error}")
    return 0


def _video_text(path: Path) -> str:
    """``video.mkv (1234567 B, mjpeg 1920x1080, 7200 frames)``; the error if unreadable."""
    from stipi_daemon.storage.video import probe_video

    try:
        info = probe_video(path)
    except SessionError as exc:
        return f"{path.name} ({path.stat().st_size} B, unreadable: {exc})"
    crop = "" if info.crop is None else ", crop " + ",".join(str(v) for v in info.crop)
    return (
        f"{path.name} ({info.size_bytes} B, {info.codec} {info.width}x{info.height} "
        f"{info.image}{crop}, {info.frames} frames)"
    )


def _cmd_show(args: argparse.Namespace) -> int:
    with SessionReader(_session_dir(_root(args), args.session_id)) as reader:
        status = reader.status
        meta = reader.meta()
        counts = reader.counts()
        report = reader.integrity_check()
        video = reader.video_path
        if video is None:
            video_text = "none"
        elif video.exists():
            video_text = _video_text(video)
        else:
            video_text = f"{video.name} (reserved, not present)"
        facts = [
            ("session", reader.session_id),
            ("directory", str(reader.directory)),
            ("status", status.value),
            ("created", str(reader.manifest["created_utc"])),
            ("finished", meta.get("finished_utc", "-")),
            ("duration", _fmt_optional(reader.duration_s(), "{:.3f} s")),
            ("video", video_text),
            ("integrity", "ok" if report.ok else "FAILED: " + "; ".join(report.problems)),
        ]
        if status.value == "recording" and reader.writer_owner is not None:
            facts.append(("writer", json.dumps(reader.writer_owner)))
        width = max(len(k) for k, _ in facts)
        for key, value in facts:
            print(f"{key.ljust(width)}  {value}")
        print("rows:")
        name_width = max(len(name) for name in counts)
        for name, n in counts.items():
            print(f"  {name.ljust(name_width)}  {n:>9}")
        print("manifest:")
        print(_indent(json.dumps(reader.manifest, indent=2)))
        try:
            summary = reader.summary
        except SessionError as exc:
            print(f"summary: unreadable: {exc}")
            return 1
        if summary is None:
            print("summary: none")
        else:
            print("summary:")
            print(_indent(json.dumps(summary, indent=2)))
        return 0 if report.ok else 1


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())


def _cmd_export(args: argparse.Namespace) -> int:
    with SessionReader(_session_dir(_root(args), args.session_id)) as reader:
        written = export_session(reader, args.out, args.fmt, overwrite=args.overwrite)
    for path in written:
        print(path)
    return 0
