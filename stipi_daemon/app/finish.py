"""Finishing a measurement: summary, run statistics, representative frames, report.

When the acquisition loop (:mod:`stipi_daemon.app.acquisition`) ends, the daemon writes
``summary.json`` (:func:`session_summary` with :func:`run_stats` under ``run``), stores the
representative raw frames the keeper chose (:func:`store_frames`, through
:mod:`stipi_daemon.report.frames`), closes the session with its final status
(:func:`finish_session`; best effort after a storage failure), prints the results and
writes the session's report (:func:`write_report`; a report that cannot be drawn is noted,
never costs the session). None of these raises for a frame or report failure: what was
recorded is kept.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from stipi_daemon import __version__
from stipi_daemon.analysis.validity import assess_validity
from stipi_daemon.app.console import (
    VERDICT_STYLES,
    OperatorConsole,
    format_results,
    verdict_status,
)
from stipi_daemon.app.devices import Devices
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import SessionError, StipiError
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase
from stipi_daemon.report.frames import write_representative_frames
from stipi_daemon.storage.writer import SessionWriter

__all__ = [
    "finish_session",
    "percentiles",
    "print_results",
    "run_stats",
    "session_summary",
    "storage_failure",
    "store_frames",
    "write_report",
]


def session_summary(pipeline: MeasurementPipeline, truth: dict[str, Any] | None) -> dict[str, Any]:
    """What ``summary.json`` holds about the measurement (the run's statistics come later).

    Parameters
    ----------
    pipeline : MeasurementPipeline
        The finished measurement.
    truth : dict or None
        A simulated scene's ground truth (stored as ``ground_truth``).
    """
    start, rel = pipeline.start, pipeline.release
    out: dict[str, Any] = {
        "status": "complete" if pipeline.phase == Phase.DONE else "fault",
        "phase": str(pipeline.phase),
        "end_reason": pipeline.state.end_reason,
        "measurement": None if start is None else asdict(start) | {"t0_refined_s": pipeline.t0_s},
        "measurement_flags": sorted(pipeline.state.flags),
        "results": None if pipeline.result is None else pipeline.result.to_dict(),
        "analysis_error": pipeline.analysis_error,
        "notes": list(pipeline.notes),
        "release": None if pipeline.release is None else pipeline.release.to_dict(),
        **assess_validity(
            pipeline.result,
            ended_done=pipeline.phase == Phase.DONE,
            end_reason=pipeline.state.end_reason,
            analysis_error=pipeline.analysis_error,
            invalid_reasons=None if rel is None else rel.invalid_reasons(),
            caveats=None if rel is None else rel.caveats(),
            extra_flags=() if rel is None else rel.flags,
        ),
    }
    if truth is not None:
        out["ground_truth"] = truth
    return out


def percentiles(values: list[float]) -> dict[str, float | None]:
    """Median, 99th percentile and maximum of ``values`` (None each when empty)."""
    if not values:
        return {"median": None, "p99": None, "max": None}
    a = np.asarray(values, dtype=np.float64)
    return {
        "median": float(np.median(a)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def run_stats(
    devices: Devices,
    *,
    clock: SessionClock,
    wall_s: float,
    counts: dict[str, int],
    latencies_s: list[float],
    merge_released_by_timeout: int,
    keeper: RepresentativeFrames,
) -> dict[str, Any]:
    """The run's statistics (``summary.json``'s ``run``); stores the representative frames.

    Parameters
    ----------
    devices : Devices
        The (closed) devices and the session.
    clock : SessionClock
        The session clock. On a simulated run's clock (which waits for the daemon) the
        statistics are the same on every machine: the wall time and the pace are not in
        them (the session's ``meta`` table has them, :func:`finish_session`).
    wall_s : float
        Wall time of the run [s].
    counts : dict
        Frames, force samples, gaps and dropped frames recorded.
    latencies_s : list of float
        Per frame: capture to the moment the measurement took its S_k [s of session time]
        (the row was added before, in the capture thread, and committed within
        :data:`~stipi_daemon.app.frame_measurer.COMMIT_SPACING_WALL_S` of wall time).
    merge_released_by_timeout : int
        Items the merger fed without waiting for the other stream.
    keeper : RepresentativeFrames
        The chosen frames, stored now in the session directory.
    """
    camera = devices.camera
    timing: dict[str, Any] = {"clock": "simulated"}
    if not clock.waits_for_daemon:
        timing = {"clock": "wall", "speed": clock.speed, "wall_s": wall_s}
    return {
        "software": __version__,
        **timing,
        **counts,
        "frame_latency_s": percentiles(latencies_s),
        "merge_released_by_timeout": merge_released_by_timeout,
        "probe": devices.probe.stats_dict(),
        "camera": camera.stats.as_dict() | {"source": camera.camera.metadata()},
        "representative_frames": store_frames(keeper, devices.writer.directory),
        "video": None if devices.recorder is None else devices.recorder.stats(),
    }


def note_video_left_out(summary: dict[str, Any], left_out: int) -> dict[str, Any]:
    """``summary`` with the frames left out of the session video (the encoders could not
    keep up on a real device's wall time) said in its verdict line and notes: their S_k is
    stored and in the results, but the video cannot show or count them again. The
    verdict's status stays (the results do not change); unchanged when none was left out.
    """
    if left_out <= 0:
        return summary
    said = (
        f"{left_out} frame{'s' if left_out != 1 else ''} left out of the session video (the "
        "encoder could not keep up): their S_k are stored and in the results, but a recount "
        "or the report cannot show them"
    )
    verdict = dict(summary.get("verdict") or {})
    verdict["line"] = f"{verdict.get('line', '').rstrip()} Video: {said}.".strip()
    return summary | {"verdict": verdict, "notes": [*summary.get("notes", []), said]}


def store_frames(keeper: RepresentativeFrames, session_dir: Path) -> list[str] | dict[str, str]:
    """Store the representative frames; a failure is recorded, never raised."""
    try:
        return [p.name for p in write_representative_frames(session_dir, keeper.selected())]
    except Exception as exc:
        return {"error": str(exc)}


def finish_session(
    writer: SessionWriter,
    status: str,
    summary: dict[str, Any],
    storage_error: SessionError | None,
    meta: dict[str, str] | None = None,
) -> None:
    """Write the final status and summary (and ``meta`` entries: how the run went on this
    machine, e.g. its wall time) and close the session.

    After a storage failure (``storage_error``) this is best effort: the disk that failed
    may still take the final state (``fault``, with the error), and nothing is raised.
    """
    if storage_error is None:
        writer.finish(status, summary, meta)
        writer.close()
        return
    with contextlib.suppress(SessionError):
        writer.finish("fault", summary | {"status": "fault", "storage_error": str(storage_error)})
    with contextlib.suppress(SessionError):
        writer.close()


def unfinished_summary(status: str, end_reason: str) -> dict[str, Any]:
    """``summary.json`` of a session whose measurement did not end (``status`` ``aborted``
    or ``fault``): why (``end_reason``), and the verdict it gives (no result)."""
    return {
        "status": status,
        "end_reason": end_reason,
        **assess_validity(None, ended_done=False, end_reason=end_reason),
    }


def storage_failure(writer: SessionWriter, storage_error: SessionError) -> SessionError:
    """The one-line error the daemon raises when storing failed while recording: the
    session's rows, or its video (caused by the recorder's
    :class:`~stipi_daemon.storage.video.VideoError`)."""
    from stipi_daemon.storage.video import VideoError

    cause = storage_error.__cause__ or storage_error
    what = "the session could not be stored"
    if isinstance(cause, VideoError):
        what = "the session video could not be written"
    return SessionError(
        f"{writer.directory}: recording stopped, {what} ({cause}); "
        "the rows and video frames committed before are kept"
    )


def print_results(
    console: OperatorConsole,
    summary: dict[str, Any],
    session_dir: Path,
    stop_error: BaseException | None,
) -> None:
    """Print the results, where the session is, the report's fate and a source's error.

    The verdict line is green only when the verdict is ``complete``."""
    style = VERDICT_STYLES[verdict_status(summary)]
    for line in format_results(summary):
        console.line(line, style if line.startswith("verdict: ") else None)
    console.line(f"session written to {session_dir}")
    console.line(write_report(session_dir))
    if stop_error is not None and isinstance(stop_error, StipiError):
        console.line(f"source ended with an error: {stop_error}")


def write_report(session_dir: Path) -> str:
    """Write the finished session's report; a failure is noted, never raised."""
    try:
        from stipi_daemon.report.write import write_session_report

        return f"report written to {write_session_report(session_dir).html_path}"
    except Exception as exc:
        note: Path | None = None
        with contextlib.suppress(Exception):
            from stipi_daemon.report.write import record_report_failure

            note = record_report_failure(session_dir, exc)
        return f"report not written: {exc}" + (f" (noted in {note})" if note else "")
