"""Probe calibration: S_k to depth change (Eq. (4)) and to force (Eq. (5)), Section IV.B.

This module owns the calibration coefficients of one STIP-I probe (:class:`Calibration`),
their least-squares estimation from calibration measurements (:func:`fit_depth_calibration`,
:func:`fit_force_calibration`), the inverse relations a simulator needs (depth change or
force to pixel area), and the versioned calibration file (:func:`save_calibration`,
:func:`load_calibration`). It does not compute pitting parameters or decide what to do with
values outside a calibration's domain (clipping d_s to [0, l], S_max <= C1): that is
:mod:`~stipi_daemon.analysis.pitting`'s job. Apart from the two file functions it does no I/O.

Models
------
Eq. (4): ``d_s = -alpha1 * S0**2 + alpha2 * S0`` with d_s [mm] and S0 [px]; no intercept, so
d_s(0) = 0. A calibration requires alpha2 > 0 (depth grows from S0 = 0); with alpha1 > 0 the
parabola peaks at the vertex ``S0 = alpha2 / (2 alpha1)`` and only ``0 <= S0 < vertex`` (the
increasing branch) is meaningful.

Eq. (5): ``F_r = (S_max - C1) / C2``, i.e. the occluded area grows linearly with force,
``S = C1 + C2 F``, with C1 [px] and C2 > 0 [px/N]. It is fitted as S on F because the force is
the quantity set (and measured with a gauge) during calibration.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Final

import numpy as np
import numpy.typing as npt
from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, ValidationError

from stipi_daemon.analysis.imaging import ROI, CircleROI, RectROI, describe_roi, same_roi
from stipi_daemon.errors import AnalysisError, CalibrationError
from stipi_daemon.yamlfile import read_utf8

__all__ = [
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "DEFAULT_INDENTER_LENGTH_MM",
    "Calibration",
    "DepthFit",
    "ForceFit",
    "calibration_from_fits",
    "fit_depth_calibration",
    "fit_force_calibration",
    "load_calibration",
    "save_calibration",
]

CALIBRATION_FORMAT: Final = "stipi-calibration"
"""Value of the ``"format"`` key of a calibration file."""
CALIBRATION_VERSION: Final = 1
"""Calibration file version written and read by this module."""
DEFAULT_INDENTER_LENGTH_MM: Final = 12.0
"""Indenter length l of Eq. (3) in the paper [mm]."""


# --------------------------------------------------------------------------------------------
# Fit results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DepthFit:
    """Least-squares fit of Eq. (4), ``d_s = -alpha1 S0^2 + alpha2 S0``.

    Attributes
    ----------
    alpha1_mm_per_px2, alpha2_mm_per_px : float
        Coefficients [mm/px^2], [mm/px].
    alpha1_se_mm_per_px2, alpha2_se_mm_per_px : float
        Standard errors of the coefficients (residual variance with n - 2 degrees of
        freedom) [mm/px^2], [mm/px].
    correlation : float
        Correlation coefficient of the two estimates [1], in [-1, 1].
    residuals_mm : tuple of float
        Measured minus fitted depth change, in input order [mm].
    r_squared : float
        ``1 - RSS / sum((d - mean(d))^2)`` [1] (centred, so comparable to a line with an
        intercept; it can be negative for a bad model).
    n_points : int
        Number of calibration points.
    s0_range_px : tuple of float
        Smallest and largest S0 measured [px]: the range the fit is valid over.
    depth_range_mm : tuple of float
        Smallest and largest depth change measured [mm].
    """

    alpha1_mm_per_px2: float
    alpha2_mm_per_px: float
    alpha1_se_mm_per_px2: float
    alpha2_se_mm_per_px: float
    correlation: float
    residuals_mm: tuple[float, ...]
    r_squared: float
    n_points: int
    s0_range_px: tuple[float, float]
    depth_range_mm: tuple[float, float]

    @property
    def rms_residual_mm(self) -> float:
        """Root-mean-square residual [mm]."""
        return math.sqrt(math.fsum(r * r for r in self.residuals_mm) / self.n_points)

    @property
    def vertex_px(self) -> float:
        """S0 at the parabola's vertex, ``alpha2 / (2 alpha1)`` [px]; inf if alpha1 <= 0."""
        return _vertex_px(self.alpha1_mm_per_px2, self.alpha2_mm_per_px)


@dataclass(frozen=True)
class ForceFit:
    """Least-squares fit of Eq. (5) written as ``S = C1 + C2 F``.

    Attributes
    ----------
    c1_px, c2_px_per_n : float
        Intercept [px] and slope [px/N].
    c1_se_px, c2_se_px_per_n : float
        Standard errors (n - 2 degrees of freedom) [px], [px/N].
    correlation : float
        Correlation coefficient of the two estimates [1].
    residuals_px : tuple of float
        Measured minus fitted S, in input order [px].
    r_squared : float
        Coefficient of determination [1].
    n_points : int
        Number of calibration points.
    force_range_n : tuple of float
        Smallest and largest applied force [N]: the range the fit is valid over.
    s_range_px : tuple of float
        Smallest and largest S measured [px].
    """

    c1_px: float
    c2_px_per_n: float
    c1_se_px: float
    c2_se_px_per_n: float
    correlation: float
    residuals_px: tuple[float, ...]
    r_squared: float
    n_points: int
    force_range_n: tuple[float, float]
    s_range_px: tuple[float, float]

    @property
    def rms_residual_px(self) -> float:
        """Root-mean-square residual [px]."""
        return math.sqrt(math.fsum(r * r for r in self.residuals_px) / self.n_points)


