"""Export of a session to CSV, Parquet or MATLAB, and of the sessions' results table.

This module owns the conversion of the tables read by :class:`~.reader.SessionReader`
into ``<out>/<table>.csv`` or ``<out>/<table>.parquet`` (via pyarrow), plus copies of
``manifest.json`` (with the session's metadata: subject, site, operator, note),
``summary.json`` and the video (``video.mkv``, unchanged) so that the export carries its
configuration, calibration, results and primary data; ``validity.<csv|parquet>``: one
row per reported quantity (value, unit, ``valid``/``flagged``/``invalid``/``unknown``, the
flags that concern it, the reason) and a last row ``verdict`` (the session's verdict and
its line), so a spreadsheet never shows a number without its validity; and
``session.<csv|parquet>``: the session's row of the results table
(:mod:`.results_table`). ``mat`` writes one MATLAB file ``<out>/<session_id>.mat``
(:func:`export_mat`) and the video beside it, ``<out>/<session_id>.mkv`` (unchanged, named
in the ``.mat``). :func:`write_results_table` writes one row per session of a
sessions directory. All tables are read from one database snapshot.

A session that fails its integrity check (:meth:`~.reader.SessionReader.integrity_check`:
database, manifest, summary, the video against its rows) is not exported, with one line
naming every problem, unless the caller allows it (``allow_damaged``); such an export
carries the problems (``integrity.txt``, or the ``.mat``'s ``integrity_problems``).

Where exports go: by default ``exports/<session_id>/`` and ``exports/results.csv`` next
to the sessions directory (``<root>/../exports``; :func:`default_export_dir`). An export
never writes into a session: :func:`check_export_target` refuses a target inside any
session directory, the sessions directory itself, or a new directory directly in it
(it would be listed as a session), before anything is written.

CSV: a header row of column names (which carry the units), integers in decimal, floats in
Python's shortest round-trip form, NULL as an empty field. Parquet: int64, float64 (NULL
as null) and string columns; each field's metadata holds its ``unit`` and ``doc``.
"""

from __future__ import annotations

import contextlib
import csv
import filecmp
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import DamagedSessionError, SessionError
from stipi_daemon.storage import layout
from stipi_daemon.storage.reader import (
    QUANTITY_PATHS,
    IntegrityReport,
    SessionReader,
    quantity_status,
    quantity_value,
    session_dirs,
    verdict_of,
)
from stipi_daemon.storage.results_table import (
    collect_rows,
    quantity_cells,
    session_row,
    table_format,
    write_rows,
)
from stipi_daemon.storage.schema import FORMAT_NAME, FRAMES, TABLES, VIDEO_FRAMES, Table

ExportFormat = Literal["csv", "parquet", "mat"]
EXPORT_FORMATS: Final[tuple[ExportFormat, ...]] = ("csv", "parquet", "mat")
#: Name of the directory next to the sessions directory that exports go to by default.
EXPORTS_DIR: Final = "exports"
#: Format name and version stored in a ``.mat`` export.
MAT_FORMAT: Final = "stipi-session-mat"
MAT_VERSION: Final = 1
#: Larger than any session manifest: a bigger manifest.json is not read to tell a session.
_MANIFEST_MAX_BYTES: Final = 16 * 1024 * 1024
#: File of a csv/parquet export of a session that failed its integrity check (exported with
#: ``allow_damaged``): one line, every problem.
INTEGRITY_NAME: Final = "integrity.txt"


