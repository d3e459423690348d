"""Session directory layout: file names, manifest, atomic JSON files, free space.

This module owns what a session directory holds besides the database: the names of its
files, the manifest (built at creation, validated on every read), atomic writing of JSON
files (``manifest.json``, ``summary.json``), session identifiers, and the free-space check
done before a session is created. It does not touch the SQLite database (:mod:`.writer`,
:mod:`.reader`) nor the writer lock (:mod:`.lock`).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import re
import secrets
import shutil
import socket
import sqlite3
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Final

from stipi_daemon import __version__
from stipi_daemon.errors import SessionError
from stipi_daemon.storage.metadata import check_metadata
from stipi_daemon.storage.schema import FORMAT_NAME, FORMAT_VERSION, SCHEMA_VERSION, to_jsonable

DB_NAME: Final = "session.sqlite"
MANIFEST_NAME: Final = "manifest.json"
SUMMARY_NAME: Final = "summary.json"
VIDEO_NAME: Final = "video.mkv"
LOCK_NAME: Final = "writer.lock"

#: Default root of the session directories, relative to the working directory.
DEFAULT_ROOT: Final = Path("sessions")
#: Default minimum free space on the session's file system before a session is created [B].
DEFAULT_MIN_FREE_BYTES: Final = 512 * 1024 * 1024

_SESSION_ID_RE: Final = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


def new_session_id(now: datetime | None = None) -> str:
    """A new session id: UTC time to the second and 6 random hex digits.

    Example: ``20250114T093012Z-3fa9c1``. Ids sort by creation time.
    """
    now = now or datetime.now(UTC)
    return f"{now.astimezone(UTC):%Y%m%dT%H%M%SZ}-{secrets.token_hex(3)}"


def check_session_id(session_id: str) -> str:
    """Return ``session_id`` if it is a safe directory name, else raise :class:`SessionError`."""
    if not _SESSION_ID_RE.fullmatch(session_id):
        raise SessionError(
            f"session id {session_id!r} is not allowed: use 1-128 letters, digits, '.', '_' "
            "or '-', starting with a letter or digit"
        )
    return session_id


def utc_now_iso() -> str:
    """Current UTC time as ISO 8601 with microseconds and a ``Z`` suffix."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError("unreachable")  # pragma: no cover


def check_free_space(root: Path, min_free_bytes: int, setting: str = "min_free_bytes") -> int:
    """Raise :class:`SessionError` unless ``root``'s file system has ``min_free_bytes`` free.

    Parameters
    ----------
    root : Path
        Existing directory the session will be created in.
    min_free_bytes : int
        Required free space [B] (``0`` disables the check).
    setting : str
        The setting the requirement came from, named in the error so that the user knows
        what to change (the daemon: ``config field storage.min_free_mb = 100 MB``).

    Returns
    -------
    int
        Free space available to this user [B].
    """
    free_b = shutil.disk_usage(root).free
    if free_b < min_free_bytes:
        raise SessionError(
            f"not enough free disk space for a new session in {root}: {_fmt_bytes(free_b)} "
            f"free, {_fmt_bytes(min_free_bytes)} required ({setting})"
        )
    return free_b


def software_versions(extra: Mapping[str, str | None] | None = None) -> dict[str, str | None]:
    """Versions of the software that records a session (``None`` if a module is missing).

    Parameters
    ----------
    extra : mapping, optional
        Further entries supplied by the caller, which knows what produced the data it
        stores; the daemon adds ``sk_kernel``, the routine that counted S_k (see
        :func:`stipi_daemon.analysis.imaging.sk_kernel`; every routine gives identical
        counts). Storage records them as given.
    """
    import numpy

    try:
        import cv2

        opencv: str | None = str(cv2.__version__)
    except ImportError:  # pragma: no cover - opencv is a dependency
        opencv = None
    versions: dict[str, str | None] = {
        "stipi_daemon": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "opencv": opencv,
        "sqlite": sqlite3.sqlite_version,
    }
    versions.update(extra or {})
    return versions


