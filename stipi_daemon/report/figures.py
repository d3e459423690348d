"""Figure data of the session report: the arrays each figure plots.

Force and S_k over time with the measurement's phases, the Kelvin-Voigt recovery fitted to
S_k with its residuals, the VPR curves of Eq. (10) and their normalised form against the
reference grades with the severity window and threshold (Fig. 10 and 12), and the window
search (Fig. 11), each built from one :class:`~.inputs.ReportInput` (or its results) as a
frozen record of arrays. It is pure: no file access, no drawing (:mod:`.render`), so tests
can compare every plotted sample with the session's rows. Times are on the session clock
[s] unless a name says "since T_0".
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.analysis.pitting import DEFAULT_SETTLE_FRACTION, DEFAULT_WINDOW_S
from stipi_daemon.analysis.recovery_fit import (
    kelvin_voigt_recovery,
    settling_time_from_time_constant,
)
from stipi_daemon.analysis.severity import (
    SeverityReference,
    find_severity_window,
    normalised_depth,
)
from stipi_daemon.analysis.vpr import KPA_PER_N_PER_MM2
from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.inputs import FloatArray, ReportInput, number_at, value_at
from stipi_daemon.report.numbers import value_text
from stipi_daemon.report.series import TimeGap, broken_line, find_gaps, isolated_outliers
from stipi_daemon.report.verdict import QuantityStatus, combined, read_validity
from stipi_daemon.storage.schema import Transition

__all__ = [
    "GRADE_MATCH_NOTE",
    "VPR_HORIZON_S",
    "VPR_SAMPLES",
    "FitFigure",
    "ForceFigure",
    "NormalisedCurve",
    "PhaseSpan",
    "SkFigure",
    "VprFigure",
    "WindowSearchFigure",
    "fit_figure",
    "force_figure",
    "grade_note",
    "measurement_curves",
    "omitted_curves",
    "phase_spans",
    "recorded_outliers",
    "s_k_figure",
    "vpr_figure",
    "window_search_figure",
]

#: Time span of the VPR curves (Figs. 10 and 12) [s since T_0]: the paper's recovery window.
VPR_HORIZON_S: Final = DEFAULT_WINDOW_S
#: Samples of the VPR curves over :data:`VPR_HORIZON_S` (0.1 s apart).
VPR_SAMPLES: Final = 1051


# --------------------------------------------------------------------------------------------
# Force and S_k over time
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhaseSpan:
    """The measurement was in ``phase`` from ``start_s`` to ``end_s`` [s]."""

    phase: str
    start_s: float
    end_s: float


def phase_spans(transitions: Sequence[Transition], t_end_s: float) -> tuple[PhaseSpan, ...]:
    """The phases between consecutive transitions; the last lasts until ``t_end_s`` [s].

    Spans of zero or negative length (a terminal phase entered at the last sample) are
    left out.
    """
    out: list[PhaseSpan] = []
    for i, tr in enumerate(transitions):
        end = transitions[i + 1].t_host_s if i + 1 < len(transitions) else t_end_s
        if end > tr.t_host_s:
            out.append(PhaseSpan(tr.new_state, float(tr.t_host_s), float(end)))
    return tuple(out)


@dataclass(frozen=True)
class ForceFigure:
    """Force over time with the phases shaded.

    Attributes
    ----------
    t_s, force_n : numpy.ndarray
        Every force sample as stored [s], [N] (NaN: lost, drawn as a gap).
    line_t_s, line_force_n : numpy.ndarray
        The same with a NaN point inside each gap of :attr:`gaps` (the plotted line).
    gaps : tuple of TimeGap
        Intervals without force samples (:func:`~.series.find_gaps`).
    phases : tuple of PhaseSpan
        Phases of the measurement.
    target_n, tolerance_n : float or None
        The pitting force band target +- tolerance [N] the state machine enforced.
    release_n : float or None
        Force below which the release is detected [N].
    applied_force_n : float or None
        F_a of Eq. (7) (mean over the pitting hold) [N].
    hold_s : tuple of float or None
        The pitting hold [s] over which F_a was averaged: from its start to its end or
        T_0, whichever comes first.
    t0_s : float or None
        T_0, the start of the recovery [s].
    release_s : float or None
        The release the state machine detected [s] (T_0 before its refinement).
    """

    t_s: FloatArray
    force_n: FloatArray
    line_t_s: FloatArray
    line_force_n: FloatArray
    gaps: tuple[TimeGap, ...]
    phases: tuple[PhaseSpan, ...]
    target_n: float | None
    tolerance_n: float | None
    release_n: float | None
    applied_force_n: float | None
    hold_s: tuple[float, float] | None
    t0_s: float | None
    release_s: float | None


def force_figure(inp: ReportInput) -> ForceFigure:
    """Data of the force-over-time figure."""
    m = value_at(inp.config, "measurement")
    start = number_at(inp.summary, "measurement", "t_pit_start_s")
    end = number_at(inp.summary, "measurement", "t_pit_end_s")
    t0 = inp.t0_s
    gaps = find_gaps(inp.force_times_s)
    line_t, line_f = broken_line(inp.force_times_s, inp.force_n, gaps)
    return ForceFigure(
        t_s=inp.force_times_s,
        force_n=inp.force_n,
        line_t_s=line_t,
        line_force_n=line_f,
        gaps=gaps,
        phases=phase_spans(inp.transitions, inp.t_end_s),
        target_n=number_at(m, "target_force_n"),
        tolerance_n=number_at(m, "force_tolerance_n"),
        release_n=number_at(m, "release_force_n"),
        applied_force_n=number_at(inp.results, "applied_force_n"),
        # The hold F_a averages over ends at T_0 at the latest (the pipeline's rule).
        hold_s=None if start is None or end is None else (start, min(end, t0 or end)),
        t0_s=inp.t0_s,
        release_s=number_at(inp.summary, "measurement", "t0_s"),
    )


@dataclass(frozen=True)
class SkFigure:
    """S_k over time with T_0, T_s and the settling line (Eq. 6).

    Attributes
    ----------
    t_s, s_k_px : numpy.ndarray
        Every frame as stored: capture time [s], S_k [px].
    line_t_s, line_s_k_px : numpy.ndarray
        The plotted line: every frame but the outlier frames (drawn as markers), with a NaN
        point inside each gap of :attr:`gaps`.
    gaps : tuple of TimeGap
        Intervals without frames (:func:`~.series.find_gaps`).
    nan_frame_t_s : numpy.ndarray
        Capture times of frames whose S_k is not finite (dropped by the analysis) [s].
    outlier_t_s, outlier_s_k_px : numpy.ndarray
        Outlier frames after T_0 [s], [px]: those the analysis recorded leaving out
        (``pitting.observation.outlier_frame_times_s``), else
        :func:`~.series.isolated_outliers`.
    outlier_source : {"analysis", "report"}
        Which of the two found them.
    release_gap_s : tuple of float or None
        The frames around T_0 when the analysis recorded that the release was not observed
        (``pitting.observation.release_gap_s``) [s].
    phases : tuple of PhaseSpan
        Phases of the measurement.
    release_s : float or None
        The release the state machine detected [s].
    t0_s, ts_s : float or None
        T_0 (start of recovery) and T_s (S_k settled) [s].
    s0_px, s_max_px : float or None
        S_0 (at T_0) and S_max [px].
    settle_fraction : float
        f of Eq. (6) [-] (0.98).
    settle_level_px : float or None
        f * S_max [px], the line S_k must reach for T_s.
    recovery_time_s : float or None
        T_r = T_s - T_0 [s].
    recovery_time_invalid : str or None
        Why T_r is not valid (``summary["validity"]``); None when it is not invalid.
    flags : tuple of str
        The pitting parameters' flags.
    """

    t_s: FloatArray
    s_k_px: FloatArray
    line_t_s: FloatArray
    line_s_k_px: FloatArray
    gaps: tuple[TimeGap, ...]
    nan_frame_t_s: FloatArray
    outlier_t_s: FloatArray
    outlier_s_k_px: FloatArray
    outlier_source: Literal["analysis", "report"]
    release_gap_s: tuple[float, float] | None
    phases: tuple[PhaseSpan, ...]
    release_s: float | None
    t0_s: float | None
    ts_s: float | None
    s0_px: float | None
    s_max_px: float | None
    settle_fraction: float
    settle_level_px: float | None
    recovery_time_s: float | None
    flags: tuple[str, ...]
    recovery_time_invalid: str | None = None


def _observed(results: Mapping[str, Any] | None) -> Mapping[str, Any] | None:
    """What the analysis recorded about frame coverage (``results.pitting.observation``)."""
    for keys in (("pitting", "observation"), ("pitting", "observed")):
        v = value_at(results, *keys)
        if isinstance(v, Mapping):
            return v
    return None


def _recorded_pair(results: Mapping[str, Any] | None, key: str) -> tuple[float, float] | None:
    """``observed[key]`` as a (start, end) pair of finite-or-inf floats [s], else None."""
    v = value_at(_observed(results), key)
    if not isinstance(v, list) or len(v) != 2:
        return None
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
        return None
    return float(v[0]), float(v[1])


def recorded_outliers(inp: ReportInput) -> NDArray[np.bool_]:
    """The frames the analysis recorded leaving out as outliers (none when not recorded)."""
    recorded = value_at(_observed(inp.results), "outlier_frame_times_s")
    if not isinstance(recorded, list):
        return np.zeros(inp.frame_times_s.shape, dtype=bool)
    times = np.asarray(
        [x for x in recorded if isinstance(x, int | float) and not isinstance(x, bool)],
        dtype=np.float64,
    )
    return np.isin(inp.frame_times_s, times)


def _outlier_frames(inp: ReportInput) -> tuple[NDArray[np.bool_], Literal["analysis", "report"]]:
    """The outlier frames the analysis recorded, else the report's own check."""
    if isinstance(value_at(_observed(inp.results), "outlier_frame_times_s"), list):
        return recorded_outliers(inp), "analysis"
    return isolated_outliers(inp.frame_times_s, inp.s_k_px, inp.t0_s), "report"


