"""Reading one session directory into a :class:`~stipi_daemon.report.inputs.ReportInput`.

The I/O side of the report's data: the session's rows are read in one database snapshot
through :class:`~stipi_daemon.storage.SessionReader` (read-only, so a report never changes
a session), with the manifest, ``summary.json`` and the representative frames
(:mod:`stipi_daemon.report.frames`). Frames are timed by their capture time, as the
pipeline and an offline replay time them. Nothing is computed here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stipi_daemon.report.frames import read_representative_frames
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.storage import SessionReader

__all__ = ["load_report_input"]


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
        summary = reader.summary
        manifest = reader.manifest
        session_id = reader.session_id
        path = reader.directory
    calibration = manifest.get("calibration")
    config = manifest.get("config")
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
    )
