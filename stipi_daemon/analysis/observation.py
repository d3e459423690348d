"""What the camera did and did not observe: frame gaps and isolated outlier frames.

The pitting parameters (Eqs. 3-6) and the recovery fit assume S_k was sampled regularly
and that each frame shows the surface. This module finds where that fails, from the series
itself (pure, no I/O):

* a **frame gap** is an interval between consecutive usable frames longer than
  :data:`GAP_FACTOR` times the median frame interval (frames the camera lost, and frames
  whose S_k is NaN, leave such intervals);
* an **outlier frame** is an isolated frame whose S_k departs from the running median of
  its neighbours (:data:`OUTLIER_HALF_WIDTH` frames each side) by more than
  :data:`OUTLIER_THRESHOLD` robust standard deviations of the series' residuals, and by more
  than :data:`OUTLIER_FLOOR_FRACTION` of the series' level, plus
  :data:`OUTLIER_STEP_ALLOWANCE` local frame-to-frame steps (a Hampel filter). A dark frame
  (the whole ROI counted) or a bright one (nothing counted) is one. The running median of a
  monotone series is the series itself, so a clean recovery has no outlier.

It does not decide what a gap or an outlier does to a result: :mod:`pitting` (T_0, S_0,
S_max, T_s), :mod:`results` (the fit) and :mod:`validity` do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "GAP_FACTOR",
    "MATERIAL_GAP_PERIODS",
    "OUTLIER_FLOOR_FRACTION",
    "OUTLIER_HALF_WIDTH",
    "OUTLIER_STEP_ALLOWANCE",
    "OUTLIER_THRESHOLD",
    "RELEASE_BOUND_PERIODS",
    "FrameGap",
    "Observed",
    "find_frame_gaps",
    "find_outlier_frames",
    "gap_covering",
    "median_frame_period_s",
    "noise_sigma",
    "release_gap",
    "running_median",
]

#: An interval between usable frames longer than this many median frame periods is a gap.
GAP_FACTOR: Final = 1.5
#: Neighbours each side of a frame in the outlier test's running median [frames].
OUTLIER_HALF_WIDTH: Final = 3
#: A frame is an outlier beyond this many robust standard deviations of the residuals [-].
OUTLIER_THRESHOLD: Final = 6.0
#: ... and beyond this fraction of the series' median level (S_k quantisation, clean
#: series whose residuals are all 0) [-].
OUTLIER_FLOOR_FRACTION: Final = 0.01
#: The release counts as observed when the usable frames around T_0 (the last before it and
#: the first at or after it) are at most this many median frame periods apart, i.e. at
#: most two frames are missing there [-].
RELEASE_BOUND_PERIODS: Final = 3.0
#: A gap beside the settling crossing or the maximum matters when it is longer than this
#: many frame periods (at least two frames missing in a row) [-].
MATERIAL_GAP_PERIODS: Final = 2.5
#: ... plus this many local frame-to-frame steps (a fast rise moves a window's median) [-].
OUTLIER_STEP_ALLOWANCE: Final = 2.0
#: Robust standard deviation per median absolute deviation (normal distribution) [-].
_MAD_TO_SIGMA: Final = 1.4826


@dataclass(frozen=True)
class FrameGap:
    """An interval with no usable frame.

    Attributes
    ----------
    start_s, end_s : float
        The usable frames that bound the gap [s] (the last before it, the first after it).
    """

    start_s: float
    end_s: float

    @property
    def length_s(self) -> float:
        """Time between the bounding frames [s]."""
        return self.end_s - self.start_s

    def describe(self) -> str:
        """``"no frame between 18.80 and 20.00 s"``."""
        return f"no frame between {self.start_s:.2f} and {self.end_s:.2f} s"


@dataclass(frozen=True)
class Observed:
    """What the frames of one recovery show about their own coverage.

    Attributes
    ----------
    frame_period_s : float
        Median interval between usable frames [s].
    gaps : tuple[FrameGap, ...]
        Gaps that overlap the recovery window (T_0, T_0 + window].
    release_gap : FrameGap or None
        The gap around T_0 when the release was not observed (see
        :data:`RELEASE_BOUND_PERIODS`): S_0 is unknown.
    settling_gap : FrameGap or None
        The gap the settling crossing T_s of Eq. (6) lies in (T_r is uncertain by its length).
    maximum_gap : FrameGap or None
        A gap next to the frame that sets S_max (the maximum may lie in it).
    outlier_times_s : tuple[float, ...]
        Times of the outlier frames left out of S_0, S_max, T_s and the fit [s].
    s0_frame_s : float or None
        Time of the frame S_0 was taken from [s].
    """

    frame_period_s: float
    gaps: tuple[FrameGap, ...] = ()
    release_gap: FrameGap | None = None
    settling_gap: FrameGap | None = None
    maximum_gap: FrameGap | None = None
    outlier_times_s: tuple[float, ...] = ()
    s0_frame_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: gaps as ``[start_s, end_s]`` pairs, outlier frame times [s]."""

        def pair(g: FrameGap | None) -> list[float] | None:
            return None if g is None else [g.start_s, g.end_s]

        return {
            "frame_period_s": self.frame_period_s,
            "frame_gaps_s": [[g.start_s, g.end_s] for g in self.gaps],
            "release_gap_s": pair(self.release_gap),
            "settling_gap_s": pair(self.settling_gap),
            "maximum_gap_s": pair(self.maximum_gap),
            "outlier_frame_times_s": list(self.outlier_times_s),
            "s0_frame_s": self.s0_frame_s,
        }


