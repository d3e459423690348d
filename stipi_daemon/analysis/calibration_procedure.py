"""The calibration procedure of Section IV.B: calibration points from recordings, fit report.

The paper calibrates the probe against direct measurements (Fig. 9 (b)): the occluded
area S against the force applied to the sensing probe (Eq. (5)), and the initial area S_0
against the indenter displacement d_s (Eq. (4)). This module turns recorded calibration
runs into those points - force plateaus found in a load-cell series, each giving the mean
force and the mean S over the plateau (:func:`find_force_plateaus`,
:func:`force_points`), and operator-marked intervals at known displacements, each giving
the mean S_0 (:func:`displacement_points`) - and formats the fit report
(:func:`fit_report`). The least-squares fits, their refusals and the calibration file are
:mod:`stipi_daemon.analysis.calibration`'s; reading files is
:mod:`stipi_daemon.app.offline_io`'s. No I/O here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.calibration import Calibration, DepthFit, ForceFit
from stipi_daemon.errors import CalibrationError

__all__ = [
    "DEFAULT_MIN_FORCE_N",
    "DEFAULT_MIN_PLATEAU_S",
    "DEFAULT_PLATEAU_TOLERANCE_N",
    "DEFAULT_TRIM_S",
    "DisplacementInterval",
    "DisplacementPoint",
    "ForcePoint",
    "depth_domain_problem",
    "displacement_points",
    "find_force_plateaus",
    "fit_domain_warnings",
    "fit_report",
    "force_domain_problem",
    "force_points",
]

FloatArray = npt.NDArray[np.float64]

#: Largest force range (max - min) inside a plateau [N].
DEFAULT_PLATEAU_TOLERANCE_N = 0.5
#: Shortest plateau kept [s].
DEFAULT_MIN_PLATEAU_S = 2.0
#: Plateaus whose mean force is below this are the unloaded probe and are not used [N].
DEFAULT_MIN_FORCE_N = 1.0
#: Time cut from each end of a plateau before averaging (settling, operator's hand) [s].
DEFAULT_TRIM_S = 0.25


def _arrays(
    name_t: str, t: npt.ArrayLike, name_v: str, v: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    ta = np.asarray(t, dtype=np.float64)
    va = np.asarray(v, dtype=np.float64)
    if ta.ndim != 1 or ta.shape != va.shape:
        raise CalibrationError(
            f"{name_t} and {name_v} must be 1-D of equal length, got {ta.shape} and {va.shape}"
        )
    if ta.size and (not np.all(np.isfinite(ta)) or np.any(np.diff(ta) <= 0.0)):
        raise CalibrationError(f"{name_t} must be finite and strictly increasing")
    return ta, va


def _moving_median(v: FloatArray, width: int) -> FloatArray:
    """Centred moving median; NaN where the window holds a NaN; ends use shorter windows."""
    if width <= 1 or v.size == 0:
        return v.copy()
    half = width // 2
    padded = np.concatenate([np.full(half, np.nan), v, np.full(width - 1 - half, np.nan)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, width)
    out = np.empty(v.size, dtype=np.float64)
    for i, w in enumerate(windows):
        # Pads at the ends are not data: drop them; a NaN inside the data marks a loss.
        lo, hi = max(0, half - i), width - max(0, i + width - half - v.size)
        part = w[lo:hi]
        out[i] = np.nan if np.isnan(part).any() else float(np.median(part))
    return out


def find_force_plateaus(
    times_s: npt.ArrayLike,
    force_n: npt.ArrayLike,
    *,
    tolerance_n: float = DEFAULT_PLATEAU_TOLERANCE_N,
    min_duration_s: float = DEFAULT_MIN_PLATEAU_S,
    min_force_n: float = DEFAULT_MIN_FORCE_N,
    smooth_samples: int = 5,
) -> list[tuple[float, float]]:
    """Intervals where the applied force is held constant.

    A plateau is a maximal run of consecutive finite samples whose force stays within a
    band of width ``tolerance_n`` (max - min), lasting at least ``min_duration_s``, with
    a mean force of at least ``min_force_n``, and without a drift across it larger than
    half the tolerance (a slow ramp is not a plateau). The band test runs on the force
    after a centred moving median over ``smooth_samples`` samples, so that one noisy
    sample does not split a plateau. Runs are grown greedily from the first sample; a
    non-finite sample ends a run.

    Parameters
    ----------
    times_s : array_like
        Sample times [s], strictly increasing.
    force_n : array_like
        Forces [N]; NaN for lost samples.
    tolerance_n : float
        Band width [N], > 0.
    min_duration_s : float
        Shortest plateau [s], > 0.
    min_force_n : float
        Smallest mean force of a plateau [N].
    smooth_samples : int
        Width of the moving median, >= 1 (1: none).

    Returns
    -------
    list of (float, float)
        ``(t_start_s, t_end_s)`` of each plateau, in time order.
    """
    t, f = _arrays("times_s", times_s, "force_n", force_n)
    if not (tolerance_n > 0.0 and min_duration_s > 0.0 and smooth_samples >= 1):
        raise CalibrationError("tolerance_n and min_duration_s must be > 0, smooth_samples >= 1")
    out: list[tuple[float, float]] = []

    def close(i0: int, i1: int) -> None:  # samples i0..i1 inclusive
        if i1 <= i0 or t[i1] - t[i0] < min_duration_s:
            return
        seg_t, seg_f = t[i0 : i1 + 1], g[i0 : i1 + 1]
        if float(seg_f.mean()) < min_force_n:
            return
        slope = float(np.polyfit(seg_t - seg_t[0], seg_f, 1)[0])
        if abs(slope) * float(seg_t[-1] - seg_t[0]) > tolerance_n / 2.0:
            return
        out.append((float(seg_t[0]), float(seg_t[-1])))

    g = _moving_median(f, smooth_samples)
    i0 = -1
    lo = hi = 0.0
    for i in range(t.size):
        v = float(g[i])
        if not math.isfinite(v):
            if i0 >= 0:
                close(i0, i - 1)
            i0 = -1
            continue
        if i0 < 0:
            i0, lo, hi = i, v, v
            continue
        if max(hi, v) - min(lo, v) <= tolerance_n:
            lo, hi = min(lo, v), max(hi, v)
            continue
        close(i0, i - 1)
        i0, lo, hi = i, v, v
    if i0 >= 0:
        close(i0, t.size - 1)
    return out


@dataclass(frozen=True)
class ForcePoint:
    """One Eq. (5) calibration point from a force plateau.

    Attributes
    ----------
    t_start_s, t_end_s : float
        Averaging interval (the plateau after trimming) [s].
    force_n, force_sd_n : float
        Mean and standard deviation of the force [N].
    s_px, s_sd_px : float
        Mean and standard deviation of S over the frames in the interval [px].
    n_samples, n_frames : int
        Force samples and frames averaged.
    """

    t_start_s: float
    t_end_s: float
    force_n: float
    force_sd_n: float
    s_px: float
    s_sd_px: float
    n_samples: int
    n_frames: int


def force_points(
    force_times_s: npt.ArrayLike,
    force_n: npt.ArrayLike,
    frame_times_s: npt.ArrayLike,
    s_k_px: npt.ArrayLike,
    plateaus: Sequence[tuple[float, float]],
    *,
    trim_s: float = DEFAULT_TRIM_S,
    min_frames: int = 3,
) -> list[ForcePoint]:
    """Average force and S over each plateau (Eq. (5) calibration points).

    Raises
    ------
    CalibrationError
        A plateau is shorter than twice ``trim_s``, or holds fewer than ``min_frames``
        frames (named by its interval).
    """
    ft, fv = _arrays("force_times_s", force_times_s, "force_n", force_n)
    st, sv = _arrays("frame_times_s", frame_times_s, "s_k_px", s_k_px)
    out: list[ForcePoint] = []
    for a, b in plateaus:
        ta, tb = a + trim_s, b - trim_s
        if tb <= ta:
            raise CalibrationError(
                f"force plateau [{a:.3f}, {b:.3f}] s is shorter than twice the trim ({trim_s} s)"
            )
        fsel = (ft >= ta) & (ft <= tb) & np.isfinite(fv)
        ssel = (st >= ta) & (st <= tb) & np.isfinite(sv)
        n_f, n_s = int(np.count_nonzero(fsel)), int(np.count_nonzero(ssel))
        if n_s < min_frames or n_f < 1:
            raise CalibrationError(
                f"force plateau [{ta:.3f}, {tb:.3f}] s holds {n_s} frame(s) and {n_f} force "
                f"sample(s): at least {min_frames} frames and 1 sample needed (camera running?)"
            )
        out.append(
            ForcePoint(
                t_start_s=ta,
                t_end_s=tb,
                force_n=float(np.mean(fv[fsel])),
                force_sd_n=float(np.std(fv[fsel])),
                s_px=float(np.mean(sv[ssel])),
                s_sd_px=float(np.std(sv[ssel])),
                n_samples=n_f,
                n_frames=n_s,
            )
        )
    return out


@dataclass(frozen=True)
class DisplacementInterval:
    """An interval during which the indenter was held at a known displacement.

    Attributes
    ----------
    t_start_s, t_end_s : float
        The interval [s] on the recording's clock.
    depth_change_mm : float
        d_s of Eq. (4) at that displacement [mm].
    """

    t_start_s: float
    t_end_s: float
    depth_change_mm: float


@dataclass(frozen=True)
class DisplacementPoint:
    """One Eq. (4) calibration point: mean S_0 at a known d_s.

    Attributes
    ----------
    interval : DisplacementInterval
        Where it was measured.
    s0_px, s0_sd_px : float
        Mean and standard deviation of S over the interval [px].
    n_frames : int
        Frames averaged.
    """

    interval: DisplacementInterval
    s0_px: float
    s0_sd_px: float
    n_frames: int


def displacement_points(
    frame_times_s: npt.ArrayLike,
    s_k_px: npt.ArrayLike,
    intervals: Sequence[DisplacementInterval],
    *,
    min_frames: int = 3,
) -> list[DisplacementPoint]:
    """Average S over each marked interval (Eq. (4) calibration points).

    Raises
    ------
    CalibrationError
        An interval is empty or reversed, or holds fewer than ``min_frames`` frames.
    """
    st, sv = _arrays("frame_times_s", frame_times_s, "s_k_px", s_k_px)
    out: list[DisplacementPoint] = []
    for k, iv in enumerate(intervals, start=1):
        if not iv.t_end_s > iv.t_start_s:
            raise CalibrationError(
                f"displacement interval {k}: t_end_s {iv.t_end_s} is not after "
                f"t_start_s {iv.t_start_s}"
            )
        sel = (st >= iv.t_start_s) & (st <= iv.t_end_s) & np.isfinite(sv)
        n = int(np.count_nonzero(sel))
        if n < min_frames:
            raise CalibrationError(
                f"displacement interval {k} [{iv.t_start_s:g}, {iv.t_end_s:g}] s holds {n} "
                f"frame(s), at least {min_frames} needed (frames span "
                f"{float(st[0]) if st.size else math.nan:g}.."
                f"{float(st[-1]) if st.size else math.nan:g} s)"
            )
        out.append(
            DisplacementPoint(
                interval=iv,
                s0_px=float(np.mean(sv[sel])),
                s0_sd_px=float(np.std(sv[sel])),
                n_frames=n,
            )
        )
    return out


def depth_domain_problem(
    depth_change_mm: Sequence[float] | FloatArray, indenter_length_mm: float
) -> tuple[int, str] | None:
    """The first Eq. (4) calibration point outside the domain of Eq. (3), with why.

    Eq. (3), ``D_p = l - d_s``, defines the depth change d_s on ``[0, l]`` (Section III.B:
    the indenter of length l moves by at most its length), so a pitting depth lies in
    ``[0, l]`` too. A measured d_s outside it (another unit, a displacement of the stage
    rather than of the indenter, the wrong ``l``) would calibrate Eq. (4) to give
    negative pitting depths.

    Parameters
    ----------
    depth_change_mm : sequence of float
        Measured depth changes d_s [mm].
    indenter_length_mm : float
        Indenter length l [mm], > 0.

    Returns
    -------
    (int, str) or None
        Index of the first point outside ``0 <= d_s <= l`` and a description
        ("d_s = 31 mm is above l = 12 mm: D_p = l - d_s would be -19 mm"); None if all
        lie inside.

    Raises
    ------
    CalibrationError
        ``indenter_length_mm`` is not finite and > 0.
    """
    length = float(indenter_length_mm)
    if not (math.isfinite(length) and length > 0.0):
        raise CalibrationError(f"indenter length l must be finite and > 0 mm, got {length}")
    d = np.asarray(depth_change_mm, dtype=np.float64)
    bad = np.flatnonzero(~((d >= 0.0) & (d <= length)))
    if bad.size == 0:
        return None
    i = int(bad[0])
    v = float(d[i])
    where = "above l" if v > length else "below 0"
    return i, (
        f"d_s = {v:g} mm is {where} = {length:g} mm: Eq. (3) needs 0 <= d_s <= l "
        f"(D_p = l - d_s would be {length - v:g} mm)"
    )


def force_domain_problem(force_n: Sequence[float] | FloatArray) -> tuple[int, str] | None:
    """The first Eq. (5) calibration point with a negative force, with why (None: none).

    Eq. (5) maps the occluded area to the force pressing the sensing probe, which cannot
    pull: F >= 0 [N].
    """
    f = np.asarray(force_n, dtype=np.float64)
    bad = np.flatnonzero(~(f >= 0.0))
    if bad.size == 0:
        return None
    i = int(bad[0])
    return i, f"F = {float(f[i]):g} N is negative: Eq. (5) needs a pressing force F >= 0"


def fit_domain_warnings(cal: Calibration) -> list[str]:
    """Where the fitted Eqs. (4)-(5) leave their domain over the calibrated range.

    Eq. (4) increases over its S0 range, so its largest d_s is at the top of the range
    and its smallest at the bottom; outside ``[0, l]`` the analysis clips d_s and flags
    D_p (``depth_clipped``), so a calibration that does so inside its own range is
    reported here. Each entry is one line; empty when none.
    """
    out: list[str] = []
    length = cal.indenter_length_mm
    if cal.s0_valid_range_px is not None:
        s_lo, s_hi = cal.s0_valid_range_px
        top = cal.depth_change_mm(s_hi)
        if top > length:
            out.append(
                f"Eq. (4) reaches d_s = {top:.4g} mm > l = {length:g} mm at S0 = {s_hi:.6g} px:"
                f" D_p = l - d_s < 0 there (clipped to 0 and flagged depth_clipped)"
            )
        bottom = cal.depth_change_mm(s_lo)
        if bottom < 0.0:
            out.append(
                f"Eq. (4) gives d_s = {bottom:.4g} mm < 0 at S0 = {s_lo:.6g} px: D_p > l there"
                " (clipped to l and flagged depth_clipped)"
            )
    return out


def _se(value: float, se: float) -> str:
    rel = abs(se / value) * 100.0 if value != 0.0 else math.inf
    return f"{value:.6g} +- {se:.2g} ({rel:.2g} %)"


def fit_report(cal: Calibration) -> list[str]:
    """Human-readable report of a fitted calibration: coefficients with standard errors,
    correlation, R^2, RMS and per-point residuals, valid ranges."""
    lines: list[str] = []
    d: DepthFit | None = cal.depth_fit
    f: ForceFit | None = cal.force_fit
    lines.append("Eq. (4)  d_s = -alpha1 S0^2 + alpha2 S0")
    if d is not None:
        lines += [
            f"  alpha1 = {_se(d.alpha1_mm_per_px2, d.alpha1_se_mm_per_px2)} mm/px^2",
            f"  alpha2 = {_se(d.alpha2_mm_per_px, d.alpha2_se_mm_per_px)} mm/px",
            f"  correlation(alpha1, alpha2) = {d.correlation:+.3f}",
            f"  R^2 = {d.r_squared:.6f}, RMS residual = {d.rms_residual_mm:.3g} mm, "
            f"n = {d.n_points}",
            f"  valid S0 range = [{d.s0_range_px[0]:.6g}, {d.s0_range_px[1]:.6g}] px, "
            f"d_s range = [{d.depth_range_mm[0]:.4g}, {d.depth_range_mm[1]:.4g}] mm",
            "  residuals [mm]: " + ", ".join(f"{r:+.3g}" for r in d.residuals_mm),
        ]
    else:
        lines.append(
            f"  alpha1 = {cal.alpha1_mm_per_px2:.6g} mm/px^2, "
            f"alpha2 = {cal.alpha2_mm_per_px:.6g} mm/px"
        )
    lines.append("Eq. (5)  F_r = (S_max - C1) / C2   (fitted as S = C1 + C2 F)")
    if f is not None:
        lines += [
            f"  C1 = {_se(f.c1_px, f.c1_se_px)} px",
            f"  C2 = {_se(f.c2_px_per_n, f.c2_se_px_per_n)} px/N",
            f"  correlation(C1, C2) = {f.correlation:+.3f}",
            f"  R^2 = {f.r_squared:.6f}, RMS residual = {f.rms_residual_px:.4g} px, "
            f"n = {f.n_points}",
            f"  valid force range = [{f.force_range_n[0]:.4g}, {f.force_range_n[1]:.4g}] N, "
            f"S range = [{f.s_range_px[0]:.6g}, {f.s_range_px[1]:.6g}] px",
            "  residuals [px]: " + ", ".join(f"{r:+.4g}" for r in f.residuals_px),
        ]
    else:
        lines.append(f"  C1 = {cal.c1_px:.6g} px, C2 = {cal.c2_px_per_n:.6g} px/N")
    lines.append(
        f"indenter length l = {cal.indenter_length_mm:g} mm, threshold p = "
        + ("not recorded" if cal.threshold_p is None else str(cal.threshold_p))
    )
    return lines
