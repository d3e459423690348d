"""Reading sessions back: :class:`SessionReader`, status, integrity, listing.

A reader opens a session directory read-only (``mode=ro``): it never changes a session,
and it can read one that a writer in another process is still recording (SQLite WAL lets
readers see every committed transaction while the writer goes on). On opening, the
directory, the manifest (format and version) and the database schema (version, tables,
columns) are validated; a bad directory raises :class:`~stipi_daemon.errors.SessionError`
naming the file and the problem. Tables come back as numpy structured arrays or as row
iterators. The status combines the stored state with the writer lock: ``recording`` with no
live writer is ``interrupted``. Writing is :mod:`.writer`; export to CSV/Parquet is
:mod:`.export`.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, Self

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import DamagedSessionError, SessionError
from stipi_daemon.storage import layout
from stipi_daemon.storage.lock import read_owner, writer_alive
from stipi_daemon.storage.metadata import Metadata, matches, metadata_of
from stipi_daemon.storage.schema import (
    CLOCK_PROBES,
    EVENTS,
    FORCE_SAMPLES,
    FORMAT_NAME,
    FRAMES,
    GAPS,
    LIVE_PARAMETERS,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_VERSION,
    TABLES,
    TABLES_BY_NAME,
    TRANSITIONS,
    VIDEO_FRAMES,
    Event,
    SessionState,
    Table,
    Transition,
    rows_to_array,
    tables_of_version,
)

if TYPE_CHECKING:
    from stipi_daemon.storage.video_readback import VideoCheck

_MAX_INTEGRITY_MESSAGES: Final = 5


@dataclass(frozen=True)
class IntegrityReport:
    """Result of :meth:`SessionReader.integrity_check`.

    Attributes
    ----------
    directory : Path
        The session directory checked.
    problems : tuple of str
        One line per problem found (empty when everything is sound).
    """

    directory: Path
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems

    def raise_if_bad(self) -> None:
        """Raise :class:`SessionError` (one line, every problem) unless the check passed."""
        if self.problems:
            raise DamagedSessionError("; ".join(self.problems))


def _damage_problem(check: VideoCheck, rows: list[tuple[int, int, int, float]]) -> list[str]:
    """One line naming the damaged frames of a :class:`~.video.VideoCheck` (the first
    :data:`_MAX_INTEGRITY_MESSAGES` with their ``seq`` and byte offset), or none."""
    if not check.damaged:
        return []
    named = []
    for frame in check.damaged[:_MAX_INTEGRITY_MESSAGES]:
        i = frame.frame_index
        seq = f"seq {rows[i][0]}, " if i < len(rows) else ""
        named.append(f"frame {i} ({seq}byte {frame.pos_bytes}): {frame.damage}")
    more = len(check.damaged) - len(named)
    return [
        f"{check.path}: {len(check.damaged)} damaged frames: "
        + "; ".join(named)
        + (f" (+{more} more)" if more else "")
    ]


def _resolve_table(table: str | Table) -> Table:
    if isinstance(table, Table):
        return table
    try:
        return TABLES_BY_NAME[table]
    except KeyError:
        raise SessionError(
            f"no session table {table!r} (tables: {', '.join(TABLES_BY_NAME)})"
        ) from None


class SessionReader:
    """Read-only view of one session directory.

    Parameters
    ----------
    directory : Path or str
        The session directory (``<root>/<session_id>``).

    Raises
    ------
    SessionError
        The directory, manifest or database is missing, unreadable, of another format or
        version, or not a session database.
    """

    def __init__(self, directory: Path | str) -> None:
        self.directory = Path(directory)
        #: Schema version of the database (1: written before video was recorded).
        self.schema_version: int = SCHEMA_VERSION
        if not self.directory.is_dir():
            raise SessionError(f"{self.directory}: session directory does not exist")
        self.manifest: dict[str, Any] = layout.load_manifest(self.manifest_path)
        db = self.db_path
        if not db.is_file():
            raise SessionError(f"{db}: session database is missing")
        if db.stat().st_size == 0:
            raise DamagedSessionError(f"{db}: session database is empty (0 bytes)")
        #: Private copy of the database and its WAL when it lies on read-only media
        #: (:func:`_open_read_only`); removed on close.
        self._copy_dir: Path | None = None
        self._conn, self._copy_dir = _open_read_only(db)
        try:
            problem = self._schema_problem()
        except sqlite3.DatabaseError as exc:
            self.close()
            raise DamagedSessionError(_unreadable(db, exc)) from None
        if problem is not None:
            self.close()
            raise SessionError(f"{db}: {problem}")

    # ------------------------------------------------------------------ files
    @property
    def db_path(self) -> Path:
        return self.directory / layout.DB_NAME

    @property
    def manifest_path(self) -> Path:
        return self.directory / layout.MANIFEST_NAME

    @property
    def summary_path(self) -> Path:
        return self.directory / layout.SUMMARY_NAME

    @property
    def lock_path(self) -> Path:
        return self.directory / layout.LOCK_NAME

    @property
    def session_id(self) -> str:
        return str(self.manifest["session_id"])

    @property
    def video_path(self) -> Path | None:
        """Path of the reserved video file if the manifest reserves one, else None."""
        name = self.manifest["files"].get("video")
        return None if name is None else self.directory / str(name)

    @property
    def metadata(self) -> Metadata:
        """Subject, site, operator and note (:mod:`.metadata`; all None for a session
        recorded before metadata existed). Raises :class:`SessionError` naming the manifest
        and the field when a stored value breaks the rules."""
        return metadata_of(self.manifest, self.manifest_path)

    @property
    def label(self) -> str | None:
        """What tells this session apart at a glance (:func:`session_label`)."""
        return session_label(self.manifest, self.metadata)

    @property
    def summary(self) -> dict[str, Any] | None:
        """The final results (``summary.json``), or None if none was written (yet)."""
        if not self.summary_path.exists():
            return None
        return layout.load_json_object(self.summary_path, "summary")

    # ------------------------------------------------------------------ database
    def _query(self, sql: str, params: tuple[Any, ...] = ()) -> list[Any]:
        try:
            return self._conn.execute(sql, params).fetchall()
        except sqlite3.DatabaseError as exc:
            raise DamagedSessionError(f"{self.db_path}: cannot read ({exc})") from None

    def _schema_problem(self) -> str | None:
        """A one-line description of what is wrong with the schema, or None."""
        version = self._conn.execute("PRAGMA user_version").fetchone()[0]
        names = {
            r[0] for r in self._conn.execute("SELECT name FROM sqlite_master WHERE type='table'")
        }
        if version == 0 and "meta" not in names:
            return "not a stipi session database (no schema version, no meta table)"
        if version not in READABLE_SCHEMA_VERSIONS:
            return (
                f"schema version {version} is not supported (this stipi-daemon reads "
                f"versions {', '.join(str(v) for v in sorted(READABLE_SCHEMA_VERSIONS))})"
            )
        if "meta" not in names:
            return "table 'meta' is missing"
        meta = dict(self._conn.execute("SELECT key, value FROM meta").fetchall())
        if meta.get("format") != FORMAT_NAME:
            return f"meta format is {meta.get('format')!r}, expected {FORMAT_NAME!r}"
        if meta.get("schema_version") != str(version):
            return (
                f"meta schema_version {meta.get('schema_version')!r} disagrees with "
                f"PRAGMA user_version {version}"
            )
        if "state" not in meta:
            return "meta row 'state' is missing"
        self.schema_version = int(version)
        for table in tables_of_version(version):
            if table.name not in names:
                return f"table {table.name!r} is missing"
            have = {r[1] for r in self._conn.execute(f"PRAGMA table_info({table.name})")}
            missing = [c for c in table.column_names if c not in have]
            if missing:
                return f"table {table.name!r} lacks column(s) {', '.join(missing)}"
        return None

    def meta(self) -> dict[str, str]:
        """The ``meta`` key/value rows as stored now."""
        return dict(self._query("SELECT key, value FROM meta"))

    @property
    def status(self) -> SessionState:
        """``complete``/``aborted``/``fault`` as finished, ``recording`` while a live writer
        holds the lock, ``interrupted`` when the writer died before finishing."""
        # Probe the lock before reading the state: a writer that finishes in between is
        # then seen as finished, never as interrupted (writers never restart).
        alive = writer_alive(self.lock_path)
        stored = self.meta().get("state", "")
        try:
            state = SessionState(stored)
        except ValueError:
            raise SessionError(f"{self.db_path}: unknown session state {stored!r}") from None
        if state is SessionState.RECORDING and not alive:
            return SessionState.INTERRUPTED
        return state

    @property
    def writer_owner(self) -> dict[str, Any] | None:
        """pid, host and start time of the writer recorded in the lock file, if any."""
        return read_owner(self.lock_path)

    @contextmanager
    def snapshot(self) -> Iterator[Self]:
        """Read several tables from one consistent database state.

        Inside the ``with`` block every query sees the same committed state, even while
        a writer keeps committing.
        """
        try:
            self._conn.execute("BEGIN")
        except sqlite3.DatabaseError as exc:
            raise DamagedSessionError(f"{self.db_path}: cannot read ({exc})") from None
        try:
            yield self
        finally:
            self._conn.execute("COMMIT")

    def has_table(self, table: str | Table) -> bool:
        """Whether this session's schema version has ``table`` (version 1: no video_frames)."""
        return _resolve_table(table) in tables_of_version(self.schema_version)

    def count(self, table: str | Table) -> int:
        """Number of rows in ``table`` (0 for a table its schema version lacks)."""
        t = _resolve_table(table)
        if not self.has_table(t):
            return 0
        return int(self._query(f"SELECT count(*) FROM {t.name}")[0][0])

    def counts(self) -> dict[str, int]:
        """Number of rows of every table."""
        return {t.name: self.count(t) for t in TABLES}

    def iter_rows(self, table: str | Table, batch_size: int = 10_000) -> Iterator[tuple[Any, ...]]:
        """Rows of ``table`` in insertion order, as stored (NULL is None); none for a table
        the session's schema version lacks."""
        t = _resolve_table(table)
        if not self.has_table(t):
            return
        try:
            cursor = self._conn.execute(t.select_sql)
            while batch := cursor.fetchmany(batch_size):
                yield from batch
        except sqlite3.DatabaseError as exc:
            raise DamagedSessionError(
                f"{self.db_path}: cannot read table {t.name} ({exc})"
            ) from None

    def array(self, table: str | Table) -> npt.NDArray[np.void]:
        """Whole ``table`` as a structured array (NULL reals are NaN, text is ``object``)."""
        t = _resolve_table(table)
        return rows_to_array(t, list(self.iter_rows(t)))

    def force_samples(self) -> npt.NDArray[np.void]:
        """Fields ``sample_index, adc_counts, t_mcu_raw_us [us], t_mcu_us [us],
        t_host_s [s], force_n [N]``."""
        return self.array(FORCE_SAMPLES)

    def frames(self) -> npt.NDArray[np.void]:
        """Fields ``seq, t_capture_host_s [s], t_host_s [s], s_k [px], flags``."""
        return self.array(FRAMES)

    def video_frames(self) -> npt.NDArray[np.void]:
        """Fields ``seq, frame_index, pts_ms [ms], t_capture_host_s [s]`` (empty for a
        session without video)."""
        return self.array(VIDEO_FRAMES)

    def gaps(self) -> npt.NDArray[np.void]:
        """Fields ``stream, start_index, count, t_host_s [s], cause``."""
        return self.array(GAPS)

    def clock_probes(self) -> npt.NDArray[np.void]:
        """Fields ``t_mcu_raw_us [us], t_mcu_us [us], t_host_s [s]``."""
        return self.array(CLOCK_PROBES)

    def live_parameters(self) -> npt.NDArray[np.void]:
        """Fields ``t_host_s [s], name, value`` (long format, one row per name and time)."""
        return self.array(LIVE_PARAMETERS)

    def events(self) -> list[Event]:
        """Events with their ``detail`` decoded."""
        return [Event(t, kind, json.loads(detail)) for t, kind, detail in self.iter_rows(EVENTS)]

    def transitions(self) -> list[Transition]:
        """State-machine transitions in order."""
        return [Transition(*row) for row in self.iter_rows(TRANSITIONS)]

    def time_span_s(self) -> tuple[float, float] | None:
        """First and last host time of the force samples and frames [s], or None if empty."""
        rows = self._query(
            "SELECT min(t), max(t) FROM (SELECT min(t_host_s) AS t FROM force_samples "
            "UNION ALL SELECT max(t_host_s) FROM force_samples "
            "UNION ALL SELECT min(t_host_s) FROM frames UNION ALL SELECT max(t_host_s) FROM frames)"
        )
        first, last = rows[0]
        return None if first is None else (float(first), float(last))

    def duration_s(self) -> float | None:
        """Span of the recorded force samples and frames [s], or None if there are none."""
        span = self.time_span_s()
        return None if span is None else span[1] - span[0]

    # ------------------------------------------------------------------ integrity
    def integrity_check(self, *, decode: bool = False) -> IntegrityReport:
        """Check the whole directory: manifest, database pages, schema, summary, video.

        Runs SQLite's ``PRAGMA integrity_check`` (reads every page: proportional to the
        file size), re-validates the manifest and the schema version, checks that the
        manifest and the database belong to the same session, that ``summary.json`` (if
        present) parses, and the video against its ``video_frames`` rows
        (:meth:`_video_problems`). The video's bytes are checked by default (every cluster's
        CRC-32, every packet demuxed: 0.3-1.0 s for 114 MB, docs/storage.md); ``decode``
        decodes every frame too (about 2 ms per 420x420 FFV1 frame, 9-13 ms per 1080p JPEG:
        minutes for a long session), which only a decoder error the bytes cannot show needs.
        """
        problems: list[str] = []
        try:
            manifest = layout.load_manifest(self.manifest_path)
        except SessionError as exc:
            problems.append(str(exc))
            manifest = None
        try:
            messages = [str(r[0]) for r in self._conn.execute("PRAGMA integrity_check")]
            if messages != ["ok"]:
                shown = messages[:_MAX_INTEGRITY_MESSAGES]
                more = len(messages) - len(shown)
                problems.append(
                    f"{self.db_path}: integrity_check failed: "
                    + " | ".join(m.replace("\n", " ") for m in shown)
                    + (f" (+{more} more)" if more else "")
                )
            schema = self._schema_problem()
            if schema is not None:
                problems.append(f"{self.db_path}: {schema}")
            else:
                meta_id = self.meta().get("session_id")
                if manifest is not None and meta_id != manifest["session_id"]:
                    problems.append(
                        f"{self.manifest_path}: session_id {manifest['session_id']!r} differs "
                        f"from the database's {meta_id!r}"
                    )
        except (sqlite3.DatabaseError, SessionError) as exc:
            problems.append(f"{self.db_path}: not readable ({exc})")
        try:
            self.summary  # noqa: B018 - parse it
        except SessionError as exc:
            problems.append(str(exc))
        try:
            problems += self._video_problems(decode)
        except sqlite3.DatabaseError as exc:
            problems.append(f"{self.db_path}: video_frames not readable ({exc})")
        except SessionError as exc:  # names its file: the database or the video
            problems.append(str(exc))
        return IntegrityReport(self.directory, tuple(problems))

    def _video_problems(self, decode: bool) -> list[str]:
        """The video, its ``video_frames`` rows and their ``frames`` rows.

        The file must be sound (:func:`~.video_readback.check_video`: no frame failing its
        CRC-32 or, with ``decode``, its decoding; no damaged header or broken structure). The
        rows:
        frame indices 0, 1, 2, ..., each row's ``pts_ms`` the file's for that frame, each
        ``seq`` once and in ``frames`` (once) with the same capture time. Frames against
        rows: a recording that ended cleanly (``complete``, ``aborted``, and ``fault``
        without a storage or video failure) holds exactly one frame per row and ends whole.
        One that did not (killed: ``interrupted``/``recording``; or stopped by a storage or
        video failure) may end in a cut-off element, hold up to
        :data:`~.video.UNINDEXED_FRAMES_MAX` frames more than rows (the row batches not
        stored), and lack the newest frames of at most one commit interval of capture time
        (the block the muxer holds, the FFV1 encoders' queue). Which of the two is read
        before the rows: a recording that finishes while they are read (``sessions show``
        of a live session) was read as the one that did not end yet.
        """
        clean = self._ended_cleanly()
        rows = [
            (int(r[0]), int(r[1]), int(r[2]), float(r[3])) for r in self.iter_rows(VIDEO_FRAMES)
        ]
        n = len(rows)
        path = self.video_path
        if path is None or not path.is_file():
            missing = f"{path or self.directory}: video is missing, {n} video_frames rows"
            return [missing] if n else []
        from stipi_daemon.storage.video_readback import check_video

        check = check_video(path, decode=decode)
        problems = list(check.problems) + _damage_problem(check, rows)
        problems += self._video_row_problems(rows)
        if check.cut_at is not None and clean:
            problems.append(
                f"{path}: ends inside an element at byte {check.cut_at} of {check.size_bytes} "
                "(cut off, in a recording that ended cleanly)"
            )
        problems += self._video_count_problems(check.frames, rows, clean, path)
        shared = min(n, len(check.pts_ms))
        wrong = [i for i in range(shared) if check.pts_ms[i] not in (None, rows[i][2])]
        if wrong:
            i = wrong[0]
            problems.append(
                f"{path}: {len(wrong)} frames have another pts than their video_frames row, "
                f"first frame {i} (seq {rows[i][0]}): {check.pts_ms[i]} ms in the file, "
                f"{rows[i][2]} ms in the row"
            )
        return problems

    def _ended_cleanly(self) -> bool:
        """Whether the recording ended cleanly: finished (``complete``, ``aborted``,
        ``fault``) without a storage failure (``summary.storage_error``) or a video failure
        (``summary.run.video.error``), after which the recorder hands over every row."""
        state = self.meta().get("state")
        finished = (SessionState.COMPLETE, SessionState.ABORTED, SessionState.FAULT)
        if state not in {s.value for s in finished}:
            return False
        try:
            summary = self.summary or {}
        except SessionError:
            return False  # reported by integrity_check; the rule cannot be chosen
        run = summary.get("run")
        video = run.get("video") if isinstance(run, dict) else None
        video_error = video.get("error") if isinstance(video, dict) else None
        return summary.get("storage_error") is None and video_error is None

    def _video_count_problems(
        self, frames: int, rows: list[tuple[int, int, int, float]], clean: bool, path: Path
    ) -> list[str]:
        """Frames in the file against rows (see :meth:`_video_problems`)."""
        from stipi_daemon.storage.video import UNINDEXED_FRAMES_MAX

        n = len(rows)
        what = f"{path}: video holds {frames} frames, video_frames has {n} rows"
        if clean:
            return [] if frames == n else [f"{what} (the recording ended cleanly)"]
        if frames - n > UNINDEXED_FRAMES_MAX:
            return [
                f"{what}: more frames without rows than a recording that did not end "
                f"cleanly leaves ({UNINDEXED_FRAMES_MAX})"
            ]
        interval_s = float(self.meta().get("commit_interval_s", "0.2"))
        if frames < n and rows[-1][3] - rows[frames][3] > interval_s:
            return [f"{what} (more than one commit interval, {interval_s:g} s, missing)"]
        return []

    def _video_row_problems(self, rows: list[tuple[int, int, int, float]]) -> list[str]:
        """``video_frames`` rows against themselves and the ``frames`` table."""
        n = len(rows)
        problems: list[str] = []
        if [i for _, i, _, _ in rows] != list(range(n)):
            problems.append(f"{self.db_path}: video_frames frame_index is not 0..{n - 1}")
        checks = (
            (
                "SELECT seq, count(*) FROM video_frames GROUP BY seq HAVING count(*) > 1",
                "seq {} appears {} times in video_frames",
            ),
            (
                # NOT IN: SQLite builds a table of the seqs once (not a scan per row)
                "SELECT seq, 0 FROM video_frames WHERE seq NOT IN (SELECT seq FROM frames)",
                "video_frames seq {} has no frames row",
            ),
            (
                "SELECT v.seq, count(*) FROM video_frames v JOIN frames f ON f.seq = v.seq "
                "GROUP BY v.id HAVING count(*) > 1",
                "video_frames seq {} has {} frames rows",
            ),
            (
                "SELECT v.seq, v.t_capture_host_s - f.t_capture_host_s FROM video_frames v "
                "JOIN frames f ON f.seq = v.seq WHERE v.t_capture_host_s != f.t_capture_host_s",
                "video_frames seq {} has another capture time than its frames row ({:+.6g} s)",
            ),
        )
        for sql, text in checks:
            found = self._query(sql + " ORDER BY 1") if n else []
            if found:
                more = f" (+{len(found) - 1} more)" if len(found) > 1 else ""
                problems.append(f"{self.db_path}: " + text.format(*found[0]) + more)
        return problems

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        self._conn.close()
        if self._copy_dir is not None:
            shutil.rmtree(self._copy_dir, ignore_errors=True)
            self._copy_dir = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


