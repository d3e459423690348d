"""Recording one session: :class:`SessionWriter`.

The writer owns a session directory while it records: it creates the directory, the
manifest and the SQLite database (WAL mode), holds the writer lock, buffers rows, and
commits them in batches (``executemany``) at least every ``commit_interval_s`` (default
0.2 s), from a background thread, from the calling thread when an ``add_*`` call finds a
commit due, and on :meth:`~SessionWriter.commit` / :meth:`~SessionWriter.finish`. Every
commit is a WAL transaction: once it returns, a ``kill -9`` of the process cannot undo it,
so a killed recording loses at most the rows added during the last commit interval (see
``docs/storage.md`` for power loss). The writer is synchronous and thread-safe (one lock);
the asyncio daemon calls it from a writer task. Reading sessions back is :mod:`.reader`.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Literal, Self

from stipi_daemon.errors import ConfigError, SessionError
from stipi_daemon.storage import layout
from stipi_daemon.storage.lock import WriterLock
from stipi_daemon.storage.schema import (
    CLOCK_PROBES,
    EVENTS,
    FINAL_STATES,
    FORCE_SAMPLES,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES,
    GAPS,
    LIVE_PARAMETERS,
    SCHEMA_VERSION,
    TABLES,
    TRANSITIONS,
    VIDEO_FRAMES,
    SessionState,
    Table,
    coerce_row,
    coerce_rows,
    schema_ddl,
)

_log = logging.getLogger(__name__)

#: Default commit interval [s]; a kill -9 loses at most this much recent data.
DEFAULT_COMMIT_INTERVAL_S: Final = 0.2
#: Commits are due this fraction of the interval after the oldest buffered row, leaving the
#: rest of the interval as headroom for thread wake-up latency and the commit itself.
COMMIT_LEAD_FRACTION: Final = 0.75
#: Shortest period at which the idle commit thread looks for a first row [s] (see
#: :class:`SessionWriter`); shorter commit intervals wake it instead.
IDLE_POLL_MIN_S: Final = 0.005

Synchronous = Literal["NORMAL", "FULL"]


@dataclass(frozen=True)
class StorageOptions:
    """How a session is stored.

    Parameters
    ----------
    commit_interval_s : float
        Longest time a row waits in memory before it is committed [s]; a process crash
        loses at most the rows of the last interval. 0.001-60 s, default 0.2 s. Commits
        are scheduled at 3/4 of it (:data:`COMMIT_LEAD_FRACTION`) so that scheduling
        delays on a loaded machine still keep the bound.
    synchronous : {"NORMAL", "FULL"}
        SQLite ``PRAGMA synchronous``. ``NORMAL``: every commit survives a process crash
        (kill -9); a power loss or kernel crash may lose commits since the last WAL
        checkpoint. ``FULL``: every commit is also fsynced and survives power loss, at the
        price of one fsync per commit (about 7 per second at the default interval).
    min_free_bytes : int
        Free space required on the file system before a session is created [B].
    min_free_setting : str
        Where ``min_free_bytes`` came from, named in the too-little-space error (the
        daemon gives its config field ``storage.min_free_mb``).
    background_commit : bool
        Run the commit timer in a background thread (default). Without it, commits happen
        only inside ``add_*``/``commit``/``finish`` calls, and the loss bound holds only if
        the caller makes a call at least every quarter interval.
    """

    commit_interval_s: float = DEFAULT_COMMIT_INTERVAL_S
    synchronous: Synchronous = "NORMAL"
    min_free_bytes: int = layout.DEFAULT_MIN_FREE_BYTES
    background_commit: bool = True
    min_free_setting: str = "StorageOptions.min_free_bytes"

    def __post_init__(self) -> None:
        if not 0.001 <= self.commit_interval_s <= 60.0:
            raise ConfigError(
                f"storage.commit_interval_s = {self.commit_interval_s!r}: must be within 0.001-60 s"
            )
        if self.synchronous not in ("NORMAL", "FULL"):
            raise ConfigError(
                f"storage.synchronous = {self.synchronous!r}: must be 'NORMAL' or 'FULL'"
            )
        if self.min_free_bytes < 0:
            raise ConfigError(f"storage.min_free_bytes = {self.min_free_bytes}: must be >= 0")


@dataclass
class WriterStats:
    """Counters of a writer (for logs and benchmarks)."""

    rows: dict[str, int] = field(default_factory=lambda: {t.name: 0 for t in TABLES})
    commits: int = 0
    max_commit_s: float = 0.0
    """Longest commit so far [s]."""
    commit_log: list[tuple[float, dict[str, int]]] | None = None
    """Off (None) by default. Set it to a list to record every commit as
    ``(time.monotonic() when it completed [s], rows committed so far per table)``; the
    counts are the highest committed row numbers in insertion order (benchmarks measure
    write-to-disk latency with it)."""


class SessionWriter:
    """Records one session into ``<root>/<session_id>/``; create with :meth:`create`.

    Rows are validated when added (a bad row raises :class:`SessionError` and nothing of
    its batch is buffered), held in memory, and committed within ``commit_interval_s``.
    If a commit fails (disk full, I/O error), the rows stay buffered, the error is raised
    by the next call, and later commits retry them.
    """

    def __init__(
        self,
        *,
        directory: Path,
        connection: sqlite3.Connection,
        lock: WriterLock,
        manifest: dict[str, Any],
        options: StorageOptions,
    ) -> None:
        self.directory = directory
        self.manifest = manifest
        self.options = options
        self.stats = WriterStats()
        self._conn = connection
        self._lock = lock
        self._cond = threading.Condition(threading.RLock())
        self._pending: dict[str, list[tuple[Any, ...]]] = {t.name: [] for t in TABLES}
        self._pending_since: float | None = None
        self._failure: BaseException | None = None
        self._state: SessionState = SessionState.RECORDING
        self._closed = False
        self._commit_after_s = COMMIT_LEAD_FRACTION * options.commit_interval_s
        # The commit thread looks for pending rows this often when it has none, rather than
        # being woken by every first row after a commit: that wake-up (a futex and a thread
        # switch per frame in the live daemon, whose event loop commits frames itself every
        # few ms) cost more than the commit it was for. It finds a first row within a quarter
        # interval, before the row's commit is due (at ``_commit_after_s``, 3/4 of it): the
        # commit schedule is the same as with a wake-up.
        # Below IDLE_POLL_MIN_S (commit intervals under 20 ms) the looks would cost more than
        # the wake-ups: the thread then waits untimed and the first row wakes it.
        poll_s = (1.0 - COMMIT_LEAD_FRACTION) * options.commit_interval_s
        self._idle_poll_s: float | None = poll_s if poll_s >= IDLE_POLL_MIN_S else None
        self._timer_idle = False  # the commit thread waits untimed for a first row
        self._thread: threading.Thread | None = None
        if options.background_commit:
            self._thread = threading.Thread(
                target=self._commit_loop,
                name=f"stipi-session-commit-{self.session_id}",
                daemon=True,
            )
            self._thread.start()

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(
        cls,
        root: Path | str,
        config: object,
        calibration: object,
        firmware: object | None = None,
        *,
        session_id: str | None = None,
        video: bool = False,
        options: StorageOptions | None = None,
        software: Mapping[str, str | None] | None = None,
        metadata: Mapping[str, str | None] | None = None,
    ) -> SessionWriter:
        """Create a new session directory and start recording into it.

        Parameters
        ----------
        root : Path or str
            Directory holding the sessions (created if missing).
        config : mapping or pydantic model
            The daemon configuration, stored in the manifest.
        calibration : mapping or pydantic model
            The calibration in force, stored in the manifest.
        firmware : mapping or None
            Firmware information from ``GET_INFO`` (None when no probe answered).
        session_id : str, optional
            Directory name; by default UTC time plus random digits (:func:`layout.new_session_id`).
        video : bool
            Reserve ``video.mkv`` in the manifest; the caller writes the file
            (:class:`~stipi_daemon.storage.video.VideoRecorder`).
        options : StorageOptions, optional
            Commit interval, durability, free-space minimum.
        software : mapping, optional
            Versions of the routines that produced the data (e.g. ``sk_kernel``), recorded
            in the manifest beside the storage's own software versions.
        metadata : mapping, optional
            Subject, site, operator and note (:mod:`.metadata`), stored as the manifest's
            ``metadata`` (every field null when not given).

        Raises
        ------
        SessionError
            Too little free space, the session directory exists already, a value of the
            manifest is not JSON-serialisable, or the database cannot be created.
        """
        options = options or StorageOptions()
        root = Path(root)
        try:
            root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SessionError(f"{root}: cannot create the sessions directory: {exc}") from exc
        layout.check_free_space(root, options.min_free_bytes, options.min_free_setting)
        session_id = layout.check_session_id(session_id or layout.new_session_id())
        directory = root / session_id
        created_utc = layout.utc_now_iso()
        created_monotonic_s = time.monotonic()
        created_unix_s = time.time()
        # Serialise the manifest before touching the disk: a bad config value fails here.
        manifest = layout.build_manifest(
            session_id=session_id,
            created_utc=created_utc,
            created_monotonic_s=created_monotonic_s,
            created_unix_s=created_unix_s,
            config=config,
            calibration=calibration,
            firmware=firmware,
            video=video,
            commit_interval_s=options.commit_interval_s,
            synchronous=options.synchronous,
            software=software,
            metadata=metadata,
        )
        try:
            directory.mkdir()
        except FileExistsError:
            raise SessionError(f"{directory}: session directory exists already") from None
        except OSError as exc:
            raise SessionError(f"{directory}: cannot create session directory: {exc}") from exc
        lock = WriterLock.acquire(directory / layout.LOCK_NAME, started_utc=created_utc)
        try:
            conn = _create_database(
                directory / layout.DB_NAME,
                options,
                {
                    "format": FORMAT_NAME,
                    "format_version": str(FORMAT_VERSION),
                    "schema_version": str(SCHEMA_VERSION),
                    "session_id": session_id,
                    "state": SessionState.RECORDING.value,
                    "created_utc": created_utc,
                    "created_monotonic_s": repr(created_monotonic_s),
                    "created_unix_s": repr(created_unix_s),
                    "commit_interval_s": repr(options.commit_interval_s),
                    "synchronous": options.synchronous,
                },
            )
            layout.write_json_atomic(directory / layout.MANIFEST_NAME, manifest, what="manifest")
            layout.fsync_directory(directory)
        except BaseException:
            lock.release()
            raise
        return cls(
            directory=directory, connection=conn, lock=lock, manifest=manifest, options=options
        )

    # ------------------------------------------------------------------ properties
    @property
    def session_id(self) -> str:
        return str(self.manifest["session_id"])

    @property
    def db_path(self) -> Path:
        return self.directory / layout.DB_NAME

    @property
    def summary_path(self) -> Path:
        return self.directory / layout.SUMMARY_NAME

    @property
    def video_path(self) -> Path | None:
        """Where the caller writes the raw video, or None if none was reserved."""
        name = self.manifest["files"]["video"]
        return None if name is None else self.directory / str(name)

    @property
    def state(self) -> SessionState:
        return self._state

    @property
    def pending_rows(self) -> int:
        """Rows added but not yet committed."""
        with self._cond:
            return self._count_pending()

    # ------------------------------------------------------------------ adding rows
    def add_force_samples(self, rows: Iterable[object]) -> int:
        """Add load-cell samples.

        Parameters
        ----------
        rows : iterable of ForceSampleRow-like sequences, or a structured array
            ``(sample_index, adc_counts, t_mcu_raw_us [us], t_mcu_us [us], t_host_s [s],
            force_n [N] or None)`` each.

        Returns
        -------
        int
            Number of rows added.
        """
        return self._add(FORCE_SAMPLES, coerce_rows(FORCE_SAMPLES, rows))

    def add_frames(self, rows: Iterable[object]) -> int:
        """Add camera frames: ``(seq, t_capture_host_s [s], t_host_s [s], s_k [px], flags)``.

        ``flags`` is a comma-separated string or an iterable of flag strings
        (:class:`~stipi_daemon.analysis.flags.Flag`); ``""`` for none.
        """
        return self._add(FRAMES, coerce_rows(FRAMES, rows))

    def add_video_frames(self, rows: Iterable[object]) -> int:
        """Add stored video frames: ``(seq, frame_index, pts_ms [ms], t_capture_host_s [s])``.

        Each ties a frame of the session's video file to the ``frames`` row of the same
        ``seq`` (:mod:`.video`).
        """
        return self._add(VIDEO_FRAMES, coerce_rows(VIDEO_FRAMES, rows))

    def fail(self, error: SessionError) -> None:
        """Stop storing because a companion file failed (the video on a full disk).

        The next ``add_*``/``commit`` call raises ``error``, as after a failed commit, so the
        daemon stops recording rows and video together; rows buffered so far are kept.
        """
        with self._cond:
            self._failure = error

    def add_event(
        self, t_host_s: float, kind: str, detail: Mapping[str, Any] | None = None
    ) -> None:
        """Add an event at host time ``t_host_s`` [s] with JSON-serialisable ``detail``."""
        self._add(EVENTS, [coerce_row(EVENTS, (t_host_s, kind, dict(detail or {})))])

    def add_transition(self, t_host_s: float, old: str, new: str, reason: str) -> None:
        """Add a pit/release state-machine transition ``old`` → ``new`` at ``t_host_s`` [s]."""
        self._add(TRANSITIONS, [coerce_row(TRANSITIONS, (t_host_s, old, new, reason))])

    def add_gap(
        self, stream: str, start_index: int, count: int, t_host_s: float, cause: str
    ) -> None:
        """Add a gap: ``count`` samples/frames of ``stream`` lost from ``start_index``."""
        row = coerce_row(GAPS, (stream, start_index, count, t_host_s, cause))
        if row[2] < 1:
            raise SessionError(f"gaps row 0, column count: {count} must be >= 1")
        self._add(GAPS, [row])

    def add_clock_probe(self, mcu_raw_us: int, mcu_unwrapped_us: int, host_s: float) -> None:
        """Add a clock-sync pair: probe time (raw and unwrapped) [us] ↔ host time [s]."""
        self._add(CLOCK_PROBES, [coerce_row(CLOCK_PROBES, (mcu_raw_us, mcu_unwrapped_us, host_s))])

    def add_live_parameters(self, t_host_s: float, parameters: Mapping[str, float | None]) -> int:
        """Add live parameter estimates at ``t_host_s`` [s], one row per name.

        Names should carry their unit (``d_p_mm``, ``f_r_n``, ``t_r_s``, ``e_kpa``,
        ``eta_n_s_per_mm2``, ``tau_s``); None or NaN is stored as NULL.
        """
        rows = [(t_host_s, name, value) for name, value in parameters.items()]
        return self._add(LIVE_PARAMETERS, coerce_rows(LIVE_PARAMETERS, rows))

    def _add(self, table: Table, rows: list[tuple[Any, ...]]) -> int:
        if not rows:
            return 0
        with self._cond:
            self._check_writable()
            self._pending[table.name].extend(rows)
            now = time.monotonic()
            if self._pending_since is None:
                self._pending_since = now  # the commit thread finds it at its next look
                if self._timer_idle:  # ... or, when it does not look, is woken
                    self._cond.notify_all()
            elif now - self._pending_since >= self._commit_after_s:
                try:
                    self._commit_locked()
                except SessionError as exc:
                    # The rows are buffered (this call succeeded); the next call reports it.
                    self._failure = exc
        return len(rows)

    # ------------------------------------------------------------------ committing
    def commit(self) -> None:
        """Commit every buffered row now (durable per ``options.synchronous``)."""
        with self._cond:
            self._check_open()
            self._raise_failure()
            self._commit_locked()

    flush = commit

    def _commit_locked(self) -> None:
        if self._pending_since is None:
            return
        t0 = time.monotonic()
        conn = self._conn
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                for table in TABLES:
                    rows = self._pending[table.name]
                    if rows:
                        conn.executemany(table.insert_sql, rows)
                conn.execute("COMMIT")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            raise SessionError(
                f"{self.db_path}: commit failed, {self._count_pending()} rows kept in memory "
                f"for retry: {exc}"
            ) from exc
        for table in TABLES:
            self.stats.rows[table.name] += len(self._pending[table.name])
            self._pending[table.name] = []
        self._pending_since = None
        self.stats.commits += 1
        t_end = time.monotonic()
        self.stats.max_commit_s = max(self.stats.max_commit_s, t_end - t0)
        if self.stats.commit_log is not None:
            self.stats.commit_log.append((t_end, dict(self.stats.rows)))

    def _count_pending(self) -> int:
        return sum(len(rows) for rows in self._pending.values())

    def _commit_loop(self) -> None:
        commit_after_s = self._commit_after_s
        with self._cond:
            while not self._closed:
                if self._pending_since is None:
                    self._timer_idle = self._idle_poll_s is None
                    self._cond.wait(self._idle_poll_s)
                    self._timer_idle = False
                    continue
                remaining = self._pending_since + commit_after_s - time.monotonic()
                if remaining > 0:
                    self._cond.wait(remaining)
                    continue
                try:
                    self._commit_locked()
                except SessionError as exc:
                    self._failure = exc
                    # Retry one interval later; the caller sees the error on its next call.
                    self._cond.wait(commit_after_s)
                except BaseException as exc:  # pragma: no cover - defensive
                    self._failure = exc
                    return

    def _raise_failure(self) -> None:
        failure, self._failure = self._failure, None
        if failure is not None:
            if isinstance(failure, SessionError):
                raise SessionError(str(failure)) from failure
            raise SessionError(f"{self.db_path}: background commit failed: {failure}") from failure

    def _check_open(self) -> None:
        if self._closed:
            raise SessionError(f"{self.directory}: session writer is closed")

    def _check_writable(self) -> None:
        self._check_open()
        if self._state is not SessionState.RECORDING:
            raise SessionError(
                f"{self.directory}: session is finished ({self._state.value}); no rows can be added"
            )
        self._raise_failure()

    # ------------------------------------------------------------------ ending
    def write_summary(self, summary: Mapping[str, Any]) -> Path:
        """Write ``summary.json`` atomically (temp file, fsync, rename, directory fsync)."""
        with self._cond:
            self._check_open()
        layout.write_json_atomic(self.summary_path, summary, what="summary")
        return self.summary_path

    def finish(
        self,
        status: str,
        summary: Mapping[str, Any] | None = None,
        meta: Mapping[str, str] | None = None,
    ) -> None:
        """End the recording: commit all rows, write the summary, store the final state.

        Parameters
        ----------
        status : {"complete", "aborted", "fault"}
            How the measurement ended.
        summary : mapping, optional
            Final results, written atomically to ``summary.json`` before the state is
            stored (so a ``complete`` session always has its summary).
        meta : mapping, optional
            More ``meta`` table entries stored with the final state.

        The final commit is made with ``synchronous=FULL``: the finished session is durable
        against power loss whatever ``options.synchronous`` is.
        """
        try:
            state = SessionState(status)
        except ValueError:
            state = SessionState.RECORDING
        if state not in FINAL_STATES:
            raise SessionError(
                f"finish status {status!r} is not one of "
                + ", ".join(sorted(s.value for s in FINAL_STATES))
            )
        with self._cond:
            self._check_writable()
            self._commit_locked()
            if summary is not None:
                layout.write_json_atomic(self.summary_path, summary, what="summary")
            try:
                self._conn.execute("PRAGMA synchronous=FULL")
                self._conn.execute("BEGIN IMMEDIATE")
                self._conn.executemany(
                    "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                    [
                        ("state", state.value),
                        ("finished_utc", layout.utc_now_iso()),
                        ("finished_monotonic_s", repr(time.monotonic())),
                        *(meta or {}).items(),
                    ],
                )
                self._conn.execute("COMMIT")
            except sqlite3.Error as exc:
                if self._conn.in_transaction:
                    self._conn.execute("ROLLBACK")
                raise SessionError(f"{self.db_path}: cannot store final state: {exc}") from exc
            self._state = state

    def close(self) -> None:
        """Commit buffered rows, stop the commit thread, close the database, drop the lock.

        Closing a session that was not finished leaves it ``recording`` with no writer:
        readers report it as ``interrupted``. A finished session is converted from WAL to
        a single self-contained file (rollback journal) when no reader has it open.
        Idempotent.
        """
        with self._cond:
            if self._closed:
                return
            error: SessionError | None = None
            try:
                self._commit_locked()
            except SessionError as exc:
                error = exc
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
        try:
            if self._state in FINAL_STATES:
                self._to_single_file()
            self._conn.close()
        finally:
            self._lock.release()
        if error is not None:
            raise error

    def _to_single_file(self) -> None:
        try:
            self._conn.execute("PRAGMA busy_timeout=100")
            self._conn.execute("PRAGMA journal_mode=DELETE")
        except sqlite3.OperationalError as exc:
            _log.info("%s stays in WAL mode (a reader has it open): %s", self.db_path, exc)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _create_database(
    path: Path, options: StorageOptions, meta: Mapping[str, str]
) -> sqlite3.Connection:
    """Create the session database in WAL mode with the schema and ``meta`` rows."""
    try:
        conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    except sqlite3.Error as exc:
        raise SessionError(f"{path}: cannot create database: {exc}") from exc
    try:
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise SessionError(f"{path}: the file system does not support WAL mode (got {mode})")
        conn.execute(f"PRAGMA synchronous={options.synchronous}")
        conn.execute("PRAGMA busy_timeout=5000")
        conn.execute("BEGIN IMMEDIATE")
        for statement in schema_ddl():
            conn.execute(statement)
        conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", list(meta.items()))
        conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        conn.execute("COMMIT")
    except sqlite3.Error as exc:
        conn.close()
        raise SessionError(f"{path}: cannot create database: {exc}") from exc
    except BaseException:
        conn.close()
        raise
    return conn
