"""Reading one session directory into a :class:`~stipi_daemon.report.inputs.ReportInput`.

The I/O side of the report's data: the session's rows are read in one database snapshot
through :class:`~stipi_daemon.storage.SessionReader` (read-only, so a report never changes
a session), with the manifest (configuration, calibration, session metadata),
``summary.json``, the representative frames (:mod:`stipi_daemon.report.frames`) and the
newest analysis of the recording that ``stipi-daemon analyze`` wrote beside it
(``analysis-*.json``: for a session that ended early, the results its recording allows).
Frames are timed by their capture time, as the pipeline and an offline replay time them.
Nothing is computed here.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

import numpy as np

from stipi_daemon.errors import SessionError
from stipi_daemon.report.frames import read_representative_frames
from stipi_daemon.report.inputs import GapRecord, ReportInput
from stipi_daemon.storage import SessionReader

__all__ = ["ANALYSIS_FORMAT", "load_report_input", "read_rescued_analysis"]

#: ``format`` of the documents ``stipi-daemon analyze`` writes (app/analyze.OUTPUT_FORMAT).
ANALYSIS_FORMAT: Final = "stipi-offline-analysis"


def read_rescued_analysis(directory: Path, session_id: str) -> tuple[str, Mapping[str, Any]] | None:
    """The newest ``analysis-*.json`` of this session beside it: (file name, its summary).

    Files that cannot be read, are not an analysis document of this session, or hold no
    summary are passed over (an analysis beside the session never stops its report).
    """
    for path in sorted(directory.glob("analysis-*.json"), reverse=True):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(doc, dict) or doc.get("format") != ANALYSIS_FORMAT:
            continue
        source = doc.get("input")
        summary = doc.get("summary")
        if not isinstance(source, dict) or source.get("session_id") != session_id:
            continue
        if isinstance(summary, dict):
            return path.name, summary
    return None


def load_report_input(directory: str | Path) -> ReportInput:
    """Read what the report of the session in ``directory`` shows.

    Raises
    ------
    SessionError
        The directory is not a readable session, or its representative frames are damaged.
    """
    with SessionReader(directory) as reader:
        status = reader.status.value
        with reader.snapshot():
            frames = reader.frames()
            force = reader.force_samples()
            transitions = tuple(reader.transitions())
            gaps = reader.gaps()
        summary = reader.summary
        manifest = reader.manifest
        session_id = reader.session_id
        path = reader.directory
        metadata, metadata_problem = _metadata(reader)
    calibration = manifest.get("calibration")
    config = manifest.get("config")
    rescued = read_rescued_analysis(path, session_id)
    return ReportInput(
        session_id=session_id,
        status=status,
        created_utc=str(manifest.get("created_utc")) if manifest.get("created_utc") else None,
        frame_seq=np.asarray(frames["seq"], dtype=np.int64),
        frame_times_s=np.asarray(frames["t_capture_host_s"], dtype=np.float64),
        s_k_px=np.asarray(frames["s_k"], dtype=np.float64),
        force_times_s=np.asarray(force["t_host_s"], dtype=np.float64),
        force_n=np.asarray(force["force_n"], dtype=np.float64),
        transitions=transitions,
        summary=summary,
        config=config if isinstance(config, dict) else {},
        calibration=calibration if isinstance(calibration, dict) else {},
        representative=read_representative_frames(path),
        rescued=None if rescued is None else rescued[1],
        rescued_file=None if rescued is None else rescued[0],
        metadata=metadata,
        metadata_problem=metadata_problem,
        gap_records=tuple(
            GapRecord(
                str(g["stream"]),
                int(g["start_index"]),
                int(g["count"]),
                float(g["t_host_s"]),
                str(g["cause"]),
            )
            for g in gaps
        ),
    )


def _metadata(reader: SessionReader) -> tuple[dict[str, str | None] | None, str | None]:
    """The manifest's metadata (None: recorded before it was kept) and why it is unreadable.

    A malformed record does not stop the report: the page says what is wrong with it.
    """
    if "metadata" not in reader.manifest:
        return None, None
    try:
        return dict(reader.metadata), None
    except SessionError as exc:
        return None, str(exc)
