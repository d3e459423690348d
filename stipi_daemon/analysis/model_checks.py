"""The primary quantities against the recovery models that fit the recovery.

Eq. (6) reads T_r off the recorded S_k and its window's S_max; the recovery models
(:mod:`~stipi_daemon.analysis.recovery_models`) say what the recovery is. This module owns
the rules that make the first consult the second, for the early stop of the state machine
and for the validity of the results (docs/analysis.md, "Validity of each result";
docs/settling.md):

* *Models with weight* (:func:`supported_fits`): every fitted model whose weight is at
  least :data:`SUPPORT_RATIO` (1/8) of the best model's, i.e. an evidence ratio of at most
  8 against it (Royall's 1/8 likelihood interval, Burnham & Anderson 2002, Sec. 4.2; a
  QAICc difference of at most 2 ln 8 = 4.2). The weights are the comparison's decision
  weights: Akaike weights of QAICc, which are the AICc weights when the residuals are
  independent (variance inflation c = 1) and give more models weight when they are not.
* *Eq. (6) on a model's curve* (:func:`curve_recovery_time_s`): the time after T_0 at
  which the curve first reaches f x its value at a horizon H (the S_max of a record that
  ends at H; H = inf: f x the settled level S_inf, the time the recovery settles).
* *Early stop* (:func:`early_stop_check`): a recording may end at t only when, for every
  model with weight, T_r of the record so far differs from T_r of the record continued
  to the end of the recovery window by at most the accepted bias. Kelvin-Voigt's own bound
  (:mod:`~stipi_daemon.analysis.settling_rules`) is one case of it; a power-law or
  two-time-constant recovery is judged by its own curve.
* *Result checks* (:func:`model_checks`, :func:`uncertainty_checks`): the flags of
  :class:`ResultCheck` with the amount each rule found.

Tolerances: :mod:`~stipi_daemon.analysis.tolerances` (T_r and tau: 5 % or 2 frame
periods). Pure: no I/O. Domain: S_k in pixels, times in seconds; a falling or
flat curve (amplitude <= 0) has no T_r (None).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.recovery_models import (
    MODELS,
    ModelFit,
    RecoveryModelComparison,
    fit_recovery_models,
)
from stipi_daemon.analysis.tolerances import recovery_time_tolerance_s
from stipi_daemon.errors import AnalysisError

if TYPE_CHECKING:
    from stipi_daemon.analysis.observation import Observed

__all__ = [
    "STOP_CHECK_POINTS",
    "SUPPORT_RATIO",
    "EarlyStopCheck",
    "ResultCheck",
    "curve_recovery_time_s",
    "early_stop_check",
    "model_checks",
    "supported_fits",
    "uncertainty_checks",
]

#: A model has weight when its weight is at least this fraction of the best model's [-].
SUPPORT_RATIO: Final = 1.0 / 8.0
#: Most points an early-stop check fits: longer records are averaged in blocks of
#: consecutive frames first (the fit's cost grows with the points; 400 keep a check near
#: 0.1 s, and a block spans at most 105 s / 400 = 0.26 s of the recovery) [-].
STOP_CHECK_POINTS: Final = 400


@dataclass(frozen=True)
class ResultCheck:
    """One rule that fired on a measurement's results.

    Attributes
    ----------
    flag : Flag
        The flag it sets (its quantities and effect: ``validity.FLAG_RULES``).
    reason : str
        The rule and the amount, in one line.
    """

    flag: Flag
    reason: str


def _weight(fit: ModelFit) -> float | None:
    return fit.qaicc_weight if fit.qaicc_weight is not None else fit.akaike_weight


def supported_fits(comparison: RecoveryModelComparison) -> tuple[ModelFit, ...]:
    """The fitted models whose weight is at least :data:`SUPPORT_RATIO` of the best's."""
    weighted = [
        (w, f)
        for f in comparison.fits
        if f.parameters is not None and (w := _weight(f)) is not None and math.isfinite(w)
    ]
    if not weighted:
        return ()
    best = max(w for w, _ in weighted)
    return tuple(f for w, f in weighted if w >= SUPPORT_RATIO * best)