def s_k_figure(inp: ReportInput) -> SkFigure:
    """Data of the S_k-over-time figure."""
    p = value_at(inp.results, "pitting")
    fraction = number_at(inp.config, "analysis", "settle_fraction") or DEFAULT_SETTLE_FRACTION
    s_max = number_at(p, "s_max_px")
    flags = value_at(p, "flags")
    t, s = inp.frame_times_s, inp.s_k_px
    gaps = find_gaps(t)
    outliers, source = _outlier_frames(inp)
    line_t, line_s = broken_line(t[~outliers], s[~outliers], gaps)
    return SkFigure(
        t_s=t,
        s_k_px=s,
        line_t_s=line_t,
        line_s_k_px=line_s,
        gaps=gaps,
        nan_frame_t_s=t[~np.isfinite(s)],
        outlier_t_s=t[outliers],
        outlier_s_k_px=s[outliers],
        outlier_source=source,
        release_gap_s=_recorded_pair(inp.results, "release_gap_s"),
        phases=phase_spans(inp.transitions, inp.t_end_s),
        release_s=number_at(inp.summary, "measurement", "t0_s"),
        t0_s=inp.t0_s,
        ts_s=number_at(p, "ts_s"),
        s0_px=number_at(p, "s0_px"),
        s_max_px=s_max,
        settle_fraction=fraction,
        settle_level_px=None if s_max is None else fraction * s_max,
        recovery_time_s=number_at(p, "recovery_time_s"),
        flags=tuple(flags) if isinstance(flags, list) else (),
        recovery_time_invalid=_invalid(read_validity(inp.summary), "recovery_time_s"),
    )


