"""Session storage: one directory per measurement, an SQLite database in WAL mode inside.

``<root>/<session_id>/`` holds ``session.sqlite`` (every force sample, frame, event,
transition, gap, clock probe and live parameter), ``manifest.json`` (format, versions,
config, calibration, firmware; written at creation), ``summary.json`` (final results,
written atomically at the end), optionally ``video.mkv`` (the camera stream, recorded by
:mod:`.video`, read back by :mod:`.video_readback`), and ``writer.lock`` while a writer is
alive. :class:`SessionWriter` records, :class:`SessionReader` reads (also while another
process records), :func:`export_session` writes CSV/Parquet. This package is an adapter:
it stores what it is given and computes nothing. The layout, schema and durability
argument are in ``docs/storage.md``.
"""

from stipi_daemon.storage.export import EXPORT_FORMATS, export_session
from stipi_daemon.storage.layout import (
    DB_NAME,
    DEFAULT_MIN_FREE_BYTES,
    DEFAULT_ROOT,
    LOCK_NAME,
    MANIFEST_NAME,
    SUMMARY_NAME,
    VIDEO_NAME,
)
from stipi_daemon.storage.reader import (
    IntegrityReport,
    SessionListing,
    SessionReader,
    list_sessions,
)
from stipi_daemon.storage.schema import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SCHEMA_VERSION,
    TABLES,
    Event,
    ForceSampleRow,
    FrameRow,
    SessionState,
    Transition,
)
from stipi_daemon.storage.writer import (
    DEFAULT_COMMIT_INTERVAL_S,
    SessionWriter,
    StorageOptions,
)

__all__ = [
    "DB_NAME",
    "DEFAULT_COMMIT_INTERVAL_S",
    "DEFAULT_MIN_FREE_BYTES",
    "DEFAULT_ROOT",
    "EXPORT_FORMATS",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "LOCK_NAME",
    "MANIFEST_NAME",
    "SCHEMA_VERSION",
    "SUMMARY_NAME",
    "TABLES",
    "VIDEO_NAME",
    "Event",
    "ForceSampleRow",
    "FrameRow",
    "IntegrityReport",
    "SessionListing",
    "SessionReader",
    "SessionState",
    "SessionWriter",
    "StorageOptions",
    "Transition",
    "export_session",
    "list_sessions",
]