#: Longest label shown [characters] (:func:`session_label`).
LABEL_CHARS: Final = 32


def session_label(manifest: dict[str, Any], metadata: Metadata) -> str | None:
    """A short label of a session: the first line of its note (cut to
    :data:`LABEL_CHARS` characters, ``…`` marking the cut), else ``scene:<name>`` for a
    session of simulated devices (the scene file's name), else None."""
    note = metadata.get("note")
    if note:
        line = note.strip().splitlines()[0].strip()
        return line if len(line) <= LABEL_CHARS else line[: LABEL_CHARS - 1].rstrip() + "…"
    config = manifest.get("config")
    for section, key in (("camera", None), ("probe", "transport")):
        node = config.get(section) if isinstance(config, dict) else None
        if key is not None and isinstance(node, dict):
            node = node.get(key)
        scene = node.get("scene") if isinstance(node, dict) else None
        if isinstance(scene, str) and scene:
            return "scene:" + Path(scene).stem
    return None


@dataclass(frozen=True)
class SessionListing:
    """One line of :func:`list_sessions`; ``error`` is set (and the rest may be None) for a
    directory that cannot be read.

    ``metadata`` holds subject, site, operator and note (:mod:`.metadata`), ``label`` the
    session's short label (:func:`session_label`), ``validity`` the summary's verdict.
    """

    session_id: str
    directory: Path
    created_utc: str | None = None
    status: str = "error"
    duration_s: float | None = None
    n_frames: int | None = None
    n_samples: int | None = None
    severity: str | None = None
    validity: str = "unknown"
    error: str | None = None
    metadata: Metadata | None = None
    label: str | None = None

    @property
    def subject(self) -> str | None:
        return None if self.metadata is None else self.metadata.get("subject")

    @property
    def site(self) -> str | None:
        return None if self.metadata is None else self.metadata.get("site")

    @property
    def operator(self) -> str | None:
        return None if self.metadata is None else self.metadata.get("operator")