# --------------------------------------------------------------------------------------------
# Recovery fit
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FitFigure:
    """The fitted Kelvin-Voigt recovery against the data, with residuals.

    Attributes
    ----------
    t_since_t0_s : numpy.ndarray
        Times of the fitted frames since T_0 [s].
    s_k_px, model_px, residual_px : numpy.ndarray
        Data, model offset - amplitude exp(-(t - T_0)/tau) and data - model [px].
    t0_s : float
        T_0 [s].
    tau_s, tau_se_s, amplitude_px, offset_px : float or None
        Fitted parameters and tau's standard error.
    rmse_px : float or None
        Root-mean-square residual [px] as the fit reported it.
    r_squared : float or None
        Coefficient of determination.
    n_points : int or None
        Points the fit reported using (equals ``t_since_t0_s.size`` for a stored session).
    flags : tuple of str
        The fit's flags.
    tau_invalid : str or None
        Why tau is not valid (``summary["validity"]``); None when it is not invalid.
    rejected_t_since_t0_s, rejected_s_k_px : numpy.ndarray
        Frames of the fit window the analysis left out as outliers [s since T_0], [px].
    """

    t_since_t0_s: FloatArray
    s_k_px: FloatArray
    model_px: FloatArray
    residual_px: FloatArray
    t0_s: float
    tau_s: float
    tau_se_s: float | None
    amplitude_px: float
    offset_px: float
    rmse_px: float | None
    r_squared: float | None
    n_points: int | None
    flags: tuple[str, ...]
    tau_invalid: str | None = None
    rejected_t_since_t0_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    rejected_s_k_px: FloatArray = field(default_factory=lambda: np.zeros(0))


