"""Hashes that make a study dataset's provenance: a session's data, analysis settings.

``data_hash`` is a SHA-256 over what a session recorded, not over its files' bytes: the
manifest (parsed, as canonical JSON), the ``meta`` rows and every row of every table of
``session.sqlite`` in insertion order, and the video file's bytes. It is therefore the same
for a copy of the session on another disk, for a database the writer converted from WAL
to a single file, and whatever the files' modification times; it changes when a row, the
manifest, the stored state or the video changes. ``summary.json`` is not part of it: the
summary is the recorded analysis of the data (hashed on its own, :func:`file_hash`).

``settings_hash`` is a SHA-256 over canonical JSON (sorted keys, no spaces) of the
settings an analysis ran with; :func:`recorded_settings` names those the daemon recorded
in a session's manifest (the config's ``analysis``, ``imaging`` and ``measurement``
sections and the calibration in force).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from stipi_daemon.storage.reader import SessionReader
from stipi_daemon.storage.schema import tables_of_version

#: Prefix of every hash value (the algorithm, as in ``sha256:<hex>``).
HASH_PREFIX: Final = "sha256:"
_CHUNK_BYTES: Final = 1 << 20


def canonical_json(value: Any) -> bytes:
    """``value`` as canonical JSON bytes: sorted keys, no spaces, UTF-8, NaN refused."""
    return json.dumps(
        value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode("utf-8")


def settings_hash(settings: Mapping[str, Any]) -> str:
    """``sha256:<hex>`` of the canonical JSON of ``settings``."""
    return HASH_PREFIX + hashlib.sha256(canonical_json(dict(settings))).hexdigest()


def recorded_settings(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """The analysis settings a session's manifest recorded: the config's ``analysis``,
    ``imaging`` and ``measurement`` sections and the calibration (missing ones null)."""
    config = manifest.get("config")
    config = config if isinstance(config, dict) else {}
    return {
        "analysis": config.get("analysis"),
        "imaging": config.get("imaging"),
        "measurement": config.get("measurement"),
        "calibration": manifest.get("calibration"),
    }


def file_hash(path: Path) -> str | None:
    """``sha256:<hex>`` of a file's bytes, or None when there is no such file."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while block := f.read(_CHUNK_BYTES):
                digest.update(block)
    except FileNotFoundError:
        return None
    return HASH_PREFIX + digest.hexdigest()


def data_hash(reader: SessionReader) -> str:
    """``sha256:<hex>`` of an open session's data (see the module doc).

    Rows are hashed as the ``repr`` of their stored Python values (ints, floats in their
    shortest round-trip form, text, None), table by table, each table's name and row count
    delimiting it, so that no two different sessions share the byte stream hashed.

    Raises
    ------
    SessionError
        A table cannot be read.
    """
    digest = hashlib.sha256()
    digest.update(b"manifest\0" + canonical_json(reader.manifest) + b"\0")
    digest.update(b"meta\0" + canonical_json(sorted(reader.meta().items())) + b"\0")
    with reader.snapshot():
        for table in tables_of_version(reader.schema_version):
            n = 0
            digest.update(table.name.encode() + b"\0")
            for row in reader.iter_rows(table):
                digest.update(repr(row).encode("utf-8"))
                digest.update(b"\n")
                n += 1
            digest.update(f"\0{n}\0".encode())
    video = reader.video_path
    video_digest = file_hash(video) if video is not None else None
    digest.update(b"video\0" + (video_digest or "none").encode())
    return HASH_PREFIX + digest.hexdigest()