def build_manifest(
    *,
    session_id: str,
    created_utc: str,
    created_monotonic_s: float,
    created_unix_s: float,
    config: object,
    calibration: object,
    firmware: object | None,
    video: bool,
    commit_interval_s: float,
    synchronous: str,
    software: Mapping[str, str | None] | None = None,
    metadata: Mapping[str, str | None] | None = None,
) -> dict[str, Any]:
    """The manifest of a new session (plain JSON types).

    ``software`` adds the caller's entries to the manifest's software versions
    (:func:`software_versions`). ``metadata`` (subject, site, operator, note;
    :mod:`.metadata`) is checked and stored as ``manifest["metadata"]``, every field
    present (null when not given).

    ``created_monotonic_s`` and ``created_unix_s`` are read together at creation: they tie
    the host monotonic clock of every ``t_host_s`` column to UTC
    (``unix_s = t_host_s - created_monotonic_s + created_unix_s``, up to the host's
    clock adjustments during the session).
    """
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "schema_version": SCHEMA_VERSION,
        "session_id": session_id,
        "created_utc": created_utc,
        "clock_reference": {
            "monotonic_s": created_monotonic_s,
            "unix_s": created_unix_s,
        },
        "hostname": socket.gethostname(),
        "config": to_jsonable(config, "config"),
        "calibration": to_jsonable(calibration, "calibration"),
        "firmware": None if firmware is None else to_jsonable(firmware, "firmware"),
        "software": software_versions(software),
        "files": {
            "database": DB_NAME,
            "summary": SUMMARY_NAME,
            "video": VIDEO_NAME if video else None,
        },
        "storage": {"commit_interval_s": commit_interval_s, "synchronous": synchronous},
        "metadata": check_metadata(metadata or {}, "session"),
    }


_MANIFEST_FIELDS: Final[dict[str, tuple[type, ...]]] = {
    "session_id": (str,),
    "created_utc": (str,),
    "hostname": (str,),
    "config": (dict,),
    "calibration": (dict,),
    "firmware": (dict, type(None)),
    "software": (dict,),
    "files": (dict,),
}


def load_json_object(path: Path, what: str) -> dict[str, Any]:
    """Read a JSON object from ``path``; :class:`SessionError` names file and problem."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SessionError(f"{path}: {what} is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"{path}: cannot read {what}: {exc}") from None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError(
            f"{path}: {what} is not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})"
        ) from None
    if not isinstance(value, dict):
        raise SessionError(f"{path}: {what} must be a JSON object, got {type(value).__name__}")
    return value


def load_manifest(path: Path) -> dict[str, Any]:
    """Read and validate ``manifest.json``: format name, version and required fields."""
    manifest = load_json_object(path, "manifest")
    fmt = manifest.get("format")
    if fmt != FORMAT_NAME:
        raise SessionError(f"{path}: format is {fmt!r}, expected {FORMAT_NAME!r}")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise SessionError(
            f"{path}: format_version {version!r} is not supported "
            f"(this stipi-daemon reads version {FORMAT_VERSION})"
        )
    for key, types in _MANIFEST_FIELDS.items():
        if key not in manifest:
            raise SessionError(f"{path}: field {key!r} is missing")
        if not isinstance(manifest[key], types):
            raise SessionError(
                f"{path}: field {key!r} has type {type(manifest[key]).__name__}, expected "
                + " or ".join("null" if t is type(None) else t.__name__ for t in types)
            )
    return manifest


def write_json_atomic(path: Path, value: object, *, what: str = "value") -> None:
    """Write ``value`` as JSON to ``path`` atomically and durably.

    The text goes to ``<path>.tmp`` (flushed and fsynced), is renamed over ``path``
    (``os.replace`` is atomic on POSIX), and the directory is fsynced so that the rename
    itself survives a power loss. A reader therefore sees either the old file or the whole
    new one, never a partial file; a failed write (disk full) removes ``<path>.tmp``.
    """
    text = json.dumps(to_jsonable(value, what), indent=2, allow_nan=False) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_directory(path.parent)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)  # a disk-full stop leaves no partial file behind
        raise SessionError(f"{path}: cannot write {what}: {exc}") from exc


def fsync_directory(directory: Path) -> None:
    """fsync a directory so that file creations and renames in it are durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