def fit_figure(inp: ReportInput) -> FitFigure | None:
    """Data of the recovery-fit figure; None when the session has no fitted recovery."""
    fr = value_at(inp.results, "fitted_recovery")
    t0 = number_at(inp.results, "pitting", "t0_s")
    tau, amp, off = (
        number_at(fr, "tau_s"),
        number_at(fr, "amplitude_px"),
        number_at(fr, "offset_px"),
    )
    window = value_at(fr, "window_s")
    if t0 is None or tau is None or amp is None or off is None or not isinstance(window, list):
        return None
    lo, hi = float(window[0]), float(window[1])
    t, s = inp.frame_times_s, inp.s_k_px
    sel = (t >= lo) & (t <= hi) & (t >= t0) & np.isfinite(s)
    rejected = sel & recorded_outliers(inp)
    sel &= ~rejected
    ts, ss = t[sel], s[sel]
    model = kelvin_voigt_recovery(ts, t0, off, amp, tau)
    n = value_at(fr, "n_points")
    flags = value_at(fr, "flags")
    return FitFigure(
        t_since_t0_s=ts - t0,
        s_k_px=ss,
        model_px=model,
        residual_px=ss - model,
        t0_s=t0,
        tau_s=tau,
        tau_se_s=number_at(fr, "tau_se_s"),
        amplitude_px=amp,
        offset_px=off,
        rmse_px=number_at(fr, "rmse_px"),
        r_squared=number_at(fr, "r_squared"),
        n_points=n if isinstance(n, int) else None,
        flags=tuple(flags) if isinstance(flags, list) else (),
        tau_invalid=_invalid(read_validity(inp.summary), "tau_s"),
        rejected_t_since_t0_s=t[rejected] - t0,
        rejected_s_k_px=s[rejected],
    )


# --------------------------------------------------------------------------------------------
# VPR curves (Figs. 10-12)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NormalisedCurve:
    """One VPR curve D(t) = D_p exp(-r t) (Eq. 10), in mm and normalised.

    Attributes
    ----------
    label : str
        Legend text in Fig. 10 (the depth curve, decaying at :attr:`decay_rate_per_s`).
    kind : {"reference", "paper", "fitted"}
        A reference grade, or this session's paper (eta = E T_r) or fitted estimator.
    severe : bool or None
        The grade's clinical class (references), or the session's class from this estimator.
    decay_rate_per_s : float
        r [1/s] of the depth curve.
    depth_mm : float or None
        D_p [mm] (None: the reference has no depth; only the normalised curve is drawn).
    depth_curve_mm : numpy.ndarray or None
        D(t) [mm] on :attr:`VprFigure.t_s`.
    normalised_rate_per_s : float
        Decay rate of the normalised curve used for the severity [1/s]: r itself, except for
        the fitted estimator, classified at 1/T_r with T_r the settling time its tau implies
        (:func:`~stipi_daemon.analysis.severity.classify_fit`).
    normalised : numpy.ndarray
        exp(-r' t) on :attr:`VprFigure.t_s` [-].
    window_mean_depth_fraction : float
        Mean normalised depth over the severity window's samples [-].
    normalised_label : str
        Legend text in Fig. 12 (the normalised curve, decaying at
        :attr:`normalised_rate_per_s`). It differs from :attr:`label` exactly when the two
        rates differ: the fit's curve is D_p exp(-t/tau) in Fig. 10 (eta_tau = E tau) but is
        classified at 1/T_r(tau) in Fig. 12 (eta = E T_r(tau)), so each names its own time.
    nearest_grade : str or None
        The reference grade this curve's estimator found nearest (``results.severity``):
        matched on the normalised curve, not on the depth.
    """

    label: str
    kind: Literal["reference", "paper", "fitted"]
    severe: bool | None
    decay_rate_per_s: float
    depth_mm: float | None
    depth_curve_mm: FloatArray | None
    normalised_rate_per_s: float
    normalised: FloatArray
    window_mean_depth_fraction: float
    normalised_label: str = ""
    nearest_grade: str | None = None


