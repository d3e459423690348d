"""What the report reads from one recorded session: :class:`ReportInput`.

A session's rows (frames, force samples, transitions), its manifest's configuration and
calibration, ``summary.json`` and its representative frames, as plain arrays and mappings,
with the few times every figure needs (T_0, first and last sample). It is pure: reading a
session directory into it is :mod:`.load`'s job. The helpers :func:`value_at`,
:func:`number_at` and :func:`flags_at` read a nested summary that may lack any level, for
the modules that build figures and tables from it. Times are on the session clock [s].
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.frames import RepresentativeFrame
from stipi_daemon.storage.schema import Transition

__all__ = ["FloatArray", "GapRecord", "ReportInput", "flags_at", "number_at", "value_at"]

FloatArray = npt.NDArray[np.float64]


def value_at(d: Any, *keys: str) -> Any:
    """``d[k1][k2]...``, or None as soon as a level is missing or not a mapping."""
    for k in keys:
        if not isinstance(d, Mapping):
            return None
        d = d.get(k)
    return d


def number_at(d: Any, *keys: str) -> float | None:
    """:func:`value_at` as a float, or None unless it is a finite number (not a bool)."""
    v = value_at(d, *keys)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def flags_at(d: Any) -> tuple[str, ...]:
    """``d["flags"]`` as strings; empty when ``d`` has no list of flags."""
    v = value_at(d, "flags")
    return tuple(str(f) for f in v) if isinstance(v, list) else ()


@dataclass(frozen=True)
class GapRecord:
    """One row of the session's ``gaps`` table: samples or frames the session lacks.

    Attributes
    ----------
    stream : str
        ``force`` or ``frames``.
    start_index : int
        First missing sample index or frame number.
    count : int
        Samples or frames missing.
    t_s : float
        Session time the gap was recorded at [s].
    cause : str
        Why (``link``, ``probe``, ``camera``, ``processing_behind``, ...).
    """

    stream: str
    start_index: int
    count: int
    t_s: float
    cause: str


@dataclass(frozen=True)
class ReportInput:
    """One recorded session, as the report needs it.

    Attributes
    ----------
    session_id, status : str
        The session's id and final state (``complete``, ``fault``, ``interrupted``...).
    created_utc : str or None
        Creation time (ISO 8601, UTC).
    frame_seq : numpy.ndarray
        Camera frame numbers (``frames.seq``).
    frame_times_s : numpy.ndarray
        Frame capture times (``frames.t_capture_host_s``) [s], the times the pipeline used.
    s_k_px : numpy.ndarray
        S_k of those frames, Eq. (2) [px].
    force_times_s, force_n : numpy.ndarray
        Force samples (``force_samples.t_host_s`` [s], ``force_n`` [N]; NaN when lost).
    transitions : tuple of Transition
        State-machine transitions in order.
    summary : mapping or None
        ``summary.json`` (None when the session has none).
    config : mapping
        The configuration recorded in the manifest.
    calibration : mapping
        The calibration recorded in the manifest (``threshold_p``, ``roi``...).
    representative : tuple of RepresentativeFrame
        Representative raw frames stored with the session (may be empty).
    rescued : mapping or None
        The summary of the newest analysis of this recording written beside the session by
        ``stipi-daemon analyze`` (``analysis-*.json``), when there is one.
    rescued_file : str or None
        That file's name.
    metadata : mapping or None
        Who and what the session is of, from the manifest's ``metadata`` (``subject``,
        ``site``, ``operator``, ``note``; a field not given is None); None for a session
        recorded before metadata was kept.
    metadata_problem : str or None
        Why the manifest's ``metadata`` could not be read (one line), when it could not.
    gap_records : tuple of GapRecord
        The session's ``gaps`` rows in order (lost samples, frames dropped by the camera,
        frames stored as gaps for coming too late).
    """

    session_id: str
    status: str
    created_utc: str | None
    frame_seq: npt.NDArray[np.int64]
    frame_times_s: FloatArray
    s_k_px: FloatArray
    force_times_s: FloatArray
    force_n: FloatArray
    transitions: tuple[Transition, ...]
    summary: Mapping[str, Any] | None
    config: Mapping[str, Any]
    calibration: Mapping[str, Any]
    representative: tuple[RepresentativeFrame, ...] = ()
    rescued: Mapping[str, Any] | None = None
    rescued_file: str | None = None
    metadata: Mapping[str, str | None] | None = None
    metadata_problem: str | None = None
    gap_records: tuple[GapRecord, ...] = ()

    def __post_init__(self) -> None:
        if not (self.frame_seq.shape == self.frame_times_s.shape == self.s_k_px.shape):
            raise AnalysisError(
                f"session {self.session_id}: {self.frame_seq.size} frame numbers, "
                f"{self.frame_times_s.size} frame times, {self.s_k_px.size} S_k values"
            )
        if self.force_times_s.shape != self.force_n.shape:
            raise AnalysisError(
                f"session {self.session_id}: {self.force_times_s.size} force times but "
                f"{self.force_n.size} forces"
            )

    @property
    def results(self) -> Mapping[str, Any] | None:
        """``summary["results"]``, or None when the session has no results."""
        r = value_at(self.summary, "results")
        return r if isinstance(r, Mapping) else None

    @property
    def t0_s(self) -> float | None:
        """T_0 the analysis used [s]: the results' one, else the refined or detected one."""
        for keys in (
            ("results", "pitting", "t0_s"),
            ("measurement", "t0_refined_s"),
            ("measurement", "t0_s"),
        ):
            v = number_at(self.summary, *keys)
            if v is not None:
                return v
        return None

    @property
    def t_end_s(self) -> float:
        """Last sample time of either stream [s] (0 when there is none)."""
        ends = [float(np.max(a)) for a in (self.frame_times_s, self.force_times_s) if a.size]
        return max(ends) if ends else 0.0

    @property
    def t_start_s(self) -> float:
        """First sample time of either stream [s] (0 when there is none)."""
        starts = [float(np.min(a)) for a in (self.frame_times_s, self.force_times_s) if a.size]
        return min(starts) if starts else 0.0
