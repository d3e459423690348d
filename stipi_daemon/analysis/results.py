"""Whole-measurement analysis: from a recovery series to every result the paper reports.

This module composes the analysis core for one measurement: the pitting parameters
(Eqs. 3-6, :mod:`~stipi_daemon.analysis.pitting`), the paper's VPR model (Eqs. 7-10,
:mod:`~stipi_daemon.analysis.vpr`), the fitted Kelvin-Voigt recovery
(:mod:`~stipi_daemon.analysis.recovery_fit`) and the severity classification (Section
IV.C, :mod:`~stipi_daemon.analysis.severity`), for both estimators side by side; and every
recovery model of :mod:`~stipi_daemon.analysis.recovery_models` fitted to the same frames
as the Kelvin-Voigt fit, with AICc weights, bootstrap 95 % intervals on tau, T_r, F_r and
eta, and the ``KELVIN_VOIGT_REJECTED`` flag when the data reject the single exponential. It also
owns the applied force F_a of Eq. (7) measured from the load cell during the pitting hold.
It does not own how T_0 is found (the state machine or
:func:`~stipi_daemon.analysis.pitting.detect_recovery_start` decide it), nor any I/O.

Domain: the series must hold at least two frames at or after T_0 (else
:class:`~stipi_daemon.errors.AnalysisError`). Parts that cannot be computed are ``None``
with the reason in :attr:`MeasurementResult.notes`: no recovery (``no_recovery``) leaves
T_r, eta and the paper's severity undefined; a zero pitting depth leaves E undefined; a
fit that does not converge leaves the fitted estimator undefined.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.image_quality import (
    FramePictures,
    ImageQuality,
    QualityRule,
    judge_pictures,
)
from stipi_daemon.analysis.model_checks import (
    ResultCheck,
    model_checks,
    supported_fits,
    uncertainty_checks,
)
from stipi_daemon.analysis.observation import noise_sigma
from stipi_daemon.analysis.pitting import (
    DEFAULT_PERSIST_FRAMES,
    DEFAULT_SETTLE_FRACTION,
    DEFAULT_WINDOW_S,
    PittingParameters,
    compute_pitting_parameters,
    rebound_force_n,
)
from stipi_daemon.analysis.recovery_fit import RecoveryFit, fit_recovery
from stipi_daemon.analysis.recovery_models import (
    DEFAULT_REPLICATES,
    RecoveryModelComparison,
    fit_recovery_models,
)
from stipi_daemon.analysis.severity import (
    SeverityReference,
    SeverityResult,
    classify_decay_rate,
    classify_fit,
    classify_vpr,
)
from stipi_daemon.analysis.vpr import VPRModel
from stipi_daemon.errors import AnalysisError

__all__ = [
    "FIT_GAP_FRACTION",
    "POOR_FIT_NOISE_RATIO",
    "POOR_FIT_R_SQUARED",
    "AnalysisSettings",
    "MeasurementResult",
    "analyze_recovery",
    "applied_force_n_from_samples",
    "depth_relative_sd",
    "force_at_rail_fraction",
    "force_full_scale_n",
]


#: A fit whose window has gaps covering more than this fraction of its span is flagged
#: ``FRAME_GAPS_IN_FIT`` [-].
FIT_GAP_FRACTION = 0.1
#: A fit is flagged ``POOR_FIT`` (its tau is not reported as a result) when its residuals
#: are structured: R^2 below this [-] ...
POOR_FIT_R_SQUARED = 0.99
#: ... and an RMS residual larger than this many times the frame-to-frame noise
#: (:func:`~stipi_daemon.analysis.observation.noise_sigma`), which noise alone cannot
#: explain. A faithful fit of a noisy, barely rising series has a low R^2 but residuals at
#: the noise level: it is not poor [-].
POOR_FIT_NOISE_RATIO = 3.0
#: F_a is invalid (``FORCE_AT_FULL_SCALE``) when more than this fraction of the hold's
#: load-cell samples sit at full scale [-].
FORCE_RAIL_FRACTION = 0.01


class AnalysisSettings(BaseModel):
    """Settings of the whole-measurement analysis (the ``analysis:`` section of a config).

    Attributes
    ----------
    indenter_radius_mm : float
        R of Eq. (7) [mm]; the paper's indenter is 15 mm in diameter.
    applied_force_n : float or None
        F_a of Eq. (7) [N]. ``None`` (default) uses the mean load-cell force over the
        pitting hold, as measured; a number fixes it (the paper states 16 N).
    settle_fraction : float
        Fraction of S_max that defines T_s in Eq. (6) [-].
    recovery_window_s : float
        Recovery window after T_0 analysed [s] (the paper's 105 s).
    persist_frames : int
        Frames a 98 % crossing must persist to count (rejects a single noisy frame).
    bootstrap_replicates : int
        Moving-block bootstrap replicates per recovery model for the 95 % intervals
        (0: none) [-].
    bootstrap_seed : int
        Seed of the bootstrap: the same session gives the same intervals [-].
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    indenter_radius_mm: float = Field(7.5, gt=0.0, allow_inf_nan=False)
    applied_force_n: float | None = Field(None, gt=0.0, allow_inf_nan=False)
    settle_fraction: float = Field(DEFAULT_SETTLE_FRACTION, gt=0.0, lt=1.0)
    recovery_window_s: float = Field(DEFAULT_WINDOW_S, gt=0.0, allow_inf_nan=False)
    persist_frames: int = Field(DEFAULT_PERSIST_FRAMES, ge=1)
    bootstrap_replicates: int = Field(DEFAULT_REPLICATES, ge=0, le=100_000)
    bootstrap_seed: int = Field(0, ge=0)


@dataclass(frozen=True)
class MeasurementResult:
    """Every result of one measurement, both recovery estimators side by side.

    Attributes
    ----------
    pitting : PittingParameters
        D_p [mm], F_r [N], T_r [s] and their flags (Eqs. 3-6).
    applied_force_n : float
        F_a used in Eq. (7) [N].
    indenter_radius_mm : float
        R used in Eq. (7) [mm].
    paper_model : VPRModel or None
        E [kPa] from Eq. (7), eta = E * T_r [N*s/mm^2] from Eq. (8): the paper's estimator.
    fit : RecoveryFit
        Kelvin-Voigt recovery fitted to the S_k series after T_0 (tau [s] +- SE).
    fit_model : VPRModel or None
        E from Eq. (7), eta = E * tau [N*s/mm^2] from the fitted time constant.
    severity_paper, severity_fit : SeverityResult or None
        Section IV.C classification from each estimator.
    notes : tuple[str, ...]
        Why a part is ``None``, in words.
    models : RecoveryModelComparison or None
        Every recovery model fitted to the frames of ``fit``, with AICc weights and 95 %
        intervals; None when the comparison could not run (the reason is in ``notes``).
    checks : tuple[ResultCheck, ...]
        The rules of :mod:`~stipi_daemon.analysis.model_checks` (and the severity's
        ambiguity) that fired, each with its flag and the amount; their flags are in
        :attr:`flags`.
    """

    pitting: PittingParameters
    applied_force_n: float
    indenter_radius_mm: float
    paper_model: VPRModel | None
    fit: RecoveryFit
    fit_model: VPRModel | None
    severity_paper: SeverityResult | None
    severity_fit: SeverityResult | None
    notes: tuple[str, ...]
    models: RecoveryModelComparison | None = None
    checks: tuple[ResultCheck, ...] = ()
    image_quality: ImageQuality | None = None
    quality_rules: tuple[QualityRule, ...] = ()
    force_at_rail_fraction: float = 0.0

    @property
    def flags(self) -> frozenset[Flag]:
        """Union of every part's flags (of the model comparison: ``KELVIN_VOIGT_REJECTED``)."""
        out = set(self.pitting.flags) | set(self.fit.flags)
        if self.force_at_rail_fraction > FORCE_RAIL_FRACTION:
            out.add(Flag.FORCE_AT_FULL_SCALE)
        if self.models is not None and self.models.kelvin_voigt_rejected:
            out.add(Flag.KELVIN_VOIGT_REJECTED)
        for sev in (self.severity_paper, self.severity_fit):
            if sev is not None:
                out |= sev.flags
        out |= {c.flag for c in self.checks}
        return frozenset(out)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary with units in the keys (``summary.json``)."""
        p = self.pitting

        def model(m: VPRModel | None) -> dict[str, Any] | None:
            if m is None:
                return None
            return {
                "elasticity_kpa": m.elasticity_kpa,
                "viscosity_n_s_per_mm2": m.viscosity_n_s_per_mm2,
                "time_constant_s": m.time_constant_s,
                "depth_mm": m.depth_mm,
            }

        def severity(s: SeverityResult | None) -> dict[str, Any] | None:
            if s is None:
                return None
            return {
                "severity": s.severity,
                "nearest_grade": s.nearest_grade,
                "recovered_percent": s.recovered_percent,
                "threshold_recovered_percent": s.threshold_recovered_percent,
                "window_s": [s.window_start_s, s.window_end_s],
                "grade_distances": dict(s.grade_distances),
                "flags": sorted(s.flags),
            }

        f = self.fit
        return {
            "pitting": {
                "depth_mm": p.depth_mm,
                "indentation_depth_mm": p.depth_mm,
                "residual_depth_mm": p.residual_depth_mm,
                "spring_back_px": p.spring_back_px,
                "depth_change_mm": p.depth_change_mm,
                "rebound_force_n": p.rebound_force_n,
                "recovery_time_s": p.recovery_time_s,
                "t0_s": p.t0_s,
                "ts_s": p.ts_s,
                "s0_px": p.s0_px,
                "s_max_px": p.s_max_px,
                "flags": sorted(p.flags),
                "observation": p.observed.to_dict(),
            },
            "applied_force_n": self.applied_force_n,
            "indenter_radius_mm": self.indenter_radius_mm,
            "paper_estimator": model(self.paper_model),
            "fitted_recovery": {
                "tau_s": f.tau_s,
                "tau_se_s": f.tau_se_s,
                "amplitude_px": f.amplitude,
                "amplitude_se_px": f.amplitude_se,
                "offset_px": f.offset,
                "offset_se_px": f.offset_se,
                "window_s": [f.t_start_s, f.t_end_s],
                "n_points": f.n_points,
                "rmse_px": f.rmse,
                "r_squared": f.r_squared,
                "flags": sorted(f.flags),
                "model": model(self.fit_model),
            },
            "severity": {
                "paper_estimator": severity(self.severity_paper),
                "fitted_recovery": severity(self.severity_fit),
            },
            "recovery_models": None if self.models is None else self.models.to_dict("px"),
            "checks": [{"flag": str(c.flag), "reason": c.reason} for c in self.checks],
            "image_quality": None if self.image_quality is None else self.image_quality.to_dict(),
            "image_quality_rules": [
                {"quantity": r.quantity, "invalid": r.invalid, "reason": r.reason}
                for r in self.quality_rules
            ],
            "force_at_full_scale_fraction": self.force_at_rail_fraction,
            "flags": sorted(self.flags),
            "notes": list(self.notes),
        }


def applied_force_n_from_samples(
    times_s: ArrayLike, force_n: ArrayLike, t_start_s: float, t_end_s: float
) -> float:
    """F_a of Eq. (7) [N]: the mean load-cell force over the pitting hold.

    Parameters
    ----------
    times_s, force_n : array_like
        Force samples: times [s] and forces [N]; non-finite samples are ignored.
    t_start_s, t_end_s : float
        The pitting hold [s], inclusive.

    Raises
    ------
    AnalysisError
        No finite force sample lies in the hold, or the mean is not > 0.
    """
    t = np.asarray(times_s, dtype=np.float64)
    f = np.asarray(force_n, dtype=np.float64)
    if t.shape != f.shape:
        raise AnalysisError(f"times_s and force_n differ in length: {t.shape} vs {f.shape}")
    sel = (t >= t_start_s) & (t <= t_end_s) & np.isfinite(t) & np.isfinite(f)
    if not np.any(sel):
        raise AnalysisError(
            f"no force sample in the pitting hold [{t_start_s:.3f}, {t_end_s:.3f}] s"
        )
    mean = float(np.mean(f[sel]))
    if not mean > 0.0:
        raise AnalysisError(f"mean force over the pitting hold is {mean:.3f} N, not > 0")
    return mean


def force_at_rail_fraction(
    times_s: ArrayLike,
    force_n: ArrayLike,
    t_start_s: float,
    t_end_s: float,
    full_scale_n: float,
    resolution_n: float,
) -> float:
    """Fraction of the hold's load-cell samples at the sensor's full scale [-].

    A sample within half a count (``resolution_n`` / 2 [N]) of ``full_scale_n`` [N] (the
    force of the ADC's largest count, or the load cell's range) is at the rail: the true
    force there is at least that, so their mean, F_a, is a lower bound. Samples as in
    :func:`applied_force_n_from_samples`; 0 when none lies in the hold or the full scale
    is not finite.
    """
    t = np.asarray(times_s, dtype=np.float64)
    f = np.asarray(force_n, dtype=np.float64)
    sel = (t >= t_start_s) & (t <= t_end_s) & np.isfinite(t) & np.isfinite(f)
    if not np.any(sel) or not math.isfinite(full_scale_n):
        return 0.0
    at_rail = f[sel] >= full_scale_n - 0.5 * max(resolution_n, 0.0)
    return float(np.mean(at_rail))


def force_full_scale_n(info: Mapping[str, Any] | None) -> tuple[float, float] | None:
    """The load cell's full scale and one count [N] from what the probe reported.

    ``info`` is the probe's information as the session records it (the manifest's
    ``firmware``: ``adc_bits``, and the calibration the forces were computed with,
    ``zero_counts_used`` and ``span_un_per_count_used``, else the probe's own
    ``zero_counts`` and ``span_un_per_count``). The full scale is the force of the ADC's
    largest code, (2^bits - 1 - zero) * span [N]. None when any of these is missing.
    """
    if not info:
        return None
    bits = info.get("adc_bits")
    zero = info.get("zero_counts_used", info.get("zero_counts"))
    span = info.get("span_un_per_count_used", info.get("span_un_per_count"))
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in (bits, zero, span)):
        return None
    assert isinstance(bits, int | float) and isinstance(zero, int | float)
    assert isinstance(span, int | float)
    count_n = float(span) * 1e-6
    if not (1 <= bits <= 32 and count_n > 0.0):
        return None
    return ((2 ** int(bits) - 1 - float(zero)) * count_n, count_n)


def analyze_recovery(
    times_s: ArrayLike,
    s_k: ArrayLike,
    t0_s: float,
    calibration: Calibration,
    applied_force_n: float,
    settings: AnalysisSettings,
    reference: SeverityReference,
    *,
    pictures: FramePictures | None = None,
    force_rail_fraction: float = 0.0,
) -> MeasurementResult:
    """Analyse one measurement's S_k series from T_0 on, with both recovery estimators.

    Parameters
    ----------
    times_s : array_like
        Frame times [s] (strictly increasing), on the same clock as ``t0_s``.
    s_k : array_like
        Occluded pixel counts S_k [px] (Eq. 2) of those frames.
    t0_s : float
        Start of the recovery T_0 [s] (the release).
    calibration : Calibration
        Eqs. (4)-(5) coefficients in the pixel units of ``s_k``.
    applied_force_n : float
        F_a [N] for Eq. (7).
    settings : AnalysisSettings
        Radius, window, settling fraction.
    reference : SeverityReference
        Reference grade curves for Section IV.C.
    pictures : FramePictures or None
        Picture statistics of (some of) the frames (the image-quality rules,
        :mod:`~stipi_daemon.analysis.image_quality`); None: not judged.
    force_rail_fraction : float
        :func:`force_at_rail_fraction` of the hold (``FORCE_AT_FULL_SCALE`` above
        :data:`FORCE_RAIL_FRACTION`) [-].

    Raises
    ------
    AnalysisError
        The series is unusable (see :func:`~stipi_daemon.analysis.pitting.validate_series`).
    """
    if not (math.isfinite(applied_force_n) and applied_force_n > 0.0):
        raise AnalysisError(f"applied_force_n must be finite and > 0, got {applied_force_n}")
    pitting = compute_pitting_parameters(
        times_s,
        s_k,
        t0_s,
        calibration,
        settle_fraction=settings.settle_fraction,
        window_s=settings.recovery_window_s,
        persist_frames=settings.persist_frames,
    )
    notes: list[str] = []
    radius = settings.indenter_radius_mm

    paper_model: VPRModel | None = None
    try:
        paper_model = VPRModel.from_pitting(
            pitting, applied_force_n=applied_force_n, indenter_radius_mm=radius
        )
    except AnalysisError as exc:
        notes.append(f"paper estimator undefined: {exc}")

    fit, pitting, cross_notes = _checked_fit(times_s, s_k, pitting, settings.recovery_window_s)
    notes.extend(cross_notes)
    models = _compared_models(
        times_s,
        s_k,
        pitting,
        calibration,
        settings,
        None if paper_model is None else paper_model.elasticity_kpa,
        notes,
    )
    fit_model: VPRModel | None = None
    if fit.tau_s is not None:
        try:
            fit_model = fit.to_vpr(
                pitting.depth_mm, applied_force_n=applied_force_n, indenter_radius_mm=radius
            )
        except AnalysisError as exc:
            notes.append(f"fitted estimator undefined: {exc}")
    else:
        notes.append(f"recovery fit gave no time constant (flags: {sorted(fit.flags)})")

    severity_paper, severity_fit = _severities(paper_model, fit, reference, notes)

    checks = _result_checks(pitting, fit, models, settings.settle_fraction)
    quality, rules = _judged_pictures(pictures, times_s, s_k, pitting, calibration, settings)
    return MeasurementResult(
        pitting=pitting,
        applied_force_n=float(applied_force_n),
        indenter_radius_mm=radius,
        paper_model=paper_model,
        fit=fit,
        fit_model=fit_model,
        severity_paper=severity_paper,
        severity_fit=severity_fit,
        notes=tuple(notes),
        models=models,
        checks=checks + _severity_checks(pitting, models, checks, severity_paper, reference),
        image_quality=quality,
        quality_rules=tuple(rules),
        force_at_rail_fraction=float(force_rail_fraction),
    )


def _severities(
    paper_model: VPRModel | None,
    fit: RecoveryFit,
    reference: SeverityReference,
    notes: list[str],
) -> tuple[SeverityResult | None, SeverityResult | None]:
    """The severity by the paper's estimator and by the fitted recovery (Section IV.C),
    each flagged ``ESTIMATORS_DISAGREE`` when they name different classes (and the fit is
    not poor); why one is undefined goes to ``notes``."""
    severity_paper: SeverityResult | None = None
    if paper_model is not None:
        try:
            severity_paper = classify_vpr(paper_model, reference)
        except AnalysisError as exc:
            notes.append(f"severity (paper estimator) undefined: {exc}")
    severity_fit: SeverityResult | None = None
    if fit.tau_s is not None:
        try:
            severity_fit = classify_fit(fit, reference)
        except AnalysisError as exc:
            notes.append(f"severity (fitted recovery) undefined: {exc}")

    if (
        severity_paper is not None
        and severity_fit is not None
        and Flag.POOR_FIT not in fit.flags
        and severity_paper.severity != severity_fit.severity
    ):
        notes.append(
            f"severity: the paper's estimator says {severity_paper.severity}, the fitted "
            f"recovery {severity_fit.severity} (nearest grade {severity_fit.nearest_grade})"
        )
        severity_paper = replace(
            severity_paper, flags=severity_paper.flags | {Flag.ESTIMATORS_DISAGREE}
        )
        severity_fit = replace(severity_fit, flags=severity_fit.flags | {Flag.ESTIMATORS_DISAGREE})
    return severity_paper, severity_fit


def _result_checks(
    pitting: PittingParameters,
    fit: RecoveryFit,
    models: RecoveryModelComparison | None,
    settle_fraction: float,
) -> tuple[ResultCheck, ...]:
    """The primary quantities against the recovery models, and the uncertainties beyond
    tolerance (:mod:`~stipi_daemon.analysis.model_checks`)."""
    obs = pitting.observed
    out = uncertainty_checks(
        obs,
        recovery_time_s=pitting.recovery_time_s,
        tau_s=fit.tau_s if Flag.TIME_CONSTANT_UNCERTAIN in fit.flags else None,
        tau_se_s=fit.tau_se_s,
        tau_frame_s=obs.frame_period_s,
    )
    if Flag.NO_RECOVERY in pitting.flags or Flag.RISE_WITHIN_SETTLING_BAND in pitting.flags:
        return out  # no rise to time: T_r is invalid already, the models have nothing to say
    return out + model_checks(
        models,
        recovery_time_s=pitting.recovery_time_s,
        s_max_px=pitting.s_max_px,
        frame_period_s=obs.frame_period_s,
        settle_fraction=settle_fraction,
    )


def _severity_checks(
    pitting: PittingParameters,
    models: RecoveryModelComparison | None,
    checks: tuple[ResultCheck, ...],
    severity: SeverityResult | None,
    reference: SeverityReference,
) -> tuple[ResultCheck, ...]:
    """``SEVERITY_AMBIGUOUS`` when T_r's uncertainty spans more than one class or grade.

    The paper's class follows the decay rate 1/T_r (Section IV.C). T_r's range is the
    reported T_r, the frame gap its crossing lies in, the T_r of every recovery model with
    weight and the best model's 95 % interval; the class at both ends of the range (the
    classification is monotonic in the rate) says which classes remain.
    """
    tr = pitting.recovery_time_s
    if severity is None or tr is None or tr <= 0.0:
        return ()
    times = [tr]
    gap = pitting.observed.settling_gap
    if gap is not None:
        times += [gap.start_s - pitting.t0_s, gap.end_s - pitting.t0_s]
    if (
        models is not None
        and models.best_model is not None
        and not any(c.flag is Flag.MODEL_NOT_SETTLED for c in checks)
    ):
        times += [q for f in supported_fits(models) if (q := f.quantities.get("recovery_time_s"))]
        ci = models.fit(models.best_model).ci95.get("recovery_time_s")
        times += list(ci or ())
    times = [t for t in times if t > 0.0 and math.isfinite(t)]
    lo, hi = min(times), max(times)
    ends = []
    for t in (lo, hi):
        try:
            ends.append(classify_decay_rate(1.0 / t, reference))
        except AnalysisError:
            return ()
    names = {(e.severity, e.nearest_grade) for e in ends}
    if len(names) == 1:
        return ()
    grades = [g.name for g in reference.grades]
    first, last = sorted(grades.index(e.nearest_grade) for e in ends)
    remain = ", ".join(grades[first : last + 1])
    classes = " or ".join(sorted({e.severity for e in ends}))
    return (
        ResultCheck(
            Flag.SEVERITY_AMBIGUOUS,
            f"T_r between {lo:.2f} and {hi:.2f} s leaves grades {remain} ({classes}): "
            "the class is not named",
        ),
    )


def _judged_pictures(
    pictures: FramePictures | None,
    times_s: ArrayLike,
    s_k: ArrayLike,
    pitting: PittingParameters,
    calibration: Calibration,
    settings: AnalysisSettings,
) -> tuple[ImageQuality | None, list[QualityRule]]:
    """:func:`~stipi_daemon.analysis.image_quality.judge_pictures` on this measurement."""
    if pictures is None:
        return None, []
    slope = abs(2.0 * calibration.alpha1_mm_per_px2 * pitting.s0_px - calibration.alpha2_mm_per_px)
    quantities = {
        "depth_mm": pitting.depth_mm,
        "depth_slope_mm_per_px": slope,
        "c2_px_per_n": calibration.c2_px_per_n,
        "rebound_force_n": pitting.rebound_force_n,
    }
    if pitting.recovery_time_s is not None:
        quantities["recovery_time_s"] = pitting.recovery_time_s
    return judge_pictures(
        pictures,
        times_s,
        s_k,
        t0_s=pitting.t0_s,
        ts_s=pitting.ts_s,
        window_s=settings.recovery_window_s,
        quantities=quantities,
        period_s=pitting.observed.frame_period_s,
    )


def _checked_fit(
    times_s: ArrayLike, s_k: ArrayLike, pitting: PittingParameters, window_s: float
) -> tuple[RecoveryFit, PittingParameters, list[str]]:
    """The Kelvin-Voigt fit on the observed frames, judged, and T_r cross-checked with it.

    The fit uses the usable frames only: outlier frames (``pitting.observed``) are left out,
    lost frames are simply absent. It is flagged ``FRAME_GAPS_IN_FIT`` when gaps cover more
    than :data:`FIT_GAP_FRACTION` of its span or of its first 3 tau (where the rise is seen),
    ``POOR_FIT`` when R^2 is below :data:`POOR_FIT_R_SQUARED` and the RMS residual exceeds
    :data:`POOR_FIT_NOISE_RATIO` times the frame-to-frame noise. A good fit whose tau [s]
    is longer than its span means the recovery is slower than the window: the paper's T_r
    (Eq. 6) is then flagged ``NOT_SETTLED`` whatever the 98 % rule found (a tissue that
    barely recovers "settles" within a frame by that rule alone).

    Returns
    -------
    tuple
        The judged fit, the pitting parameters (flags updated) and notes.
    """
    t, s = _usable_frames(times_s, s_k, pitting)
    obs = pitting.observed
    fit = fit_recovery(t, s, pitting.t0_s, window_s)
    flags = set(fit.flags)
    notes: list[str] = []
    span = fit.t_end_s - fit.t0_s

    def gapped(end_s: float) -> bool:
        """Gaps cover more than FIT_GAP_FRACTION of (T_0, end_s]."""
        length = end_s - fit.t0_s
        covered = sum(max(0.0, min(g.end_s, end_s) - max(g.start_s, fit.t0_s)) for g in obs.gaps)
        return length > 0.0 and covered > FIT_GAP_FRACTION * length

    # Over the whole span, and over the first 3 tau, where the rise (and tau) is seen.
    rise_end = fit.t_end_s if fit.tau_s is None else min(fit.t_end_s, fit.t0_s + 3 * fit.tau_s)
    if gapped(fit.t_end_s) or gapped(rise_end):
        flags.add(Flag.FRAME_GAPS_IN_FIT)
    window = (t >= fit.t0_s) & (t <= fit.t_end_s) & np.isfinite(s)
    noise = noise_sigma(s[window])
    if (
        fit.r_squared is not None
        and fit.r_squared < POOR_FIT_R_SQUARED
        and fit.rmse > POOR_FIT_NOISE_RATIO * noise
    ):
        flags.add(Flag.POOR_FIT)
    fit = replace(fit, flags=frozenset(flags))
    good = fit.tau_s is not None and not flags & {Flag.POOR_FIT, Flag.FIT_NOT_CONVERGED}
    if (
        good
        and fit.tau_s is not None
        and fit.tau_s > span
        and Flag.NOT_SETTLED not in pitting.flags
    ):
        notes.append(
            f"fitted tau = {fit.tau_s:.1f} s exceeds the {span:.1f} s observed: the recovery "
            "did not settle within the window (T_r by the 98 % rule alone would be "
            f"{pitting.recovery_time_s} s)"
        )
        pitting = replace(pitting, flags=pitting.flags | {Flag.NOT_SETTLED})
    return fit, pitting, notes


def depth_relative_sd(
    times_s: NDArray[np.float64],
    s_k: NDArray[np.float64],
    pitting: PittingParameters,
    calibration: Calibration,
) -> float:
    """Relative standard uncertainty of D_p [-] from the noise of the one frame S_0 is.

    D_p = l - d_s(S_0) (Eqs. 3-4), so sd(D_p) = |2 alpha1 S_0 - alpha2| sigma_S, with
    sigma_S the frame-to-frame noise of the recovery frames [px]
    (:func:`~stipi_daemon.analysis.observation.noise_sigma`); divided by D_p. 0 when D_p
    is not positive or there are too few frames to tell the noise. A calibration's own
    error and F_a's are not in it.
    """
    depth = pitting.depth_mm
    window = (times_s > pitting.t0_s) & np.isfinite(s_k)
    if not (math.isfinite(depth) and depth > 0.0) or np.count_nonzero(window) < 3:
        return 0.0
    slope = 2.0 * calibration.alpha1_mm_per_px2 * pitting.s0_px - calibration.alpha2_mm_per_px
    rel = abs(slope) * noise_sigma(s_k[window]) / depth
    return rel if math.isfinite(rel) else 0.0


def _usable_frames(
    times_s: ArrayLike, s_k: ArrayLike, pitting: PittingParameters
) -> tuple[np.ndarray, np.ndarray]:
    """Frame times [s] and S_k [px] without the outlier frames (what the fits use)."""
    t = np.asarray(times_s, dtype=np.float64)
    s = np.asarray(s_k, dtype=np.float64)
    obs = pitting.observed
    if obs.outlier_times_s:
        keep = ~np.isin(t, np.asarray(obs.outlier_times_s, dtype=np.float64))
        t, s = t[keep], s[keep]
    return t, s


def _compared_models(
    times_s: ArrayLike,
    s_k: ArrayLike,
    pitting: PittingParameters,
    calibration: Calibration,
    settings: AnalysisSettings,
    elasticity_kpa: float | None,
    notes: list[str],
) -> RecoveryModelComparison | None:
    """Every recovery model on the Kelvin-Voigt fit's frames; F_r by Eq. (5), eta = E T_r.

    None (with a note) when the comparison refuses the series.
    """
    t, s = _usable_frames(times_s, s_k, pitting)

    def force(s_max_px: float) -> float | None:
        try:
            return rebound_force_n(s_max_px, calibration).value
        except AnalysisError:
            return None

    try:
        models = fit_recovery_models(
            t,
            s,
            pitting.t0_s,
            settings.recovery_window_s,
            settle_fraction=settings.settle_fraction,
            replicates=settings.bootstrap_replicates,
            seed=settings.bootstrap_seed,
            rebound_force=force,
            elasticity_kpa=elasticity_kpa,
            depth_rel_sd=depth_relative_sd(t, s, pitting, calibration),
        )
    except AnalysisError as exc:
        notes.append(f"recovery models not compared: {exc}")
        return None
    if models.kelvin_voigt_rejected and models.best_model is not None:
        best = models.fit(models.best_model)
        notes.append(
            f"the recovery is not one exponential: {best.model} explains it best "
            f"(QAICc lower than Kelvin-Voigt's by {models.kelvin_voigt_delta_qaicc:.0f}); "
            f"its tau = {best.quantities['tau_s']} s, T_r = {best.quantities['recovery_time_s']} s"
        )
    return models