def _csv_value(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _write_csv(path: Path, table: Table, rows: list[tuple[Any, ...]]) -> None:
    with open(path, "w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(table.column_names)
        writer.writerows([_csv_value(v) for v in row] for row in rows)


def _write_parquet(path: Path, table: Table, rows: list[tuple[Any, ...]]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"int": pa.int64(), "real": pa.float64(), "real_null": pa.float64()}
    fields = []
    arrays = []
    for i, column in enumerate(table.columns):
        pa_type = types.get(column.kind, pa.string())
        fields.append(
            pa.field(
                column.name,
                pa_type,
                nullable=column.kind == "real_null",
                metadata={"unit": column.unit, "doc": column.doc},
            )
        )
        arrays.append(pa.array([row[i] for row in rows], type=pa_type))
    schema = pa.schema(fields, metadata={"table": table.name, "doc": table.doc})
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path)


#: Columns of the validity file: name, kind ("text" or "real_null"), unit, doc.
VALIDITY_COLUMNS: Final = (
    ("quantity", "text", "", "quantity name (summary.json 'validity' key) or 'verdict'"),
    ("value", "real_null", "", "the recorded value (numeric quantities; in the unit column)"),
    ("label", "text", "", "the recorded value of a non-numeric quantity (severity class)"),
    ("unit", "text", "", "unit of value"),
    ("status", "text", "", "valid, flagged, invalid or unknown; for 'verdict' its status"),
    ("flags", "text", "", "the flags that concern the quantity, separated by ';'"),
    ("reason", "text", "", "why the quantity is flagged or invalid; for 'verdict' its line"),
)


def validity_rows(summary: dict[str, Any] | None) -> list[tuple[Any, ...]]:
    """One row per quantity of the validity schema, then the verdict (see
    :data:`VALIDITY_COLUMNS`); quantities of an old summary read as ``unknown``."""
    validity = (summary or {}).get("validity")
    validity = validity if isinstance(validity, dict) else {}
    rows: list[tuple[Any, ...]] = []
    for quantity, (_, unit) in QUANTITY_PATHS.items():
        value = quantity_value(summary, quantity)
        entry = validity.get(quantity)
        entry = entry if isinstance(entry, dict) else {}
        number = float(value) if isinstance(value, int | float) else None
        label = None if value is None or number is not None else str(value)
        flags = ";".join(str(f) for f in entry.get("flags") or [])
        status = quantity_status(summary, quantity)
        rows.append((quantity, number, label, unit, status, flags, entry.get("reason")))
    verdict = (summary or {}).get("verdict")
    line = verdict.get("line") if isinstance(verdict, dict) else None
    rows.append(("verdict", None, None, "", verdict_of(summary), "", line))
    return rows


def _summary_or_none(reader: SessionReader) -> dict[str, Any] | None:
    """The session's summary; None when it is missing or unreadable (validity unknown)."""
    try:
        return reader.summary
    except SessionError:
        return None


def _write_validity(path: Path, fmt: ExportFormat, rows: list[tuple[Any, ...]]) -> None:
    names = [c[0] for c in VALIDITY_COLUMNS]
    if fmt == "csv":
        with open(path, "w", encoding="utf-8", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow(names)
            writer.writerows([_csv_value(v) for v in row] for row in rows)
        return
    import pyarrow as pa
    import pyarrow.parquet as pq

    fields, arrays = [], []
    for i, (name, kind, unit, doc) in enumerate(VALIDITY_COLUMNS):
        pa_type = pa.float64() if kind == "real_null" else pa.string()
        fields.append(pa.field(name, pa_type, metadata={"unit": unit, "doc": doc}))
        arrays.append(pa.array([row[i] for row in rows], type=pa_type))
    schema = pa.schema(fields, metadata={"table": "validity", "doc": "validity per quantity"})
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path)


def default_export_dir(session_dir: Path) -> Path:
    """``<root>/../exports/<session_id>``: the default target of a session's export."""
    return session_dir.parent.parent / EXPORTS_DIR / session_dir.name


def default_table_path(root: Path) -> Path:
    """``<root>/../exports/results.csv``: the default results table of a sessions root."""
    return root.parent / EXPORTS_DIR / "results.csv"


def _holds_session(directory: Path) -> bool:
    """A session directory: a session's manifest (``manifest.json`` of format
    :data:`~.schema.FORMAT_NAME`) beside its database or writer lock. A stray
    ``session.sqlite`` or ``writer.lock`` (a 0-byte file at the file system's root)
    makes no directory a session, nor does an export's copy of a manifest."""
    manifest = directory / layout.MANIFEST_NAME
    if not any((directory / name).exists() for name in (layout.DB_NAME, layout.LOCK_NAME)):
        return False
    try:
        if not manifest.is_file() or manifest.stat().st_size > _MANIFEST_MAX_BYTES:
            return False
        doc = json.loads(manifest.read_bytes())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("format") == FORMAT_NAME


def check_export_target(
    out: Path,
    roots: Sequence[Path],
    sessions: Sequence[Path] = (),
    *,
    is_file: bool = False,
    what: str = "an export",
) -> None:
    """Refuse an export target that would write into a session.

    Parameters
    ----------
    out : Path
        The target directory (or file with ``is_file``).
    roots : sequence of Path
        Sessions directories: neither may be the target directory, nor may the target be
        a new directory directly in one (it would be listed as a session).
    sessions : sequence of Path
        Session directories to protect besides every directory holding a session's
        manifest (the exported session, each session of ``roots``).
    what : str
        What would write there, for the message (``"an export"``, ``"an analysis"``).

    Raises
    ------
    SessionError
        One line naming ``out`` and the session or sessions directory it would write into.
    """
    target = out.resolve()
    protected = {p.resolve() for p in sessions}
    for root in roots:
        if root.is_dir():
            protected.update(p.resolve() for p in session_dirs(root))
    directory = target.parent if is_file else target
    for p in (directory, *directory.parents):
        if p in protected or _holds_session(p):
            raise SessionError(
                f"--out {out}: inside the session directory {p}; {what} never writes "
                "into a session (choose a directory outside the sessions directory)"
            )
    for root in roots:
        r = root.resolve()
        if not is_file and (target == r or target.parent == r):
            raise SessionError(
                f"--out {out}: {'is' if target == r else 'is directly in'} the sessions "
                f"directory {root}, where an export would look like a session (choose a "
                f"directory outside it, e.g. {root.parent / EXPORTS_DIR})"
            )


def _refuse_conflicts(pairs: Sequence[tuple[Path | None, Path]]) -> None:
    """Raise :class:`SessionError` naming the first ``(source, target)`` pair whose target
    exists (without ``--overwrite``); a copy whose target already holds the same bytes is
    no conflict."""
    for src, dst in pairs:
        if dst.exists() and not (src is not None and filecmp.cmp(src, dst, shallow=False)):
            raise SessionError(f"{dst}: exists already (use --overwrite to replace it)")


def _integrity_line(reader: SessionReader, problems: tuple[str, ...]) -> str:
    """One line: the session failed its integrity check, and every problem."""
    return f"{reader.directory}: integrity check failed: " + "; ".join(problems)


def _checked_integrity(
    reader: SessionReader, integrity: IntegrityReport | None, allow_damaged: bool
) -> tuple[str, ...]:
    """The problems of the session's integrity check (run here unless given); raises
    when there are some and ``allow_damaged`` is not set."""
    report = reader.integrity_check() if integrity is None else integrity
    if report.problems and not allow_damaged:
        raise DamagedSessionError(
            _integrity_line(reader, report.problems)
            + " (not exported; --allow-damaged exports it as it is)"
        )
    return report.problems


def export_session(
    reader: SessionReader,
    out_dir: Path | str,
    fmt: ExportFormat,
    *,
    overwrite: bool = False,
    roots: Sequence[Path] = (),
    allow_damaged: bool = False,
    integrity: IntegrityReport | None = None,
) -> list[Path]:
    """Write a session to ``out_dir``: one file per table, or one ``.mat`` file, and its video.

    Parameters
    ----------
    reader : SessionReader
        The open session.
    out_dir : Path or str
        Target directory (created if missing); :func:`check_export_target` refuses one in
        a session (the exported one, a session of ``roots`` or of the session's own
        sessions directory) before anything is written.
    fmt : {"csv", "parquet", "mat"}
        File format; ``mat`` writes ``<out_dir>/<session_id>.mat`` (:func:`export_mat`) and
        the session's video beside it as ``<out_dir>/<session_id>.mkv``.
    overwrite : bool
        Replace existing files; otherwise an existing target file raises (a copy whose
        target holds the same bytes, e.g. ``manifest.json`` of an export in the other
        format, is not a conflict).
    roots : sequence of Path
        Further sessions directories to protect.
    allow_damaged : bool
        Export a session that fails its integrity check
        (:meth:`~.reader.SessionReader.integrity_check`) as it is; the export then carries
        the problems (:data:`INTEGRITY_NAME`, or the ``.mat``'s ``integrity_problems``).
    integrity : IntegrityReport, optional
        The session's integrity check when the caller ran it already (run here otherwise).

    Returns
    -------
    list of Path
        The files written (tables in :data:`~.schema.TABLES` order, the validity file, the
        session's row, then the JSON files and the session's ``video.mkv``, copied as it is,
        then :data:`INTEGRITY_NAME` for a damaged session; ``mat``: the ``.mat``, then the
        video).

    Raises
    ------
    SessionError
        Unknown format, a target in a session, a session failing its integrity check
        without ``allow_damaged`` (one line, every problem), an existing target file
        without ``overwrite``, or a write error. Nothing is written then.
    """
    if fmt not in EXPORT_FORMATS:
        raise SessionError(f"export format {fmt!r} is not one of {', '.join(EXPORT_FORMATS)}")
    out = Path(out_dir)
    check_export_target(out, [*roots, reader.directory.parent], [reader.directory])
    problems = _checked_integrity(reader, integrity, allow_damaged)
    if fmt == "mat":
        return _export_mat_files(reader, out, overwrite, problems)
    targets = [out / f"{t.name}.{fmt}" for t in TABLES]
    validity_target, row_target = out / f"validity.{fmt}", out / f"session.{fmt}"
    extras = [
        src
        for src in (reader.manifest_path, reader.summary_path, reader.video_path)
        if src is not None
        and src.exists()
        and src.name in (layout.MANIFEST_NAME, layout.SUMMARY_NAME, layout.VIDEO_NAME)
    ]
    written_here = [*targets, validity_target, row_target]
    if problems:
        written_here.append(out / INTEGRITY_NAME)
    if not overwrite:
        _refuse_conflicts(
            [*((None, t) for t in written_here), *((src, out / src.name) for src in extras)]
        )
    writer = _write_csv if fmt == "csv" else _write_parquet
    staged = _Staged(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with reader.snapshot():
            for table, target in zip(TABLES, targets, strict=True):
                writer(staged.path(target), table, _export_rows(reader, table))
            row = session_row(reader)
        summary = _summary_or_none(reader)
        _write_validity(staged.path(validity_target), fmt, validity_rows(summary))
        write_rows(staged.path(row_target), [row], fmt)
        copies = [staged.copy(src, out / src.name) for src in extras]
        if problems:
            staged.path(out / INTEGRITY_NAME).write_text(
                _integrity_line(reader, problems) + "\n", encoding="utf-8"
            )
        staged.commit()
    except OSError as exc:
        staged.discard()
        raise SessionError(f"{out}: export failed (nothing written): {exc}") from exc
    except BaseException:
        staged.discard()
        raise
    return [*targets, validity_target, row_target, *copies, *written_here[len(targets) + 2 :]]


class _Staged:
    """Files of one export written under temporary names beside their targets, then
    renamed into place together (:meth:`commit`); on failure (disk full) :meth:`discard`
    removes every temporary file and the directories the export created, so a failed
    export leaves nothing partial behind and replaces nothing."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.pairs: list[tuple[Path, Path]] = []
        self.new_dirs = [p for p in (out, *out.parents) if not p.exists()]

    def path(self, target: Path) -> Path:
        """The temporary name to write ``target`` under (hidden, same suffix)."""
        tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")
        self.pairs.append((tmp, target))
        return tmp

    def copy(self, src: Path, dst: Path) -> Path:
        """``src`` copied byte for byte to ``dst`` (left as it is when it holds them)."""
        if not (dst.exists() and filecmp.cmp(src, dst, shallow=False)):
            shutil.copyfile(src, self.path(dst))
        return dst

    def commit(self) -> None:
        for tmp, target in self.pairs:
            os.replace(tmp, target)
        self.pairs = []

    def discard(self) -> None:
        for tmp, _ in self.pairs:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        for d in self.new_dirs:  # deepest first; only if left empty
            with contextlib.suppress(OSError):
                d.rmdir()


def _export_rows(reader: SessionReader, table: Table) -> list[tuple[Any, ...]]:
    """The rows of ``table``; frames and video frames in capture order (by ``seq``:
    the measurer's workers may store them out of it)."""
    rows = list(reader.iter_rows(table))
    if table.name in (FRAMES.name, VIDEO_FRAMES.name) and "seq" in table.column_names:
        i = table.column_names.index("seq")
        rows.sort(key=lambda row: row[i])
    return rows


def _export_mat_files(
    reader: SessionReader, out: Path, overwrite: bool, problems: tuple[str, ...]
) -> list[Path]:
    """``<out>/<session_id>.mat`` and the session's video beside it, ``<session_id>.mkv``
    (byte for byte; named in the ``.mat``'s ``video_file``); the files written."""
    target = out / f"{reader.session_id}.mat"
    video, video_target = reader.video_path, None
    pairs: list[tuple[Path | None, Path]] = [(None, target)]
    if video is not None and video.is_file():
        video_target = out / f"{reader.session_id}{video.suffix}"
        pairs.append((video, video_target))
    if not overwrite:
        _refuse_conflicts(pairs)
    staged = _Staged(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        export_mat(
            reader,
            staged.path(target),
            video_file=None if video_target is None else video_target.name,
            integrity_problems=problems,
        )
        copies = [] if video is None or video_target is None else [staged.copy(video, video_target)]
        staged.commit()
    except OSError as exc:
        staged.discard()
        raise SessionError(f"{out}: export failed (nothing written): {exc}") from exc
    except BaseException:
        staged.discard()
        raise
    return [target, *copies]


def write_results_table(
    root: Path,
    out: Path,
    where: dict[str, str | None] | None = None,
    *,
    overwrite: bool = False,
) -> tuple[Path, int]:
    """Write one row per session of ``root`` (:mod:`.results_table`) to ``out``.

    The format follows ``out``'s suffix (``.csv`` or ``.parquet``); ``where`` keeps the
    sessions whose metadata equals each given value (unreadable sessions are kept as
    ``error`` rows). Returns the file and the number of rows.

    Raises
    ------
    SessionError
        ``root`` is not a directory, ``out`` has another suffix, lies in a session, exists
        without ``overwrite``, or cannot be written.
    """
    fmt = table_format(out)
    check_export_target(out, [root], is_file=True)
    rows = collect_rows(root, where)
    if out.exists() and not overwrite:
        raise SessionError(f"{out}: exists already (use --overwrite to replace it)")
    staged = _Staged(out.parent)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_rows(staged.path(out), rows, fmt)
        staged.commit()
    except OSError as exc:
        staged.discard()
        raise SessionError(f"{out}: cannot write the results table: {exc}") from exc
    return out, len(rows)


# ------------------------------------------------------------------------------ MATLAB
_EXACT_DOUBLE_INT: Final = 2**53


def _mat_none(value: Any) -> Any:
    """A value savemat can store: None becomes an empty matrix (MATLAB ``[]``)."""
    return np.zeros((0, 0)) if value is None else value


def _mat_column(kind: str, values: list[Any]) -> npt.NDArray[Any]:
    """One column as a vector: numbers as double (NULL as NaN; integers as int64 when one
    exceeds 2^53 and a double would round it), text as a cell array."""
    if kind in ("text", "json"):
        return np.array(["" if v is None else str(v) for v in values] or [], dtype=object)
    if kind == "int" and any(abs(int(v)) > _EXACT_DOUBLE_INT for v in values):
        return np.array(values, dtype=np.int64)
    return np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)


def _mat_table(reader: SessionReader, table: Table) -> dict[str, Any]:
    rows = _export_rows(reader, table)
    return {c.name: _mat_column(c.kind, [r[i] for r in rows]) for i, c in enumerate(table.columns)}


def _mat_results(summary: dict[str, Any] | None) -> dict[str, Any]:
    """``results.<quantity>`` = struct(value, unit, status, flags, reason), plus verdict."""
    cells = quantity_cells(summary)
    out: dict[str, Any] = {}
    for q, (_, unit) in QUANTITY_PATHS.items():
        flags = cells[f"{q}_flags"]
        out[q] = {
            "value": _mat_none(cells[q]),
            "unit": unit,
            "status": cells[f"{q}_status"],
            "flags": np.array(flags.split(";") if flags else [], dtype=object),
            "reason": _mat_none(cells[f"{q}_reason"]),
        }
    out["severity_grade"] = _mat_none(cells["severity_grade"])
    out["verdict"] = {"status": cells["verdict"], "line": _mat_none(cells["verdict_line"])}
    return out


def export_mat(
    reader: SessionReader,
    path: Path,
    *,
    video_file: str | None = None,
    integrity_problems: Sequence[str] = (),
) -> None:
    """Write a session to a MATLAB file (scipy.io.savemat, format 5, columns as n-by-1).

    Variables: ``format``, ``format_version``, ``session_id``; ``video_file`` (the name of
    the session's video copied beside the file, ``<session_id>.mkv``; ``''`` when none is);
    ``integrity_problems`` (a cell array: the session's integrity check problems when it
    was exported damaged, else empty); ``metadata`` (subject,
    site, operator, note; ``[]`` when not set); one struct per table (``force_samples``,
    ``frames`` with ``s_k`` [px], ``events``, ``transitions``, ``gaps``, ``clock_probes``,
    ``live_parameters``, ``video_frames``), each field one column (numbers as double,
    NULL as NaN, text as a cell array); ``units.<table>.<column>``; ``results.<quantity>``
    (value, unit, status, flags, reason; an invalid quantity's value is ``[]``) and
    ``results.verdict``; ``manifest_json`` and ``summary_json`` (the files as text).
    """
    import scipy.io

    with reader.snapshot():
        tables = {t.name: _mat_table(reader, t) for t in TABLES}
    summary = _summary_or_none(reader)
    data: dict[str, Any] = {
        "format": MAT_FORMAT,
        "format_version": MAT_VERSION,
        "session_id": reader.session_id,
        "video_file": video_file or "",
        "integrity_problems": np.array(list(integrity_problems), dtype=object),
        "metadata": {k: _mat_none(v) for k, v in reader.metadata.items()},
        **tables,
        "units": {t.name: {c.name: c.unit for c in t.columns} for t in TABLES},
        "results": _mat_results(summary),
        "manifest_json": json.dumps(reader.manifest, indent=2),
        "summary_json": "" if summary is None else json.dumps(summary, indent=2),
    }
    try:
        scipy.io.savemat(path, data, oned_as="column", do_compression=True)
    except OSError as exc:
        raise SessionError(f"{path}: cannot write the MATLAB file: {exc}") from exc