def _connect(uri: str) -> sqlite3.Connection:
    conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
    conn.execute("PRAGMA busy_timeout=5000")
    return conn


def _is_corrupt(exc: sqlite3.Error) -> bool:
    """Whether SQLite says the file itself is damaged (not a database, malformed)."""
    name = getattr(exc, "sqlite_errorname", "") or ""
    return name.startswith(("SQLITE_NOTADB", "SQLITE_CORRUPT"))


def _unreadable(db: Path, exc: sqlite3.Error) -> str:
    if _is_corrupt(exc):
        return f"{db}: not a readable SQLite database, truncated or corrupt ({exc})"
    return f"{db}: cannot read the database ({exc})"


def _open_read_only(db: Path) -> tuple[sqlite3.Connection, Path | None]:
    """Open a session database read-only; also one copied to read-only media.

    ``mode=ro`` reads a WAL database in place, and while a writer records, when SQLite
    can use (or create) the ``-shm`` index beside it. A session copied to read-only media
    without its ``-shm`` (a recorder killed before its last checkpoint) cannot get one:
    without a ``-wal`` (or an empty one) the database file alone is the data, opened with
    ``immutable=1``; with a ``-wal``, the committed rows still in it would be lost that
    way, so the database and its WAL are copied to a private temporary directory and
    read there (the media are never written). Returns the connection and that directory
    (None: read in place).

    Raises
    ------
    SessionError
        SQLite cannot open or read it; "truncated or corrupt" only when SQLite says the
        file is not a database or is malformed.
    """
    uri = db.resolve().as_uri()
    conn: sqlite3.Connection | None = None
    try:
        conn = _connect(uri + "?mode=ro")
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn, None
    except sqlite3.Error as exc:
        if conn is not None:
            conn.close()
        shm = db.with_name(db.name + "-shm")
        if _is_corrupt(exc) or shm.exists() or os.access(db.parent, os.W_OK):
            raise DamagedSessionError(_unreadable(db, exc)) from None
    wal = db.with_name(db.name + "-wal")
    copy_dir: Path | None = None
    try:
        if not wal.exists() or wal.stat().st_size == 0:
            conn = _connect(uri + "?immutable=1")
        else:
            copy_dir = Path(tempfile.mkdtemp(prefix="stipi-read-only-"))
            shutil.copyfile(db, copy_dir / db.name)
            shutil.copyfile(wal, copy_dir / wal.name)
            conn = _connect((copy_dir / db.name).as_uri() + "?mode=ro")
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except (sqlite3.Error, OSError) as exc:
        if copy_dir is not None:
            shutil.rmtree(copy_dir, ignore_errors=True)
        if isinstance(exc, OSError):
            raise SessionError(
                f"{db}: read-only media: cannot copy it to read its WAL ({exc})"
            ) from None
        raise DamagedSessionError(_unreadable(db, exc)) from None
    return conn, copy_dir


