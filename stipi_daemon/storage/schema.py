"""Schema of a session database: tables, columns, units, row validation.

This module owns the description of every table in ``session.sqlite`` (column names, SQL
types, numpy dtypes, units), the DDL derived from it, the schema version, and the pure
validation that turns a caller's row into the exact tuple SQLite will store. It does no
I/O: opening files, committing and reading back live in :mod:`.writer` and :mod:`.reader`.

Every time column is named for its clock and unit: ``t_mcu_raw_us`` is the probe's
``micros()`` modulo 2^32 as received, ``t_mcu_us`` its 64-bit unwrapped count, ``t_host_s``
the host's monotonic clock (``time.monotonic()``) in seconds, onto which MCU times are
mapped by the clock fit. Storing all three lets alignment be redone offline.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Final, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import SessionError

#: Name of the on-disk format, written to the manifest and the ``meta`` table.
FORMAT_NAME: Final = "stipi-session"
#: Version of the directory layout and manifest (``manifest.json`` ``format_version``).
FORMAT_VERSION: Final = 1
#: Version of the SQLite schema (``PRAGMA user_version`` and ``meta.schema_version``).
#: 2 added the ``video_frames`` table (every stored video frame tied to its ``frames`` row).
SCHEMA_VERSION: Final = 2
#: Schema versions a reader accepts; version 1 sessions have no ``video_frames`` table.
READABLE_SCHEMA_VERSIONS: Final = frozenset({1, 2})

_INT64_MIN: Final = -(2**63)
_INT64_MAX: Final = 2**63 - 1

ColumnKind = Literal["int", "real", "real_null", "text", "json"]
"""How a column is validated and stored.

``int``: INTEGER NOT NULL, any integral number in int64 range. ``real``: REAL NOT NULL,
finite. ``real_null``: REAL, NaN/None stored as NULL (read back as NaN), ±inf kept.
``text``: TEXT NOT NULL. ``json``: TEXT NOT NULL holding a JSON object.
"""

_SQL_TYPE: Final[dict[str, str]] = {
    "int": "INTEGER NOT NULL",
    "real": "REAL NOT NULL",
    "real_null": "REAL",
    "text": "TEXT NOT NULL",
    "json": "TEXT NOT NULL",
}
_NUMPY_TYPE: Final[dict[str, Any]] = {
    "int": np.int64,
    "real": np.float64,
    "real_null": np.float64,
    "text": object,
    "json": object,
}


class SessionState(StrEnum):
    """State of a session as stored in ``meta.state`` (plus the derived ``interrupted``)."""

    RECORDING = "recording"
    """The writer created the session and has not finished it (it may still be running)."""
    COMPLETE = "complete"
    """The measurement ran to its end and the summary was written."""
    ABORTED = "aborted"
    """The user or the daemon stopped the measurement before its end."""
    FAULT = "fault"
    """The measurement stopped on an error (probe lost, camera failure...)."""
    INTERRUPTED = "interrupted"
    """Never stored: ``recording`` with no live writer (the process was killed or crashed)."""


#: States a writer may end a session with.
FINAL_STATES: Final = frozenset({SessionState.COMPLETE, SessionState.ABORTED, SessionState.FAULT})


@dataclass(frozen=True)
class Column:
    """One column of a session table.

    Parameters
    ----------
    name : str
        Column name; carries its unit (``_s``, ``_us``, ``_n``).
    kind : ColumnKind
        Storage and validation rule.
    unit : str
        Unit, ``"-"`` for dimensionless or text.
    doc : str
        One-line meaning.
    """

    name: str
    kind: ColumnKind
    unit: str
    doc: str

    @property
    def sql_type(self) -> str:
        return _SQL_TYPE[self.kind]

    @property
    def numpy_type(self) -> Any:
        return _NUMPY_TYPE[self.kind]


@dataclass(frozen=True)
class Table:
    """One session table: its name, meaning and columns (the ``id`` key is implicit)."""

    name: str
    doc: str
    columns: tuple[Column, ...]

    @property
    def column_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    @property
    def dtype(self) -> np.dtype[np.void]:
        """Structured numpy dtype of the table's rows (text columns are ``object``)."""
        return np.dtype([(c.name, c.numpy_type) for c in self.columns])

    @property
    def ddl(self) -> str:
        cols = ",\n    ".join(f"{c.name} {c.sql_type}" for c in self.columns)
        return f"CREATE TABLE {self.name} (\n    id INTEGER PRIMARY KEY,\n    {cols}\n)"

    @property
    def insert_sql(self) -> str:
        names = ", ".join(self.column_names)
        marks = ", ".join("?" for _ in self.columns)
        return f"INSERT INTO {self.name} ({names}) VALUES ({marks})"

    @property
    def select_sql(self) -> str:
        return f"SELECT {', '.join(self.column_names)} FROM {self.name} ORDER BY id"


