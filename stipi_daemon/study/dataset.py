"""The study dataset on disk: its layout, the tables' schemas with units, atomic files.

A study dataset is one directory (``docs/study.md``)::

    DATASET/study.json                                   format, version, index state
    DATASET/sessions/site=S/probe=P/date=D/<uid>.parquet       one row per session
    DATASET/force_samples/site=S/probe=P/date=D/<uid>.parquet  the session's samples
    DATASET/frames/site=S/probe=P/date=D/<uid>.parquet         the session's frames
    DATASET/results/analysis=A/site=S/probe=P/date=D/<uid>.parquet  one row per analysis
    DATASET/analyses/<A>.json                            how analysis version A was made

Partition values are percent-encoded (``Lab%20A``; DuckDB and pyarrow decode them); a
session without a site or probe is filed under ``unknown``. Every Parquet file carries
each column's unit and meaning in its field metadata (``unit``, ``doc``) and, for the
whole file, the schema metadata ``table`` and ``units`` (JSON: column -> unit). Files are
written atomically: a temporary name beginning with ``.`` in the same directory (which no
``*.parquet`` pattern matches), fsync, rename, directory fsync; a crash never leaves a
half file that counts. This module owns the layout and the schemas; :mod:`.index` fills
the dataset from sessions and :mod:`.query` reads it.
"""

from __future__ import annotations

import json
import os
import urllib.parse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Final

import pyarrow as pa
import pyarrow.parquet as pq

from stipi_daemon.errors import SessionError, StipiError
from stipi_daemon.storage.layout import fsync_directory, utc_now_iso, write_json_atomic
from stipi_daemon.storage.results_table import COLUMNS as RESULT_TABLE_COLUMNS
from stipi_daemon.storage.results_table import quantity_cells

#: ``study.json``'s ``format`` and ``version``.
STUDY_FORMAT: Final = "stipi-study"
STUDY_VERSION: Final = 1
STUDY_FILE: Final = "study.json"
ANALYSES_DIR: Final = "analyses"
#: Analysis version of the results the daemon recorded (each session's ``summary.json``).
RECORDED: Final = "recorded"
#: Partition value of a session without a site or a probe id.
UNKNOWN: Final = "unknown"
#: The tables, in the order they are documented.
TABLE_NAMES: Final = ("sessions", "force_samples", "frames", "results")
#: Hive partition keys of every table (``results`` has ``analysis`` first).
PARTITION_KEYS: Final = ("site", "probe", "date")


class StudyError(StipiError):
    """A study dataset cannot be created, read or queried (one line: what and where)."""


@dataclass(frozen=True)
class ColumnSpec:
    """One column of a dataset table: name (unit in it), Arrow type, unit, meaning."""

    name: str
    type: pa.DataType
    unit: str
    doc: str


_TS: Final = pa.timestamp("us", tz="UTC")
_SINCE: Final = "since the session's creation"