def _severity_text(value: Any) -> str | None:
    """A severity value as shown: a string, or ``"<class> (<grade>)"`` from an object."""
    if isinstance(value, dict):
        label = next((value[k] for k in ("severity", "label", "class") if k in value), None)
        grade = next((value[k] for k in ("nearest_grade", "grade") if k in value), None)
        if label is not None and grade is not None:
            return f"{label} ({grade})"
        return None if label is None and grade is None else str(label or grade)
    return None if value is None else str(value)


def severity_of(summary: dict[str, Any] | None) -> str | None:
    """The severity shown for a summary, or None.

    The daemon writes the paper estimator's class under
    ``summary["results"]["severity"]["paper_estimator"]`` (a serialised
    :class:`~stipi_daemon.analysis.severity.SeverityResult`); older or hand-written
    summaries may hold ``summary["severity"]``. A string is shown as it is; an object's
    class (``severity``, ``label`` or ``class``) and grade (``nearest_grade`` or ``grade``)
    as ``"severe (3+)"``. A severity whose validity is ``invalid`` is never shown as a
    result: ``"invalid"`` instead.
    """
    if summary is None:
        return None
    results = summary.get("results")
    value: Any = None
    if isinstance(results, dict) and isinstance(results.get("severity"), dict):
        value = results["severity"].get("paper_estimator")
    if value is None:
        value = summary.get("severity")
    shown = _severity_text(value)
    if shown is not None and quantity_status(summary, "severity") == "invalid":
        return "invalid"
    return shown