#: What Figs. 10 and 12 say about the grade a session is matched to.
GRADE_MATCH_NOTE: Final = (
    "grades are matched on the normalised curve D(t)/D_p (Fig. 12), not on the depth D_p"
)


@dataclass(frozen=True)
class VprFigure:
    """The VPR curves of Eq. (10) (Fig. 10) and their normalised form (Fig. 12).

    Attributes
    ----------
    t_s : numpy.ndarray
        Times since T_0 [s], 0 to :data:`VPR_HORIZON_S`.
    references : tuple of NormalisedCurve
        The reference grades (mildest first).
    measurements : tuple of NormalisedCurve
        This session's curves (paper estimator, fitted estimator) when it has them.
    window_start_s, window_end_s : float
        The severity window [s since T_0] (the paper's 11-20 s).
    window_sample_times_s : tuple of float
        Its samples [s].
    threshold_depth_fraction : float
        The mild/severe threshold as a normalised depth [-].
    threshold_recovered_percent : float
        The same as a recovered percentage [%] (the paper's 62 %).
    mild_grade, severe_grade : str
        The grades the window separates.
    omitted : tuple of str
        This session's curves left out because a quantity they need is invalid (why).
    grade_note : str
        How this session's nearest grade was found (empty without a curve of this session):
        on the normalised shape, so a curve may start below the depth of its own grade.
    """

    t_s: FloatArray
    references: tuple[NormalisedCurve, ...]
    measurements: tuple[NormalisedCurve, ...]
    window_start_s: float
    window_end_s: float
    window_sample_times_s: tuple[float, ...]
    threshold_depth_fraction: float
    threshold_recovered_percent: float
    mild_grade: str
    severe_grade: str
    omitted: tuple[str, ...] = ()
    grade_note: str = ""


def _curve(
    label: str,
    kind: Literal["reference", "paper", "fitted"],
    severe: bool | None,
    rate: float,
    depth_mm: float | None,
    t: FloatArray,
    window_t: FloatArray,
    normalised_rate: float | None = None,
    normalised_label: str | None = None,
    nearest_grade: str | None = None,
) -> NormalisedCurve:
    nrate = rate if normalised_rate is None else normalised_rate
    return NormalisedCurve(
        label=label,
        kind=kind,
        severe=severe,
        decay_rate_per_s=rate,
        depth_mm=depth_mm,
        depth_curve_mm=None if depth_mm is None else depth_mm * normalised_depth(t, rate),
        normalised_rate_per_s=nrate,
        normalised=normalised_depth(t, nrate),
        window_mean_depth_fraction=float(np.mean(normalised_depth(window_t, nrate))),
        normalised_label=label if normalised_label is None else normalised_label,
        nearest_grade=nearest_grade,
    )


def _invalid(validity: Mapping[str, QuantityStatus] | None, *quantities: str) -> str | None:
    """Why one of ``quantities`` is invalid (None: none is)."""
    v = combined(validity, quantities) if validity is not None else None
    if v is None or v.status != "invalid":
        return None
    return v.reason or "invalid"


def omitted_curves(validity: Mapping[str, QuantityStatus] | None) -> tuple[str, ...]:
    """Why :func:`measurement_curves` leaves a curve out, one line per curve left out."""
    out = []
    depth = _invalid(validity, "depth_mm")
    if depth is not None:
        out.append(f"this session's depth curves D(t) (D_p not valid: {depth})")
    paper = _invalid(validity, "elasticity_kpa", "viscosity_n_s_per_mm2")
    if paper is not None:
        out.append(f"the paper estimator's curve (E or η not valid: {paper})")
    fit = _invalid(validity, "tau_s")
    if fit is not None:
        out.append(f"the fitted curve (τ not valid: {fit})")
    return tuple(out)