FORCE_SAMPLES: Final = Table(
    "force_samples",
    "Load-cell samples from SAMPLES frames, one row per sample, in arrival order.",
    (
        Column("sample_index", "int", "-", "probe sample counter (first_index + i); may restart"),
        Column("adc_counts", "int", "counts", "raw ADC reading (10 bit on the 32u4)"),
        Column("t_mcu_raw_us", "int", "us", "probe micros() mod 2^32 of the sample"),
        Column("t_mcu_us", "int", "us", "probe time unwrapped to 64 bit"),
        Column("t_host_s", "real", "s", "probe time mapped onto the host monotonic clock"),
        Column("force_n", "real_null", "N", "force from the calibration; NULL if none"),
    ),
)
FRAMES: Final = Table(
    "frames",
    "Camera frames: sequence, times and occluded pixel count S_k (Eq. 2).",
    (
        Column("seq", "int", "-", "camera frame sequence number"),
        Column("t_capture_host_s", "real", "s", "capture time on the host monotonic clock"),
        Column("t_host_s", "real", "s", "host monotonic time the frame was processed"),
        Column("s_k", "int", "px", "occluded pixel count in the ROI, Eq. (2)"),
        Column("flags", "text", "-", "comma-separated quality flags (analysis.flags.Flag)"),
    ),
)
EVENTS: Final = Table(
    "events",
    "Discrete events (button, probe status, operator notes...).",
    (
        Column("t_host_s", "real", "s", "host monotonic time of the event"),
        Column("kind", "text", "-", "event kind"),
        Column("detail_json", "json", "-", "event details as a JSON object"),
    ),
)
TRANSITIONS: Final = Table(
    "transitions",
    "State transitions of the pit/release state machine.",
    (
        Column("t_host_s", "real", "s", "host monotonic time of the transition"),
        Column("old_state", "text", "-", "state left"),
        Column("new_state", "text", "-", "state entered"),
        Column("reason", "text", "-", "why the transition happened"),
    ),
)
GAPS: Final = Table(
    "gaps",
    "Lost samples or frames, accounted exactly from sequence/index gaps.",
    (
        Column("stream", "text", "-", "which stream lost data: 'force', 'frames', ..."),
        Column("start_index", "int", "-", "first missing sample index / frame seq"),
        Column("count", "int", "-", "number of missing samples / frames"),
        Column("t_host_s", "real", "s", "host monotonic time the gap was detected"),
        Column("cause", "text", "-", "e.g. 'link', 'probe_buffer', 'camera'"),
    ),
)
CLOCK_PROBES: Final = Table(
    "clock_probes",
    "Pairs of probe time and host time used to fit the MCU to host clock mapping.",
    (
        Column("t_mcu_raw_us", "int", "us", "probe micros() mod 2^32"),
        Column("t_mcu_us", "int", "us", "probe time unwrapped to 64 bit"),
        Column("t_host_s", "real", "s", "host monotonic time of reception"),
    ),
)
LIVE_PARAMETERS: Final = Table(
    "live_parameters",
    "Live analysis parameters as they evolve, one row per (time, name).",
    (
        Column("t_host_s", "real", "s", "host monotonic time of the estimate"),
        Column("name", "text", "-", "parameter name with unit, e.g. 'd_p_mm', 'e_kpa'"),
        Column("value", "real_null", "(name)", "value; NULL if undefined at that time"),
    ),
)