#: Where each quantity of the validity schema sits in ``summary["results"]``, and its unit.
QUANTITY_PATHS: Final[dict[str, tuple[tuple[str, ...], str]]] = {
    "depth_mm": (("pitting", "depth_mm"), "mm"),
    "rebound_force_n": (("pitting", "rebound_force_n"), "N"),
    "recovery_time_s": (("pitting", "recovery_time_s"), "s"),
    "elasticity_kpa": (("paper_estimator", "elasticity_kpa"), "kPa"),
    "viscosity_n_s_per_mm2": (("paper_estimator", "viscosity_n_s_per_mm2"), "N*s/mm^2"),
    "severity": (("severity", "paper_estimator", "severity"), ""),
    "tau_s": (("fitted_recovery", "tau_s"), "s"),
    "viscosity_fit_n_s_per_mm2": (
        ("fitted_recovery", "model", "viscosity_n_s_per_mm2"),
        "N*s/mm^2",
    ),
    "applied_force_n": (("applied_force_n",), "N"),
}


def quantity_value(summary: dict[str, Any] | None, quantity: str) -> Any:
    """The recorded value of one quantity of :data:`QUANTITY_PATHS` (None when absent)."""
    node: Any = None if summary is None else summary.get("results")
    for key in QUANTITY_PATHS[quantity][0]:
        if not isinstance(node, dict):
            return None
        node = node.get(key)
    return node