# --------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------


def _vertex_px(alpha1: float, alpha2: float) -> float:
    if alpha1 <= 0.0:
        return math.inf
    return alpha2 / (2.0 * alpha1)


def _finite(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise CalibrationError(f"field '{name}': must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise CalibrationError(f"field '{name}': must be finite, got {v}")
    return v


def _check_range(name: str, rng: tuple[float, float] | None) -> None:
    if rng is None:
        return
    if len(rng) != 2:
        raise CalibrationError(f"field '{name}': must be a (low, high) pair, got {rng!r}")
    lo, hi = _finite(name, rng[0]), _finite(name, rng[1])
    if lo > hi:
        raise CalibrationError(f"field '{name}': low {lo} > high {hi}")


@dataclass(frozen=True)
class Calibration:
    """Calibration coefficients of one probe for Eqs. (4) and (5).

    Attributes
    ----------
    alpha1_mm_per_px2 : float
        alpha1 of Eq. (4) [mm/px^2]; any finite value (0 = linear, > 0 = saturating).
    alpha2_mm_per_px : float
        alpha2 of Eq. (4) [mm/px], > 0.
    c1_px : float
        C1 of Eq. (5), occluded area at zero force [px].
    c2_px_per_n : float
        C2 of Eq. (5), area per unit force [px/N], > 0.
    indenter_length_mm : float
        Indenter length l of Eq. (3) [mm], > 0.
    threshold_p : int or None
        Threshold p of Eq. (1) [8-bit intensity] the calibration was measured with. S_k
        depends on p, so measurements must use the same p.
    s0_valid_range_px : tuple of float or None
        S0 range the depth calibration was measured over [px]; outside it Eq. (4) is
        extrapolated. Must lie below the vertex when alpha1 > 0.
    force_valid_range_n : tuple of float or None
        Force range the force calibration was measured over [N].
    depth_fit, force_fit : DepthFit or ForceFit or None
        Fit reports the coefficients came from, if any.
    probe_id : str or None
        Identifier of the probe (e.g. its BLE name).
    created_utc : datetime or None
        When the calibration was made (timezone-aware).
    frame_size_px : tuple of int or None
        ``(width, height)`` of the camera frames its S values were counted in [px]. S is a
        pixel count: at another resolution the same occlusion covers another number of
        pixels, and Eqs. (4)-(5) give a wrong depth and force with nothing to show it, so
        the daemon and ``analyze`` refuse a camera or video of another size. None: not
        recorded (a calibration fitted from pairs without ``--frame-size``).
    roi : CircleROI or RectROI or None
        The region of interest its S values were counted in [px, camera-frame
        coordinates]. S counts the occluded pixels within it: a smaller ROI that cuts into
        the occluded area lowers S, a larger one that reaches past the lit disc adds its
        dark pixels, so the daemon refuses another ROI and ``analyze`` flags results counted
        in one (``roi_not_calibrated``). The whole frame is the rect of ``frame_size_px``
        (:func:`~stipi_daemon.analysis.imaging.whole_frame_roi`), the same S as any ROI
        holding the frame. None: not recorded (older files; pairs fitted without
        ``--roi``).

    Raises
    ------
    CalibrationError
        On construction, for a non-finite coefficient, alpha2 <= 0, C2 <= 0, a non-positive
        indenter length, p outside 0..255, a malformed range, an S0 range that reaches the
        vertex of Eq. (4), a frame size that is not two positive integers, or an ROI that
        is not a CircleROI or RectROI.
    """

    alpha1_mm_per_px2: float
    alpha2_mm_per_px: float
    c1_px: float
    c2_px_per_n: float
    indenter_length_mm: float = DEFAULT_INDENTER_LENGTH_MM
    threshold_p: int | None = None
    s0_valid_range_px: tuple[float, float] | None = None
    force_valid_range_n: tuple[float, float] | None = None
    depth_fit: DepthFit | None = None
    force_fit: ForceFit | None = None
    probe_id: str | None = None
    created_utc: datetime | None = None
    frame_size_px: tuple[int, int] | None = None
    roi: CircleROI | RectROI | None = None

    def __post_init__(self) -> None:
        _finite("alpha1_mm_per_px2", self.alpha1_mm_per_px2)
        if _finite("alpha2_mm_per_px", self.alpha2_mm_per_px) <= 0.0:
            raise CalibrationError(
                f"field 'alpha2_mm_per_px': must be > 0 (Eq. (4) must increase from S0 = 0), "
                f"got {self.alpha2_mm_per_px}"
            )
        _finite("c1_px", self.c1_px)
        if _finite("c2_px_per_n", self.c2_px_per_n) <= 0.0:
            raise CalibrationError(
                f"field 'c2_px_per_n': must be > 0 (force must increase the occluded area), "
                f"got {self.c2_px_per_n}"
            )
        if _finite("indenter_length_mm", self.indenter_length_mm) <= 0.0:
            raise CalibrationError(
                f"field 'indenter_length_mm': must be > 0, got {self.indenter_length_mm}"
            )
        p = self.threshold_p
        if p is not None and (
            isinstance(p, bool) or not isinstance(p, int | np.integer) or not 0 <= p <= 255
        ):
            raise CalibrationError(f"field 'threshold_p': must be an integer 0..255, got {p!r}")
        _check_range("s0_valid_range_px", self.s0_valid_range_px)
        _check_range("force_valid_range_n", self.force_valid_range_n)
        if self.s0_valid_range_px is not None:
            lo, hi = self.s0_valid_range_px
            if lo < 0.0:
                raise CalibrationError(f"field 's0_valid_range_px': S0 must be >= 0, got {lo}")
            if hi >= self.vertex_px:
                raise CalibrationError(
                    f"field 's0_valid_range_px': range [{lo}, {hi}] px reaches the vertex of "
                    f"Eq. (4) at S0 = {self.vertex_px} px, where d_s stops increasing"
                )
        if self.created_utc is not None and self.created_utc.utcoffset() is None:
            raise CalibrationError("field 'created_utc': must be timezone-aware")
        size = self.frame_size_px
        if size is not None and not (
            len(size) == 2
            and all(not isinstance(v, bool) and isinstance(v, int | np.integer) for v in size)
            and min(size) > 0
        ):
            raise CalibrationError(
                f"field 'frame_size_px': must be [width, height], two integers > 0 [px], "
                f"got {size!r}"
            )
        if self.roi is not None and not isinstance(self.roi, CircleROI | RectROI):
            raise CalibrationError(f"field 'roi': must be a circle or rect ROI, got {self.roi!r}")

    def frame_size_problem(self, width_px: int, height_px: int, where: str) -> str | None:
        """Why S counted in ``width_px`` x ``height_px`` frames cannot use this calibration,
        or None when they can (the same size, or a calibration that records none).

        ``where`` names what has those frames (the camera, a session, a video file).
        """
        if self.frame_size_px is None or tuple(self.frame_size_px) == (width_px, height_px):
            return None
        w, h = self.frame_size_px
        return (
            f"{where} has {width_px}x{height_px} px frames, but the calibration was made at "
            f"{w}x{h} px (its field 'frame_size_px'): S is a pixel count, so D_p and F_r "
            "(Eqs. 4-5) would be wrong"
        )

    def holds_in_roi(self, roi: CircleROI | RectROI | None) -> bool:
        """Whether this calibration holds for S counted in ``roi`` [px] (None: the whole
        frame): it was made in the same pixels (the same ROI, or both holding the whole frame
        of its ``frame_size_px``), or it records no ROI."""
        return self.roi is None or same_roi(roi, self.roi, self.frame_size_px)

    def roi_problem(self, roi: CircleROI | RectROI | None, where: str) -> str | None:
        """Why S counted in ``roi`` [px] (None: the whole frame) cannot use this
        calibration, or None when they can (the same ROI, both holding the whole frame of
        the calibration's ``frame_size_px``, or a calibration that records none).

        ``where`` names what counts in that ROI (a config field, ``--roi``, a session).
        """
        if self.holds_in_roi(roi):
            return None
        return (
            f"{where} counts S in {describe_roi(roi)}, but the calibration was made in "
            f"{describe_roi(self.roi)} (its field 'roi'): S is the occluded pixel count "
            "within the ROI, so D_p and F_r (Eqs. 4-5) would be wrong"
        )

    @property
    def vertex_px(self) -> float:
        """S0 at the vertex of Eq. (4), ``alpha2 / (2 alpha1)`` [px]; inf when alpha1 <= 0.

        Eq. (4) increases for ``0 <= S0 < vertex_px`` and decreases beyond it.
        """
        return _vertex_px(self.alpha1_mm_per_px2, self.alpha2_mm_per_px)

    @property
    def max_depth_change_mm(self) -> float:
        """Largest d_s Eq. (4) can give, at the vertex, ``alpha2^2 / (4 alpha1)`` [mm].

        inf when alpha1 <= 0.
        """
        if self.alpha1_mm_per_px2 <= 0.0:
            return math.inf
        return self.alpha2_mm_per_px * (self.alpha2_mm_per_px / (4.0 * self.alpha1_mm_per_px2))

    def depth_change_mm(self, s0_px: float) -> float:
        """Depth change d_s from the initial occluded area S0, Eq. (4) [mm].

        Parameters
        ----------
        s0_px : float
            S0 [px], finite and >= 0.

        Returns
        -------
        float
            ``-alpha1 S0^2 + alpha2 S0`` [mm], unclipped. Beyond :attr:`vertex_px` the value
            decreases again and is not physical; outside :attr:`s0_valid_range_px` it is an
            extrapolation. Clipping to [0, l] is the caller's (pitting.py) decision.

        Raises
        ------
        AnalysisError
            If ``s0_px`` is NaN, inf or negative.
        """
        s0 = float(s0_px)
        if not math.isfinite(s0) or s0 < 0.0:
            raise AnalysisError(f"S0 must be a finite pixel count >= 0, got {s0_px!r}")
        return s0 * (self.alpha2_mm_per_px - self.alpha1_mm_per_px2 * s0)

    def s0_for_depth_change(self, depth_change_mm: float) -> float:
        """Inverse of Eq. (4): S0 [px] giving a depth change, on the increasing branch.

        Solves ``alpha1 S0^2 - alpha2 S0 + d = 0`` for the root with ``0 <= S0 < vertex``
        in the cancellation-free form ``S0 = 2 d / (alpha2 (1 + sqrt(1 - 4 alpha1 d /
        alpha2^2)))``, which also covers alpha1 = 0 (``S0 = d / alpha2``) and alpha1 < 0.

        Parameters
        ----------
        depth_change_mm : float
            d_s [mm], finite, 0 <= d <= :attr:`max_depth_change_mm`.

        Returns
        -------
        float
            S0 [px], >= 0.

        Raises
        ------
        AnalysisError
            If d is not finite, negative (Eq. (4) gives d < 0 only for S0 < 0) or above the
            vertex value, where Eq. (4) has no real solution.
        """
        d = float(depth_change_mm)
        if not math.isfinite(d):
            raise AnalysisError(f"depth change must be finite, got {depth_change_mm!r}")
        if d < 0.0:
            raise AnalysisError(
                f"depth change {d} mm < 0: Eq. (4) gives negative d_s only for S0 < 0"
            )
        a1, a2 = self.alpha1_mm_per_px2, self.alpha2_mm_per_px
        # r = 4 a1 d / a2^2, formed without squaring a2 (no overflow/underflow of a2^2).
        r = (4.0 * a1 / a2) * (d / a2) if a1 != 0.0 else 0.0
        if r > 1.0:
            raise AnalysisError(
                f"depth change {d} mm exceeds the maximum of Eq. (4), "
                f"{self.max_depth_change_mm} mm at the vertex S0 = {self.vertex_px} px"
            )
        return (2.0 * (d / a2)) / (1.0 + math.sqrt(1.0 - r))

    def rebound_force_n(self, s_max_px: float) -> float:
        """Rebound force F_r from the largest occluded area, Eq. (5) [N].

        Parameters
        ----------
        s_max_px : float
            S_max [px], finite.

        Returns
        -------
        float
            ``(S_max - C1) / C2`` [N], unclipped: S_max <= C1 gives F_r <= 0, below what the
            probe resolves; pitting.py flags that case (REBOUND_BELOW_OFFSET).

        Raises
        ------
        AnalysisError
            If ``s_max_px`` is NaN or inf.
        """
        s = float(s_max_px)
        if not math.isfinite(s):
            raise AnalysisError(f"S_max must be finite, got {s_max_px!r}")
        return (s - self.c1_px) / self.c2_px_per_n

    def area_for_force_px(self, force_n: float) -> float:
        """Inverse of Eq. (5): occluded area ``S = C1 + C2 F`` at a force [px].

        Parameters
        ----------
        force_n : float
            Force on the probe [N], finite.

        Returns
        -------
        float
            S [px], unclipped (it can be < 0 when C1 < 0 and F is small).

        Raises
        ------
        AnalysisError
            If ``force_n`` is NaN or inf.
        """
        f = float(force_n)
        if not math.isfinite(f):
            raise AnalysisError(f"force must be finite, got {force_n!r}")
        return self.c1_px + self.c2_px_per_n * f


# --------------------------------------------------------------------------------------------
# Least-squares fits
# --------------------------------------------------------------------------------------------

_FloatArray = npt.NDArray[np.float64]


def _as_vector(name: str, values: Sequence[float] | npt.ArrayLike) -> _FloatArray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{name}: not a sequence of numbers ({exc})") from exc
    if arr.ndim != 1:
        raise CalibrationError(f"{name}: must be one-dimensional, got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        i = int(bad[0])
        raise CalibrationError(f"{name}: non-finite value {arr[i]} at index {i}")
    return arr


def _paired(
    s_name: str, s_values: npt.ArrayLike, y_name: str, y_values: npt.ArrayLike
) -> tuple[_FloatArray, _FloatArray]:
    s = _as_vector(s_name, s_values)
    y = _as_vector(y_name, y_values)
    if s.size != y.size:
        raise CalibrationError(
            f"mismatched lengths: {s.size} {s_name} values but {y.size} {y_name} values"
        )
    if s.size < 3:
        raise CalibrationError(
            f"too few points: {s.size} given, at least 3 needed (2 coefficients plus one "
            "degree of freedom for their standard errors)"
        )
    neg = np.flatnonzero(s < 0.0)
    if neg.size:
        i = int(neg[0])
        raise CalibrationError(f"{s_name}: negative pixel count {s[i]} at index {i}")
    return s, y


@dataclass(frozen=True)
class _Ols:
    coef: _FloatArray
    cov: _FloatArray
    residuals: _FloatArray


def _ols(design: _FloatArray, y: _FloatArray) -> _Ols:
    """Ordinary least squares via SVD; covariance sigma^2 (X^T X)^-1 with n - k dof."""
    n, k = design.shape
    u, sing, vt = np.linalg.svd(design, full_matrices=False)
    if sing[-1] <= sing[0] * 1e-12:
        raise CalibrationError(
            "calibration points do not determine the coefficients (design matrix is singular)"
        )
    coef = vt.T @ ((u.T @ y) / sing)
    residuals = y - design @ coef
    sigma2 = float(residuals @ residuals) / (n - k)
    v_scaled = vt.T / sing
    cov = sigma2 * (v_scaled @ v_scaled.T)
    return _Ols(coef, cov, residuals)


def _r_squared(y: _FloatArray, residuals: _FloatArray) -> float:
    sst = float(np.sum((y - y.mean()) ** 2))
    rss = float(residuals @ residuals)
    return 1.0 - rss / sst


def _correlation(cov: _FloatArray) -> float:
    denom = math.sqrt(float(cov[0, 0]) * float(cov[1, 1]))
    if denom == 0.0:
        return 0.0
    return max(-1.0, min(1.0, float(cov[0, 1]) / denom))


def fit_depth_calibration(
    s0_px: Sequence[float] | npt.ArrayLike, depth_change_mm: Sequence[float] | npt.ArrayLike
) -> DepthFit:
    """Fit Eq. (4), ``d_s = -alpha1 S0^2 + alpha2 S0``, by least squares.

    S0 is divided by its largest value before solving (SVD of the scaled design matrix) so
    that S0 up to ~1e8 px does not make the problem ill-conditioned; coefficients and
    standard errors are scaled back.

    Parameters
    ----------
    s0_px : sequence of float
        Occluded areas S0 measured at known indenter depth changes [px], >= 0.
    depth_change_mm : sequence of float
        The corresponding depth changes d_s [mm].

    Returns
    -------
    DepthFit
        Coefficients, standard errors, residuals, R^2, n and measured ranges.

    Raises
    ------
    CalibrationError
        Mismatched lengths; non-finite value (named with its index); negative S0; fewer than
        3 points; all S0 equal; fewer than 3 distinct non-zero S0 values (S0 = 0 carries no
        information since Eq. (4) has no intercept); all depth changes equal; a fit that
        decreases over the measured range, or that decreases from S0 = 0 (alpha2 <= 0); a
        vertex inside the measured S0 range (Eq. (4) not invertible there).
    """
    s, d = _paired("S0", s0_px, "depth change", depth_change_mm)
    s_lo, s_hi = float(s.min()), float(s.max())
    if s_lo == s_hi:
        raise CalibrationError(
            f"all S0 values are equal ({s_lo:.6g} px): no depth-vs-area relation"
        )
    distinct = np.unique(s[s > 0.0]).size
    if distinct < 3:
        raise CalibrationError(
            f"too few distinct S0 values: {distinct} distinct non-zero S0 values, at least 3 "
            "needed (S0 = 0 carries no information: Eq. (4) has no intercept)"
        )
    if float(d.min()) == float(d.max()):
        raise CalibrationError(
            f"all depth-change values are equal ({float(d[0]):.6g} mm): no depth-vs-area relation"
        )
    scale = s_hi
    x = s / scale
    fit = _ols(np.column_stack([-(x * x), x]), d)
    a1 = float(fit.coef[0]) / scale**2
    a2 = float(fit.coef[1]) / scale
    se1 = math.sqrt(max(float(fit.cov[0, 0]), 0.0)) / scale**2
    se2 = math.sqrt(max(float(fit.cov[1, 1]), 0.0)) / scale
    # Monotonicity on the measured range: d'(S) = a2 - 2 a1 S, linear in S, so its sign at
    # the range ends decides (evaluated in scaled units to stay well inside float range).
    slope_lo = float(fit.coef[1]) - 2.0 * float(fit.coef[0]) * (s_lo / scale)
    slope_hi = float(fit.coef[1]) - 2.0 * float(fit.coef[0]) * 1.0
    vertex = _vertex_px(a1, a2) if a1 > 0.0 else (a2 / (2.0 * a1) if a1 < 0.0 else math.nan)
    if slope_lo <= 0.0 and slope_hi <= 0.0:
        raise CalibrationError(
            f"depth fit decreases over the measured S0 range [{s_lo:.6g}, {s_hi:.6g}] px "
            f"(alpha1 = {a1:.6g} mm/px^2, alpha2 = {a2:.6g} mm/px): depth must grow with area"
        )
    if slope_lo <= 0.0 or slope_hi <= 0.0:
        raise CalibrationError(
            f"vertex of the depth fit at S0 = {vertex:.6g} px lies inside the measured S0 range "
            f"[{s_lo:.6g}, {s_hi:.6g}] px: Eq. (4) is not invertible there "
            f"(alpha1 = {a1:.6g} mm/px^2, alpha2 = {a2:.6g} mm/px)"
        )
    if a2 <= 0.0:
        raise CalibrationError(
            f"depth fit decreases from S0 = 0 (alpha2 = {a2:.6g} mm/px <= 0, vertex at S0 = "
            f"{vertex:.6g} px, below the measured range [{s_lo:.6g}, {s_hi:.6g}] px): "
            "Eq. (4) would give negative depth changes for small S0"
        )
    return DepthFit(
        alpha1_mm_per_px2=a1,
        alpha2_mm_per_px=a2,
        alpha1_se_mm_per_px2=se1,
        alpha2_se_mm_per_px=se2,
        correlation=_correlation(fit.cov),
        residuals_mm=tuple(float(r) for r in fit.residuals),
        r_squared=_r_squared(d, fit.residuals),
        n_points=int(s.size),
        s0_range_px=(s_lo, s_hi),
        depth_range_mm=(float(d.min()), float(d.max())),
    )


def fit_force_calibration(
    s_px: Sequence[float] | npt.ArrayLike, force_n: Sequence[float] | npt.ArrayLike
) -> ForceFit:
    """Fit Eq. (5) as the line ``S = C1 + C2 F`` by least squares (S regressed on F).

    S is divided by its largest magnitude and F is centred and scaled before solving, so the
    problem stays well conditioned for S up to ~1e8 px; coefficients and standard errors are
    transformed back.

    Parameters
    ----------
    s_px : sequence of float
        Occluded areas S measured at known forces [px], >= 0.
    force_n : sequence of float
        The applied forces F [N] (the regressor).

    Returns
    -------
    ForceFit
        Coefficients, standard errors, residuals, R^2, n and measured ranges.

    Raises
    ------
    CalibrationError
        Mismatched lengths; non-finite value (named with its index); negative S; fewer than 3
        points; fewer than 3 distinct force values; all S equal; a slope C2 <= 0 (force must
        increase the occluded area).
    """
    s, f = _paired("S", s_px, "force", force_n)
    distinct = np.unique(f).size
    if distinct < 3:
        raise CalibrationError(
            f"too few distinct force values: {distinct} distinct, at least 3 needed for a "
            "line with standard errors"
        )
    s_lo, s_hi = float(s.min()), float(s.max())
    if s_lo == s_hi:
        raise CalibrationError(
            f"all S values are equal ({s_lo:.6g} px): the area does not change with force"
        )
    s_scale = s_hi  # > 0 since S >= 0 and not all equal
    f_mean = float(f.mean())
    f_scale = float(np.max(np.abs(f - f_mean)))
    u = (f - f_mean) / f_scale
    fit = _ols(np.column_stack([np.ones_like(u), u]), s / s_scale)
    b0, b1 = float(fit.coef[0]), float(fit.coef[1])
    c2 = b1 * s_scale / f_scale
    c1 = s_scale * (b0 - b1 * f_mean / f_scale)
    # Var(C1) = s^2 [Var(b0) + k^2 Var(b1) - 2 k Cov(b0, b1)], k = f_mean / f_scale.
    k = f_mean / f_scale
    var_c1 = float(fit.cov[0, 0]) + k * k * float(fit.cov[1, 1]) - 2.0 * k * float(fit.cov[0, 1])
    se_c1 = s_scale * math.sqrt(max(var_c1, 0.0))
    se_c2 = s_scale / f_scale * math.sqrt(max(float(fit.cov[1, 1]), 0.0))
    cov_c = np.array(
        [
            [var_c1, float(fit.cov[0, 1]) - k * float(fit.cov[1, 1])],
            [float(fit.cov[0, 1]) - k * float(fit.cov[1, 1]), float(fit.cov[1, 1])],
        ]
    )
    if c2 <= 0.0:
        raise CalibrationError(
            f"non-positive slope C2 = {c2:.6g} px/N over forces [{float(f.min()):.6g}, "
            f"{float(f.max()):.6g}] N: force must increase the occluded area"
        )
    return ForceFit(
        c1_px=c1,
        c2_px_per_n=c2,
        c1_se_px=se_c1,
        c2_se_px_per_n=se_c2,
        correlation=_correlation(cov_c),
        residuals_px=tuple(float(r) * s_scale for r in fit.residuals),
        r_squared=_r_squared(s / s_scale, fit.residuals),
        n_points=int(s.size),
        force_range_n=(float(f.min()), float(f.max())),
        s_range_px=(s_lo, s_hi),
    )


def calibration_from_fits(
    depth: DepthFit,
    force: ForceFit,
    indenter_length_mm: float = DEFAULT_INDENTER_LENGTH_MM,
    threshold_p: int | None = None,
    *,
    probe_id: str | None = None,
    created_utc: datetime | None = None,
    frame_size_px: tuple[int, int] | None = None,
    roi: CircleROI | RectROI | None = None,
) -> Calibration:
    """Build a :class:`Calibration` from a depth fit (Eq. (4)) and a force fit (Eq. (5)).

    The measured S0 and force ranges become the calibration's valid ranges and the fit
    reports are kept with it.

    Parameters
    ----------
    depth : DepthFit
        Result of :func:`fit_depth_calibration`.
    force : ForceFit
        Result of :func:`fit_force_calibration`.
    indenter_length_mm : float
        Indenter length l [mm].
    threshold_p : int or None
        Threshold p of Eq. (1) the calibration frames were counted with [8-bit intensity].
    probe_id : str or None
        Probe identifier.
    created_utc : datetime or None
        Creation time (timezone-aware); None leaves it to :func:`save_calibration`.
    frame_size_px : tuple of int or None
        ``(width, height)`` of the frames the S values were counted in [px].
    roi : CircleROI or RectROI or None
        The ROI the S values were counted in [px].
    """
    return Calibration(
        alpha1_mm_per_px2=depth.alpha1_mm_per_px2,
        alpha2_mm_per_px=depth.alpha2_mm_per_px,
        c1_px=force.c1_px,
        c2_px_per_n=force.c2_px_per_n,
        indenter_length_mm=indenter_length_mm,
        threshold_p=threshold_p,
        s0_valid_range_px=depth.s0_range_px,
        force_valid_range_n=force.force_range_n,
        depth_fit=depth,
        force_fit=force,
        probe_id=probe_id,
        created_utc=created_utc,
        frame_size_px=frame_size_px,
        roi=roi,
    )


# --------------------------------------------------------------------------------------------
# Calibration file (JSON, versioned)
# --------------------------------------------------------------------------------------------


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


class _DepthFitV1(_Model):
    alpha1_mm_per_px2: float
    alpha2_mm_per_px: float
    alpha1_se_mm_per_px2: float = Field(ge=0)
    alpha2_se_mm_per_px: float = Field(ge=0)
    correlation: float = Field(ge=-1, le=1)
    residuals_mm: tuple[float, ...]
    r_squared: float
    n_points: int = Field(ge=3)
    s0_range_px: tuple[float, float]
    depth_range_mm: tuple[float, float]


class _ForceFitV1(_Model):
    c1_px: float
    c2_px_per_n: float
    c1_se_px: float = Field(ge=0)
    c2_se_px_per_n: float = Field(ge=0)
    correlation: float = Field(ge=-1, le=1)
    residuals_px: tuple[float, ...]
    r_squared: float
    n_points: int = Field(ge=3)
    force_range_n: tuple[float, float]
    s_range_px: tuple[float, float]


class _CalibrationFileV1(_Model):
    format: str
    version: int
    created_utc: AwareDatetime
    probe_id: str | None = None
    alpha1_mm_per_px2: float
    alpha2_mm_per_px: float = Field(gt=0)
    c1_px: float
    c2_px_per_n: float = Field(gt=0)
    indenter_length_mm: float = Field(gt=0)
    threshold_p: int | None = Field(default=None, ge=0, le=255)
    s0_valid_range_px: tuple[float, float] | None = None
    force_valid_range_n: tuple[float, float] | None = None
    depth_fit: _DepthFitV1 | None = None
    force_fit: _ForceFitV1 | None = None
    frame_size_px: tuple[Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]] | None = None
    roi: ROI | None = None


def _fit_dict(fit: DepthFit | ForceFit) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in fit.__dataclass_fields__:
        value = getattr(fit, name)
        out[name] = list(value) if isinstance(value, tuple) else value
    return out


def save_calibration(path: str | os.PathLike[str], cal: Calibration) -> Path:
    """Write a calibration file atomically (temporary file + ``os.replace``).

    The file is JSON with ``"format": "stipi-calibration"``, ``"version": 1``, the
    coefficients under unit-suffixed keys, the valid ranges, the fit reports (if any),
    ``frame_size_px``, ``roi`` (written as the config's ``imaging.roi``), ``probe_id`` and
    ``created_utc`` (the calibration's, or the current UTC time when it has none). An
    existing file at ``path`` is replaced only once the new one is complete.

    Parameters
    ----------
    path : str or PathLike
        Destination file.
    cal : Calibration
        Calibration to write.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    OSError
        If the directory is not writable; no partial file is left behind.
    """
    dest = Path(path)
    created = cal.created_utc if cal.created_utc is not None else datetime.now(UTC)
    doc: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "version": CALIBRATION_VERSION,
        "created_utc": created.isoformat(),
        "probe_id": cal.probe_id,
        "alpha1_mm_per_px2": cal.alpha1_mm_per_px2,
        "alpha2_mm_per_px": cal.alpha2_mm_per_px,
        "c1_px": cal.c1_px,
        "c2_px_per_n": cal.c2_px_per_n,
        "indenter_length_mm": cal.indenter_length_mm,
        "threshold_p": None if cal.threshold_p is None else int(cal.threshold_p),
        "s0_valid_range_px": None if cal.s0_valid_range_px is None else list(cal.s0_valid_range_px),
        "force_valid_range_n": (
            None if cal.force_valid_range_n is None else list(cal.force_valid_range_n)
        ),
        "depth_fit": None if cal.depth_fit is None else _fit_dict(cal.depth_fit),
        "force_fit": None if cal.force_fit is None else _fit_dict(cal.force_fit),
        "frame_size_px": None if cal.frame_size_px is None else [int(v) for v in cal.frame_size_px],
        "roi": None if cal.roi is None else cal.roi.model_dump(mode="json"),
    }
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, dest)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        raise
    return dest