def _curve(fit: ModelFit) -> tuple[float, float, np.ndarray] | None:
    """(offset, amplitude, u) of a fitted curve in the series' unit; None if not fitted."""
    p = fit.parameters
    if p is None:
        return None
    model = MODELS[fit.model]
    u = np.asarray([q.to_solver(p[q.name]) for q in model.SHAPE_PARAMETERS], dtype=np.float64)
    return p["offset"], p["amplitude"], u


def curve_recovery_time_s(
    fit: ModelFit, settle_fraction: float, horizon_s: float = math.inf
) -> float | None:
    """Eq. (6) on a fitted curve recorded from T_0 to T_0 + ``horizon_s`` [s].

    S_max is the curve's value at the horizon (its settled level S_inf for ``inf``); the
    result is the first time the curve reaches ``settle_fraction`` x S_max (0 when S_0 is
    already there). None for a curve that does not rise (amplitude <= 0, S_max <= 0), an
    unfitted model, or a level the curve never reaches in floating point.
    """
    c = _curve(fit)
    if c is None:
        return None
    offset, amplitude, u = c
    model = MODELS[fit.model]
    if not amplitude > 0.0:
        return None
    if math.isinf(horizon_s):
        s_max = offset
    else:
        g, _ = model.shape(np.asarray([max(horizon_s, 0.0)]), u[None, :])
        s_max = offset - amplitude * float(g[0, 0])
    s0 = offset - amplitude
    if not s_max > 0.0:
        return None
    level = settle_fraction * s_max
    if level <= s0:
        return 0.0
    remaining = (offset - level) / amplitude
    if not 0.0 < remaining < 1.0:
        return None
    t = model.time_to_remaining(u, remaining)
    return t if math.isfinite(t) else None


@dataclass(frozen=True)
class EarlyStopCheck:
    """Whether the models that fit the recovery so far allow it to end now.

    Attributes
    ----------
    allowed : bool
    reason : str
        Which model decided and by how much T_r would still move.
    """

    allowed: bool
    reason: str


def early_stop_check(
    times_s: ArrayLike,
    s_px: ArrayLike,
    t0_s: float,
    window_end_s: float,
    *,
    settle_fraction: float,
    bias_fraction: float,
) -> EarlyStopCheck:
    """May a recovery recorded up to its last frame end there (module docstring)?

    Fits every recovery model (no bootstrap) to the frames from T_0 on and, for each
    model with weight, compares Eq. (6) on its curve recorded to the last frame with Eq.
    (6) recorded to ``window_end_s``. Allowed when none moves by more than
    ``bias_fraction`` of the latter. Refused when no model can be fitted or weighed.

    Parameters
    ----------
    times_s, s_px : array_like
        Frame times [s] (strictly increasing) and S_k [px] of the recovery so far (at
        least one frame); averaged in blocks to :data:`STOP_CHECK_POINTS` points.
    t0_s : float
        T_0 [s].
    window_end_s : float
        End of the recovery window [s] (T_0 + the longest recovery).
    settle_fraction : float
        f of Eq. (6), in (0, 1).
    bias_fraction : float
        Largest relative change of T_r accepted, in (0, 1).
    """
    t, s = _blocks(np.asarray(times_s, dtype=np.float64), np.asarray(s_px, dtype=np.float64))
    elapsed = float(t[-1]) - t0_s if t.size else 0.0
    try:
        comparison = fit_recovery_models(
            t, s, t0_s, elapsed, settle_fraction=settle_fraction, replicates=0
        )
    except AnalysisError as exc:
        return EarlyStopCheck(False, f"no recovery model could be fitted ({exc})")
    fits = supported_fits(comparison)
    if not fits:
        return EarlyStopCheck(False, "no recovery model could be weighed")
    horizon = window_end_s - t0_s
    worst: tuple[float, str] = (0.0, "")
    for fit in fits:
        now = curve_recovery_time_s(fit, settle_fraction, elapsed)
        full = curve_recovery_time_s(fit, settle_fraction, horizon)
        if now is None or full is None:
            return EarlyStopCheck(False, f"{fit.model} gives no T_r for this record")
        change = abs(full - now) / full if full > 0.0 else (0.0 if now == 0.0 else math.inf)
        if change > worst[0] or not worst[1]:
            worst = (
                change,
                f"{fit.model}: T_r {now:.2f} s now, {full:.2f} s at the window's end",
            )
    ok = worst[0] <= bias_fraction
    verb = "may stop" if ok else "keeps recording"
    return EarlyStopCheck(
        ok,
        f"{verb}: {worst[1]} ({100 * worst[0]:.2f} % against {100 * bias_fraction:g} %)",
    )


