"""Figure data of the session report: the arrays each figure plots and the tables it shows.

This module owns what a report shows, as plain arrays and records built from one
recorded session (:class:`ReportInput`): force and S_k over time with the measurement's
phases, the Kelvin-Voigt recovery fitted to S_k with its residuals, the VPR curves of
Eq. (10) and their normalised form against the reference grades with the severity window
and threshold (the paper's Figs. 10-12), the parameter table with uncertainties, flags and
(for simulated sessions) the ground truth, the representative frames with their Eq. (1)
thresholding, and the comparison of several sessions (per-parameter mean and spread, as the
paper's Tables I and II). It is pure: no file access (:mod:`.load`), no drawing
(:mod:`.render`), no HTML (:mod:`.html`), so tests can compare every plotted sample with
the session's rows. Times are on the session clock [s] unless a name says "since T_0".
"""

from __future__ import annotations

import ast
import inspect
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cache
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.analysis import flags as flags_module
from stipi_daemon.analysis.imaging import (
    ROI,
    CircleROI,
    RectROI,
    occluded_pixel_count,
    roi_mask,
    threshold_binary_inverted,
    to_gray,
)
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
from stipi_daemon.errors import AnalysisError, SessionError
from stipi_daemon.measurement.replay import compare_ground_truth
from stipi_daemon.report.frames import KINDS, RepresentativeFrame
from stipi_daemon.storage.schema import Transition

__all__ = [
    "COMPARE_PARAMETERS",
    "CompareGroup",
    "CompareStat",
    "CompareTable",
    "FitFigure",
    "ForceFigure",
    "FramePanel",
    "NormalisedCurve",
    "OverlaySeries",
    "ParameterRow",
    "PhaseSpan",
    "ReportInput",
    "SkFigure",
    "VprFigure",
    "WindowSearchFigure",
    "compare_table",
    "fit_figure",
    "flag_descriptions",
    "force_figure",
    "frame_panels",
    "overlay_force",
    "overlay_s_k",
    "parameter_table",
    "phase_spans",
    "s_k_figure",
    "vpr_figure",
    "window_search_figure",
]

FloatArray = npt.NDArray[np.float64]

#: Time span of the VPR curves (Figs. 10 and 12) [s since T_0]: the paper's recovery window.
VPR_HORIZON_S: Final = DEFAULT_WINDOW_S
#: Samples of the VPR curves over :data:`VPR_HORIZON_S` (0.1 s apart).
VPR_SAMPLES: Final = 1051


# --------------------------------------------------------------------------------------------
# Input
# --------------------------------------------------------------------------------------------


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, Mapping):
            return None
        d = d.get(k)
    return d