def _bound(value: object) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def _describe_error(err: Any) -> str:
    loc = ".".join(str(part) for part in err["loc"])
    kind = err["type"]
    ctx = err.get("ctx") or {}
    value = err.get("input")
    if kind == "greater_than":
        msg = f"must be > {_bound(ctx['gt'])} (got {value!r})"
    elif kind == "greater_than_equal":
        msg = f"must be >= {_bound(ctx['ge'])} (got {value!r})"
    elif kind == "less_than_equal":
        msg = f"must be <= {_bound(ctx['le'])} (got {value!r})"
    elif kind == "missing":
        msg = "missing"
    elif kind == "extra_forbidden":
        msg = "unknown field"
    else:
        msg = f"{err['msg']} (got {value!r})"
    return f"field '{loc}': {msg}"


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read and validate a calibration file written by :func:`save_calibration`.

    Parameters
    ----------
    path : str or PathLike
        Calibration file (JSON, format ``stipi-calibration``, version 1).

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationError
        Naming the file and the problem: unreadable file, invalid or truncated JSON (with
        line, column and character position, and a note when the file looks truncated),
        not a JSON object, wrong ``format``, missing
        or unsupported ``version``, and any invalid field (named, e.g.
        ``calib.json: field 'c2_px_per_n': must be > 0 (got -1.0)``).
    """
    src = Path(path)
    text = read_utf8(src, "calibration file", CalibrationError)
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        stripped = text.rstrip()
        truncated = not stripped.endswith("}") or exc.pos >= len(stripped)
        hint = " (the file looks truncated)" if truncated else ""
        raise CalibrationError(
            f"{src}: invalid JSON{hint}: {exc.msg} at line {exc.lineno}, column {exc.colno} "
            f"(char {exc.pos})"
        ) from exc
    if not isinstance(raw, dict):
        raise CalibrationError(f"{src}: not a calibration file (top level is not a JSON object)")
    fmt = raw.get("format")
    if fmt != CALIBRATION_FORMAT:
        raise CalibrationError(
            f"{src}: field 'format': expected {CALIBRATION_FORMAT!r}, got {fmt!r} "
            "(not a stipi calibration file)"
        )
    if "version" not in raw:
        raise CalibrationError(
            f"{src}: field 'version': missing (this program reads version {CALIBRATION_VERSION})"
        )
    version = raw["version"]
    if isinstance(version, bool) or version != CALIBRATION_VERSION:
        raise CalibrationError(
            f"{src}: field 'version': unsupported version {version!r} (this program reads "
            f"version {CALIBRATION_VERSION})"
        )
    try:
        model = _CalibrationFileV1.model_validate_json(text)
    except ValidationError as exc:
        errors = exc.errors()
        detail = "; ".join(_describe_error(e) for e in errors[:3])
        more = f" (+{len(errors) - 3} more)" if len(errors) > 3 else ""
        raise CalibrationError(f"{src}: {detail}{more}") from exc
    try:
        depth_fit = None
        if model.depth_fit is not None:
            depth_fit = DepthFit(**model.depth_fit.model_dump())
            _check_fit_len("depth_fit", len(depth_fit.residuals_mm), depth_fit.n_points)
        force_fit = None
        if model.force_fit is not None:
            force_fit = ForceFit(**model.force_fit.model_dump())
            _check_fit_len("force_fit", len(force_fit.residuals_px), force_fit.n_points)
        return Calibration(
            alpha1_mm_per_px2=model.alpha1_mm_per_px2,
            alpha2_mm_per_px=model.alpha2_mm_per_px,
            c1_px=model.c1_px,
            c2_px_per_n=model.c2_px_per_n,
            indenter_length_mm=model.indenter_length_mm,
            threshold_p=model.threshold_p,
            s0_valid_range_px=model.s0_valid_range_px,
            force_valid_range_n=model.force_valid_range_n,
            depth_fit=depth_fit,
            force_fit=force_fit,
            probe_id=model.probe_id,
            created_utc=model.created_utc,
            frame_size_px=model.frame_size_px,
            roi=model.roi,
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{src}: {exc}") from exc


def _check_fit_len(name: str, n_residuals: int, n_points: int) -> None:
    if n_residuals != n_points:
        raise CalibrationError(
            f"field '{name}.residuals': {n_residuals} residuals but n_points = {n_points}"
        )