def measurement_curves(
    results: Mapping[str, Any] | None,
    t: FloatArray,
    window_t: FloatArray,
    label_prefix: str = "this session",
    validity: Mapping[str, QuantityStatus] | None = None,
) -> tuple[NormalisedCurve, ...]:
    """This session's VPR curves from its results (none without E and eta).

    A curve whose quantities are invalid in ``validity`` is left out (the paper
    estimator's without a valid E and eta, the fit's without a valid tau); an invalid D_p
    leaves the curves normalised only (no depth curve).
    """
    out: list[NormalisedCurve] = []
    if results is None:
        return ()
    depth = None if _invalid(validity, "depth_mm") else number_at(results, "pitting", "depth_mm")
    paper_ok = _invalid(validity, "elasticity_kpa", "viscosity_n_s_per_mm2") is None
    fit_ok = _invalid(validity, "tau_s") is None
    paper = value_at(results, "paper_estimator")
    e, eta = number_at(paper, "elasticity_kpa"), number_at(paper, "viscosity_n_s_per_mm2")
    sev = value_at(results, "severity", "paper_estimator")
    if paper_ok and e is not None and eta is not None and e > 0.0 and eta > 0.0:
        t_r = number_at(results, "pitting", "recovery_time_s")
        out.append(
            _curve(
                f"{label_prefix}: η = E·T_r (Eq. 8)"
                + ("" if t_r is None else f", T_r = {value_text(t_r, 's')}"),
                "paper",
                _severe(sev),
                e / KPA_PER_N_PER_MM2 / eta,
                depth,
                t,
                window_t,
                nearest_grade=_grade(sev),
            )
        )
    fit = _fitted_curve(results, t, window_t, label_prefix, depth) if fit_ok else None
    if fit is not None:
        out.append(fit)
    return tuple(out)


def _severe(sev: Any) -> bool | None:
    cls = value_at(sev, "severity")
    return None if cls is None else cls == "severe"


def _grade(sev: Any) -> str | None:
    g = value_at(sev, "nearest_grade")
    return None if g is None else str(g)


def _fitted_curve(
    results: Mapping[str, Any],
    t: FloatArray,
    window_t: FloatArray,
    label_prefix: str,
    depth: float | None,
) -> NormalisedCurve | None:
    """The fit's curve: D_p exp(-t/tau) (eta_tau = E tau), classified at 1/T_r(tau).

    T_r(tau) is the 98 % settling time an ideal recovery with this tau, S_0 and S_inf
    shows (:func:`~stipi_daemon.analysis.recovery_fit.settling_time_from_time_constant`),
    the time the reference grades' rates 1/T_r are on (Eq. 8). None without a fitted tau.
    """
    fr = value_at(results, "fitted_recovery")
    tau, amp, off = (
        number_at(fr, "tau_s"),
        number_at(fr, "amplitude_px"),
        number_at(fr, "offset_px"),
    )
    if tau is None or tau <= 0.0:
        return None
    t_r_equiv: float | None = None
    if amp is not None and off is not None and off > 0.0 and off - amp >= 0.0:
        try:
            t_r_equiv = settling_time_from_time_constant(tau, off - amp, off)
        except AnalysisError:
            t_r_equiv = None
    sev = value_at(results, "severity", "fitted_recovery")
    label = f"{label_prefix}, fit: η_τ = E·τ, τ = {value_text(tau, 's')}"
    if t_r_equiv is not None and t_r_equiv > 0.0:
        normalised_label = (
            f"{label_prefix}, fit: η = E·T_r(τ), T_r(τ) = {value_text(t_r_equiv, 's')} "
            "(98 % settling time of the fit)"
        )
        nrate: float | None = 1.0 / t_r_equiv
    else:
        normalised_label = f"{label_prefix}, fit: η_τ = E·τ (no settling time: not classified)"
        nrate = None
    return _curve(
        label,
        "fitted",
        _severe(sev),
        1.0 / tau,
        depth,
        t,
        window_t,
        normalised_rate=nrate,
        normalised_label=normalised_label,
        nearest_grade=_grade(sev),
    )


def _window(
    results: Mapping[str, Any] | None, reference: SeverityReference
) -> tuple[float, float, FloatArray, float, str, str]:
    """Window [s], its samples, threshold depth fraction, grades: as classified, else reference."""
    sw = find_severity_window(reference)
    start, end = sw.start_s, sw.end_s
    threshold = sw.threshold_depth_fraction
    for est in ("paper_estimator", "fitted_recovery"):
        sev = value_at(results, "severity", est)
        w = value_at(sev, "window_s")
        pct = number_at(sev, "threshold_recovered_percent")
        if isinstance(w, list) and len(w) == 2 and pct is not None:
            start, end, threshold = float(w[0]), float(w[1]), 1.0 - pct / 100.0
            break
    step = reference.window.step_s
    n = round((end - start) / step) + 1
    samples = start + step * np.arange(max(n, 1), dtype=np.float64)
    return start, end, samples, threshold, sw.mild_grade, sw.severe_grade