def _blocks(t: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Means of blocks of consecutive frames, at most :data:`STOP_CHECK_POINTS` of them."""
    k = math.ceil(t.size / STOP_CHECK_POINTS)
    if k <= 1:
        return t, s
    starts = np.arange(0, t.size, k)
    counts = np.diff(np.append(starts, t.size))
    return np.add.reduceat(t, starts) / counts, np.add.reduceat(s, starts) / counts


def _names(fits: Sequence[ModelFit]) -> str:
    return ", ".join(f"{f.model} {_weight(f) or 0.0:.2f}" for f in fits)


def model_checks(
    comparison: RecoveryModelComparison | None,
    *,
    recovery_time_s: float | None,
    s_max_px: float,
    frame_period_s: float,
    settle_fraction: float,
) -> tuple[ResultCheck, ...]:
    """Eq. (6)'s T_r and S_max against the models with weight (docs/analysis.md).

    * ``MODEL_NOT_SETTLED``: the best model reaches f x its settled level more than T_r's
      tolerance after the recording's last frame: the window ended before the recovery
      settled, T_r and S_max (F_r) are lower bounds.
    * ``MODELS_DISAGREE``: the models with weight put T_r (Eq. 6 on their curves over the
      fitted span) further apart than T_r's tolerance.
    * ``SETTLED_LEVEL_OFF_MODEL``: on the best model's curve, the level f x the measured
      S_max is reached more than T_r's tolerance away from its own T_r: the measured S_max
      is off the settled level the model reads, and moves the 98 % crossing by that much.
    * ``RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL``: the reported T_r lies outside the best
      model's 95 % interval by more than T_r's tolerance. Within it the difference is no
      error by the tolerance's own standard, and it has causes the interval does not hold:
      Eq. 6's frame quantisation, and noise, which raises S_max (the largest of noisy
      frames) and with it the 98 % crossing (0.1 % noise: about 2 % of T_r).
    """
    if comparison is None or comparison.best_model is None:
        return ()
    best = comparison.fit(comparison.best_model)
    if best.parameters is None or not best.parameters["amplitude"] > 0.0:
        return ()
    f = settle_fraction
    span = comparison.t_end_s - comparison.t0_s
    best_tr = best.quantities.get("recovery_time_s")
    ref = recovery_time_s if recovery_time_s is not None else best_tr
    tol = recovery_time_tolerance_s(ref or 0.0, frame_period_s)
    out: list[ResultCheck] = []
    settle = curve_recovery_time_s(best, f)
    if settle is None or settle > span + tol:
        when = "never" if settle is None else f"only {settle:.1f} s after T_0"
        past = "" if settle is None else f", {settle - span:.1f} s after the record's end"
        out.append(
            ResultCheck(
                Flag.MODEL_NOT_SETTLED,
                f"the recovery did not settle within the record: the best recovery model "
                f"({best.model}) reaches {100 * f:g} % of its settled level "
                f"({best.parameters['offset']:.0f} px) {when}{past} at {span:.1f} s: T_r and "
                "S_max are lower bounds",
            )
        )
    fits = supported_fits(comparison)
    trs = [(q, fit) for fit in fits if (q := fit.quantities.get("recovery_time_s")) is not None]
    if len(trs) > 1:
        lo, hi = min(q for q, _ in trs), max(q for q, _ in trs)
        if hi - lo > tol:
            out.append(
                ResultCheck(
                    Flag.MODELS_DISAGREE,
                    f"the recovery models with weight ({_names(fits)}) put T_r between "
                    f"{lo:.2f} and {hi:.2f} s: {hi - lo:.2f} s apart, tolerance {tol:.2f} s",
                )
            )
    if best_tr is not None and s_max_px > 0.0:
        at_measured = _time_to_level(best, f * s_max_px)
        if at_measured is not None and abs(at_measured - best_tr) > tol:
            model_smax = best.quantities.get("s_max") or 0.0
            out.append(
                ResultCheck(
                    Flag.SETTLED_LEVEL_OFF_MODEL,
                    f"S_max = {s_max_px:.0f} px is {s_max_px - model_smax:+.0f} px off the best "
                    f"model's ({best.model}) {model_smax:.0f} px; on its curve that moves the "
                    f"{100 * f:g} % crossing by {at_measured - best_tr:+.2f} s "
                    f"(tolerance {tol:.2f} s)",
                )
            )
    ci = best.ci95.get("recovery_time_s")
    if ci is not None and recovery_time_s is not None:
        lo_ci, hi_ci = ci
        off = lo_ci - recovery_time_s if recovery_time_s < lo_ci else recovery_time_s - hi_ci
        if off > tol:
            out.append(
                ResultCheck(
                    Flag.RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL,
                    f"T_r = {recovery_time_s:.2f} s lies {off:.2f} s outside the best model's "
                    f"({best.model}) 95 % interval [{lo_ci:.2f}, {hi_ci:.2f}] s "
                    f"(tolerance {tol:.2f} s)",
                )
            )
    return tuple(out)


def _time_to_level(fit: ModelFit, level_px: float) -> float | None:
    """First time after T_0 [s] at which the fitted curve reaches ``level_px``; None if it
    never does."""
    c = _curve(fit)
    if c is None:
        return None
    offset, amplitude, u = c
    s0 = offset - amplitude
    if level_px <= s0:
        return 0.0
    remaining = (offset - level_px) / amplitude
    if not 0.0 < remaining < 1.0:
        return None
    t = MODELS[fit.model].time_to_remaining(u, remaining)
    return t if math.isfinite(t) else None


def uncertainty_checks(
    observed: Observed,
    *,
    recovery_time_s: float | None,
    tau_s: float | None,
    tau_se_s: float | None,
    tau_frame_s: float,
) -> tuple[ResultCheck, ...]:
    """Quantities whose own stated uncertainty exceeds their tolerance (invalid).

    * ``RECOVERY_TIME_UNCERTAIN``: the 98 % crossing lies in a frame gap longer than T_r's
      tolerance (T_r is uncertain by the gap's length).
    * ``TIME_CONSTANT_UNCERTAIN`` (set by :func:`~stipi_daemon.analysis.recovery_fit.
      fit_recovery`; here its amount): the fitted tau's standard error exceeds tau's
      tolerance (T_r's: 5 % or 2 frame periods), or tau has no standard error.
    """
    out: list[ResultCheck] = []
    frame = observed.frame_period_s
    gap = observed.settling_gap
    if gap is not None and recovery_time_s is not None:
        tol = recovery_time_tolerance_s(recovery_time_s, frame)
        if gap.length_s > tol:
            out.append(
                ResultCheck(
                    Flag.RECOVERY_TIME_UNCERTAIN,
                    f"the 98 % crossing lies in a gap ({gap.describe()}): T_r uncertain by "
                    f"{gap.length_s:.2f} s, beyond its tolerance {tol:.2f} s",
                )
            )
    if tau_s is not None:
        tol = recovery_time_tolerance_s(tau_s, tau_frame_s)
        if tau_se_s is None or not tau_se_s <= tol:
            se = "none" if tau_se_s is None else f"{tau_se_s:.2f} s"
            out.append(
                ResultCheck(
                    Flag.TIME_CONSTANT_UNCERTAIN,
                    f"tau = {tau_s:.2f} s has a standard error of {se}, beyond its tolerance "
                    f"{tol:.2f} s",
                )
            )
    return tuple(out)
