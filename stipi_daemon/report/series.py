"""What the report derives from a stored time series: gaps, broken lines, outlier frames.

A session stores every frame's capture time and S_k and every force sample; it does not
store where the stream was interrupted. The report shows it: :func:`find_gaps` finds the
intervals longer than :data:`GAP_FACTOR` times the median sampling period, and
:func:`broken_line` inserts a NaN inside each so that a plotted line stops at a gap
instead of drawing a straight segment across it (matplotlib leaves NaN points out).
:func:`isolated_outliers` finds single frames far from their neighbours (a dark or bright
frame in the recovery), when the analysis did not record which frames it rejected.
:func:`gap_facts` says the same in words for the report's facts: the gaps the figures
shade and the gap records the session stored. Pure (no I/O, no drawing). Times are in
seconds, S_k in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.observation import GAP_FACTOR, find_frame_gaps, median_frame_period_s
from stipi_daemon.report.inputs import FloatArray, GapRecord, ReportInput

__all__ = [
    "GAP_FACTOR",
    "OUTLIER_MIN_FRACTION",
    "OUTLIER_NEIGHBOURS",
    "OUTLIER_NOISE_FACTOR",
    "TimeGap",
    "broken_line",
    "find_gaps",
    "gap_facts",
    "isolated_outliers",
]

#: Frames on each side whose median an outlier candidate is compared with.
OUTLIER_NEIGHBOURS: Final = 2
#: A frame is an outlier when it lies further than this many robust noise SDs from the
#: median of its neighbours...
OUTLIER_NOISE_FACTOR: Final = 8.0
#: ...and further than this fraction of the series' range (so smooth noise never counts).
OUTLIER_MIN_FRACTION: Final = 0.1


@dataclass(frozen=True)
class TimeGap:
    """An interval without samples.

    Attributes
    ----------
    start_s, end_s : float
        The last sample before the gap and the first after it [s].
    missing : int
        Samples expected in it at the median period and not recorded (at least 1).
    """

    start_s: float
    end_s: float
    missing: int

    @property
    def duration_s(self) -> float:
        """Length of the gap [s]."""
        return self.end_s - self.start_s


def find_gaps(times_s: FloatArray) -> tuple[TimeGap, ...]:
    """Intervals between consecutive samples longer than :data:`GAP_FACTOR` median periods.

    The analysis' gap rule (:func:`~stipi_daemon.analysis.observation.find_frame_gaps`),
    applied to any sampled series (frames or force samples), with the samples missing.

    Parameters
    ----------
    times_s : numpy.ndarray
        Sample times [s], increasing (non-finite times are ignored).

    Returns
    -------
    tuple of TimeGap
        In time order; empty with fewer than three samples or a zero median period.
    """
    t = times_s[np.isfinite(times_s)]
    period = median_frame_period_s(t)
    if t.size < 3 or period <= 0.0:
        return ()
    return tuple(
        TimeGap(g.start_s, g.end_s, max(1, round(g.length_s / period) - 1))
        for g in find_frame_gaps(t, period)
    )


def _stream_facts(what: str, gaps: tuple[TimeGap, ...], records: list[GapRecord]) -> str:
    """``<n> <what> gaps (longest <x> s; <k> <unit> recorded missing: <k1> <cause1>, ...)``."""
    n = len(gaps)
    text = f"{n} {what} gap{'' if n == 1 else 's'}"
    inner = []
    if gaps:
        inner.append(f"longest {max(g.duration_s for g in gaps):.2f} s")
    if records:
        by_cause: dict[str, int] = {}
        for g in records:
            by_cause[g.cause] = by_cause.get(g.cause, 0) + g.count
        unit = "samples" if what == "force" else "frames"
        causes = ", ".join(f"{k} {c}" for c, k in by_cause.items())
        inner.append(f"{sum(by_cause.values())} {unit} recorded missing: {causes}")
    return text + (f" ({'; '.join(inner)})" if inner else "")


def gap_facts(inp: ReportInput) -> str:
    """The report's facts on gaps, from the records the figures use.

    The gaps the force and S_k figures shade (:func:`find_gaps` on the stored sample and
    frame times: the figures call it on the same arrays) with the longest of each, and the
    session's own gap records (``gaps`` table: lost samples by cause; frames the camera
    dropped or that came too late to be measured, ``processing_behind``), e.g. ``frames:
    20 frame gaps (longest 47.45 s; 2847 frames recorded missing: 2847
    processing_behind); force: 0 force gaps``.
    """
    frames = _stream_facts(
        "frame", find_gaps(inp.frame_times_s), [g for g in inp.gap_records if g.stream == "frames"]
    )
    force = _stream_facts(
        "force", find_gaps(inp.force_times_s), [g for g in inp.gap_records if g.stream == "force"]
    )
    return f"frames: {frames}; force: {force}"


def broken_line(
    times_s: FloatArray, values: FloatArray, gaps: tuple[TimeGap, ...]
) -> tuple[FloatArray, FloatArray]:
    """``times_s``, ``values`` with one NaN point inside each gap, so a line breaks there.

    The NaN point is placed at the middle of the gap; every stored sample is kept, in order.
    """
    if not gaps:
        return times_s.copy(), values.copy()
    mids = np.asarray([0.5 * (g.start_s + g.end_s) for g in gaps], dtype=np.float64)
    at = np.searchsorted(times_s, mids)
    t = np.insert(times_s, at, mids)
    v = np.insert(values.astype(np.float64), at, np.nan)
    return t, v


def isolated_outliers(
    times_s: FloatArray, s_k_px: FloatArray, t_from_s: float | None
) -> npt.NDArray[np.bool_]:
    """Single frames after ``t_from_s`` far from the median of their neighbours.

    Only the finite frames after ``t_from_s`` are considered (the step at the release is
    not an outlier). For each, r = S_k - median of the :data:`OUTLIER_NEIGHBOURS` frames on
    each side (the frame itself excluded; the ends repeat the first and last frame). The
    noise sigma is 1.4826 median |r| (the median absolute deviation, robust to the outliers
    themselves).
    A frame is an outlier when |r| > :data:`OUTLIER_NOISE_FACTOR` sigma and
    |r| > :data:`OUTLIER_MIN_FRACTION` of the range of the neighbour medians: a dark frame
    (S_k jumps up) or a bright one (S_k drops) that its neighbours do not follow.

    Returns
    -------
    numpy.ndarray of bool
        One entry per frame; False before ``t_from_s`` (None: nowhere) and for NaN frames.
    """
    out = np.zeros(times_s.shape, dtype=bool)
    k = OUTLIER_NEIGHBOURS
    if t_from_s is None:
        return out
    ok = np.flatnonzero(np.isfinite(s_k_px) & np.isfinite(times_s) & (times_s > t_from_s))
    if ok.size < 2 * k + 1:
        return out
    s = s_k_px[ok]
    windows = np.lib.stride_tricks.sliding_window_view(np.pad(s, k, mode="edge"), 2 * k + 1)
    med = np.median(np.delete(windows, k, axis=1), axis=1)
    r = np.abs(s - med)
    sigma = 1.4826 * float(np.median(r))
    spread = float(np.max(med) - np.min(med))
    out[ok[(r > OUTLIER_NOISE_FACTOR * sigma) & (r > OUTLIER_MIN_FRACTION * spread)]] = True
    return out