def release_gap(times_s: NDArray[np.float64], t0_s: float, period_s: float) -> FrameGap | None:
    """The interval around T_0 without a usable frame, when the release was not observed.

    Parameters
    ----------
    times_s : numpy.ndarray
        Times of the usable frames [s], strictly increasing.
    t0_s : float
        T_0 [s].
    period_s : float
        Frame period [s].

    Returns
    -------
    FrameGap or None
        None when the last usable frame before T_0 and the first at or after it are at most
        :data:`RELEASE_BOUND_PERIODS` periods apart (with no frame before T_0: when the
        first frame is within that bound of T_0); else the frames that bound the gap.
    """
    i = int(np.searchsorted(times_s, t0_s, side="left"))
    if i >= times_s.size:
        return FrameGap(float(times_s[-1]), math.inf)
    after = float(times_s[i])
    before = float(times_s[i - 1]) if i > 0 else t0_s
    if after - before <= RELEASE_BOUND_PERIODS * period_s:
        return None
    return FrameGap(before, after)


def median_frame_period_s(times_s: NDArray[np.float64]) -> float:
    """Median interval between consecutive frames [s]; 0 with fewer than two frames."""
    if times_s.size < 2:
        return 0.0
    return float(np.median(np.diff(times_s)))


def find_frame_gaps(
    times_s: NDArray[np.float64], period_s: float | None = None
) -> tuple[FrameGap, ...]:
    """Every interval between consecutive usable frames longer than GAP_FACTOR periods.

    Parameters
    ----------
    times_s : numpy.ndarray
        Times of the usable frames [s], strictly increasing.
    period_s : float, optional
        Frame period [s]; default the median interval of ``times_s``.
    """
    period = median_frame_period_s(times_s) if period_s is None else period_s
    if times_s.size < 2 or period <= 0.0:
        return ()
    steps = np.diff(times_s)
    idx = np.flatnonzero(steps > GAP_FACTOR * period)
    return tuple(FrameGap(float(times_s[i]), float(times_s[i + 1])) for i in idx.tolist())


def gap_covering(gaps: tuple[FrameGap, ...], lo_s: float, hi_s: float) -> FrameGap | None:
    """The first gap that overlaps the open interval (lo_s, hi_s) [s], or None."""
    for gap in gaps:
        if gap.start_s < hi_s and gap.end_s > lo_s:
            return gap
    return None


