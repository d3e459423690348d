"""What ``stipi-daemon sessions list`` and ``sessions show`` print.

``list``: one line per session under a root (optionally only those whose subject, site or
operator equal given values exactly): id, creation time, status, subject, site, operator,
label (the note's first line, else ``scene:<name>`` for simulated devices), validity (the
summary's verdict), duration, row counts and severity; then one line per unreadable
session. ``show``: a session's facts (metadata included), row counts, manifest and
summary. The data come from :mod:`stipi_daemon.storage`; this module only formats them.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from stipi_daemon.errors import EXIT_DAMAGED, EXIT_OK, SessionError
from stipi_daemon.storage import SessionReader, list_sessions
from stipi_daemon.storage.metadata import METADATA_FIELDS

__all__ = ["format_table", "list_text", "show_text"]

#: Header of ``sessions list``.
LIST_HEADER = (
    "ID",
    "CREATED (UTC)",
    "STATUS",
    "SUBJECT",
    "SITE",
    "OPERATOR",
    "LABEL",
    "VALIDITY",
    "DURATION",
    "FRAMES",
    "SAMPLES",
    "SEVERITY",
)


def _opt(value: object, fmt: str = "{}") -> str:
    return "-" if value is None else fmt.format(value)


def _created(text: str | None) -> str:
    """ISO time to the second (``2026-01-14T09:30:12Z``)."""
    if not text:
        return "-"
    return text.split(".")[0] + "Z" if "." in text else text


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Left-aligned text table with two spaces between columns."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]
    lines = [header, *rows]
    return "\n".join(
        "  ".join(str(cell).ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
        for line in lines
    )


def list_text(root: Path, where: dict[str, str | None] | None = None) -> str:
    """The ``sessions list`` output for ``root`` (sessions whose metadata match ``where``)."""
    listings = list_sessions(root, where)
    if not listings:
        wanted = {k: v for k, v in (where or {}).items() if v is not None}
        match = "".join(f" with {k} {v!r}" for k, v in wanted.items())
        return f"no sessions{match} in {root}"
    rows = [
        [
            s.session_id,
            _created(s.created_utc),
            s.status,
            _opt(s.subject),
            _opt(s.site),
            _opt(s.operator),
            _opt(s.label),
            s.validity,
            _opt(s.duration_s, "{:.1f} s"),
            _opt(s.n_frames),
            _opt(s.n_samples),
            s.severity or "-",
        ]
        for s in listings
    ]
    lines = [format_table(LIST_HEADER, rows)]
    lines += [f"{s.session_id}: {s.error}" for s in listings if s.error is not None]
    return "\n".join(lines)


def _video_text(path: Path) -> str:
    """``video.mkv (1234567 B, mjpeg 1920x1080, 7200 frames)``; why not, if it cannot be
    probed (unreadable, or holding no frame yet)."""
    from stipi_daemon.storage.video_readback import probe_video

    try:
        info = probe_video(path)
    except SessionError as exc:
        return f"{path.name} ({path.stat().st_size} B: {exc})"
    crop = "" if info.crop is None else ", crop " + ",".join(str(v) for v in info.crop)
    if info.crop is not None and info.frame_size is not None:
        crop += f" of {info.frame_size[0]}x{info.frame_size[1]}"
    return (
        f"{path.name} ({info.size_bytes} B, {info.codec} {info.width}x{info.height} "
        f"{info.image}{crop}, {info.frames} frames)"
    )


def _integrity_text(problems: Sequence[str], decoded: bool) -> str:
    """``ok`` or ``FAILED: ...``; with ``decoded``, that every video frame was decoded."""
    checked = " (every video frame decoded)" if decoded else ""
    return ("ok" if not problems else "FAILED: " + "; ".join(problems)) + checked


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())


def _facts(
    reader: SessionReader, problems: Sequence[str], *, decoded: bool = False
) -> list[tuple[str, str]]:
    status = reader.status
    video = reader.video_path
    if video is None:
        video_text = "none"
    elif video.exists():
        video_text = _video_text(video)
    else:
        video_text = f"{video.name} (reserved, not present)"
    metadata = reader.metadata
    facts = [
        ("session", reader.session_id),
        ("directory", str(reader.directory)),
        ("status", status.value),
        ("created", str(reader.manifest["created_utc"])),
        ("finished", reader.meta().get("finished_utc", "-")),
        ("duration", _opt(reader.duration_s(), "{:.3f} s")),
    ]
    for field in METADATA_FIELDS:
        value = metadata[field]
        facts.append((field, "-" if value is None else value.replace("\n", "\n" + " " * 11)))
    facts += [
        ("label", _opt(reader.label)),
        ("video", video_text),
        ("integrity", _integrity_text(problems, decoded and video is not None and video.exists())),
    ]
    if status.value == "recording" and reader.writer_owner is not None:
        facts.append(("writer", json.dumps(reader.writer_owner)))
    return facts


def show_text(directory: Path, *, decode: bool = False) -> tuple[str, int]:
    """The ``sessions show`` output and exit status (1: integrity failed or the summary is
    unreadable). ``decode``: the integrity check also decodes every video frame
    (:meth:`SessionReader.integrity_check`), which finds a frame whose bytes are whole but
    that does not decode; the ``integrity`` line says which check ran."""
    with SessionReader(directory) as reader:
        report = reader.integrity_check(decode=decode)
        facts = _facts(reader, report.problems, decoded=decode)
        counts = reader.counts()
        width = max(len(k) for k, _ in facts)
        lines = [f"{key.ljust(width)}  {value}" for key, value in facts]
        lines.append("rows:")
        name_width = max(len(name) for name in counts)
        lines += [f"  {name.ljust(name_width)}  {n:>9}" for name, n in counts.items()]
        lines += ["manifest:", _indent(json.dumps(reader.manifest, indent=2))]
        try:
            summary = reader.summary
        except SessionError as exc:
            return "\n".join([*lines, f"summary: unreadable: {exc}"]), EXIT_DAMAGED
        if summary is None:
            lines.append("summary: none")
        else:
            lines += ["summary:", _indent(json.dumps(summary, indent=2))]
        return "\n".join(lines), EXIT_OK if report.ok else EXIT_DAMAGED