SESSIONS_COLUMNS: Final[tuple[ColumnSpec, ...]] = (
    ColumnSpec("session_uid", pa.string(), "", "unique in the dataset: session_id, +hash if taken"),
    ColumnSpec("session_id", pa.string(), "", "the session directory's id (manifest)"),
    ColumnSpec("path", pa.string(), "", "absolute path of the session directory when indexed"),
    ColumnSpec("data_hash", pa.string(), "", "sha256 of the session's data (study.hashing)"),
    ColumnSpec("summary_hash", pa.string(), "", "sha256 of summary.json's bytes; null: none"),
    ColumnSpec("status", pa.string(), "", "complete, aborted, fault or interrupted"),
    ColumnSpec("subject", pa.string(), "", "who or what was measured (manifest metadata)"),
    ColumnSpec("site", pa.string(), "", "where it was recorded; 'unknown' when not given"),
    ColumnSpec("operator", pa.string(), "", "who held the probe (manifest metadata)"),
    ColumnSpec("note", pa.string(), "", "free text (manifest metadata)"),
    ColumnSpec("label", pa.string(), "", "the note's first line, or scene:<name>"),
    ColumnSpec("probe_id", pa.string(), "", "the probe (USB serial, BLE address, 'emulated')"),
    ColumnSpec("transport", pa.string(), "", "the link recorded (serial:/dev/..., ble:..)"),
    ColumnSpec("created_utc", _TS, "UTC", "when the session was created"),
    ColumnSpec("t0_host_s", pa.float64(), "s", "host monotonic time that t_s counts from"),
    ColumnSpec("duration_s", pa.float64(), "s", "span of the recorded samples and frames"),
    ColumnSpec("verdict", pa.string(), "", "complete, flagged, invalid, incomplete, unknown"),
    ColumnSpec("has_video", pa.bool_(), "", "whether the session holds its video file"),
    ColumnSpec("n_force_samples", pa.int64(), "", "force samples recorded"),
    ColumnSpec("n_frames", pa.int64(), "", "frames recorded"),
    ColumnSpec("n_video_frames", pa.int64(), "", "frames stored in the video file"),
    ColumnSpec("schema_version", pa.int64(), "", "session database schema version"),
    ColumnSpec("package_version", pa.string(), "", "stipi-daemon version that recorded it"),
    ColumnSpec("indexed_utc", _TS, "UTC", "when this row was written"),
)

FORCE_SAMPLES_COLUMNS: Final[tuple[ColumnSpec, ...]] = (
    ColumnSpec("session_uid", pa.string(), "", "the session (sessions.session_uid)"),
    ColumnSpec("seq", pa.int64(), "", "row number in arrival order, from 0"),
    ColumnSpec("t_s", pa.float64(), "s", f"sample time {_SINCE}: t_host_s - sessions.t0_host_s"),
    ColumnSpec("force_n", pa.float64(), "N", "force from the calibration; null if none"),
    ColumnSpec("sample_index", pa.int64(), "", "probe sample counter (may restart)"),
    ColumnSpec("adc_counts", pa.int64(), "counts", "raw ADC reading"),
    ColumnSpec("t_mcu_raw_us", pa.int64(), "us", "probe micros() mod 2^32"),
    ColumnSpec("t_mcu_us", pa.int64(), "us", "probe time unwrapped to 64 bit"),
    ColumnSpec("t_host_s", pa.float64(), "s", "probe time on the host monotonic clock"),
)

FRAMES_COLUMNS: Final[tuple[ColumnSpec, ...]] = (
    ColumnSpec("session_uid", pa.string(), "", "the session (sessions.session_uid)"),
    ColumnSpec("seq", pa.int64(), "", "camera frame sequence number"),
    ColumnSpec(
        "t_s", pa.float64(), "s", f"capture time {_SINCE}: t_capture_host_s - sessions.t0_host_s"
    ),
    ColumnSpec("s_k_px", pa.int64(), "px", "occluded pixel count S_k in the ROI, Eq. (2)"),
    ColumnSpec("t_capture_host_s", pa.float64(), "s", "capture time, host monotonic clock"),
    ColumnSpec("t_host_s", pa.float64(), "s", "host monotonic time the frame was processed"),
    ColumnSpec("flags", pa.string(), "", "comma-separated quality flags"),
)

_RESULT_TYPES: Final = {"int": pa.int64(), "real": pa.float64(), "text": pa.string()}
#: Columns of :func:`~stipi_daemon.storage.results_table.quantity_cells`: verdict and
#: every quantity's value, status, flags and reason, typed as the results table types them.
_QUANTITY_COLUMNS: Final = tuple(
    ColumnSpec(name, _RESULT_TYPES[kind], unit, doc)
    for name, kind, unit, doc in RESULT_TABLE_COLUMNS
    if name in quantity_cells(None)
)

