"""``study index``: sessions directories into a study dataset, incrementally.

Every session directory directly under each given root is read with
:class:`~stipi_daemon.storage.reader.SessionReader` and written as one file per table
(:mod:`.dataset`): its ``sessions`` row (metadata, counts, verdict, the probe, the data
hash; built from :func:`~stipi_daemon.storage.results_table.session_row`), its force
samples, its frames, and its ``results`` row of analysis version ``recorded`` (the
daemon's own ``summary.json`` with its provenance: the data hash, the hash of the analysis
settings recorded in the manifest, the version of the stipi-daemon that recorded it).

Incremental: ``study.json`` keeps, per session, its path, data hash, summary hash, the
size and modification time of its files and the dataset files written for it. A session
whose files have the same sizes and times as when it was indexed is not opened again; one
whose data hash and summary hash are unchanged is not rewritten; a changed one has its
files replaced (the old ones removed when its site, probe or date moved it to another
partition). Nothing is ever removed that indexing did not write, and sessions whose
directories have gone stay in the dataset.

A session that cannot be read is reported (path and reason, one line) and skipped; a
session a live writer is still recording is skipped with a note. A copy of an indexed
session (same id, same data hash, another path) is not indexed twice; a different session
under an id already taken gets the id plus 8 hex digits of its path's hash as its
``session_uid``.
"""

from __future__ import annotations

import hashlib
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import pyarrow as pa
import pyarrow.parquet as pq

from stipi_daemon import __version__
from stipi_daemon.errors import SessionError
from stipi_daemon.storage import layout
from stipi_daemon.storage.lock import WriterLock
from stipi_daemon.storage.reader import SessionReader, session_dirs
from stipi_daemon.storage.results_table import session_row
from stipi_daemon.storage.schema import VIDEO_FRAMES, SessionState
from stipi_daemon.study.dataset import (
    RECORDED,
    STUDY_FILE,
    UNKNOWN,
    StudyError,
    load_state,
    new_state,
    partition_dir,
    remove_files,
    results_row,
    save_state,
    to_table,
    utc_timestamp,
    write_parquet_atomic,
)
from stipi_daemon.study.hashing import data_hash, file_hash, recorded_settings, settings_hash

#: The lock file an indexing run holds in the dataset (``flock``; gone when it ends).
LOCK_NAME: Final = "index.lock"
#: Save ``study.json`` at least this often while indexing [s] (and at the end).
SAVE_INTERVAL_S: Final = 5.0
_DATE_RE: Final = re.compile(r"\d{4}-\d{2}-\d{2}")


@dataclass
class IndexReport:
    """What one ``study index`` run did.

    ``added``/``replaced`` hold session uids, ``unchanged`` counts sessions left as they
    were, ``skipped`` holds one line per session not indexed (``PATH: reason``) and
    ``notes`` one line per session deliberately passed over (recording, a copy).
    """

    dataset: Path
    added: list[str] = field(default_factory=list)
    replaced: list[str] = field(default_factory=list)
    unchanged: int = 0
    skipped: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def line(self) -> str:
        return (
            f"{self.dataset}: {len(self.added)} added, {len(self.replaced)} replaced, "
            f"{self.unchanged} unchanged, {len(self.skipped)} unreadable, "
            f"{len(self.notes)} passed over"
        )


def _stat_signature(directory: Path) -> dict[str, list[int] | None]:
    """Size [B] and modification time [ns] of every file that makes a session."""
    names = (
        layout.MANIFEST_NAME,
        layout.DB_NAME,
        layout.DB_NAME + "-wal",
        layout.SUMMARY_NAME,
        layout.VIDEO_NAME,
    )
    out: dict[str, list[int] | None] = {}
    for name in names:
        try:
            st = (directory / name).stat()
        except FileNotFoundError:
            out[name] = None
        else:
            out[name] = [st.st_size, st.st_mtime_ns]
    return out


def probe_id_of(manifest: Mapping[str, Any]) -> str:
    """The probe a session was recorded with: the manifest's ``firmware.probe_id``; for a
    session recorded before it existed, ``emulated`` for an emulated probe, else the
    transport recorded (``serial:/dev/ttyACM0``: a port, not a probe); else ``unknown``."""
    firmware = manifest.get("firmware")
    firmware = firmware if isinstance(firmware, dict) else {}
    given = firmware.get("probe_id")
    if isinstance(given, str) and given:
        return given
    transport = firmware.get("transport")
    if not isinstance(transport, str) or not transport:
        config = manifest.get("config")
        probe = config.get("probe") if isinstance(config, dict) else None
        tc = probe.get("transport") if isinstance(probe, dict) else None
        kind = tc.get("kind") if isinstance(tc, dict) else None
        return "emulated" if kind == "emulated" else UNKNOWN
    return "emulated" if transport.startswith("emulated:") else transport


