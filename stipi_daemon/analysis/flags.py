"""Quality flags attached to analysis results.

A flag says that a result is valid only with a caveat (a lower bound, an extrapolation, a
saturated input). Functions return flags instead of raising when a meaningful, labelled
result still exists; they raise :class:`~stipi_daemon.errors.AnalysisError` when none does.
Flags are strings so that they serialise unchanged into session files and reports.
"""

from __future__ import annotations

from enum import StrEnum


class Flag(StrEnum):
    """Every quality flag the analysis core can attach to a result."""

    # imaging (Eqs. 1-2)
    SATURATED_FRAME = "saturated_frame"
    """Part of the ROI is at the sensor's maximum value; S_k may be biased low."""
    EMPTY_ROI = "empty_roi"
    """The ROI does not overlap the frame; S_k is 0 by definition."""
    ROI_CLIPPED = "roi_clipped"
    """Part of the ROI lies outside the frame; only its pixels inside the frame are counted."""
    # pitting parameters (Eqs. 3-6)
    NOT_SETTLED = "not_settled"
    """S_k never reached 98 % of S_max inside the window: T_r is a lower bound."""
    SETTLED_WITHIN_ONE_FRAME = "settled_within_one_frame"
    """Recovery finished between two frames: T_r is at most one frame period."""
    NO_RECOVERY = "no_recovery"
    """S_k did not rise after T_0: there is no recovery to time."""
    REBOUND_BELOW_OFFSET = "rebound_below_offset"
    """S_max <= C1 (Eq. 5): the rebound force is below what the probe resolves; F_r set to 0."""
    DEPTH_CLIPPED = "depth_clipped"
    """d_s from Eq. 4 fell outside [0, l] and was clipped; D_p is at a bound."""
    CALIBRATION_EXTRAPOLATED = "calibration_extrapolated"
    """S_0 or S_max lies outside the range the calibration was measured over (or S_0 is past
    the vertex of Eq. 4): d_s or F_r is an extrapolation."""
    EARLY_NOISY_CROSSING = "early_noisy_crossing"
    """A short excursion crossed 98 % of S_max before the series settled; it was ignored."""
    # VPR model and recovery fit (Eqs. 7-10)
    FIT_NOT_CONVERGED = "fit_not_converged"
    """The Kelvin-Voigt recovery fit did not converge; its parameters are not reported."""
    TIME_CONSTANT_OUTSIDE_WINDOW = "time_constant_outside_window"
    """The fitted time constant is longer than the fit window or shorter than one frame."""
    CONSTANT_SERIES = "constant_series"
    """The series has no variation to fit."""
    NON_FINITE_INPUT = "non_finite_input"
    """NaN or inf samples were present and were dropped."""
    # severity (Section IV.C)
    OUTSIDE_REFERENCE_RANGE = "outside_reference_range"
    """The measurement lies beyond the reference grades; the nearest grade is an extreme."""
