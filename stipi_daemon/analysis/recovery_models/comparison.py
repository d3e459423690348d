"""Every recovery model fitted side by side, with AICc weights and bootstrap intervals.

:func:`fit_recovery_models` fits each registered model (:mod:`stipi_daemon.analysis.
recovery_models`) to the samples T_0 <= t <= T_0 + window of one series, compares them
(:mod:`.selection`: AICc and Akaike weights; QAICc for the Kelvin-Voigt rejection rule)
and gives each model 95 % confidence intervals on tau, T_r, S_max (hence F_r) and eta
by a moving-block bootstrap of its residuals (:mod:`.bootstrap`).

What each quantity is on a fitted curve y(t) = offset - amplitude g(t - T_0) (the
definitions of the simulator's ground truth, so that they compare):

* ``tau_s``: the effective time constant, the time after T_0 at which 1 - 1/e of the
  recovery S_inf - S_0 is done, g(tau) = 1/e (tau itself for Kelvin-Voigt);
* ``s0`` = offset - amplitude (the curve at T_0), ``s_max`` = the curve's maximum over the
  fitted span (at its last sample for a rising curve);
* ``recovery_time_s``: the paper's T_r (Eq. 6) read off the curve, the time after T_0 at
  which it first reaches ``settle_fraction`` x S_max (0 when S_0 is already there); only
  for a rising series (S_k), None for a falling one;
* F_r = Eq. (5) at S_max and eta = E T_r (Eq. 8), when the caller supplies Eq. (5)
  (``rebound_force``) and E (``elasticity_kpa``).

Why a moving-block bootstrap, not profile likelihood: the residuals are autocorrelated
(module :mod:`.bootstrap`), and a profile-likelihood interval rests on the likelihood of
independent Gaussian residuals, which then is too narrow; correcting it needs the same
dependence estimate and still assumes Gaussian noise, while resampling blocks of the
residuals carries their dependence and distribution into the intervals. T_r, tau_eff and
S_max are nonlinear functions of several parameters, which the bootstrap maps sample by
sample. Each replicate is the fitted curve plus a moving-block resample of the residuals
(block length by Politis-White from those residuals), refitted from the point estimate by
:func:`.base.solve_batch`; the interval is the 2.5 and 97.5 % order statistics of the
replicates (percentile method). Seeded by ``seed`` and the model's place in the registry:
the same input gives the same intervals. A model's intervals are conditional on the model:
a model that does not describe the tissue has intervals around its own (biased) curve; the
model weights say which to believe.

Cost: one fit per model plus ``replicates`` vectorised refits; docs/analysis.md gives the
measured time. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import DEFAULT_SETTLE_FRACTION, DEFAULT_WINDOW_S
from stipi_daemon.analysis.recovery_fit import MAX_ABS_VALUE, check_value_domain, fit_window
from stipi_daemon.analysis.recovery_fit import solve_scaled as kv_solve_scaled
from stipi_daemon.analysis.recovery_models.base import (
    FloatArray,
    RecoveryModel,
    solve_batch,
    solve_scaled,
)
from stipi_daemon.analysis.recovery_models.bootstrap import (
    MIN_SERIES,
    BlockLength,
    block_indices,
    block_length,
    moving_block_starts,
)
from stipi_daemon.analysis.recovery_models.registry import MODELS
from stipi_daemon.analysis.recovery_models.selection import (
    KV_REJECTION_DELTA,
    aicc,
    akaike_weights,
    floored_rss,
    qaicc,
)
from stipi_daemon.analysis.vpr import KPA_PER_N_PER_MM2
from stipi_daemon.errors import AnalysisError

__all__ = [
    "BOOTSTRAP_FAILURE_LIMIT",
    "CI_QUANTITIES",
    "DEFAULT_REPLICATES",
    "MAX_ABS_VALUE",
    "ModelFit",
    "RecoveryModelComparison",
    "fit_recovery_models",
]

#: Bootstrap replicates per model by default [-].
DEFAULT_REPLICATES = 200
#: Largest fraction of failed refits with which intervals are still reported [-].
BOOTSTRAP_FAILURE_LIMIT = 0.1
#: Quantities with a 95 % interval (keys of :attr:`ModelFit.ci95`).
CI_QUANTITIES = ("tau_s", "recovery_time_s", "s_max", "rebound_force_n", "viscosity_n_s_per_mm2")
#: Bootstrap replicates refitted together [-]: each is solved on its own (the same numbers
#: for any chunk), and a chunk's arrays (its Jacobians: chunk x frames x parameters) made
#: the analysis's peak memory at 50: 79 MB for a 105 s recovery at 60 fps; at 16 the peak
#: is 32 MB, the power-law model's starting grid (tracemalloc, the demo's session).
_CHUNK = 16
_KV = "kelvin_voigt"


@dataclass(frozen=True)
class ModelFit:
    """One model fitted to one series (units: ``series`` = the fitted series' unit).

    Attributes
    ----------
    model : str
        Registry name.
    parameters : dict or None
        Every parameter by name (offset, amplitude in the series' unit; times [s]); None
        when the model was not fitted (see ``flags``).
    n_parameters : int
        Curve parameters (k - 1: the noise variance is not counted here).
    rss : float or None
        Residual sum of squares [series^2].
    aicc, akaike_weight, qaicc, qaicc_weight, delta_qaicc : float or None
        Selection values (:mod:`.selection`); None when the model takes no part.
    quantities : dict
        ``tau_s``, ``recovery_time_s``, ``s0``, ``s_max``, ``rebound_force_n``,
        ``viscosity_n_s_per_mm2`` read off the fitted curve (None where undefined).
    ci95 : dict
        Quantity -> (low, high) 95 % percentile interval, or None.
    block : BlockLength or None
        The residuals' block length and variance inflation.
    replicates, failed_replicates : int
        Bootstrap replicates drawn and those whose refit failed.
    flags : frozenset[Flag]
    """

    model: str
    parameters: dict[str, float] | None
    n_parameters: int
    rss: float | None
    aicc: float | None = None
    akaike_weight: float | None = None
    qaicc: float | None = None
    qaicc_weight: float | None = None
    delta_qaicc: float | None = None
    quantities: dict[str, float | None] = field(default_factory=dict)
    ci95: dict[str, tuple[float, float] | None] = field(default_factory=dict)
    block: BlockLength | None = None
    replicates: int = 0
    failed_replicates: int = 0
    flags: frozenset[Flag] = frozenset()

    def to_dict(self, unit: str) -> dict[str, Any]:
        """JSON-ready, the series' unit ``unit`` in the keys (e.g. ``px``)."""
        model = MODELS[self.model]

        def key(name: str) -> str:
            return {"offset": f"offset_{unit}", "amplitude": f"amplitude_{unit}"}.get(name, name)

        q = self.quantities
        return {
            "title": model.TITLE,
            "equation": model.EQUATION,
            "source": model.SOURCE,
            "tau_meaning": model.TAU_MEANING,
            "parameters": None
            if self.parameters is None
            else {key(k): _finite(v) for k, v in self.parameters.items()},
            "n_parameters": self.n_parameters,
            f"rss_{unit}2": _finite(self.rss),
            "aicc": _finite(self.aicc),
            "akaike_weight": _finite(self.akaike_weight),
            "qaicc": _finite(self.qaicc),
            "qaicc_weight": _finite(self.qaicc_weight),
            "delta_qaicc": _finite(self.delta_qaicc),
            "tau_s": _finite(q.get("tau_s")),
            "recovery_time_s": _finite(q.get("recovery_time_s")),
            "rebound_force_n": _finite(q.get("rebound_force_n")),
            "viscosity_n_s_per_mm2": _finite(q.get("viscosity_n_s_per_mm2")),
            f"s0_{unit}": _finite(q.get("s0")),
            f"s_max_{unit}": _finite(q.get("s_max")),
            "ci95": {
                (f"s_max_{unit}" if k == "s_max" else k): None
                if v is None
                else [_finite(v[0]), _finite(v[1])]
                for k, v in self.ci95.items()
            },
            "bootstrap": {
                "replicates": self.replicates,
                "failed": self.failed_replicates,
                "block_length": None if self.block is None else self.block.length,
                "variance_inflation": None
                if self.block is None
                else _finite(self.block.variance_inflation),
            },
            "flags": sorted(self.flags),
        }


@dataclass(frozen=True)
class RecoveryModelComparison:
    """Every model fitted to one recovery (:func:`fit_recovery_models`).

    Attributes
    ----------
    fits : tuple[ModelFit, ...]
        In registry order.
    t0_s, t_start_s, t_end_s : float
        T_0 and the first and last fitted sample times [s].
    n_points : int
        Finite samples fitted.
    variance_inflation : float or None
        c of QAICc (from the best-fitting model's residuals).
    best_model : str or None
        Highest QAICc weight (the decision's criterion); None when no model has one.
    kelvin_voigt_delta_qaicc : float or None
        QAICc(Kelvin-Voigt) - min QAICc.
    replicates, seed : int
        Bootstrap settings.
    depth_rel_sd : float
        D_p's relative standard uncertainty carried into eta's interval [-] (0: E fixed).
    value_resolution : float
        Quantum of the values in the intervals [series unit] (1 for an integer S_k).
    frame_period_s : float
        How well T_0 places the release in the intervals [s] (+- this).
    release_side : str
        ``"either"``, ``"before"`` or ``"after"`` T_0 (``fit_recovery_models``).
    flags : frozenset[Flag]
        ``KELVIN_VOIGT_REJECTED`` (Kelvin-Voigt's QAICc exceeds the best by more than 10),
        ``MODEL_SELECTION_UNAVAILABLE``, ``NON_FINITE_INPUT``, ``CONSTANT_SERIES``.
    """

    fits: tuple[ModelFit, ...]
    t0_s: float
    t_start_s: float
    t_end_s: float
    n_points: int
    variance_inflation: float | None
    best_model: str | None
    kelvin_voigt_delta_qaicc: float | None
    replicates: int
    seed: int
    flags: frozenset[Flag]
    depth_rel_sd: float = 0.0
    value_resolution: float = 0.0
    frame_period_s: float = 0.0
    release_side: str = "either"

    @property
    def kelvin_voigt_rejected(self) -> bool:
        """Whether the rejection rule fired."""
        return Flag.KELVIN_VOIGT_REJECTED in self.flags

    def fit(self, name: str) -> ModelFit:
        """The fit of model ``name`` (KeyError if not compared)."""
        for f in self.fits:
            if f.model == name:
                return f
        raise KeyError(name)

    def to_dict(self, unit: str = "px") -> dict[str, Any]:
        """JSON-ready (``summary.json``'s ``recovery_models``); ``unit`` of the series."""
        return {
            "window_s": [self.t_start_s, self.t_end_s],
            "n_points": self.n_points,
            "selection": "AICc = n ln(RSS/n) + 2k + 2k(k+1)/(n-k-1), k = curve parameters + 1 "
            "(noise variance); decision by QAICc (log-likelihood / variance_inflation)",
            "kelvin_voigt_rejection_rule": f"QAICc(kelvin_voigt) - min QAICc > "
            f"{KV_REJECTION_DELTA:g}",
            "intervals": "95 % percentile, moving-block bootstrap of the residuals; each "
            "replicate also moves the settled level by U(-q/2, q/2) (q = value_resolution: the "
            "rounding of an integer S_k) and tau and T_r by U(-dt, dt) (dt = frame_period_s: "
            "where the release lies within a frame of T_0; U(0, dt) or U(-dt, 0) when "
            "release_side is before or after); eta's also draws D_p (hence E, Eq. 7) with its "
            "standard uncertainty",
            "value_resolution": self.value_resolution,
            "frame_period_s": self.frame_period_s,
            "release_side": self.release_side,
            "depth_relative_sd": self.depth_rel_sd,
            "variance_inflation": _finite(self.variance_inflation),
            "best_model": self.best_model,
            "kelvin_voigt_delta_qaicc": _finite(self.kelvin_voigt_delta_qaicc),
            "kelvin_voigt_rejected": self.kelvin_voigt_rejected,
            "bootstrap_replicates": self.replicates,
            "bootstrap_seed": self.seed,
            "flags": sorted(self.flags),
            "models": {f.model: f.to_dict(unit) for f in self.fits},
        }


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


@dataclass(frozen=True)
class _Series:
    x: FloatArray  # t - T_0 [s]
    z: FloatArray  # scaled to [0, 1]
    y_lo: float
    y_span: float
    settle_fraction: float
    rebound_force: Callable[[float], float | None] | None
    elasticity_kpa: float | None
    depth_rel_sd: float = 0.0
    #: Resolution of the values [series unit] (1 px for an integer S_k; 0: continuous).
    resolution: float = 0.0
    #: Frame period [s]: T_0 is known to within it (the median sample interval).
    frame_period_s: float = 0.0
    #: Which side of T_0 the release lies on (``fit_recovery_models``' ``release_side``).
    release_side: str = "either"

    def unscale(self, p: FloatArray) -> tuple[float, float]:
        """(offset, amplitude) in the series' unit."""
        return self.y_lo + self.y_span * float(p[0]), self.y_span * float(p[1])


def _quantised(p: FloatArray, level_error: float) -> FloatArray:
    """The curve p with its settled level moved by ``level_error`` [scaled units] and S_0
    kept: offset and amplitude both move (the rounding of a level the data sit at for
    most of the window, which no average of the rounded samples removes)."""
    out = p.copy()
    out[0] += level_error
    out[1] += level_error
    return out


def _quantities(
    model: RecoveryModel, p: FloatArray, s: _Series, origin_error_s: float = 0.0
) -> dict[str, float | None]:
    """tau, S_0, S_max, T_r, F_r, eta of the curve p (module docstring).

    ``origin_error_s`` [s] is added to the times read off the curve (tau, T_r; not below
    0): where the release lies relative to the T_0 the curve is anchored at.
    """
    offset, amplitude = s.unscale(p)
    u = p[2:]
    out: dict[str, float | None] = dict.fromkeys(
        ("tau_s", "recovery_time_s", "s0", "s_max", "rebound_force_n", "viscosity_n_s_per_mm2")
    )
    s0 = offset - amplitude
    g_end, _ = model.shape(s.x[-1:], u[None, :])
    s_end = offset - amplitude * float(g_end[0, 0])
    out["s0"], out["s_max"] = s0, max(s0, s_end)
    if amplitude != 0.0:
        tau = model.time_to_remaining(u, math.exp(-1.0))
        out["tau_s"] = max(tau + origin_error_s, 0.0) if math.isfinite(tau) else None
    if amplitude > 0.0 and s_end > 0.0:
        level = s.settle_fraction * s_end
        if level <= s0:
            out["recovery_time_s"] = 0.0
        else:
            r = min(max((offset - level) / amplitude, 1e-300), 1.0)
            tr = model.time_to_remaining(u, r) if r < 1.0 else 0.0
            tr = max(tr + origin_error_s, 0.0) if tr > 0.0 else tr
            out["recovery_time_s"] = tr if math.isfinite(tr) else None
    if s.rebound_force is not None and out["s_max"] is not None:
        out["rebound_force_n"] = s.rebound_force(out["s_max"])
    tr_s = out["recovery_time_s"]
    if s.elasticity_kpa is not None and tr_s is not None:
        out["viscosity_n_s_per_mm2"] = s.elasticity_kpa * tr_s / KPA_PER_N_PER_MM2
    return out


def _point_fit(model: RecoveryModel, s: _Series, kv: FloatArray | None) -> FloatArray | None:
    """The least-squares fit in solver coordinates, or None.

    Kelvin-Voigt is :mod:`~stipi_daemon.analysis.recovery_fit`'s own fit. Every other model
    is solved from its start-value rule and, when the Kelvin-Voigt fit exists, also from
    its nested Kelvin-Voigt point (:meth:`RecoveryModel.nested_start`); the lower cost wins,
    so a model containing Kelvin-Voigt never fits worse than it.
    """
    if model.NAME == _KV:
        return kv_solve_scaled(s.x, s.z)
    starts = [model.start(s.x, s.z)]
    if kv is not None:
        nested = model.nested_start(kv)
        if nested is not None:
            starts.append(nested)
    best: FloatArray | None = None
    best_cost = math.inf
    for start in starts:
        p = solve_scaled(model, s.x, s.z, start)
        if p is None:
            continue
        r, _ = model.residuals_batch(p[None, :], s.x, s.z[None, :], with_jacobian=False)
        cost = float(r[0] @ r[0])
        if cost < best_cost:
            best, best_cost = p, cost
    return best


def _bootstrap(
    model: RecoveryModel, p: FloatArray, s: _Series, replicates: int, rng: np.random.Generator
) -> tuple[dict[str, tuple[float, float] | None], BlockLength, int]:
    """95 % percentile intervals of the quantities; the block length; failed refits."""
    fitted = (
        s.z[None, :] + model.residuals_batch(p[None, :], s.x, s.z[None, :], with_jacobian=False)[0]
    )
    resid = s.z - fitted[0]
    block = block_length(resid)
    starts, length = moving_block_starts(s.x.size, block.length, replicates, rng)
    # E = c / D_p (Eq. 7): each replicate's D_p drawn with its standard uncertainty, after
    # the block indices so that the other intervals do not depend on it
    depth_factor = 1.0 + s.depth_rel_sd * rng.standard_normal(replicates)
    # the quantisation no resampling of residuals carries (docs/analysis.md, "Error model
    # of the intervals"): the settled level's rounding and T_0's place within a frame
    level_error = s.resolution * rng.uniform(-0.5, 0.5, replicates) / s.y_span
    lo_hi = {"either": (-1.0, 1.0), "before": (0.0, 1.0), "after": (-1.0, 0.0)}[s.release_side]
    origin_error_s = s.frame_period_s * rng.uniform(*lo_hi, replicates)
    samples: dict[str, list[float]] = {k: [] for k in CI_QUANTITIES}
    failed = 0
    for lo in range(0, replicates, _CHUNK):
        z_star = fitted + resid[block_indices(starts[lo : lo + _CHUNK], length, s.x.size)]
        p_star, ok = solve_batch(model, s.x, z_star, p)
        for b in range(p_star.shape[0]):
            shifted = _quantised(p_star[b], level_error[lo + b])
            q = _quantities(model, shifted, s, origin_error_s[lo + b]) if ok[b] else None
            d = float(depth_factor[lo + b])
            if q is None or not np.all(np.isfinite(p_star[b])) or d <= 0.0:
                failed += 1
                continue
            eta = q["viscosity_n_s_per_mm2"]
            q["viscosity_n_s_per_mm2"] = None if eta is None else eta / d
            for k in CI_QUANTITIES:
                v = q[k]
                samples[k].append(math.inf if v is None else v)
    ci: dict[str, tuple[float, float] | None] = {}
    for k, vals in samples.items():
        ci[k] = _percentile_interval(vals, replicates - failed)
    return ci, block, failed


def _percentile_interval(values: list[float], n_ok: int) -> tuple[float, float] | None:
    """2.5 and 97.5 % order statistics; None if undefined or unbounded."""
    if n_ok <= 0 or len(values) < n_ok:
        return None
    a = np.sort(np.asarray(values, dtype=np.float64))
    lo = float(a[math.floor(0.025 * (a.size - 1))])
    hi = float(a[math.ceil(0.975 * (a.size - 1))])
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    return lo, hi


def _series(
    times_s: ArrayLike, values: ArrayLike, t0_s: float, window_s: float
) -> tuple[FloatArray, FloatArray, set[Flag]]:
    tw, yw, flags = fit_window(times_s, values, t0_s, window_s)
    return tw - float(t0_s), yw, flags


def _model_names(models: Sequence[str] | None) -> list[str]:
    """The registry names to compare, Kelvin-Voigt first (default: all)."""
    names = [_KV, *[m for m in (models or MODELS) if m != _KV]]
    unknown = [m for m in names if m not in MODELS]
    if unknown:
        raise AnalysisError(f"unknown recovery model {unknown[0]!r} (known: {', '.join(MODELS)})")
    return names


def _check_settings(
    settle_fraction: float,
    replicates: int,
    seed: int,
    depth_rel_sd: float,
    elasticity_kpa: float | None,
    release_side: str,
    value_resolution: float | None,
    frame_period_s: float | None,
) -> None:
    """:func:`fit_recovery_models`' settings in their domains, else an AnalysisError
    naming the parameter."""
    if not 0.0 < settle_fraction < 1.0:
        raise AnalysisError(f"settle_fraction must be in (0, 1), got {settle_fraction}")
    if replicates < 0 or seed < 0:
        raise AnalysisError(f"replicates and seed must be >= 0, got {replicates}, {seed}")
    if not (math.isfinite(depth_rel_sd) and depth_rel_sd >= 0.0):
        raise AnalysisError(f"depth_rel_sd must be finite and >= 0, got {depth_rel_sd}")
    if elasticity_kpa is not None and not (math.isfinite(elasticity_kpa) and elasticity_kpa > 0.0):
        raise AnalysisError(f"elasticity_kpa must be finite and > 0, got {elasticity_kpa}")
    if release_side not in ("either", "before", "after"):
        raise AnalysisError(f"release_side must be either, before or after, got {release_side!r}")
    for name, v in (("value_resolution", value_resolution), ("frame_period_s", frame_period_s)):
        if v is not None and not (math.isfinite(v) and v >= 0.0):
            raise AnalysisError(f"{name} must be finite and >= 0, got {v}")


def fit_recovery_models(
    times_s: ArrayLike,
    values: ArrayLike,
    t0_s: float,
    window_s: float = DEFAULT_WINDOW_S,
    *,
    settle_fraction: float = DEFAULT_SETTLE_FRACTION,
    replicates: int = DEFAULT_REPLICATES,
    seed: int = 0,
    models: Sequence[str] | None = None,
    rebound_force: Callable[[float], float | None] | None = None,
    elasticity_kpa: float | None = None,
    depth_rel_sd: float = 0.0,
    value_resolution: float | None = None,
    frame_period_s: float | None = None,
    release_side: Literal["either", "before", "after"] = "either",
) -> RecoveryModelComparison:
    """Fit every recovery model to one series; AICc weights; bootstrap 95 % intervals.

    Parameters
    ----------
    times_s : array_like
        Sample times [s], finite and strictly increasing.
    values : array_like
        S_k [px] (or a depth [mm]: T_r, F_r and eta are then None); NaN/inf samples are
        dropped (``NON_FINITE_INPUT``).
    t0_s : float
        Start of the recovery T_0 [s].
    window_s : float
        Fitted span after T_0 [s] (the paper's 105 s by default).
    settle_fraction : float
        f of Eq. (6) for T_r on each curve, in (0, 1).
    replicates : int
        Bootstrap replicates per model, >= 0 (0: no intervals).
    seed : int
        Seed of the resampling (with the model's registry index), >= 0.
    models : sequence of str, optional
        Registry names to compare (default: all; Kelvin-Voigt is always included).
    rebound_force : callable, optional
        Eq. (5), S_max [px] -> F_r [N] (None for an S_max it cannot take).
    elasticity_kpa : float, optional
        E [kPa] for eta = E T_r (Eq. 8), finite and > 0.
    depth_rel_sd : float
        Relative standard uncertainty of D_p [-], >= 0 and finite (0: E held fixed). E =
        c/D_p (Eq. 7), so each bootstrap replicate's eta is divided by 1 + depth_rel_sd z,
        z standard normal: eta's interval carries E's uncertainty through D_p (F_a's is
        not in it).
    value_resolution : float, optional
        The values' quantum [series unit], finite and >= 0: each bootstrap replicate moves
        the settled level by a uniform draw in +-resolution/2 (the rounding of S_max that
        no average of rounded samples removes). Default: 1 when every value is an integer
        (S_k, a pixel count), else 0 (a continuous series: a depth, a sub-pixel area).
    frame_period_s : float, optional
        How well T_0 places the release [s], finite and >= 0: each replicate's tau and T_r
        move by a uniform draw in +-frame_period_s (the release lies within one frame
        period of the frame T_0 is, on either side). Default: the median sample interval.
    release_side : {"either", "before", "after"}
        Where the release lies relative to T_0, when the caller knows: ``"before"`` (T_0 is
        the first frame that shows the release: tau and T_r from the release are longer by
        U(0, frame_period_s)), ``"after"`` (T_0 is the last frame that shows the pit:
        shorter by U(0, frame_period_s)); ``"either"`` (default) draws U(-dt, dt).

    Domain: |values| <= :data:`MAX_ABS_VALUE` (1e150 in the series' unit) so that squared
    residuals stay finite; times as :func:`~stipi_daemon.analysis.recovery_fit.fit_window`.

    Raises
    ------
    AnalysisError
        Input as :func:`~stipi_daemon.analysis.recovery_fit.fit_recovery` refuses it, a
        value outside the domain, an unknown model name, or a setting outside its domain
        (a non-finite or non-positive ``elasticity_kpa``, a negative or non-finite
        ``value_resolution`` or ``frame_period_s``), each naming the parameter.
    """
    _check_settings(
        settle_fraction,
        replicates,
        seed,
        depth_rel_sd,
        elasticity_kpa,
        release_side,
        value_resolution,
        frame_period_s,
    )
    names = _model_names(models)
    x, y, flags = _series(times_s, values, t0_s, window_s)
    y_lo, y_hi = float(np.min(y)), float(np.max(y))
    check_value_domain(y_lo, y_hi)
    span = y_hi - y_lo
    if value_resolution is None:
        value_resolution = 1.0 if bool(np.all(y == np.round(y))) else 0.0
    if frame_period_s is None:
        frame_period_s = float(np.median(np.diff(x))) if x.size > 1 else 0.0
    common = {
        "t0_s": float(t0_s),
        "t_start_s": float(t0_s + x[0]),
        "t_end_s": float(t0_s + x[-1]),
        "n_points": int(x.size),
        "replicates": replicates,
        "seed": seed,
        "depth_rel_sd": float(depth_rel_sd),
        "value_resolution": float(value_resolution),
        "frame_period_s": float(frame_period_s),
        "release_side": release_side,
    }
    if span <= 1e-12 * max(abs(y_lo), abs(y_hi)) or span == 0.0:
        return _constant_series(names, flags, common)
    s = _Series(
        x,
        (y - y_lo) / span,
        y_lo,
        span,
        settle_fraction,
        rebound_force,
        elasticity_kpa,
        depth_rel_sd,
        value_resolution,
        frame_period_s,
        release_side,
    )
    return _compare(names, s, replicates, seed, flags, common)


def _constant_series(
    names: list[str], flags: set[Flag], common: dict[str, Any]
) -> RecoveryModelComparison:
    """The comparison of a series without a rise: no model fitted, no selection."""
    fits = tuple(
        ModelFit(m, None, MODELS[m].n_parameters, None, flags=frozenset({Flag.CONSTANT_SERIES}))
        for m in names
    )
    return RecoveryModelComparison(
        fits,
        variance_inflation=None,
        best_model=None,
        kelvin_voigt_delta_qaicc=None,
        flags=frozenset(flags | {Flag.CONSTANT_SERIES, Flag.MODEL_SELECTION_UNAVAILABLE}),
        **common,
    )


def _compare(
    names: list[str],
    s: _Series,
    replicates: int,
    seed: int,
    flags: set[Flag],
    common: dict[str, Any],
) -> RecoveryModelComparison:
    """Fit, select and bootstrap (see :func:`fit_recovery_models`)."""
    n = s.x.size
    points: dict[str, FloatArray | None] = {}
    fits: dict[str, ModelFit] = {}
    rss_scaled: dict[str, float] = {}
    for name in names:
        model = MODELS[name]
        if n < model.n_parameters + 1:
            points[name] = None
            fits[name] = ModelFit(
                name, None, model.n_parameters, None, flags=frozenset({Flag.TOO_FEW_POINTS})
            )
            continue
        p = _point_fit(model, s, points.get(_KV))
        points[name] = p
        if p is None:
            fits[name] = ModelFit(
                name, None, model.n_parameters, None, flags=frozenset({Flag.FIT_NOT_CONVERGED})
            )
            continue
        r, _ = model.residuals_batch(p[None, :], s.x, s.z[None, :], with_jacobian=False)
        rss_scaled[name] = float(r[0] @ r[0])
        offset, amplitude = s.unscale(p)
        params = {"offset": offset, "amplitude": amplitude, **model.natural(p[2:])}
        fits[name] = _judged(model, p, s, params, rss_scaled[name])
    # Selection on the floored RSS (scaled units: the range is 1).
    rss_f = {m: floored_rss(v, n, 1.0) for m, v in rss_scaled.items()}
    best_fit = min(rss_f, key=lambda m: rss_f[m]) if rss_f else None
    p_best = points.get(best_fit) if best_fit is not None else None
    inflation = None
    if best_fit is not None and rss_f[best_fit] > rss_scaled[best_fit]:
        inflation = 1.0  # the best fit is at the RSS floor: no residual dependence to weigh
    elif best_fit is not None and p_best is not None:
        r, _ = MODELS[best_fit].residuals_batch(
            p_best[None, :], s.x, s.z[None, :], with_jacobian=False
        )
        inflation = block_length(r[0]).variance_inflation
    a = {m: aicc(v, n, MODELS[m].n_parameters + 1) for m, v in rss_f.items()}
    qa = {
        m: None if inflation is None else qaicc(v, n, MODELS[m].n_parameters + 1, inflation)
        for m, v in rss_f.items()
    }
    wa = dict(zip(a, akaike_weights(list(a.values())), strict=True))
    wq = dict(zip(qa, akaike_weights(list(qa.values())), strict=True))
    q_min = min((v for v in qa.values() if v is not None), default=None)
    for m in rss_f:
        qv = qa[m]
        fits[m] = _replace_fit(
            fits[m],
            aicc=a[m],
            akaike_weight=wa[m],
            qaicc=qv,
            qaicc_weight=wq[m],
            delta_qaicc=None if qv is None or q_min is None else qv - q_min,
        )
    kv_delta = fits[_KV].delta_qaicc
    ranked = [m for m in names if wq.get(m) is not None]
    best = max(ranked, key=lambda m: wq[m] or 0.0) if ranked else None
    if best is None:
        flags.add(Flag.MODEL_SELECTION_UNAVAILABLE)
    elif kv_delta is not None and kv_delta > KV_REJECTION_DELTA:
        flags.add(Flag.KELVIN_VOIGT_REJECTED)
    for i, name in enumerate(names):
        p = points[name]
        if p is None or replicates == 0:
            continue
        fits[name] = _with_intervals(MODELS[name], p, s, fits[name], replicates, seed, i)
    return RecoveryModelComparison(
        tuple(fits[m] for m in names),
        variance_inflation=inflation,
        best_model=best,
        kelvin_voigt_delta_qaicc=kv_delta,
        flags=frozenset(flags),
        **common,
    )


def _replace_fit(fit: ModelFit, **changes: Any) -> ModelFit:
    from dataclasses import replace

    return replace(fit, **changes)


def _judged(
    model: RecoveryModel, p: FloatArray, s: _Series, params: dict[str, float], rss: float
) -> ModelFit:
    """A point fit with its quantities and per-model flags."""
    flags: set[Flag] = set()
    q = _quantities(model, p, s)
    span = float(s.x[-1])
    tau = q["tau_s"]
    frame = float(np.median(np.diff(s.x))) if s.x.size > 1 else span
    if tau is None or tau > span or tau < frame:
        flags.add(Flag.TIME_CONSTANT_OUTSIDE_WINDOW)
    lo, hi = model.bounds()
    at_bound = (np.isclose(p[2:], lo[2:], rtol=0, atol=1e-6)) | np.isclose(
        p[2:], hi[2:], rtol=0, atol=1e-6
    )
    if np.any(at_bound):
        flags.add(Flag.PARAMETER_AT_BOUND)
    return ModelFit(
        model.NAME,
        params,
        model.n_parameters,
        rss * s.y_span**2,
        quantities=q,
        flags=frozenset(flags),
    )


def _with_intervals(
    model: RecoveryModel,
    p: FloatArray,
    s: _Series,
    fit: ModelFit,
    replicates: int,
    seed: int,
    index: int,
) -> ModelFit:
    """``fit`` with its bootstrap intervals (or NO_CONFIDENCE_INTERVALS and why)."""
    n = s.x.size
    if n < max(MIN_SERIES, model.n_parameters + 3):
        return _replace_fit(fit, flags=fit.flags | {Flag.NO_CONFIDENCE_INTERVALS})
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    ci, block, failed = _bootstrap(model, p, s, replicates, rng)
    flags = set(fit.flags)
    if failed > BOOTSTRAP_FAILURE_LIMIT * replicates:
        ci = dict.fromkeys(ci)
        flags.add(Flag.NO_CONFIDENCE_INTERVALS)
    for k, v in fit.quantities.items():
        if k in ci and v is None:
            ci[k] = None
    return _replace_fit(
        fit,
        ci95=ci,
        block=block,
        replicates=replicates,
        failed_replicates=failed,
        flags=frozenset(flags),
    )