def _date_of(created_utc: str) -> str:
    day = created_utc[:10]
    return day if _DATE_RE.fullmatch(day) else UNKNOWN


def _t0_host_s(reader: SessionReader) -> float | None:
    """Host monotonic time t_s counts from [s]: the session's creation, as the manifest
    records it, else its first sample or frame (None: nothing recorded)."""
    reference = reader.manifest.get("clock_reference")
    value = reference.get("monotonic_s") if isinstance(reference, dict) else None
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    span = reader.time_span_s()
    return None if span is None else span[0]


@dataclass(frozen=True)
class _Indexed:
    """The dataset tables of one session and where they go."""

    uid: str
    tables: dict[str, pa.Table]
    partition: tuple[str | None, str, str]  # site, probe, date


def _session_tables(reader: SessionReader, uid: str, hashes: tuple[str, str | None]) -> _Indexed:
    """The four dataset tables of one open session (see the module doc)."""
    manifest = reader.manifest
    row = session_row(reader)
    probe_id = probe_id_of(manifest)
    site = row["site"] or UNKNOWN
    t0 = _t0_host_s(reader)
    origin = 0.0 if t0 is None else t0
    software = manifest.get("software")
    version = software.get("stipi_daemon") if isinstance(software, dict) else None
    firmware = manifest.get("firmware")
    sessions = {
        **{k: [row[k]] for k in ("session_id", "status", "subject", "operator", "note")},
        **{k: [row[k]] for k in ("label", "duration_s", "verdict", "n_frames", "n_force_samples")},
        "session_uid": [uid],
        "path": [str(reader.directory.resolve())],
        "data_hash": [hashes[0]],
        "summary_hash": [hashes[1]],
        "site": [site],
        "probe_id": [probe_id],
        "transport": [firmware.get("transport") if isinstance(firmware, dict) else None],
        "created_utc": [utc_timestamp(row["created_utc"])],
        "t0_host_s": [t0],
        "has_video": [reader.video_path is not None and reader.video_path.is_file()],
        "n_video_frames": [reader.count(VIDEO_FRAMES)],
        "schema_version": [reader.schema_version],
        "package_version": [version],
        "indexed_utc": [utc_timestamp(layout.utc_now_iso())],
    }
    force = reader.force_samples()
    frames = reader.frames()
    try:
        summary = reader.summary
        error = None if summary is not None else f"no summary.json (session {row['status']})"
    except SessionError as exc:
        summary, error = None, f"summary unreadable: {exc}"
    result = results_row(
        session_uid=uid,
        analysis_version=RECORDED,
        data_hash=hashes[0],
        settings_hash=settings_hash(recorded_settings(manifest)),
        package_version=None if version is None else str(version),
        analysed_utc=reader.meta().get("finished_utc"),
        summary=summary,
        error=error,
    )
    tables = {
        "sessions": to_table("sessions", sessions),
        "force_samples": to_table(
            "force_samples",
            {
                "session_uid": [uid] * len(force),
                "seq": range(len(force)),
                "t_s": force["t_host_s"] - origin,
                **{k: force[k] for k in ("force_n", "sample_index", "adc_counts")},
                **{k: force[k] for k in ("t_mcu_raw_us", "t_mcu_us", "t_host_s")},
            },
        ),
        "frames": to_table(
            "frames",
            {
                "session_uid": [uid] * len(frames),
                "seq": frames["seq"],
                "t_s": frames["t_capture_host_s"] - origin,
                "s_k_px": frames["s_k"],
                **{k: frames[k] for k in ("t_capture_host_s", "t_host_s", "flags")},
            },
        ),
        "results": to_table("results", {k: [v] for k, v in result.items()}),
    }
    return _Indexed(uid, tables, (site, probe_id, _date_of(str(row["created_utc"]))))


def _write(dataset: Path, indexed: _Indexed) -> list[str]:
    """Write one session's tables; their paths relative to the dataset."""
    site, probe, date = indexed.partition
    written: list[str] = []
    for name, table in indexed.tables.items():
        analysis = RECORDED if name == "results" else None
        rel = partition_dir(name, site, probe, date, analysis) / f"{indexed.uid}.parquet"
        write_parquet_atomic(dataset / rel, table)
        written.append(rel.as_posix())
    return written


def _uid_for(
    sessions: Mapping[str, Any], session_id: str, path: str, digest: str
) -> tuple[str | None, str | None]:
    """The session_uid of a session (None and why when it is a copy of an indexed one)."""
    entry = sessions.get(session_id)
    if entry is None or entry.get("path") == path:
        return session_id, None
    if entry.get("data_hash") == digest:
        return None, f"{path}: a copy of {entry.get('path')} (same data), indexed as {session_id}"
    uid = f"{session_id}-{hashlib.sha256(path.encode()).hexdigest()[:8]}"
    return uid, None


