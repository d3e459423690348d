"""Pitting parameters from an S_k series: pitting depth (Eq. 3), rebound force (Eq. 5) and
recovery time (Eq. 6) of the STIP-I paper, Section III.B.

This module owns the definitions of T_0, S_0, S_max, T_s and T_r on a sampled series, their
edge cases (no recovery, never settled, settled within one frame, a noisy early crossing),
the detection of T_0 when the caller has no release event, and the
:class:`PittingParameters` record. It does not own S_k (see ``imaging``), the calibration
coefficients or Eq. (4) (see ``calibration``), nor elasticity and viscosity (see ``vpr``).
All functions are pure; inputs outside a stated domain raise
:class:`~stipi_daemon.errors.AnalysisError`, caveated results carry :class:`Flag` values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.observation import (
    GAP_FACTOR,
    MATERIAL_GAP_PERIODS,
    OUTLIER_HALF_WIDTH,
    RELEASE_BOUND_PERIODS,
    FrameGap,
    Observed,
    find_frame_gaps,
    find_outlier_frames,
    gap_covering,
    median_frame_period_s,
    release_gap,
    running_median,
)
from stipi_daemon.analysis.settling_rules import least_squares_slope, still_rising
from stipi_daemon.errors import AnalysisError, require_finite

if TYPE_CHECKING:
    from stipi_daemon.analysis.calibration import Calibration

__all__ = [
    "DEFAULT_END_SLOPE_FRACTION",
    "DEFAULT_PERSIST_FRAMES",
    "DEFAULT_SETTLE_FRACTION",
    "DEFAULT_WINDOW_S",
    "NOTHING_OBSERVED",
    "RELEASE_STEP_UNCONTINUED",
    "SETTLING_GAP_FRACTION",
    "S_MAX_MEDIAN_HALF_WIDTH",
    "FlaggedValue",
    "PittingParameters",
    "RecoveryTime",
    "Series",
    "compute_pitting_parameters",
    "detect_recovery_start",
    "pitting_depth_mm",
    "rebound_force_n",
    "recovery_time",
    "validate_series",
]

#: Fraction of S_max that S_k must reach for the series to count as settled (Eq. 6, [-]).
DEFAULT_SETTLE_FRACTION = 0.98
#: Length of the recovery phase monitored after T_0 (paper: up to 105 s) [s].
DEFAULT_WINDOW_S = 105.0
#: Fraction of the recovery window, at its end, over which :func:`recovery_time` measures the
#: final slope of S_k to decide whether the series is still rising (see there) [-].
DEFAULT_END_SLOPE_FRACTION = 0.1
#: The default of :attr:`RecoveryTime.observed` for records built by hand: no facts.
NOTHING_OBSERVED = Observed(frame_period_s=0.0)
#: Half-width of the running median whose maximum is S_max [frames]: S_max is the largest
#: median of 5 consecutive frames (of the last 3 at the end of the window), which equals
#: the plain maximum on a clean monotone recovery within a fraction of a pixel and which no
#: single outlier frame can raise.
S_MAX_MEDIAN_HALF_WIDTH = 2
#: A gap around the settling crossing shorter than this fraction of T_r is immaterial [-].
SETTLING_GAP_FRACTION = 0.01
#: A release frame below the frames after it is a step at the release (``RELEASE_STEP``)
#: when the line through the next two frames, continued back to it, passes above it by at
#: least this fraction of the jump [-]. For a Kelvin-Voigt recovery sampled every d seconds
#: that fraction is 1 - exp(-d/tau), the share recovered in one frame: 0.8 needs tau below
#: 0.62 d (10 ms at 60 fps), far below any tissue of Table I.
RELEASE_STEP_UNCONTINUED = 0.8
#: A step of S_k is a jump (:func:`detect_recovery_start`) when at least this fraction of the
#: largest step in the search range [-] ...
JUMP_FRACTION = 0.25
#: ... and larger than this many robust standard deviations of the steps [-].
JUMP_NOISE_FACTOR = 6.0
#: Consecutive frames that must stay at or above the settling level for a crossing to count.
#: At the paper's 60 fps, 3 frames are 50 ms: long enough to reject one noisy frame, short
#: against any recovery time in Table I (2.19 s and longer).
DEFAULT_PERSIST_FRAMES = 3


@dataclass(frozen=True)
class FlaggedValue:
    """A scalar result with the quality flags that qualify it.

    Attributes
    ----------
    value : float
        The result, in the unit its producer documents.
    flags : frozenset[Flag]
        Caveats; empty when the value is an unqualified estimate.
    """

    value: float
    flags: frozenset[Flag]


@dataclass(frozen=True)
class Series:
    """A validated S_k series: finite, strictly increasing times and finite, non-negative S_k.

    Attributes
    ----------
    times_s : numpy.ndarray
        Frame times [s], strictly increasing.
    s_px : numpy.ndarray
        Occluded-pixel counts S_k at those times [px], finite and >= 0.
    dropped : int
        Number of input samples dropped because S_k was NaN or infinite.
    """

    times_s: NDArray[np.float64]
    s_px: NDArray[np.float64]
    dropped: int


def validate_series(times_s: ArrayLike, s_px: ArrayLike, *, min_samples: int = 2) -> Series:
    """Check a time series and drop samples whose value is NaN or infinite.

    Parameters
    ----------
    times_s : array_like
        Frame times [s]; one-dimensional, finite and strictly increasing.
    s_px : array_like
        Values at those times (S_k [px]); same length. NaN/inf samples are dropped and
        counted (the caller flags :attr:`Flag.NON_FINITE_INPUT`); negative values raise.
    min_samples : int
        Minimum number of finite samples required.

    Returns
    -------
    Series
        The finite samples as float64 arrays and the number dropped.

    Raises
    ------
    AnalysisError
        Shapes differ, a time is non-finite or not strictly increasing, a value is negative,
        or fewer than ``min_samples`` finite samples remain. The message names the index.
    """
    t = np.asarray(times_s, dtype=np.float64)
    s = np.asarray(s_px, dtype=np.float64)
    if t.ndim != 1 or s.ndim != 1:
        raise AnalysisError(
            f"times_s and s_px must be one-dimensional, got shapes {t.shape} and {s.shape}"
        )
    if t.shape != s.shape:
        raise AnalysisError(
            f"times_s and s_px must have the same length, got {t.size} and {s.size}"
        )
    bad_t = np.flatnonzero(~np.isfinite(t))
    if bad_t.size:
        raise AnalysisError(f"times_s[{bad_t[0]}] is {t[bad_t[0]]}: frame times must be finite")
    if t.size > 1:
        steps = np.diff(t)
        bad_step = np.flatnonzero(~(steps > 0.0))
        if bad_step.size:
            i = int(bad_step[0]) + 1
            raise AnalysisError(
                f"times_s must be strictly increasing: times_s[{i}] = {t[i]} follows "
                f"times_s[{i - 1}] = {t[i - 1]}"
            )
    finite = np.isfinite(s)
    negative = np.flatnonzero(finite & (s < 0.0))
    if negative.size:
        i = int(negative[0])
        raise AnalysisError(f"s_px[{i}] = {s[i]} is negative: S_k is a pixel count (>= 0)")
    t_ok = t[finite]
    s_ok = s[finite]
    if t_ok.size < min_samples:
        raise AnalysisError(
            f"need at least {min_samples} finite samples, got {t_ok.size} "
            f"({t.size - t_ok.size} of {t.size} were NaN or infinite)"
        )
    return Series(times_s=t_ok, s_px=s_ok, dropped=int(t.size - t_ok.size))


def pitting_depth_mm(depth_change_mm: float, indenter_length_mm: float = 12.0) -> FlaggedValue:
    """Pitting depth D_p = l - d_s, Eq. (3).

    The paper defines d_s on [0, l]. A depth change outside that range (a calibration
    extrapolated beyond its data) is clipped to the nearest bound and the result is flagged
    :attr:`Flag.DEPTH_CLIPPED`, so that D_p always lies in [0, l].

    Parameters
    ----------
    depth_change_mm : float
        Depth change of the indenter d_s from Eq. (4) [mm].
    indenter_length_mm : float
        Total indenter length l [mm]; the paper's indenter is 12 mm long.

    Returns
    -------
    FlaggedValue
        D_p [mm] in [0, l], flagged ``DEPTH_CLIPPED`` when d_s was clipped.

    Raises
    ------
    AnalysisError
        ``depth_change_mm`` is NaN/inf, or ``indenter_length_mm`` is not finite and > 0.
    """
    d_s = require_finite("depth_change_mm", depth_change_mm)
    length = require_finite("indenter_length_mm", indenter_length_mm)
    if length <= 0.0:
        raise AnalysisError(f"indenter_length_mm must be > 0, got {length}")
    flags: frozenset[Flag] = frozenset()
    if d_s < 0.0 or d_s > length:
        flags = frozenset({Flag.DEPTH_CLIPPED})
        d_s = min(max(d_s, 0.0), length)
    return FlaggedValue(value=length - d_s, flags=flags)


def rebound_force_n(s_max_px: float, calibration: Calibration) -> FlaggedValue:
    """Rebound force F_r = (S_max - C1) / C2, Eq. (5).

    Parameters
    ----------
    s_max_px : float
        Maximum occluded area S_max over the recovery window [px].
    calibration : Calibration
        Probe calibration providing C1 [px] and C2 [px/N].

    Returns
    -------
    FlaggedValue
        F_r [N]. When S_max <= C1 the probe does not resolve the force: F_r is 0 and flagged
        :attr:`Flag.REBOUND_BELOW_OFFSET`.

    Raises
    ------
    AnalysisError
        ``s_max_px`` is NaN/inf or negative, or the calibration gives a non-finite force.
    """
    s_max = require_finite("s_max_px", s_max_px)
    if s_max < 0.0:
        raise AnalysisError(f"s_max_px must be >= 0 (a pixel count), got {s_max}")
    if s_max <= calibration.c1_px:
        return FlaggedValue(value=0.0, flags=frozenset({Flag.REBOUND_BELOW_OFFSET}))
    force = float(calibration.rebound_force_n(s_max))
    if not math.isfinite(force):
        raise AnalysisError(
            f"Eq. (5) gave a non-finite rebound force for S_max = {s_max} px "
            f"(C1 = {calibration.c1_px} px, C2 = {calibration.c2_px_per_n} px/N)"
        )
    return FlaggedValue(value=force, flags=frozenset())


@dataclass(frozen=True)
class RecoveryTime:
    """Result of :func:`recovery_time` (Eq. 6).

    Attributes
    ----------
    t0_s : float
        Start of recovery T_0 [s].
    ts_s : float or None
        Settling time T_s [s] (absolute, same clock as the series); None with ``NO_RECOVERY``.
    recovery_time_s : float or None
        T_r = T_s - T_0 [s]. A lower bound with ``NOT_SETTLED``, an upper bound with
        ``SETTLED_WITHIN_ONE_FRAME``; None with ``NO_RECOVERY``.
    s0_px : float
        S_0, S_k at T_0 linearly interpolated between the two frames around T_0 [px].
    s_max_px : float
        S_max over the recovery window [px].
    level_px : float
        Settling level, ``settle_fraction * S_max`` [px].
    n_frames : int
        Finite frames in the recovery window (T_0, T_0 + window_s], outliers included.
    flags : frozenset[Flag]
        Caveats (see :class:`Flag`).
    observed : Observed
        Frame gaps and outlier frames of the recovery, and where they matter.
    after_step_px : float or None
        With ``RELEASE_STEP``: S_k of the first usable frame after the release frame, the
        residual pit once the spring-back is done [px]; None otherwise.
    """

    t0_s: float
    ts_s: float | None
    recovery_time_s: float | None
    s0_px: float
    s_max_px: float
    level_px: float
    n_frames: int
    flags: frozenset[Flag]
    observed: Observed = NOTHING_OBSERVED
    after_step_px: float | None = None


def _s_max(values: NDArray[np.float64], top_frames: int) -> float:
    if top_frames == 1:
        return float(np.max(values))
    n = min(top_frames, values.size)
    top = np.partition(values, values.size - n)[values.size - n :]
    return float(np.median(top))


def _still_rising(
    tw: NDArray[np.float64],
    sw: NDArray[np.float64],
    recovery_s: float,
    band_px: float,
    end_fraction: float,
) -> bool:
    """True when the final slope, continued for another T_r, would leave the settling band.

    The test itself (:func:`~stipi_daemon.analysis.settling_rules.still_rising`) is the one the
    state machine applies before it ends a recovery early.
    """
    if end_fraction <= 0.0:
        return False
    seg = tw >= tw[-1] - end_fraction * (tw[-1] - tw[0])
    if np.count_nonzero(seg) < 3:
        return False
    return still_rising(least_squares_slope(tw[seg], sw[seg]), recovery_s, band_px)


def recovery_time(
    times_s: ArrayLike,
    s_k: ArrayLike,
    t0_s: float,
    settle_fraction: float = DEFAULT_SETTLE_FRACTION,
    window_s: float = DEFAULT_WINDOW_S,
    *,
    persist_frames: int = DEFAULT_PERSIST_FRAMES,
    s_max_top_frames: int = 1,
    end_slope_fraction: float = DEFAULT_END_SLOPE_FRACTION,
    contact_floor_px: float = 0.0,
) -> RecoveryTime:
    """Recovery time T_r = T_s - T_0, Eq. (6).

    Definitions on a sampled series (frames at ``times_s``):

    * Outlier frames are left out of everything below, and S_0 is S_k of the first usable
      frame at or after T_0, never interpolated across the release; frame gaps are found
      (``RELEASE_NOT_OBSERVED``, ``OUTLIER_FRAMES``; see :class:`_RecoveryFrames`). The
      recovery window holds the frames with T_0 < t <= T_0 + ``window_s``.
    * S_max is the maximum over the window of the running median of
      2 * :data:`S_MAX_MEDIAN_HALF_WIDTH` + 1 consecutive frames
      (:func:`~stipi_daemon.analysis.observation.running_median`): on a clean monotone
      recovery the paper's plain maximum less at most the last frame's rise; a single
      outlier frame cannot raise it by more than the spread of its neighbours.
      ``s_max_top_frames = n > 1``: the median of the n largest values of that median.
    * T_s is the first time S_k reaches ``settle_fraction * S_max`` (98 %, the paper's
      reading "S_k reaches 98.0 % of S_max"; the level is a fraction of S_max itself, not
      of the rise S_max - S_0), linearly interpolated between the last frame below the level
      (or the point (T_0, S_0)) and the first frame at or above it.
    * A crossing counts only when S_k then stays at or above the level for
      ``persist_frames`` consecutive frames (the crossing frame included). Shorter
      excursions are skipped and the result is flagged ``EARLY_NOISY_CROSSING``.

    Edge cases:

    * ``NO_RECOVERY``: S_max <= S_0, S_k never rises above its value at T_0; T_s and T_r
      are None.
    * ``SETTLED_WITHIN_ONE_FRAME``: the first frame after T_0 already counts as settled.
      T_r is reported as the time from T_0 to that frame (at most one frame period), an
      upper bound: the shape of the rise between the two samples is unknown.
    * ``NOT_SETTLED``: no crossing persists inside the window. T_r is a lower bound: the
      time from T_0 to the last window frame, or, when the window ends during an excursion
      shorter than ``persist_frames``, to that excursion's interpolated crossing.
    * ``RISE_WITHIN_SETTLING_BAND``: S_max - S_0 is within the settling band
      (1 - settle_fraction) * S_max, so the first frame already "settles" whether or not
      anything recovered: T_r is not a measurement.
    * ``FRAME_GAP_AT_SETTLING``: the crossing lies in a gap longer than
      MATERIAL_GAP_PERIODS frames and :data:`SETTLING_GAP_FRACTION` of T_r (T_r is
      uncertain by its length); ``FRAME_GAP_AT_MAXIMUM``: such a gap is next to the frame
      that sets S_max (the maximum may lie in it). All gaps are listed in ``observed``.
    * ``NOT_SETTLED`` also when S_k is still rising at the end of the window (the 98 % level
      of the window's own S_max is always reached by a rise that never stops): if the
      least-squares slope over the last ``end_slope_fraction`` of the window, continued for
      another T_r, would leave the settling band (1 - settle_fraction) * S_max, the crossing
      is a lower bound. ``end_slope_fraction = 0`` disables the check.

    Parameters
    ----------
    times_s : array_like
        Frame times [s], finite and strictly increasing.
    s_k : array_like
        Occluded-pixel counts S_k [px]; NaN/inf frames are dropped (``NON_FINITE_INPUT``).
    t0_s : float
        Start of the recovery T_0 [s], within the series' time span.
    settle_fraction : float
        Fraction of S_max defining T_s, in (0, 1] [-]. Paper: 0.98.
    window_s : float
        Length of the recovery window after T_0 [s]. Paper: 105 s.
    persist_frames : int
        Frames a crossing must persist, >= 1 (1 gives the paper's plain first crossing).
    s_max_top_frames : int
        Number of largest window frames whose median is S_max, >= 1 (1: plain maximum).
    end_slope_fraction : float
        Fraction of the window, at its end, for the still-rising check, in [0, 1) [-].
    contact_floor_px : float
        The least S_k a contact image shows [px] (C1 of Eq. 5, the count at zero tip
        force): a release frame below it is no image of the pit (``RELEASE_STEP``).

    Returns
    -------
    RecoveryTime

    Raises
    ------
    AnalysisError
        Invalid series (see :func:`validate_series`), T_0 outside the series, a parameter
        out of range, or no finite frame in the recovery window.
    """
    series = validate_series(times_s, s_k)
    t, s = series.times_s, series.s_px
    t0, fraction, window = _check_recovery_args(
        t, t0_s, settle_fraction, window_s, persist_frames, s_max_top_frames, end_slope_fraction
    )
    flags = {Flag.NON_FINITE_INPUT} if series.dropped else set()
    win = _RecoveryFrames.of(t, s, t0, window, (fraction, contact_floor_px))
    smooth = running_median(win.sw, S_MAX_MEDIAN_HALF_WIDTH)
    s_max = _s_max(smooth, s_max_top_frames)
    band = (1.0 - fraction) * s_max
    k_max = int(np.argmax(smooth))
    if s_max <= win.s0_px:
        return _timed(win, t0, None, (s_max, fraction), flags | {Flag.NO_RECOVERY}, k_max)
    if s_max - win.s0_px <= band:
        flags.add(Flag.RISE_WITHIN_SETTLING_BAND)
    ts, search_flags = _settling_crossing(
        win.tw, win.sw, t0, win.s0_px, fraction * s_max, persist_frames, band, end_slope_fraction
    )
    return _timed(win, t0, ts, (s_max, fraction), flags | search_flags, k_max)


def _timed(
    win: _RecoveryFrames,
    t0: float,
    ts: float | None,
    s_max_fraction: tuple[float, float],
    flags: set[Flag],
    k_max: int,
) -> RecoveryTime:
    """:func:`recovery_time`'s result: T_0 and T_s [s] (None without recovery), S_max [px]
    and the settling fraction, the flags so far and the index of the window frame that
    sets S_max; adds what the gaps at the crossing and beside the maximum mean."""
    s_max, fraction = s_max_fraction
    flags = set(flags) | win.flags
    settling_gap = None
    if ts is not None and Flag.NOT_SETTLED not in flags:
        settling_gap = _crossing_gap(win, t0, ts)
    observed = Observed(
        frame_period_s=win.period_s,
        gaps=win.gaps,
        release_gap=win.release_gap,
        settling_gap=settling_gap,
        maximum_gap=_gap_beside(win, k_max),
        outlier_times_s=win.outlier_times_s,
        s0_frame_s=win.s0_frame_s,
    )
    if observed.settling_gap is not None:
        flags.add(Flag.FRAME_GAP_AT_SETTLING)
    if observed.maximum_gap is not None:
        flags.add(Flag.FRAME_GAP_AT_MAXIMUM)
    return RecoveryTime(
        t0_s=t0,
        ts_s=ts,
        recovery_time_s=None if ts is None else ts - t0,
        s0_px=win.s0_px,
        s_max_px=s_max,
        level_px=fraction * s_max,
        n_frames=win.n_frames,
        flags=frozenset(flags),
        observed=observed,
        after_step_px=win.after_step_px,
    )


@dataclass(frozen=True)
class _RecoveryFrames:
    """The usable frames of one recovery: S_0, the window without outliers, gaps.

    * Outlier frames (isolated dark or bright frames, the Hampel filter of
      :func:`~stipi_daemon.analysis.observation.find_outlier_frames`) from T_0 to the end
      of the window are left out, counted and flagged ``OUTLIER_FRAMES``.
    * S_0 is S_k of the first usable frame at or after T_0 (the frame at T_0 when there is
      one). Frames before T_0 show the pitting phase, so S_0 is never interpolated across
      the release. When the usable frames around T_0 are more than
      :data:`~stipi_daemon.analysis.observation.RELEASE_BOUND_PERIODS` frame periods apart
      the release was not observed: ``RELEASE_NOT_OBSERVED``, S_0 (hence D_p) is unknown.
    * When the frame just after the release is missing (lost, NaN, or an outlier: a
      bright or dark frame), S_0 is extrapolated back to T_0 (:func:`_s0_at_release`):
      ``S0_EXTRAPOLATED``. An outlier on the first frame is kept as S_0 when the frames
      after it are already settled: a release step within one frame looks the same, and
      S_0 then rests on that single frame (``SETTLED_WITHIN_ONE_FRAME`` flags D_p too).
    * An outlier on the first frame is kept as S_0, flagged ``RELEASE_STEP``, when it lies
      below the frames after it but not below the contact floor (C1 of Eq. 5), and no frame
      was lost between the pitting phase and it (it is the release frame): S_k fell
      at the release frame and jumped up at the next, as an instantaneous recovery (an
      elastic spring-back: a standard linear solid) makes it. A dark frame (S_k above the
      frames after it, against the recovery) and a bright one (S_k below C1, no image of
      the pit) are outliers and S_0 is extrapolated as above.
    * When the last frame before T_0 is an outlier of the pitting frames before it, the
      release may have come a frame before T_0 (a dark frame looks like the pitting phase):
      ``RELEASE_FRAME_OUTLIER``.
    * Gaps (:func:`~stipi_daemon.analysis.observation.find_frame_gaps`) that overlap the
      window are kept; S_0 [px], the window's times [s] and S_k [px] without outliers.
    """

    s0_px: float
    s0_frame_s: float
    tw: NDArray[np.float64]
    sw: NDArray[np.float64]
    n_frames: int
    period_s: float
    gaps: tuple[FrameGap, ...]
    release_gap: FrameGap | None
    outlier_times_s: tuple[float, ...]
    flags: frozenset[Flag]
    after_step_px: float | None = None

    @classmethod
    def of(
        cls,
        t: NDArray[np.float64],
        s: NDArray[np.float64],
        t0: float,
        window: float,
        levels: tuple[float, float],
    ) -> _RecoveryFrames:
        """Frames ``t`` [s], ``s`` [px] (finite) split at T_0 ``t0`` [s], window [s] long;
        ``levels`` are the settling fraction [-] and the contact floor [px].

        Raises
        ------
        AnalysisError
            No finite frame in the window.
        """
        flags: set[Flag] = set()
        period = median_frame_period_s(t)
        at_release = release_gap(t, t0, period)
        if at_release is not None:
            flags.add(Flag.RELEASE_NOT_OBSERVED)
        seg = (t >= t0) & (t <= t0 + window)
        ts_, ss_ = t[seg], s[seg]
        n_window = int(np.count_nonzero(ts_ > t0))
        if n_window == 0:
            raise AnalysisError(
                f"no finite frame in the recovery window ({t0}, {t0 + window}] s: "
                "the series ends at T_0"
            )
        fraction, floor = levels
        after_step: float | None = None
        before = t[t < t0]
        t_before = float(before[-1]) if before.size else t0
        # the release frame itself: no frame lost between the pitting phase and it
        on_time = bool(ts_[0] - t_before <= GAP_FACTOR * period)
        outlier = find_outlier_frames(ss_)
        rest = ss_[1:][~outlier[1:]]
        if outlier[0] and rest.size and rest[0] >= fraction * float(np.max(rest)):
            # The frames after it are already settled: a release step within one frame
            # (SETTLED_WITHIN_ONE_FRAME) cannot be told from an outlier; keep it as S_0.
            outlier[0] = False
        elif outlier[0] and on_time and _release_step(ts_, ss_, outlier, floor):
            outlier[0] = False
            flags.add(Flag.RELEASE_STEP)
            after_step = float(ss_[1:][~outlier[1:]][0])
        if outlier.any():
            flags.add(Flag.OUTLIER_FRAMES)
        keep_t, keep_s = ts_[~outlier], ss_[~outlier]
        in_window = keep_t > t0
        if not in_window.any():
            keep_t, keep_s, in_window = ts_, ss_, ts_ > t0
        gaps = tuple(
            g for g in find_frame_gaps(t, period) if g.end_s > t0 and g.start_s < t0 + window
        )
        s0, late = _s0_at_release(t0, t_before, keep_t, keep_s, period)
        if late and at_release is None:
            flags.add(Flag.S0_EXTRAPOLATED)
        if _last_frame_before_is_outlier(s[t < t0]):
            flags.add(Flag.RELEASE_FRAME_OUTLIER)
        return cls(
            s0_px=s0,
            s0_frame_s=float(keep_t[0]),
            tw=keep_t[in_window],
            sw=keep_s[in_window],
            n_frames=n_window,
            period_s=period,
            gaps=gaps,
            release_gap=at_release,
            outlier_times_s=tuple(float(v) for v in ts_[outlier]),
            flags=frozenset(flags),
            after_step_px=after_step,
        )

    def interval_gap(self, lo_s: float, hi_s: float, min_s: float = 0.0) -> FrameGap | None:
        """(lo_s, hi_s) [s] as a gap when it spans more than MATERIAL_GAP_PERIODS frame
        periods and more than ``min_s`` [s]."""
        length = hi_s - lo_s
        if self.period_s > 0.0 and length > max(MATERIAL_GAP_PERIODS * self.period_s, min_s):
            return gap_covering(self.gaps, lo_s, hi_s) or FrameGap(lo_s, hi_s)
        return None


def _release_step(
    ts: NDArray[np.float64], ss: NDArray[np.float64], outlier: NDArray[np.bool_], floor: float
) -> bool:
    """Whether the release frame (``ts[0]`` [s], ``ss[0]`` [px]), an outlier of the frames
    after it, shows a step at the release rather than a dark or bright frame.

    It must lie below the next usable frame (in the direction of the recovery: a dark
    frame lies above) and not below the contact floor ``floor`` [px] (C1 of Eq. 5; a bright
    frame's S_k is near 0), and the frames after it must not continue the jump: the line
    through the next two usable frames, continued back to the release frame, passes above
    it by at least :data:`RELEASE_STEP_UNCONTINUED` of the jump. A recovery that is merely
    fast for the frame rate (a concave rise sampled sparsely) continues most of its first
    rise; a standard linear solid's spring-back continues none of it.
    """
    rest_t, rest_s = ts[1:][~outlier[1:]], ss[1:][~outlier[1:]]
    if rest_s.size < 2 or not floor <= ss[0] < rest_s[0]:
        return False
    slope = float(rest_s[1] - rest_s[0]) / float(rest_t[1] - rest_t[0])
    back = float(rest_s[0]) - slope * float(rest_t[0] - ts[0])
    jump = float(rest_s[0] - ss[0])
    return back - float(ss[0]) >= RELEASE_STEP_UNCONTINUED * jump


def _last_frame_before_is_outlier(s_before: NDArray[np.float64]) -> bool:
    """Whether the last frame before T_0 is an outlier of the frames before it (S_k [px]).

    A dark or bright frame just before the image's release step looks like one more frame
    of the pitting phase, so T_0 placed at the step may be a frame late, and S_0 with it.
    The test is :func:`~stipi_daemon.analysis.observation.find_outlier_frames` on the last
    4 * OUTLIER_HALF_WIDTH + 1 frames before T_0.
    """
    tail = s_before[-(4 * OUTLIER_HALF_WIDTH + 1) :]
    return bool(tail.size > 2 * OUTLIER_HALF_WIDTH and find_outlier_frames(tail)[-1])


def _s0_at_release(
    t0: float,
    t_before: float,
    keep_t: NDArray[np.float64],
    keep_s: NDArray[np.float64],
    period: float,
) -> tuple[float, bool]:
    """S_0 [px] at T_0 ``t0`` [s], and whether it had to be extrapolated.

    ``t_before`` is the last usable frame before T_0 [s] (T_0 itself when there is none),
    ``keep_t``, ``keep_s`` the usable, non-outlier frames from T_0 on [s, px], ``period``
    the frame period [s]. S_0 is the first of those frames' S_k, unless that frame is
    late: T_0 lies in an interval without frames longer than GAP_FACTOR periods (the
    frame just after the release was lost, NaN or an outlier). A fast recovery rises by a
    good part of its amplitude in a frame or two, so S_0 is then extrapolated back to T_0
    along the line through the next two frames (when the second is within
    RELEASE_BOUND_PERIODS + 1 periods of T_0), clipped at 0.
    """
    s0 = float(keep_s[0])
    late = bool(keep_t[0] > t0 and keep_t[0] - t_before > GAP_FACTOR * period)
    if late and keep_t.size > 1 and keep_t[1] - t0 <= (RELEASE_BOUND_PERIODS + 1) * period:
        dt = float(keep_t[1] - keep_t[0])
        s0 = max(0.0, s0 - float(keep_s[1] - keep_s[0]) * float(keep_t[0] - t0) / dt)
    return s0, late


def _gap_beside(win: _RecoveryFrames, k: int) -> FrameGap | None:
    """A gap next to window frame ``k`` (the one that sets S_max), or None."""
    if k > 0:
        before = win.interval_gap(float(win.tw[k - 1]), float(win.tw[k]))
        if before is not None:
            return before
    if k + 1 < win.tw.size:
        return win.interval_gap(float(win.tw[k]), float(win.tw[k + 1]))
    return None


def _crossing_gap(win: _RecoveryFrames, t0: float, ts: float) -> FrameGap | None:
    """The gap the settling crossing T_s [s] lies in (between its bracketing frames), when
    it is longer than MATERIAL_GAP_PERIODS frames and SETTLING_GAP_FRACTION of T_r."""
    j = int(np.searchsorted(win.tw, ts, side="left"))
    if j >= win.tw.size:
        return None
    prev = t0 if j == 0 else float(win.tw[j - 1])
    return win.interval_gap(prev, float(win.tw[j]), SETTLING_GAP_FRACTION * (ts - t0))


def _check_recovery_args(
    t: NDArray[np.float64],
    t0_s: float,
    settle_fraction: float,
    window_s: float,
    persist_frames: int,
    s_max_top_frames: int,
    end_slope_fraction: float,
) -> tuple[float, float, float]:
    """Check :func:`recovery_time`'s parameters against the valid frame times ``t`` [s].

    Returns
    -------
    tuple[float, float, float]
        T_0 [s], the settling fraction [-] and the window length [s], as floats.

    Raises
    ------
    AnalysisError
        A parameter out of range or T_0 outside the series.
    """
    t0 = require_finite("t0_s", t0_s)
    fraction = require_finite("settle_fraction", settle_fraction)
    if not 0.0 < fraction <= 1.0:
        raise AnalysisError(f"settle_fraction must be in (0, 1], got {fraction}")
    window = require_finite("window_s", window_s)
    if window <= 0.0:
        raise AnalysisError(f"window_s must be > 0, got {window}")
    if persist_frames < 1:
        raise AnalysisError(f"persist_frames must be >= 1, got {persist_frames}")
    if s_max_top_frames < 1:
        raise AnalysisError(f"s_max_top_frames must be >= 1, got {s_max_top_frames}")
    if not 0.0 <= end_slope_fraction < 1.0:
        raise AnalysisError(f"end_slope_fraction must be in [0, 1), got {end_slope_fraction}")
    if not t[0] <= t0 <= t[-1]:
        raise AnalysisError(
            f"t0_s = {t0} s lies outside the series' finite samples [{t[0]}, {t[-1]}] s"
        )
    return t0, fraction, window


def _settling_crossing(
    tw: NDArray[np.float64],
    sw: NDArray[np.float64],
    t0: float,
    s0: float,
    level: float,
    persist_frames: int,
    band_px: float,
    end_slope_fraction: float,
) -> tuple[float, set[Flag]]:
    """T_s of Eq. (6) [s] in the recovery window (times ``tw`` [s], S_k ``sw`` [px]).

    The first crossing of ``level`` [px] that persists ``persist_frames`` frames, linearly
    interpolated from the last frame below it (or from (T_0, S_0)); ``band_px`` is the
    settling band (1 - settle_fraction) * S_max of the still-rising check. Returns T_s and
    the flags of :func:`recovery_time`'s edge cases (``SETTLED_WITHIN_ONE_FRAME``,
    ``EARLY_NOISY_CROSSING``, ``NOT_SETTLED``, where T_s is then a lower bound).
    """
    flags: set[Flag] = set()
    above = sw >= level
    # Runs of consecutive frames at or above the level: starts and (exclusive) ends.
    padded = np.concatenate(([False], above, [False])).astype(np.int8)
    edges = np.diff(padded)
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1)

    def crossing_time(j: int) -> float:
        t_prev, s_prev = (t0, s0) if j == 0 else (float(tw[j - 1]), float(sw[j - 1]))
        t_j, s_j = float(tw[j]), float(sw[j])
        # s_prev < level <= s_j here, so the denominator is > 0.
        return t_prev + (level - s_prev) / (s_j - s_prev) * (t_j - t_prev)

    for start, end in zip(starts.tolist(), ends.tolist(), strict=True):
        if end - start >= persist_frames:
            if start == 0:
                flags.add(Flag.SETTLED_WITHIN_ONE_FRAME)
                ts = float(tw[0])
            else:
                ts = crossing_time(start)
            if _still_rising(tw, sw, ts - t0, band_px, end_slope_fraction):
                flags.add(Flag.NOT_SETTLED)
            return ts, flags
        if end == tw.size:
            # The window ends during a short excursion: T_s is at least its crossing.
            flags.add(Flag.NOT_SETTLED)
            return (float(tw[0]) if start == 0 else crossing_time(start)), flags
        flags.add(Flag.EARLY_NOISY_CROSSING)
    flags.add(Flag.NOT_SETTLED)
    return float(tw[-1]), flags


def detect_recovery_start(
    times_s: ArrayLike,
    s_k: ArrayLike,
    *,
    search_start_s: float | None = None,
    search_end_s: float | None = None,
    smooth_frames: int = 1,
) -> float:
    """Estimate T_0, the start of the recovery, from the S_k series alone.

    Use this only when the recording has no release event (the measurement pipeline places
    T_0 at the observed force drop, :mod:`stipi_daemon.measurement.release`). The release is
    the last *jump* of S_k in the search range: the last step between consecutive frames
    larger than :data:`JUMP_FRACTION` of the largest step there and than
    :data:`JUMP_NOISE_FACTOR` robust standard deviations of the steps. Steps are taken on a
    3-frame moving median (after the optional ``smooth_frames`` one), so a single outlier
    frame is no jump. This holds whether S_k is high while the force is applied (the tip
    carries it: the press is an earlier jump up, the release a jump down) or about 0 (the
    locked indenter leaves the waveguide clear, Fig. 4 (a): the release is the only jump,
    upward). From the frame after the jump, T_0 follows the frames while S_k keeps falling
    by more than the noise threshold (the bottom of a release transient spread over
    frames), and is that frame's time.

    Parameters
    ----------
    times_s : array_like
        Frame times [s], finite and strictly increasing.
    s_k : array_like
        Occluded-pixel counts S_k [px]; NaN/inf frames are ignored.
    search_start_s, search_end_s : float, optional
        Bounds of the search [s], inclusive. Default: the whole series.
    smooth_frames : int
        Width of a moving median applied before the search, >= 1 (odd widths are centred).

    Returns
    -------
    float
        T_0 [s], the time of a frame.

    Raises
    ------
    AnalysisError
        Invalid series or bounds, fewer than three frames in the search range, or T_0 is
        the last frame of the range (nothing recovers after it).
    """
    from scipy.ndimage import median_filter  # scipy: imported where used

    series = validate_series(times_s, s_k)
    t, s = series.times_s, series.s_px
    if smooth_frames < 1:
        raise AnalysisError(f"smooth_frames must be >= 1, got {smooth_frames}")
    if smooth_frames > 1:
        s = median_filter(s, size=smooth_frames, mode="nearest")
    lo = -math.inf if search_start_s is None else require_finite("search_start_s", search_start_s)
    hi = math.inf if search_end_s is None else require_finite("search_end_s", search_end_s)
    idx = np.flatnonzero((t >= lo) & (t <= hi))
    if idx.size == 0:
        raise AnalysisError(f"no finite frame between search_start_s={lo} and search_end_s={hi}")
    if idx.size < 3:
        raise AnalysisError(f"need at least 3 frames between {lo} and {hi} s, got {idx.size}")
    seg = median_filter(s[idx], size=3, mode="nearest")
    steps = np.abs(np.diff(seg))
    sigma = 1.4826 * float(np.median(np.abs(steps - np.median(steps))))
    threshold = max(JUMP_NOISE_FACTOR * sigma, JUMP_FRACTION * float(np.max(steps)))
    jumps = np.flatnonzero(steps >= threshold)
    k = int(jumps[-1]) + 1 if jumps.size else int(np.argmin(seg))
    fall = JUMP_NOISE_FACTOR * sigma
    while k + 1 < seg.size and seg[k + 1] < seg[k] - fall:
        k += 1
    if k == seg.size - 1:
        raise AnalysisError(
            f"S_k's release is at the last searched frame (t = {t[idx[k]]} s): "
            "no recovery follows; pass search_start_s/search_end_s around the release"
        )
    return float(t[idx[k]])


@dataclass(frozen=True)
class PittingParameters:
    """The paper's pitting parameters of one measurement (Section III.B).

    Attributes
    ----------
    depth_mm : float
        Pitting depth D_p, Eq. (3) [mm], in [0, l].
    depth_change_mm : float
        Depth change d_s from Eq. (4) as the calibration gives it, before clipping [mm].
    rebound_force_n : float
        Rebound force F_r, Eq. (5) [N], >= 0.
    recovery_time_s : float or None
        Recovery time T_r, Eq. (6) [s]; see :class:`RecoveryTime` for bounds and None.
    t0_s : float
        Start of the recovery T_0 [s].
    ts_s : float or None
        Settling time T_s [s].
    s0_px : float
        S_0 [px], S_k at T_0.
    s_max_px : float
        S_max [px] over the recovery window.
    flags : frozenset[Flag]
        Union of the flags of all three parameters.
    observed : Observed
        Frame gaps and outlier frames of the recovery (see :class:`RecoveryTime`).
    residual_depth_mm : float or None
        With ``RELEASE_STEP``: the pit left once the instantaneous spring-back is done,
        l - d_s (Eqs. 3-4) of S_k at the first frame after the release frame, in [0, l]
        [mm]; ``depth_mm`` stays the indentation depth at the release frame (S_0). None
        without a step, or when that S_k is past the vertex of Eq. (4).
    spring_back_px : float or None
        With ``RELEASE_STEP``: the step of S_k right after the release frame [px].
    """

    depth_mm: float
    depth_change_mm: float
    rebound_force_n: float
    recovery_time_s: float | None
    t0_s: float
    ts_s: float | None
    s0_px: float
    s_max_px: float
    flags: frozenset[Flag]
    observed: Observed = NOTHING_OBSERVED
    residual_depth_mm: float | None = None
    spring_back_px: float | None = None


def compute_pitting_parameters(
    times_s: ArrayLike,
    s_k: ArrayLike,
    t0_s: float,
    calibration: Calibration,
    *,
    settle_fraction: float = DEFAULT_SETTLE_FRACTION,
    window_s: float = DEFAULT_WINDOW_S,
    persist_frames: int = DEFAULT_PERSIST_FRAMES,
    s_max_top_frames: int = 1,
    end_slope_fraction: float = DEFAULT_END_SLOPE_FRACTION,
) -> PittingParameters:
    """D_p, F_r and T_r (Eqs. 3-6) of one recovery series.

    S_0 and S_max are taken as :func:`recovery_time` defines them; d_s is
    ``calibration.depth_change_mm(S_0)`` (Eq. 4), D_p follows from Eq. (3) with the
    calibration's indenter length, F_r from Eq. (5). ``S0_BELOW_CONTACT_FLOOR`` is added when
    S_0 is below C1 of Eq. (5), the least count a contact image shows (an empty or
    all-zero image: D_p would be Eq. (4) at no contact, the whole indenter).
    ``CALIBRATION_EXTRAPOLATED`` is added
    when S_0 lies outside the calibration's measured S_0 range or past the vertex of Eq. (4),
    or F_r outside its measured force range.

    Parameters
    ----------
    times_s : array_like
        Frame times [s].
    s_k : array_like
        Occluded-pixel counts S_k [px].
    t0_s : float
        Start of the recovery T_0 [s] (the release event, or :func:`detect_recovery_start`).
    calibration : Calibration
        Probe calibration (alpha1, alpha2, C1, C2, indenter length).
    settle_fraction, window_s, persist_frames, s_max_top_frames, end_slope_fraction
        See :func:`recovery_time`.

    Returns
    -------
    PittingParameters

    Raises
    ------
    AnalysisError
        As :func:`recovery_time`, or when Eq. (4) gives a non-finite depth change.
    """
    rt = recovery_time(
        times_s,
        s_k,
        t0_s,
        settle_fraction,
        window_s,
        persist_frames=persist_frames,
        s_max_top_frames=s_max_top_frames,
        end_slope_fraction=end_slope_fraction,
        contact_floor_px=calibration.c1_px,
    )
    d_s = float(calibration.depth_change_mm(rt.s0_px))
    if not math.isfinite(d_s):
        raise AnalysisError(f"Eq. (4) gave a non-finite depth change for S_0 = {rt.s0_px} px")
    depth = pitting_depth_mm(d_s, calibration.indenter_length_mm)
    force = rebound_force_n(rt.s_max_px, calibration)
    extra: set[Flag] = set()
    if rt.s0_px < calibration.c1_px:
        # fewer pixels than any contact image shows: no image of the pit to read D_p from
        extra.add(Flag.S0_BELOW_CONTACT_FLOOR)
    s0_range = calibration.s0_valid_range_px
    if rt.s0_px >= calibration.vertex_px or (
        s0_range is not None and not s0_range[0] <= rt.s0_px <= s0_range[1]
    ):
        extra.add(Flag.CALIBRATION_EXTRAPOLATED)
    f_range = calibration.force_valid_range_n
    if (
        f_range is not None
        and Flag.REBOUND_BELOW_OFFSET not in force.flags
        and not f_range[0] <= force.value <= f_range[1]
    ):
        extra.add(Flag.CALIBRATION_EXTRAPOLATED)
    residual: float | None = None
    step: float | None = None
    if rt.after_step_px is not None:
        step = rt.after_step_px - rt.s0_px
        d_after = float(calibration.depth_change_mm(rt.after_step_px))
        # past the vertex of Eq. (4) d_s no longer grows with S: no depth to read there
        if math.isfinite(d_after) and rt.after_step_px < calibration.vertex_px:
            residual = pitting_depth_mm(d_after, calibration.indenter_length_mm).value
    return PittingParameters(
        depth_mm=depth.value,
        depth_change_mm=d_s,
        rebound_force_n=force.value,
        recovery_time_s=rt.recovery_time_s,
        t0_s=rt.t0_s,
        ts_s=rt.ts_s,
        s0_px=rt.s0_px,
        s_max_px=rt.s_max_px,
        flags=rt.flags | depth.flags | force.flags | frozenset(extra),
        observed=rt.observed,
        residual_depth_mm=residual,
        spring_back_px=step,
    )