VIDEO_FRAMES: Final = Table(
    "video_frames",
    "Frames stored in the session's video file, each tied to its frames row by seq.",
    (
        Column("seq", "int", "-", "camera frame sequence number (the frames row's seq)"),
        Column("frame_index", "int", "-", "position of the frame in the video file, from 0"),
        Column("pts_ms", "int", "ms", "presentation time in the video file"),
        Column("t_capture_host_s", "real", "s", "capture time on the host monotonic clock"),
    ),
)

#: Every table, in the order they are documented and exported.
TABLES: Final[tuple[Table, ...]] = (
    FORCE_SAMPLES,
    FRAMES,
    EVENTS,
    TRANSITIONS,
    GAPS,
    CLOCK_PROBES,
    LIVE_PARAMETERS,
    VIDEO_FRAMES,
)
TABLES_BY_NAME: Final[dict[str, Table]] = {t.name: t for t in TABLES}

#: The ``meta`` key/value table, created alongside the data tables.
META_DDL: Final = "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)"


def schema_ddl() -> list[str]:
    """Every statement that creates an empty session database of :data:`SCHEMA_VERSION`."""
    return [META_DDL, *(t.ddl for t in TABLES)]


def tables_of_version(version: int) -> tuple[Table, ...]:
    """The tables a session database of schema ``version`` holds (1: no ``video_frames``)."""
    return tuple(t for t in TABLES if version >= 2 or t is not VIDEO_FRAMES)


class ForceSampleRow(NamedTuple):
    """One load-cell sample, in the column order of :data:`FORCE_SAMPLES`."""

    sample_index: int
    adc_counts: int
    t_mcu_raw_us: int
    t_mcu_us: int
    t_host_s: float
    force_n: float | None


class FrameRow(NamedTuple):
    """One camera frame, in the column order of :data:`FRAMES`."""

    seq: int
    t_capture_host_s: float
    t_host_s: float
    s_k: int
    flags: str | Iterable[str] = ""


class VideoFrameRow(NamedTuple):
    """One stored video frame, in the column order of :data:`VIDEO_FRAMES`."""

    seq: int
    frame_index: int
    pts_ms: int
    t_capture_host_s: float


class Event(NamedTuple):
    """An event read back from a session."""

    t_host_s: float
    kind: str
    detail: dict[str, Any]


class Transition(NamedTuple):
    """A state-machine transition read back from a session."""

    t_host_s: float
    old_state: str
    new_state: str
    reason: str


def _where(table: Table, row: int, column: Column) -> str:
    return f"{table.name} row {row}, column {column.name}"