def _still_indexed(
    dataset: Path, entry: Mapping[str, Any], digest: str, summary_digest: str | None
) -> bool:
    """Whether an indexed session's dataset files are there and of this data and summary."""
    same = (entry.get("data_hash"), entry.get("summary_hash")) == (digest, summary_digest)
    return same and all(_intact(dataset / f) for f in entry.get("files", []))


def _intact(path: Path) -> bool:
    """Whether a dataset file is there and a readable Parquet file (its footer and
    metadata; a truncated or overwritten file is not, and is written again)."""
    try:
        pq.read_metadata(path)
    except (OSError, pa.ArrowException):
        return False
    return True


def _open_dataset(dataset: Path) -> dict[str, Any]:
    """The dataset's state, a new one (directory created) if there is none yet."""
    if (dataset / STUDY_FILE).exists():
        return load_state(dataset)
    if dataset.exists() and (not dataset.is_dir() or any(dataset.iterdir())):
        raise StudyError(
            f"{dataset}: not a study dataset (no {STUDY_FILE}) and not empty: give a new "
            "or empty directory"
        )
    try:
        dataset.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StudyError(f"{dataset}: cannot create the dataset directory: {exc}") from exc
    state = new_state(__version__)
    save_state(dataset, state)
    return state


def index_sessions(
    roots: Sequence[Path],
    dataset: Path,
    *,
    on_session: Callable[[str], None] | None = None,
) -> IndexReport:
    """Index every session under ``roots`` into ``dataset`` (see the module doc).

    ``on_session`` is called with each session directory's path before it is looked at
    (progress display).

    Raises
    ------
    StudyError
        ``dataset`` is not a study dataset, or a dataset file cannot be written.
    SessionError
        A root does not exist (checked before anything is written).
    """
    directories = [d for root in roots for d in session_dirs(root)]
    _open_dataset(dataset)
    try:
        lock = WriterLock.acquire(dataset / LOCK_NAME, started_utc=layout.utc_now_iso())
    except SessionError as exc:
        busy = "another writer" in str(exc)
        raise StudyError(
            f"{dataset}: another `study index` is writing this dataset" if busy else str(exc)
        ) from None
    try:
        state = load_state(dataset)  # as the last writer left it
        return _index_all(dataset, state, directories, on_session)
    finally:
        lock.release()


def _index_all(
    dataset: Path,
    state: dict[str, Any],
    directories: Sequence[Path],
    on_session: Callable[[str], None] | None,
) -> IndexReport:
    """Index ``directories`` into the open dataset, saving its state as it goes."""
    sessions: dict[str, Any] = state["sessions"]
    by_path = {str(e.get("path")): uid for uid, e in sessions.items()}
    report = IndexReport(dataset)
    saved = time.monotonic()
    try:
        for directory in directories:
            if on_session is not None:
                on_session(str(directory))
            _index_one(dataset, sessions, by_path, directory, report)
            if time.monotonic() - saved > SAVE_INTERVAL_S:
                save_state(dataset, state)
                saved = time.monotonic()
    finally:
        save_state(dataset, state)
    return report


def _index_one(
    dataset: Path,
    sessions: dict[str, Any],
    by_path: dict[str, str],
    directory: Path,
    report: IndexReport,
) -> None:
    """Index one session directory into ``dataset``, recording what happened
    (``by_path``: session_uid of each indexed path, kept up to date)."""
    path = str(directory.resolve())
    signature = _stat_signature(directory)
    known = by_path.get(path)
    if known is not None and sessions[known].get("stat") == signature:
        if all(_intact(dataset / f) for f in sessions[known].get("files", [])):
            report.unchanged += 1
            return
    try:
        with SessionReader(directory) as reader:
            if reader.status is SessionState.RECORDING:
                report.notes.append(f"{path}: skipped, a writer is recording it")
                return
            digest = data_hash(reader)
            summary_digest = file_hash(reader.summary_path)
            uid, note = _uid_for(sessions, reader.session_id, path, digest)
            if uid is None:
                report.notes.append(str(note))
                return
            entry = sessions.get(uid)
            if entry is not None and _still_indexed(dataset, entry, digest, summary_digest):
                entry["stat"] = signature
                report.unchanged += 1
                return
            indexed = _session_tables(reader, uid, (digest, summary_digest))
            session_id = reader.session_id
    except SessionError as exc:
        report.skipped.append(f"{path}: {exc}")
        return
    written = _write(dataset, indexed)
    if entry is not None:
        remove_files(dataset, [f for f in entry.get("files", []) if f not in written])
    sessions[uid] = {
        "session_id": session_id,
        "path": path,
        "data_hash": digest,
        "summary_hash": summary_digest,
        "stat": signature,
        "files": written,
        "indexed_utc": layout.utc_now_iso(),
    }
    by_path[path] = uid
    (report.replaced if entry is not None else report.added).append(uid)
