"""Export of a session's tables to CSV or Parquet, one file per table.

This module owns the conversion of the tables read by :class:`~.reader.SessionReader`
into ``<out>/<table>.csv`` or ``<out>/<table>.parquet`` (via pyarrow), plus copies of
``manifest.json``, ``summary.json`` and the video (``video.mkv``, unchanged) so that the
export carries its configuration, calibration, results and primary data, and
``validity.<csv|parquet>``: one row per reported quantity (value, unit,
``valid``/``flagged``/``invalid``/``unknown``, the flags that concern it, the reason) and a
last row ``verdict`` (the session's verdict and its line), so a spreadsheet never shows a
number without its validity. All tables are read from one database snapshot. It does not
open sessions or decide what to export (the ``sessions export`` command does).

CSV: a header row of column names (which carry the units), integers in decimal, floats in
Python's shortest round-trip form, NULL as an empty field. Parquet: int64, float64 (NULL
as null) and string columns; each field's metadata holds its ``unit`` and ``doc``.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path
from typing import Any, Final, Literal

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import layout
from stipi_daemon.storage.reader import (
    QUANTITY_PATHS,
    SessionReader,
    quantity_status,
    quantity_value,
    verdict_of,
)
from stipi_daemon.storage.schema import TABLES, Table

ExportFormat = Literal["csv", "parquet"]
EXPORT_FORMATS: Final[tuple[ExportFormat, ...]] = ("csv", "parquet")


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


def export_session(
    reader: SessionReader, out_dir: Path | str, fmt: ExportFormat, *, overwrite: bool = False
) -> list[Path]:
    """Write every table of a session to ``out_dir``, one file per table.

    Parameters
    ----------
    reader : SessionReader
        The open session.
    out_dir : Path or str
        Target directory (created if missing).
    fmt : {"csv", "parquet"}
        File format.
    overwrite : bool
        Replace existing files; otherwise an existing target file raises.

    Returns
    -------
    list of Path
        The files written (tables in :data:`~.schema.TABLES` order, the validity file, then
        the JSON files and the session's ``video.mkv``, copied as it is).

    Raises
    ------
    SessionError
        Unknown format, an existing target file without ``overwrite``, or a write error.
    """
    if fmt not in EXPORT_FORMATS:
        raise SessionError(f"export format {fmt!r} is not one of {', '.join(EXPORT_FORMATS)}")
    out = Path(out_dir)
    targets = [out / f"{t.name}.{fmt}" for t in TABLES]
    validity_target = out / f"validity.{fmt}"
    extras = [
        src
        for src in (reader.manifest_path, reader.summary_path, reader.video_path)
        if src is not None
        and src.exists()
        and src.name in (layout.MANIFEST_NAME, layout.SUMMARY_NAME, layout.VIDEO_NAME)
    ]
    if not overwrite:
        for target in [*targets, validity_target, *(out / src.name for src in extras)]:
            if target.exists():
                raise SessionError(f"{target}: exists already (use --overwrite to replace it)")
    writer = _write_csv if fmt == "csv" else _write_parquet
    written: list[Path] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        with reader.snapshot():
            for table, target in zip(TABLES, targets, strict=True):
                writer(target, table, list(reader.iter_rows(table)))
                written.append(target)
        _write_validity(validity_target, fmt, validity_rows(_summary_or_none(reader)))
        written.append(validity_target)
        for src in extras:
            shutil.copyfile(src, out / src.name)
            written.append(out / src.name)
    except OSError as exc:
        raise SessionError(f"{out}: export failed: {exc}") from exc
    return written