def running_median(values: NDArray[np.float64], half_width: int) -> NDArray[np.float64]:
    """Centred running median over 2 * half_width + 1 frames.

    At the start the first frame is repeated (a monotone rise keeps its first value: the
    S_0 frame right after the release is not an outlier); at the end the windows are cut
    to the frames that exist, so the last frame never outvotes its neighbours (a dark
    frame at the end of the window cannot pass as the maximum). Away from the end, a
    monotone series is its own running median; at the end, its last value differs from
    the median of the last half_width + 1 frames by about half_width / 2 frame-to-frame
    steps, under 1 px on a recovery's plateau. A single outlier frame (indeed up to
    ``half_width`` of them in a row, away from the end) cannot raise the maximum.
    """
    from scipy.ndimage import median_filter  # scipy: imported where used

    n = values.size
    if half_width < 1 or n == 0:
        return values.astype(np.float64, copy=True)
    out: NDArray[np.float64] = median_filter(
        values.astype(np.float64), size=2 * half_width + 1, mode="nearest"
    )
    for i in range(max(0, n - half_width), n):
        out[i] = float(np.median(values[max(0, i - half_width) :]))
    return out


def find_outlier_frames(values: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Isolated outlier frames of a series (the Hampel filter described in the module doc).

    Parameters
    ----------
    values : numpy.ndarray
        S_k [px] of consecutive usable frames.

    Returns
    -------
    numpy.ndarray of bool
        True for each outlier frame.
    """
    h = OUTLIER_HALF_WIDTH
    if values.size < 2 * h + 1:
        return np.zeros(values.size, dtype=bool)
    n = values.size
    reference = running_median(values, h)
    # At each end the windows are cut to the frames that exist; a cut window's median lags
    # a rising series by the local slope times the distance to the window's centre: add it
    # back (slope: the median step of the 2h + 1 end frames, which one outlier cannot set).
    # So the first frame (S_0, right after the release) is judged against the trend of the
    # frames that follow it, and the last against those before it.
    head = float(np.median(np.diff(values[: 2 * h + 1])))
    tail = float(np.median(np.diff(values[n - 2 * h - 1 :])))
    for i in range(h):
        reference[i] = float(np.median(values[: i + h + 1])) + head * (i - (i + h) / 2.0)
    for i in range(n - h, n):
        reference[i] = float(np.median(values[i - h :])) + tail * (i - (i - h + n - 1) / 2.0)
    residual = values - reference
    sigma = _MAD_TO_SIGMA * float(np.median(np.abs(residual - np.median(residual))))
    floor = OUTLIER_FLOOR_FRACTION * float(np.median(np.abs(values)))
    # One outlier in a window shifts its median by one order statistic, i.e. by about one
    # frame-to-frame step where S_k rises fast: allow OUTLIER_STEP_ALLOWANCE local steps
    # (the median of the 2h + 1 steps around each frame, mirrored at the ends: one outlier
    # sets two steps, at most three of the seven even at an end, so it cannot set it).
    from scipy.ndimage import median_filter  # scipy: imported where used

    steps = median_filter(np.abs(np.diff(values)), size=2 * h + 1, mode="mirror")
    local_step = steps[np.minimum(np.arange(n), n - 2)]
    bound = max(OUTLIER_THRESHOLD * sigma, floor, 1.0) + OUTLIER_STEP_ALLOWANCE * local_step
    out: NDArray[np.bool_] = np.abs(residual) > bound
    return out


def noise_sigma(values: NDArray[np.float64]) -> float:
    """Frame-to-frame noise of a series: robust standard deviation of one frame [px].

    1.4826 * MAD of the first differences / sqrt(2): a slowly varying signal barely moves
    consecutive differences, so this measures the noise, not the recovery. 0 with fewer
    than three values.
    """
    if values.size < 3:
        return 0.0
    d = np.diff(values)
    return _MAD_TO_SIGMA * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