def _int(value: object, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise SessionError(f"{where}: {value!r} is not an integer")
    out = int(value)
    if not _INT64_MIN <= out <= _INT64_MAX:
        raise SessionError(f"{where}: {out} does not fit in a signed 64-bit integer")
    return out


def _real(value: object, where: str, *, nullable: bool) -> float | None:
    if value is None:
        if nullable:
            return None
        raise SessionError(f"{where}: a number is required, got None")
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SessionError(f"{where}: {value!r} is not a real number")
    out = float(value)
    if nullable:
        return None if math.isnan(out) else out
    if not math.isfinite(out):
        raise SessionError(f"{where}: {out} is not a finite number")
    return out


def _text(value: object, where: str, *, flags: bool = False) -> str:
    if isinstance(value, str):
        return str(value)
    if flags and isinstance(value, Iterable):
        # A set of flags (e.g. a frozenset[Flag]) is sorted so that files are reproducible.
        items = sorted(value, key=str) if isinstance(value, set | frozenset) else list(value)
        if all(isinstance(v, str) for v in items):
            bad = [v for v in items if "," in v]
            if bad:
                raise SessionError(f"{where}: flag {bad[0]!r} contains a comma")
            return ",".join(str(v) for v in items)
    raise SessionError(f"{where}: {value!r} is not a string")


def coerce_row(table: Table, row: object, index: int = 0) -> tuple[Any, ...]:
    """Validate one row and return the tuple SQLite will store.

    Parameters
    ----------
    table : Table
        Table the row goes into.
    row : sequence or numpy record
        Values in the table's column order (:attr:`Table.column_names`).
    index : int
        Position of the row in the caller's batch, used in error messages.

    Returns
    -------
    tuple
        Plain Python values (``int``, ``float``, ``None``, ``str``).

    Raises
    ------
    SessionError
        Wrong number of values, or a value of the wrong type or out of range; the message
        names table, row and column.
    """
    if isinstance(row, np.void):
        row = row.tolist()
    if not isinstance(row, Sequence) or isinstance(row, str):
        raise SessionError(f"{table.name} row {index}: expected a sequence, got {row!r}")
    if len(row) != len(table.columns):
        raise SessionError(
            f"{table.name} row {index}: expected {len(table.columns)} values "
            f"({', '.join(table.column_names)}), got {len(row)}"
        )
    out: list[Any] = []
    for column, value in zip(table.columns, row, strict=True):
        # Fast path for the common exact types (the same result as the checks below).
        kind, tv = column.kind, type(value)
        if tv is int and kind == "int" and _INT64_MIN <= value <= _INT64_MAX:
            out.append(value)
            continue
        if tv is float and (
            (kind == "real" and math.isfinite(value)) or (kind == "real_null" and value == value)
        ):
            out.append(value)
            continue
        if tv is str and kind == "text":
            out.append(value)
            continue
        where = _where(table, index, column)
        if column.kind == "int":
            out.append(_int(value, where))
        elif column.kind == "real":
            out.append(_real(value, where, nullable=False))
        elif column.kind == "real_null":
            out.append(_real(value, where, nullable=True))
        elif column.kind == "text":
            out.append(_text(value, where, flags=column.name == "flags"))
        else:
            out.append(dumps_json_object(value, where))
    return tuple(out)


def coerce_rows(table: Table, rows: Iterable[object]) -> list[tuple[Any, ...]]:
    """Validate a batch of rows (all or none: the first bad row raises)."""
    if isinstance(rows, np.ndarray):
        if rows.dtype.names is not None:
            missing = [n for n in table.column_names if n not in rows.dtype.names]
            if missing:
                raise SessionError(
                    f"{table.name}: structured array lacks field(s) {', '.join(missing)}"
                )
            rows = rows[list(table.column_names)].tolist()
        else:
            rows = rows.tolist()
    return [coerce_row(table, row, i) for i, row in enumerate(rows)]


def to_jsonable(value: object, where: str = "value") -> Any:
    """Convert ``value`` into plain JSON types.

    numpy scalars and arrays become numbers and lists, tuples lists, sets sorted lists, enums their
    value, paths strings, dataclasses and pydantic models dicts; NaN and ±inf become
    ``null`` (strict JSON has no such numbers). Anything else raises
    :class:`SessionError` naming the key path.
    """
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, StrEnum):
        return str(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist(), where)
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise SessionError(f"{where}: key {k!r} is not a string")
            out[k] = to_jsonable(v, f"{where}.{k}")
        return out
    if isinstance(value, list | tuple):
        return [to_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, set | frozenset):  # e.g. a result's flags: sorted for stable files
        items = [to_jsonable(v, f"{where}[]") for v in value]
        return sorted(items, key=lambda v: json.dumps(v, sort_keys=True))
    model_dump = getattr(value, "model_dump", None)
    if callable(model_dump):  # pydantic model
        return to_jsonable(model_dump(mode="json"), where)
    import dataclasses
    import enum
    import pathlib

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_jsonable(dataclasses.asdict(value), where)
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value, where)
    if isinstance(value, pathlib.PurePath):
        return str(value)
    raise SessionError(f"{where}: {type(value).__name__} value {value!r} cannot be stored as JSON")


def dumps_json_object(value: object, where: str) -> str:
    """Serialise a mapping as compact strict JSON (see :func:`to_jsonable`)."""
    if not isinstance(value, Mapping):
        raise SessionError(f"{where}: expected a dict, got {type(value).__name__}")
    return json.dumps(to_jsonable(value, where), separators=(",", ":"), allow_nan=False)


def rows_to_array(table: Table, rows: list[tuple[Any, ...]]) -> npt.NDArray[np.void]:
    """Turn rows read from SQLite into a structured array (NULL reals become NaN)."""
    return np.array(rows, dtype=table.dtype)
