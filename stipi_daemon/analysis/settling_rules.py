"""When a recovery counts as settled: the tests the analysis and the state machine share.

Eq. (6) of the STIP-I paper reads T_s where S_k first reaches 98 % of S_max, and S_max is
the largest S_k of the *recorded* window (the paper watches 105 s). A recording that stops
early lowers S_max and with it the 98 % level, so T_s (and F_r, Eq. (5), from S_max) come
out low. This module owns the two tests that keep an early stop from changing the result,
so that the analysis (:func:`~stipi_daemon.analysis.pitting.recovery_time`) and the state
machine that decides when to stop (:mod:`~stipi_daemon.measurement.state_machine`) apply
the same rule:

* The *still-rising test* (:func:`still_rising`): the least-squares slope of S_k,
  continued for a horizon (T_r), must not raise S_k by more than the settling band
  (1 - f) S_max. The analysis fits the slope to the last part of the window
  (:func:`least_squares_slope`); the state machine keeps it up to date frame by frame with
  :class:`LineSums` (O(1) per frame).
* The *truncation bound* for a Kelvin-Voigt recovery (:func:`truncation_hold_factor`,
  :func:`kelvin_voigt_truncation_bias`). For S(t) = S_inf - (S_inf - S_0) e^(-t/tau)
  (t from T_0), with r = S_0 / S_inf and f the settling fraction (0.98), the whole
  recovery gives T_r = tau L, L = ln((1 - r) / (1 - f)). Recorded only up to t = T,
  eps = e^(-T/tau), S_max = S_inf - (S_inf - S_0) eps and

      T_r(T) = tau ln((1 - r) / ((1 - f) + f (1 - r) eps)),

  so the relative bias is b(T) = ln(1 + f (1 - r) eps / (1 - f)) / L
  <= f (1 - r) eps / ((1 - f) L). It stays at or below b as soon as
  T >= tau ln(f (1 - r) / (b (1 - f) L)) = (T_r / L) ln(f (1 - r) / (b (1 - f) L)).
  (About 12.5 eps for S_0 << S_inf: 1 % needs T > ~7 tau, about twice T_r.) F_r moves
  with S_max by (1 - r) eps S_inf / (S_inf - C1): about b / 10 at that T.

Domain: S_k in pixels (any non-negative unit works), times in seconds; the bound assumes a
single-exponential (Kelvin-Voigt) recovery, the model of Section III.C, and
0 <= S_0 / S_inf < f. Everything here is pure; :func:`least_squares_slope` is the only
function that uses numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "LineSums",
    "kelvin_voigt_truncation_bias",
    "least_squares_slope",
    "still_rising",
    "truncation_hold_factor",
]


def still_rising(slope_px_per_s: float, horizon_s: float, band_px: float) -> bool:
    """The still-rising test: does S_k, continued at its slope, leave the settling band?

    Parameters
    ----------
    slope_px_per_s : float
        Least-squares slope of S_k over the end of the record [px/s].
    horizon_s : float
        How long the slope is continued [s]: the recovery time T_r (Eq. (6)) in the
        analysis, an upper bound of it in the state machine.
    band_px : float
        Settling band (1 - f) S_max [px].

    Returns
    -------
    bool
        True when ``slope_px_per_s * horizon_s > band_px``: S_max is not a settled value.
    """
    return slope_px_per_s * horizon_s > band_px


def least_squares_slope(t_s: NDArray[np.float64], s_px: NDArray[np.float64]) -> float:
    """Slope of the least-squares line through ``(t_s, s_px)`` [px/s].

    Needs at least two distinct times (the caller checks); the times are centred first.
    """
    x = t_s - t_s.mean()
    return float(x @ (s_px - s_px.mean())) / float(x @ x)


@dataclass(frozen=True, slots=True)
class LineSums:
    """Sums for a least-squares line, extended one sample at a time; immutable, O(1).

    The sums of a run of samples are the difference of two snapshots
    (:meth:`since`), so the slope over any suffix of a record needs only the snapshot
    taken before its first sample. Pass times and values relative to a nearby origin (the
    state machine uses the start of the rise) so that the sums stay small: the slope is
    computed from differences of products and loses the digits the origin would cost.

    Attributes
    ----------
    n : int
        Samples added.
    sum_x_s, sum_y_px : float
        Sums of the times [s] and values [px].
    sum_xx_s2, sum_xy_px_s : float
        Sums of the squared times [s^2] and of the time-value products [px s].
    """

    n: int = 0
    sum_x_s: float = 0.0
    sum_y_px: float = 0.0
    sum_xx_s2: float = 0.0
    sum_xy_px_s: float = 0.0

    def add(self, x_s: float, y_px: float) -> LineSums:
        """The sums with the sample ``(x_s, y_px)`` added."""
        return LineSums(
            n=self.n + 1,
            sum_x_s=self.sum_x_s + x_s,
            sum_y_px=self.sum_y_px + y_px,
            sum_xx_s2=self.sum_xx_s2 + x_s * x_s,
            sum_xy_px_s=self.sum_xy_px_s + x_s * y_px,
        )

    def since(self, earlier: LineSums) -> LineSums:
        """The sums of the samples added after ``earlier`` (a snapshot of these sums)."""
        return LineSums(
            n=self.n - earlier.n,
            sum_x_s=self.sum_x_s - earlier.sum_x_s,
            sum_y_px=self.sum_y_px - earlier.sum_y_px,
            sum_xx_s2=self.sum_xx_s2 - earlier.sum_xx_s2,
            sum_xy_px_s=self.sum_xy_px_s - earlier.sum_xy_px_s,
        )

    @property
    def slope_px_per_s(self) -> float | None:
        """Least-squares slope [px/s]; None with fewer than two distinct times."""
        den = self.n * self.sum_xx_s2 - self.sum_x_s * self.sum_x_s
        if self.n < 2 or not den > 0.0:
            return None
        return (self.n * self.sum_xy_px_s - self.sum_x_s * self.sum_y_px) / den


def _check_fraction(name: str, value: float, *, upper_inclusive: bool = False) -> None:
    ok = 0.0 < value <= 1.0 if upper_inclusive else 0.0 < value < 1.0
    if not (math.isfinite(value) and ok):
        bound = "(0, 1]" if upper_inclusive else "(0, 1)"
        raise ValueError(f"{name} must be in {bound}, got {value!r}")


def kelvin_voigt_truncation_bias(
    s0_over_s_inf: float, window_over_tau: float, settle_fraction: float = 0.98
) -> float:
    """Relative bias of T_r (Eq. (6)) when a Kelvin-Voigt recovery is recorded for T only.

    Returns b = 1 - T_r(T) / T_r(inf) = ln(1 + f (1 - r) e^(-T/tau) / (1 - f)) / L,
    L = ln((1 - r) / (1 - f)) (see the module docstring): T_r read on the truncated record
    is low by the fraction b.

    Parameters
    ----------
    s0_over_s_inf : float
        r = S_0 / S_inf, in [0, f) [1].
    window_over_tau : float
        Recorded recovery T in time constants, >= 0 [1].
    settle_fraction : float
        f of Eq. (6), in (0, 1) [1].

    Raises
    ------
    ValueError
        A parameter outside its domain.
    """
    f, r, x = settle_fraction, s0_over_s_inf, window_over_tau
    _check_fraction("settle_fraction", f)
    if not (math.isfinite(r) and 0.0 <= r < f):
        raise ValueError(f"s0_over_s_inf must be in [0, settle_fraction = {f}), got {r!r}")
    if not (math.isfinite(x) and x >= 0.0):
        raise ValueError(f"window_over_tau must be finite and >= 0, got {x!r}")
    big_l = math.log((1.0 - r) / (1.0 - f))
    return math.log1p(f * (1.0 - r) * math.exp(-x) / (1.0 - f)) / big_l


def truncation_hold_factor(
    s0_over_s_max: float, settle_fraction: float, bias_fraction: float
) -> float | None:
    """How long a Kelvin-Voigt recovery must be recorded, in units of its T_r, for bias <= b.

    From the module docstring: the relative bias of T_r (Eq. (6)) stays at or below
    ``bias_fraction`` once the recovery has been recorded for

        T >= T_r * ln(f (1 - r) / (b (1 - f) L)) / L,   L = ln((1 - r) / (1 - f)).

    The factor grows as r approaches f (T_r then becomes a small difference of nearly
    equal times); with ``b = 0.005`` it is 2.0 at r = 0, 2.2 at r = 0.4, 2.9 at r = 0.8.

    Parameters
    ----------
    s0_over_s_max : float
        r = S_0 / S_max, >= 0 [1]. (With S_max of the record so far, r is slightly above
        S_0 / S_inf; the factor then errs long.)
    settle_fraction : float
        f of Eq. (6), in (0, 1) [1].
    bias_fraction : float
        Largest relative bias b of T_r accepted, in (0, 1) [1].

    Returns
    -------
    float or None
        The factor (> 0; below 1 when any record past T_r is long enough). None when
        r >= f: the whole rise lies inside the settling band and T_r (at most one frame)
        has no scale.

    Raises
    ------
    ValueError
        A parameter outside its domain.
    """
    f, r, b = settle_fraction, s0_over_s_max, bias_fraction
    _check_fraction("settle_fraction", f)
    _check_fraction("bias_fraction", b)
    if not (math.isfinite(r) and r >= 0.0):
        raise ValueError(f"s0_over_s_max must be finite and >= 0, got {r!r}")
    if r >= f:
        return None
    big_l = math.log((1.0 - r) / (1.0 - f))
    return max(0.0, math.log(f * (1.0 - r) / (b * (1.0 - f) * big_l)) / big_l)