RESULTS_COLUMNS: Final[tuple[ColumnSpec, ...]] = (
    ColumnSpec("session_uid", pa.string(), "", "the session (sessions.session_uid)"),
    ColumnSpec("analysis_version", pa.string(), "", "'recorded' or the re-analysis' name"),
    ColumnSpec("data_hash", pa.string(), "", "sha256 of the session data analysed"),
    ColumnSpec("settings_hash", pa.string(), "", "sha256 of the analysis settings"),
    ColumnSpec("package_version", pa.string(), "", "stipi-daemon version that analysed it"),
    ColumnSpec("analysed_utc", _TS, "UTC", "when the analysis finished"),
    ColumnSpec("severity_class", pa.string(), "", "mild or severe (Sec. IV.C); null if invalid"),
    *_QUANTITY_COLUMNS,
    ColumnSpec("error", pa.string(), "", "why the analysis gave no results (else null)"),
)

TABLE_COLUMNS: Final[dict[str, tuple[ColumnSpec, ...]]] = {
    "sessions": SESSIONS_COLUMNS,
    "force_samples": FORCE_SAMPLES_COLUMNS,
    "frames": FRAMES_COLUMNS,
    "results": RESULTS_COLUMNS,
}


def arrow_schema(table: str) -> pa.Schema:
    """The Arrow schema of a dataset table, units and meanings in its metadata."""
    specs = TABLE_COLUMNS[table]
    fields = [pa.field(c.name, c.type, metadata={"unit": c.unit, "doc": c.doc}) for c in specs]
    units = {c.name: c.unit for c in specs if c.unit}
    return pa.schema(fields, metadata={"table": table, "units": json.dumps(units)})


def to_table(table: str, columns: Mapping[str, Any]) -> pa.Table:
    """An Arrow table of ``table``'s schema from column values (lists or arrays; a
    missing column is all null). NaN in a float column becomes null."""
    schema = arrow_schema(table)
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise ValueError(f"{table}: columns of different lengths {sorted(lengths)}")
    n = lengths.pop() if lengths else 0
    arrays = []
    for field in schema:
        values = columns.get(field.name)
        if values is None:
            arrays.append(pa.nulls(n, field.type))
        else:
            arrays.append(pa.array(values, type=field.type, from_pandas=True))
    return pa.Table.from_arrays(arrays, schema=schema)


def utc_timestamp(text: str | None) -> datetime | None:
    """An ISO 8601 UTC time (``...Z``) as an aware datetime; None for None or bad text."""
    if not text:
        return None
    try:
        value = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def results_row(
    *,
    session_uid: str,
    analysis_version: str,
    data_hash: str,
    settings_hash: str,
    package_version: str | None,
    analysed_utc: str | None,
    summary: Mapping[str, Any] | None,
    error: str | None,
) -> dict[str, Any]:
    """One ``results`` row: provenance, then the verdict and every quantity's value and
    validity read from ``summary`` (:func:`~stipi_daemon.storage.results_table.quantity_cells`;
    an invalid quantity's value is null), and ``error`` (None: none)."""
    cells = quantity_cells(dict(summary) if summary is not None else None)
    return {
        "session_uid": session_uid,
        "analysis_version": analysis_version,
        "data_hash": data_hash,
        "settings_hash": settings_hash,
        "package_version": package_version,
        "analysed_utc": utc_timestamp(analysed_utc),
        "severity_class": cells.get("severity"),
        **cells,
        "error": error,
    }


def partition_value(value: str | None) -> str:
    """A hive partition value: percent-encoded, ``unknown`` for None or empty."""
    return urllib.parse.quote(value or UNKNOWN, safe="")


def partition_dir(
    table: str, site: str | None, probe: str | None, date: str, analysis: str | None = None
) -> Path:
    """A table's partition directory (relative to the dataset) for one session."""
    parts = [table]
    if table == "results":
        if analysis is None:
            raise ValueError("results partitions need an analysis version")
        parts.append(f"analysis={partition_value(analysis)}")
    parts += [
        f"site={partition_value(site)}",
        f"probe={partition_value(probe)}",
        f"date={partition_value(date)}",
    ]
    return Path(*parts)