def _num(d: Any, *keys: str) -> float | None:
    v = _get(d, *keys)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


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
        r = _get(self.summary, "results")
        return r if isinstance(r, Mapping) else None

    @property
    def t0_s(self) -> float | None:
        """T_0 the analysis used [s]: the results' one, else the refined or detected one."""
        for keys in (
            ("results", "pitting", "t0_s"),
            ("measurement", "t0_refined_s"),
            ("measurement", "t0_s"),
        ):
            v = _num(self.summary, *keys)
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
    """

    t_s: FloatArray
    force_n: FloatArray
    phases: tuple[PhaseSpan, ...]
    target_n: float | None
    tolerance_n: float | None
    release_n: float | None
    applied_force_n: float | None
    hold_s: tuple[float, float] | None
    t0_s: float | None


def force_figure(inp: ReportInput) -> ForceFigure:
    """Data of the force-over-time figure."""
    m = _get(inp.config, "measurement")
    start = _num(inp.summary, "measurement", "t_pit_start_s")
    end = _num(inp.summary, "measurement", "t_pit_end_s")
    t0 = inp.t0_s
    return ForceFigure(
        t_s=inp.force_times_s,
        force_n=inp.force_n,
        phases=phase_spans(inp.transitions, inp.t_end_s),
        target_n=_num(m, "target_force_n"),
        tolerance_n=_num(m, "force_tolerance_n"),
        release_n=_num(m, "release_force_n"),
        applied_force_n=_num(inp.results, "applied_force_n"),
        # The hold F_a averages over ends at T_0 at the latest (the pipeline's rule).
        hold_s=None if start is None or end is None else (start, min(end, t0 or end)),
        t0_s=inp.t0_s,
    )


@dataclass(frozen=True)
class SkFigure:
    """S_k over time with T_0, T_s and the settling line (Eq. 6).

    Attributes
    ----------
    t_s, s_k_px : numpy.ndarray
        Every frame as stored: capture time [s], S_k [px].
    phases : tuple of PhaseSpan
        Phases of the measurement.
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
    flags : tuple of str
        The pitting parameters' flags.
    """

    t_s: FloatArray
    s_k_px: FloatArray
    phases: tuple[PhaseSpan, ...]
    t0_s: float | None
    ts_s: float | None
    s0_px: float | None
    s_max_px: float | None
    settle_fraction: float
    settle_level_px: float | None
    recovery_time_s: float | None
    flags: tuple[str, ...]


def s_k_figure(inp: ReportInput) -> SkFigure:
    """Data of the S_k-over-time figure."""
    p = _get(inp.results, "pitting")
    fraction = _num(inp.config, "analysis", "settle_fraction") or DEFAULT_SETTLE_FRACTION
    s_max = _num(p, "s_max_px")
    flags = _get(p, "flags")
    return SkFigure(
        t_s=inp.frame_times_s,
        s_k_px=inp.s_k_px,
        phases=phase_spans(inp.transitions, inp.t_end_s),
        t0_s=inp.t0_s,
        ts_s=_num(p, "ts_s"),
        s0_px=_num(p, "s0_px"),
        s_max_px=s_max,
        settle_fraction=fraction,
        settle_level_px=None if s_max is None else fraction * s_max,
        recovery_time_s=_num(p, "recovery_time_s"),
        flags=tuple(flags) if isinstance(flags, list) else (),
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


def fit_figure(inp: ReportInput) -> FitFigure | None:
    """Data of the recovery-fit figure; None when the session has no fitted recovery."""
    fr = _get(inp.results, "fitted_recovery")
    t0 = _num(inp.results, "pitting", "t0_s")
    tau, amp, off = _num(fr, "tau_s"), _num(fr, "amplitude_px"), _num(fr, "offset_px")
    window = _get(fr, "window_s")
    if t0 is None or tau is None or amp is None or off is None or not isinstance(window, list):
        return None
    lo, hi = float(window[0]), float(window[1])
    t, s = inp.frame_times_s, inp.s_k_px
    sel = (t >= lo) & (t <= hi) & (t >= t0) & np.isfinite(s)
    ts, ss = t[sel], s[sel]
    model = kelvin_voigt_recovery(ts, t0, off, amp, tau)
    n = _get(fr, "n_points")
    flags = _get(fr, "flags")
    return FitFigure(
        t_since_t0_s=ts - t0,
        s_k_px=ss,
        model_px=model,
        residual_px=ss - model,
        t0_s=t0,
        tau_s=tau,
        tau_se_s=_num(fr, "tau_se_s"),
        amplitude_px=amp,
        offset_px=off,
        rmse_px=_num(fr, "rmse_px"),
        r_squared=_num(fr, "r_squared"),
        n_points=n if isinstance(n, int) else None,
        flags=tuple(flags) if isinstance(flags, list) else (),
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
        Legend text.
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


def _curve(
    label: str,
    kind: Literal["reference", "paper", "fitted"],
    severe: bool | None,
    rate: float,
    depth_mm: float | None,
    t: FloatArray,
    window_t: FloatArray,
    normalised_rate: float | None = None,
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
    )


def measurement_curves(
    results: Mapping[str, Any] | None,
    t: FloatArray,
    window_t: FloatArray,
    label_prefix: str = "this session",
) -> tuple[NormalisedCurve, ...]:
    """This session's VPR curves from its results (none without E and eta)."""
    out: list[NormalisedCurve] = []
    if results is None:
        return ()
    depth = _num(results, "pitting", "depth_mm")
    paper = _get(results, "paper_estimator")
    e, eta = _num(paper, "elasticity_kpa"), _num(paper, "viscosity_n_s_per_mm2")
    sev = _get(results, "severity", "paper_estimator", "severity")
    if e is not None and eta is not None and e > 0.0 and eta > 0.0:
        t_r = _num(results, "pitting", "recovery_time_s")
        out.append(
            _curve(
                f"{label_prefix}: η = E·T_r (Eq. 8)"
                + ("" if t_r is None else f", T_r = {t_r:.2f} s"),
                "paper",
                None if sev is None else sev == "severe",
                e / KPA_PER_N_PER_MM2 / eta,
                depth,
                t,
                window_t,
            )
        )
    fr = _get(results, "fitted_recovery")
    tau, amp, off = _num(fr, "tau_s"), _num(fr, "amplitude_px"), _num(fr, "offset_px")
    if tau is not None and tau > 0.0:
        nrate: float | None = None
        if amp is not None and off is not None and off > 0.0 and off - amp >= 0.0:
            try:
                t_r_equiv = settling_time_from_time_constant(tau, off - amp, off)
            except AnalysisError:
                t_r_equiv = 0.0
            nrate = 1.0 / t_r_equiv if t_r_equiv > 0.0 else None
        sev_fit = _get(results, "severity", "fitted_recovery", "severity")
        label = f"{label_prefix}: η = E·τ (fit), τ = {tau:.2f} s"
        if nrate is not None:
            label += f", T_r(τ) = {1.0 / nrate:.2f} s"
        out.append(
            _curve(
                label,
                "fitted",
                None if sev_fit is None else sev_fit == "severe",
                1.0 / tau,
                depth,
                t,
                window_t,
                normalised_rate=nrate,
            )
        )
    return tuple(out)