def quantity_status(summary: dict[str, Any] | None, quantity: str) -> str:
    """``valid``, ``flagged``, ``invalid``, or ``unknown`` (no validity recorded)."""
    validity = None if summary is None else summary.get("validity")
    entry = validity.get(quantity) if isinstance(validity, dict) else None
    status = entry.get("status") if isinstance(entry, dict) else None
    return status if status in ("valid", "flagged", "invalid") else "unknown"


def verdict_of(summary: dict[str, Any] | None) -> str:
    """The verdict's status (``complete``, ``flagged``, ``invalid``, ``incomplete``), or
    ``unknown`` for a summary written before verdicts existed (or none at all)."""
    verdict = None if summary is None else summary.get("verdict")
    status = verdict.get("status") if isinstance(verdict, dict) else None
    if status in ("complete", "flagged", "invalid", "incomplete"):
        return str(status)
    return "unknown"


def _is_session_dir(path: Path) -> bool:
    return path.is_dir() and any(
        (path / name).exists() for name in (layout.MANIFEST_NAME, layout.DB_NAME, layout.LOCK_NAME)
    )


def session_dirs(root: Path | str) -> list[Path]:
    """The session directories directly under ``root``, sorted by name.

    Raises
    ------
    SessionError
        ``root`` does not exist or is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise SessionError(f"{root}: sessions directory does not exist")
    return sorted(p for p in root.iterdir() if _is_session_dir(p))


def list_sessions(
    root: Path | str, where: dict[str, str | None] | None = None
) -> list[SessionListing]:
    """Every session directory under ``root``, sorted by id; unreadable ones carry ``error``.

    ``where`` keeps the sessions whose metadata equals each given (not None) value exactly,
    e.g. ``{"subject": "P-001"}``; unreadable sessions are always kept (they cannot be
    matched, and are never hidden).

    Raises
    ------
    SessionError
        ``root`` does not exist or is not a directory.
    """
    out: list[SessionListing] = []
    for directory in session_dirs(root):
        try:
            with SessionReader(directory) as reader:
                metadata = reader.metadata
                if where and not matches(metadata, where):
                    continue
                counts = reader.counts()
                try:
                    summary = reader.summary
                    severity, validity = severity_of(summary), verdict_of(summary)
                except SessionError:
                    severity, validity = "(bad summary)", "unknown"
                out.append(
                    SessionListing(
                        session_id=reader.session_id,
                        directory=directory,
                        created_utc=str(reader.manifest["created_utc"]),
                        status=reader.status.value,
                        duration_s=reader.duration_s(),
                        n_frames=counts[FRAMES.name],
                        n_samples=counts[FORCE_SAMPLES.name],
                        severity=severity,
                        validity=validity,
                        metadata=metadata,
                        label=session_label(reader.manifest, metadata),
                    )
                )
        except SessionError as exc:
            out.append(
                SessionListing(session_id=directory.name, directory=directory, error=str(exc))
            )
    return out