def vpr_figure(
    results: Mapping[str, Any] | None,
    reference: SeverityReference,
    *,
    horizon_s: float = VPR_HORIZON_S,
    samples: int = VPR_SAMPLES,
    validity: Mapping[str, QuantityStatus] | None = None,
) -> VprFigure:
    """Data of the VPR figures (Figs. 10 and 12) for one session's results.

    The severity window and threshold are the ones the session was classified with
    (``results.severity``), or the reference's when the session has none. This session's
    curves of invalid quantities (``validity``) are left out (:attr:`VprFigure.omitted`).
    """
    t = np.linspace(0.0, horizon_s, samples)
    start, end, window_t, threshold, mild, severe = _window(results, reference)
    refs = tuple(
        _curve(
            f"grade {g.name} ({'severe' if g.severe else 'mild'}), "
            f"E = {g.elasticity_kpa:g} kPa, η = {g.viscosity_n_s_per_mm2:g} N·s/mm²",
            "reference",
            g.severe,
            g.decay_rate_per_s,
            g.depth_mm,
            t,
            window_t,
            normalised_label=f"grade {g.name} ({'severe' if g.severe else 'mild'})",
        )
        for g in reference.grades
    )
    measurements = measurement_curves(results, t, window_t, validity=validity)
    return VprFigure(
        t_s=t,
        references=refs,
        measurements=measurements,
        window_start_s=start,
        window_end_s=end,
        window_sample_times_s=tuple(float(v) for v in window_t),
        threshold_depth_fraction=threshold,
        threshold_recovered_percent=100.0 * (1.0 - threshold),
        mild_grade=mild,
        severe_grade=severe,
        omitted=omitted_curves(validity) if results is not None else (),
        grade_note=grade_note(measurements),
    )


def grade_note(curves: Sequence[NormalisedCurve]) -> str:
    """How the nearest grade of these curves was found (empty without a curve).

    The grade is the reference whose normalised curve D(t)/D_p is closest: a session's
    depth D_p plays no part, so its Fig. 10 curve may start below its grade's depth.
    """
    if not curves:
        return ""
    grades = sorted({c.nearest_grade for c in curves if c.nearest_grade is not None})
    nearest = f"nearest grade {'/'.join(grades)}; " if grades else ""
    return nearest + GRADE_MATCH_NOTE


@dataclass(frozen=True)
class WindowSearchFigure:
    """Mean distance between adjacent grades per window start (the paper's Fig. 11).

    Attributes
    ----------
    pairs : tuple of (str, numpy.ndarray, numpy.ndarray)
        (label "I-II", window starts [s since T_0], mean |difference| of the normalised
        depths [-]) for each pair of adjacent reference grades.
    window_start_s, window_end_s : float
        The chosen window (largest difference between the mild and severe grades) [s].
    length_s : float
        Window length [s] (10 s).
    """

    pairs: tuple[tuple[str, FloatArray, FloatArray], ...]
    window_start_s: float
    window_end_s: float
    length_s: float


def window_search_figure(reference: SeverityReference) -> WindowSearchFigure:
    """Data of the window-search figure (Fig. 11)."""
    pairs: list[tuple[str, FloatArray, FloatArray]] = []
    for a, b in itertools.pairwise(reference.grades):
        search = reference.window.model_copy(update={"mild_grade": a.name, "severe_grade": b.name})
        sw = find_severity_window(reference, search)
        pairs.append(
            (
                f"{a.name}-{b.name}",
                np.asarray(sw.candidate_starts_s, dtype=np.float64),
                np.asarray(sw.candidate_differences, dtype=np.float64),
            )
        )
    chosen = find_severity_window(reference)
    return WindowSearchFigure(
        pairs=tuple(pairs),
        window_start_s=chosen.start_s,
        window_end_s=chosen.end_s,
        length_s=reference.window.length_s,
    )