def _window(
    results: Mapping[str, Any] | None, reference: SeverityReference
) -> tuple[float, float, FloatArray, float, str, str]:
    """Window [s], its samples, threshold depth fraction, grades: as classified, else reference."""
    sw = find_severity_window(reference)
    start, end = sw.start_s, sw.end_s
    threshold = sw.threshold_depth_fraction
    for est in ("paper_estimator", "fitted_recovery"):
        sev = _get(results, "severity", est)
        w = _get(sev, "window_s")
        pct = _num(sev, "threshold_recovered_percent")
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
) -> VprFigure:
    """Data of the VPR figures (Figs. 10 and 12) for one session's results.

    The severity window and threshold are the ones the session was classified with
    (``results.severity``), or the reference's when the session has none.
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
        )
        for g in reference.grades
    )
    return VprFigure(
        t_s=t,
        references=refs,
        measurements=measurement_curves(results, t, window_t),
        window_start_s=start,
        window_end_s=end,
        window_sample_times_s=tuple(float(v) for v in window_t),
        threshold_depth_fraction=threshold,
        threshold_recovered_percent=100.0 * (1.0 - threshold),
        mild_grade=mild,
        severe_grade=severe,
    )


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


# --------------------------------------------------------------------------------------------
# Parameter table
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterRow:
    """One line of the parameter table.

    Attributes
    ----------
    group : str
        Section of the table (pitting, VPR model, fit, severity).
    symbol, name : str
        Symbol as the paper writes it and a few words.
    key : str
        Stable identifier (unit in the name, ground-truth key where one exists).
    value : float or str or None
        The value (None: not available, see ``note``).
    uncertainty : float or None
        One standard error, in the value's unit (only the fit reports them).
    unit : str
        Unit of value and uncertainty.
    flags : tuple of str
        Quality flags of the value.
    note : str
        Why a value is missing or how it is to be read.
    truth : float or None
        Simulator ground truth, when the session has one.
    error_percent : float or None
        100 (value - truth)/|truth| [%].
    """

    group: str
    symbol: str
    name: str
    key: str
    value: float | str | None
    uncertainty: float | None
    unit: str
    flags: tuple[str, ...] = ()
    note: str = ""
    truth: float | None = None
    error_percent: float | None = None


def _flags(d: Any) -> tuple[str, ...]:
    v = _get(d, "flags")
    return tuple(str(f) for f in v) if isinstance(v, list) else ()


def parameter_table(summary: Mapping[str, Any] | None) -> tuple[ParameterRow, ...]:
    """Every result of the session's summary, with uncertainties, flags and ground truth.

    The standard error of eta = E tau is propagated from tau's alone (E has none).
    Empty when the summary has no results.
    """
    res = _get(summary, "results")
    if not isinstance(res, Mapping):
        return ()
    p = _get(res, "pitting")
    pe = _get(res, "paper_estimator")
    fr = _get(res, "fitted_recovery")
    fm = _get(fr, "model")
    pflags = _flags(p)
    fflags = _flags(fr)
    truth = _get(summary, "ground_truth")
    t_r_note = (
        "lower bound: S_k had not settled" if "not_settled" in pflags else "98 % settling time"
    )
    tau, tau_se = _num(fr, "tau_s"), _num(fr, "tau_se_s")
    e_fit = _num(fm, "elasticity_kpa")
    eta_fit_se = None if tau is None or tau_se is None or e_fit is None else e_fit * tau_se / 1e3
    pit, vpr, fit, sev = (
        "Pitting parameters (Eqs. 3-6)",
        "VPR model, paper estimator (Eqs. 7-8, 10)",
        "Kelvin-Voigt recovery fit (η = E·τ)",
        "Edema severity (Section IV.C)",
    )
    rows = [
        ParameterRow(pit, "T_0", "start of recovery", "t0_s", _num(p, "t0_s"), None, "s"),
        ParameterRow(pit, "T_s", "S_k settled (98 %)", "ts_s", _num(p, "ts_s"), None, "s", pflags),
        ParameterRow(pit, "S_0", "S_k at T_0", "s0_px", _num(p, "s0_px"), None, "px"),
        ParameterRow(pit, "S_max", "largest S_k", "s_max_px", _num(p, "s_max_px"), None, "px"),
        ParameterRow(
            pit,
            "d_s",
            "depth change (Eq. 4)",
            "depth_change_mm",
            _num(p, "depth_change_mm"),
            None,
            "mm",
            pflags,
        ),
        ParameterRow(
            pit,
            "D_p",
            "pitting depth (Eq. 3)",
            "depth_mm",
            _num(p, "depth_mm"),
            None,
            "mm",
            pflags,
        ),
        ParameterRow(
            pit,
            "F_r",
            "rebound force (Eq. 5)",
            "rebound_force_n",
            _num(p, "rebound_force_n"),
            None,
            "N",
            pflags,
        ),
        ParameterRow(
            pit,
            "T_r",
            "recovery time (Eq. 6)",
            "recovery_time_s",
            _num(p, "recovery_time_s"),
            None,
            "s",
            pflags,
            t_r_note,
        ),
        ParameterRow(
            vpr,
            "F_a",
            "applied force (mean over the hold)",
            "applied_force_n",
            _num(res, "applied_force_n"),
            None,
            "N",
        ),
        ParameterRow(
            vpr,
            "R",
            "indenter radius",
            "indenter_radius_mm",
            _num(res, "indenter_radius_mm"),
            None,
            "mm",
        ),
        ParameterRow(
            vpr,
            "E",
            "elasticity (Eq. 7)",
            "elasticity_kpa",
            _num(pe, "elasticity_kpa"),
            None,
            "kPa",
            pflags,
            "" if pe is not None else "undefined (see notes)",
        ),
        ParameterRow(
            vpr,
            "η",
            "viscosity E·T_r (Eq. 8)",
            "viscosity_n_s_per_mm2",
            _num(pe, "viscosity_n_s_per_mm2"),
            None,
            "N·s/mm²",
            pflags,
            "" if pe is not None else "undefined (see notes)",
        ),
        ParameterRow(
            fit,
            "τ",
            "time constant",
            "time_constant_s",
            tau,
            tau_se,
            "s",
            fflags,
            "" if tau is not None else "no fit (see flags and notes)",
        ),
        ParameterRow(
            fit,
            "A",
            "amplitude S_∞ - S_0",
            "amplitude_px",
            _num(fr, "amplitude_px"),
            _num(fr, "amplitude_se_px"),
            "px",
            fflags,
        ),
        ParameterRow(
            fit,
            "S_∞",
            "offset (settled S_k)",
            "offset_px",
            _num(fr, "offset_px"),
            _num(fr, "offset_se_px"),
            "px",
            fflags,
        ),
        ParameterRow(
            fit,
            "η_τ",
            "viscosity E·τ",
            "viscosity_from_time_constant_n_s_per_mm2",
            _num(fm, "viscosity_n_s_per_mm2"),
            eta_fit_se,
            "N·s/mm²",
            fflags,
            "SE from τ only",
        ),
        ParameterRow(fit, "RMSE", "residual RMS", "rmse_px", _num(fr, "rmse_px"), None, "px"),
        ParameterRow(
            fit, "R²", "coefficient of determination", "r_squared", _num(fr, "r_squared"), None, "-"
        ),
        ParameterRow(fit, "n", "frames fitted", "n_points", _num(fr, "n_points"), None, "-"),
    ]
    for est, label in (("paper_estimator", "paper estimator"), ("fitted_recovery", "fit")):
        s = _get(res, "severity", est)
        if not isinstance(s, Mapping):
            rows.append(
                ParameterRow(
                    sev,
                    "class",
                    f"severity ({label})",
                    f"severity_{est}",
                    None,
                    None,
                    "",
                    (),
                    "undefined (see notes)",
                )
            )
            continue
        w = _get(s, "window_s")
        wtext = f"{w[0]:g}-{w[1]:g} s" if isinstance(w, list) and len(w) == 2 else "?"
        thr = _num(s, "threshold_recovered_percent")
        rows += [
            ParameterRow(
                sev,
                "class",
                f"severity ({label})",
                f"severity_{est}",
                f"{s.get('severity')} (nearest grade {s.get('nearest_grade')})",
                None,
                "",
                _flags(s),
            ),
            ParameterRow(
                sev,
                "recovered",
                f"recovered over {wtext} ({label})",
                f"recovered_percent_{est}",
                _num(s, "recovered_percent"),
                None,
                "%",
                _flags(s),
                "" if thr is None else f"severe below {thr:.1f} %",
            ),
        ]
    if isinstance(truth, Mapping):
        comparisons = {c.name: c for c in compare_ground_truth(summary or {}, truth)}
        out = []
        for r in rows:
            c = comparisons.get(r.key)
            t_value = c.truth if c is not None else None
            if c is None and r.key in ("depth_change_mm", "s0_px", "s_max_px"):
                t_value = _num(truth, r.key)
            err = c.error_percent if c is not None else None
            if err is None and t_value not in (None, 0.0) and isinstance(r.value, float):
                assert t_value is not None
                err = 100.0 * (r.value - t_value) / abs(t_value)
            out.append(replace(r, truth=t_value, error_percent=err))
        rows = out
    return tuple(rows)


@cache
def flag_descriptions() -> dict[str, str]:
    """Flag value -> its description, read from :class:`~stipi_daemon.analysis.flags.Flag`.

    The descriptions are the attribute docstrings of the enum's source; empty when the
    source is not available (e.g. a zipped install).
    """
    try:
        tree = ast.parse(inspect.getsource(flags_module))
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.ClassDef) and node.name == "Flag"):
            continue
        body = node.body
        for a, b in itertools.pairwise(body):
            if (
                isinstance(a, ast.Assign)
                and isinstance(a.value, ast.Constant)
                and isinstance(a.value.value, str)
                and isinstance(b, ast.Expr)
                and isinstance(b.value, ast.Constant)
                and isinstance(b.value.value, str)
            ):
                out[a.value.value] = " ".join(b.value.value.split())
    return out


# --------------------------------------------------------------------------------------------
# Representative frames
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FramePanel:
    """A raw frame and its Eq. (1) thresholding, with the ROI.

    Attributes
    ----------
    kind, caption : str
        Which representative frame (:data:`~stipi_daemon.report.frames.KINDS`).
    seq : int
        Camera frame number.
    t_s : float
        Capture time [s].
    t_since_t0_s : float or None
        Capture time since T_0 [s].
    raw : numpy.ndarray
        The raw frame as recorded (``uint8``, gray or BGR).
    binary : numpy.ndarray
        Eq. (1) over the whole frame: 1 where gray <= p (``uint8``).
    roi_mask : numpy.ndarray
        ``bool`` (H, W), True inside the ROI.
    roi : RectROI or CircleROI or None
        The ROI (None: whole frame).
    threshold_p : int
        p of Eq. (1) [8-bit].
    s_k_recount_px : int
        S_k counted again from the stored frame, Eq. (2) [px].
    s_k_live_px : int
        S_k measured live for this frame [px].
    s_k_table_px : float or None
        S_k the session's ``frames`` table holds for ``seq`` [px].
    """

    kind: str
    caption: str
    seq: int
    t_s: float
    t_since_t0_s: float | None
    raw: npt.NDArray[np.uint8]
    binary: npt.NDArray[np.uint8]
    roi_mask: npt.NDArray[np.bool_]
    roi: RectROI | CircleROI | None
    threshold_p: int
    s_k_recount_px: int
    s_k_live_px: int
    s_k_table_px: float | None


def roi_from_mapping(value: Any, where: str) -> RectROI | CircleROI | None:
    """The ROI a manifest records (``{"kind": "circle", ...}``), or None.

    Raises
    ------
    SessionError
        The value is not a valid ROI (``where`` names the place).
    """
    if value is None:
        return None
    try:
        roi: RectROI | CircleROI = TypeAdapter(ROI).validate_python(value)
    except ValidationError as exc:
        raise SessionError(f"{where}: not a valid ROI: {exc.errors()[0]['msg']}") from None
    return roi


def frame_panels(inp: ReportInput) -> tuple[FramePanel, ...]:
    """The representative frames thresholded with the session's p and ROI.

    Raises
    ------
    SessionError
        The manifest's calibration has no threshold p or an invalid ROI while the session
        holds representative frames.
    """
    if not inp.representative:
        return ()
    p = inp.calibration.get("threshold_p")
    if isinstance(p, bool) or not isinstance(p, int):
        raise SessionError(
            f"session {inp.session_id}: manifest calibration has no integer threshold_p ({p!r})"
        )
    roi = roi_from_mapping(inp.calibration.get("roi"), f"session {inp.session_id}: calibration.roi")
    by_seq = dict(zip(inp.frame_seq.tolist(), inp.s_k_px.tolist(), strict=True))
    t0 = inp.t0_s
    out = []
    for f in inp.representative:
        gray = to_gray(f.image)
        out.append(
            FramePanel(
                kind=f.kind,
                caption=KINDS.get(f.kind, f.kind),
                seq=f.seq,
                t_s=f.t_s,
                t_since_t0_s=None if t0 is None else f.t_s - t0,
                raw=f.image,
                binary=threshold_binary_inverted(gray, p),
                roi_mask=roi_mask(f.image.shape, roi),
                roi=roi,
                threshold_p=p,
                s_k_recount_px=occluded_pixel_count(f.image, p, roi),
                s_k_live_px=f.s_k_px,
                s_k_table_px=by_seq.get(f.seq),
            )
        )
    return tuple(out)


# --------------------------------------------------------------------------------------------
# Comparison of sessions
# --------------------------------------------------------------------------------------------

#: Parameters tabulated by :func:`compare_table`: (key, symbol, unit, path in the results).
COMPARE_PARAMETERS: Final[tuple[tuple[str, str, str, tuple[str, ...]], ...]] = (
    ("depth_mm", "D_p", "mm", ("pitting", "depth_mm")),
    ("rebound_force_n", "F_r", "N", ("pitting", "rebound_force_n")),
    ("recovery_time_s", "T_r", "s", ("pitting", "recovery_time_s")),
    ("applied_force_n", "F_a", "N", ("applied_force_n",)),
    ("elasticity_kpa", "E", "kPa", ("paper_estimator", "elasticity_kpa")),
    ("viscosity_n_s_per_mm2", "η = E·T_r", "N·s/mm²", ("paper_estimator", "viscosity_n_s_per_mm2")),
    ("time_constant_s", "τ", "s", ("fitted_recovery", "tau_s")),
    (
        "viscosity_from_time_constant_n_s_per_mm2",
        "η = E·τ",
        "N·s/mm²",
        ("fitted_recovery", "model", "viscosity_n_s_per_mm2"),
    ),
)


@dataclass(frozen=True)
class CompareStat:
    """Mean and spread of one parameter over a group of sessions.

    Attributes
    ----------
    key, symbol, unit : str
        The parameter.
    values : tuple of float or None
        Each session's value, in the group's order (None: the session has none).
    n : int
        Sessions with a value.
    mean : float or None
        Mean over them.
    sd : float or None
        Sample standard deviation (n - 1), None for n < 2.
    cv_percent : float or None
        100 sd / |mean| [%].
    """

    key: str
    symbol: str
    unit: str
    values: tuple[float | None, ...]
    n: int
    mean: float | None
    sd: float | None
    cv_percent: float | None


@dataclass(frozen=True)
class CompareGroup:
    """Sessions sharing a label (e.g. repeated trials of one phantom) and their statistics."""

    label: str
    session_ids: tuple[str, ...]
    stats: tuple[CompareStat, ...]
    severe_count: int
    classified_count: int


@dataclass(frozen=True)
class CompareTable:
    """Per-session values and per-group and overall mean and spread (Tables I and II).

    Attributes
    ----------
    session_ids, labels : tuple of str
        The sessions and their labels, in the order given.
    severities : tuple of str or None
        Each session's class and nearest grade from the paper estimator (``"severe
        (III)"``), None without one.
    groups : tuple of CompareGroup
        One per distinct label, in first-appearance order.
    overall : CompareGroup
        All sessions together.
    """

    session_ids: tuple[str, ...]
    labels: tuple[str, ...]
    severities: tuple[str | None, ...]
    groups: tuple[CompareGroup, ...]
    overall: CompareGroup


def _stat(key: str, symbol: str, unit: str, values: tuple[float | None, ...]) -> CompareStat:
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    mean = float(np.mean(v)) if v.size else None
    sd = float(np.std(v, ddof=1)) if v.size >= 2 else None
    cv = None if sd is None or mean is None or mean == 0.0 else 100.0 * sd / abs(mean)
    return CompareStat(key, symbol, unit, values, int(v.size), mean, sd, cv)


def _group(label: str, members: Sequence[ReportInput]) -> CompareGroup:
    stats = tuple(
        _stat(key, symbol, unit, tuple(_num(m.results, *path) for m in members))
        for key, symbol, unit, path in COMPARE_PARAMETERS
    )
    classes = [_get(m.results, "severity", "paper_estimator", "severity") for m in members]
    return CompareGroup(
        label=label,
        session_ids=tuple(m.session_id for m in members),
        stats=stats,
        severe_count=sum(c == "severe" for c in classes),
        classified_count=sum(c is not None for c in classes),
    )


def compare_table(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> CompareTable:
    """Tabulate several sessions: each one's values, mean and spread per label and overall.

    Parameters
    ----------
    inputs : sequence of ReportInput
        The sessions (at least one).
    labels : sequence of str, optional
        One label per session (e.g. the grade); sessions with the same label form a group
        (repeated trials). Default: each session's id.

    Raises
    ------
    AnalysisError
        No session, or a label count that differs from the session count.
    """
    if not inputs:
        raise AnalysisError("nothing to compare: no session given")
    names = tuple(labels) if labels is not None else tuple(i.session_id for i in inputs)
    if len(names) != len(inputs):
        raise AnalysisError(f"{len(names)} labels for {len(inputs)} sessions")
    order: dict[str, list[ReportInput]] = {}
    for name, inp in zip(names, inputs, strict=True):
        order.setdefault(name, []).append(inp)
    severities: list[str | None] = []
    for inp in inputs:
        sev = _get(inp.results, "severity", "paper_estimator")
        cls, grade = _get(sev, "severity"), _get(sev, "nearest_grade")
        severities.append(None if cls is None else f"{cls} ({grade})")
    return CompareTable(
        session_ids=tuple(i.session_id for i in inputs),
        labels=names,
        severities=tuple(severities),
        groups=tuple(_group(name, members) for name, members in order.items()),
        overall=_group("all sessions", list(inputs)),
    )


@dataclass(frozen=True)
class OverlaySeries:
    """One session's series against time since its T_0, for overlays.

    Attributes
    ----------
    label : str
        Legend text.
    t_since_t0_s : numpy.ndarray
        Times since the session's T_0 [s].
    values : numpy.ndarray
        The series (S_k [px] or force [N]).
    """

    label: str
    t_since_t0_s: FloatArray
    values: FloatArray


def _overlay(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None, which: str
) -> tuple[OverlaySeries, ...]:
    names = list(labels) if labels is not None else [i.session_id for i in inputs]
    out = []
    for name, inp in zip(names, inputs, strict=True):
        t0 = inp.t0_s
        if t0 is None:
            continue
        t, v = (
            (inp.frame_times_s, inp.s_k_px) if which == "s_k" else (inp.force_times_s, inp.force_n)
        )
        out.append(OverlaySeries(name, t - t0, v))
    return tuple(out)


def overlay_s_k(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> tuple[OverlaySeries, ...]:
    """Each session's S_k [px] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "s_k")


def overlay_force(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> tuple[OverlaySeries, ...]:
    """Each session's force [N] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "force")