def write_parquet_atomic(path: Path, table: pa.Table) -> None:
    """Write ``table`` to ``path`` atomically (hidden temp file, fsync, rename, dir fsync).

    Raises
    ------
    StudyError
        The file cannot be written (names it and why).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            pq.write_table(table, f, compression="zstd")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_directory(path.parent)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise StudyError(f"{path}: cannot write: {exc}") from exc


def remove_files(root: Path, relative: Sequence[str]) -> None:
    """Remove files the dataset wrote (relative paths) and the partition directories
    they leave empty, up to the table directory."""
    for rel in relative:
        path = root / rel
        path.unlink(missing_ok=True)
        parent = path.parent
        while parent != root and parent.parent != root:
            try:
                parent.rmdir()
            except OSError:
                break
            parent = parent.parent


# ---------------------------------------------------------------------- study.json
def new_state(package_version: str) -> dict[str, Any]:
    """The ``study.json`` of a new dataset."""
    now = utc_now_iso()
    return {
        "format": STUDY_FORMAT,
        "version": STUDY_VERSION,
        "created_utc": now,
        "updated_utc": now,
        "package_version": package_version,
        "sessions": {},
    }


def check_output_file(path: Path, dataset: Path, *, overwrite: bool, what: str) -> None:
    """Refuse an output file (``--out`` of a query or a diff) before anything is run: one
    in the dataset (its files are the indexer's; a result there would replace one or be
    read as part of a table), in a session directory, a directory, or an existing file
    without ``overwrite``.

    Raises
    ------
    StudyError
        One line naming ``path`` and why.
    """
    from stipi_daemon.storage.export import check_export_target

    target, root = path.resolve(), dataset.resolve()
    if target == root or root in target.parents:
        raise StudyError(
            f"--out {path}: inside the dataset {dataset}; {what} never writes into its "
            "dataset (choose a file outside it)"
        )
    try:
        check_export_target(path, [], is_file=True, what=what)
    except SessionError as exc:
        raise StudyError(str(exc)) from None
    if path.is_dir():
        raise StudyError(f"--out {path}: is a directory (give a file name)")
    if path.exists() and not overwrite:
        raise StudyError(f"--out {path}: exists already (give --overwrite to replace it)")


def load_state(dataset: Path) -> dict[str, Any]:
    """Read and check a dataset's ``study.json``.

    Raises
    ------
    StudyError
        ``dataset`` is not a directory, has no ``study.json``, or it is not a stipi study
        of a version this package reads (one line naming the file).
    """
    path = dataset / STUDY_FILE
    if not dataset.is_dir():
        raise StudyError(f"{dataset}: not a study dataset (no such directory)")
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StudyError(
            f"{dataset}: not a study dataset (no {STUDY_FILE}; make one with "
            "`stipi-daemon study index ROOT --out DATASET`)"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StudyError(f"{path}: cannot read ({exc})") from None
    if not isinstance(value, dict) or value.get("format") != STUDY_FORMAT:
        raise StudyError(f"{path}: not a study dataset (format is not {STUDY_FORMAT!r})")
    if value.get("version") != STUDY_VERSION:
        raise StudyError(
            f"{path}: study version {value.get('version')!r} is not supported "
            f"(this stipi-daemon reads version {STUDY_VERSION})"
        )
    if not isinstance(value.get("sessions"), dict):
        raise StudyError(f"{path}: field 'sessions' must be an object")
    return value


def save_state(dataset: Path, state: dict[str, Any]) -> None:
    """Write ``study.json`` atomically, its ``updated_utc`` set to now."""
    state["updated_utc"] = utc_now_iso()
    try:
        write_json_atomic(dataset / STUDY_FILE, state, what="study index")
    except StipiError as exc:
        raise StudyError(str(exc)) from exc
