"""The primary quantities consult the recovery models; uncertainty beyond tolerance is
invalid (analysis/model_checks.py, results.py, validity.py).

Recoveries are written here from laws of the literature - Kelvin-Voigt, Findley's power
law, the Kohlrausch-Williams-Watts stretched exponential - and the truths (Eq. 5 at the
settled level, the reference grades' T_r = eta/E of Table II) are computed here from those
laws, not by the code under test.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from stipi_daemon.analysis import (
    AnalysisSettings,
    Calibration,
    analyze_recovery,
    fit_recovery,
    load_reference,
)
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.model_checks import (
    SUPPORT_RATIO,
    curve_recovery_time_s,
    early_stop_check,
    supported_fits,
)
from stipi_daemon.analysis.recovery_models import fit_recovery_models
from stipi_daemon.analysis.results import MeasurementResult
from stipi_daemon.analysis.validity import assess_validity

CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)
T0 = 15.0
F = 0.98
#: A 3 mm pit recovering to 6.5 N (Eqs. 4-5 of CAL).
S0_PX = CAL.s0_for_depth_change(CAL.indenter_length_mm - 3.0)
S_INF_PX = CAL.area_for_force_px(6.5)


def render(
    remaining: object, *, end_s: float = 105.0, fps: float = 30.0, noise_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """S_k [px] from T_0 - 15 s to T_0 + end_s: 40000 px in the hold, then
    S_inf - (S_inf - S_0) g(t - T_0) with the law g; whole pixels."""
    assert callable(remaining)
    t = np.arange(0.0, T0 + end_s + 1e-9, 1.0 / fps)
    x = np.clip(t - T0, 0.0, None)
    s = np.where(t < T0, 40000.0, S_INF_PX - (S_INF_PX - S0_PX) * remaining(x))
    s = s + np.random.default_rng(5).normal(0.0, noise_px, t.size)
    return t, np.round(s)


def analyse(t: np.ndarray, s: np.ndarray, replicates: int = 100) -> MeasurementResult:
    settings = AnalysisSettings(bootstrap_replicates=replicates)
    return analyze_recovery(t, s, T0, CAL, 16.0, settings, load_reference())


def validity(res: MeasurementResult) -> dict[str, dict[str, object]]:
    out: dict[str, dict[str, object]] = assess_validity(res, ended_done=True)["validity"]
    return out


# --------------------------------------------------------------------------- the curves


def test_eq6_on_a_kelvin_voigt_fit_is_the_closed_form() -> None:
    # Kelvin-Voigt: the whole recovery gives T_r = tau ln((1 - r)/(1 - f)); recorded to T,
    # T_r(T) = tau ln((1 - r)/((1 - f) + f (1 - r) e^(-T/tau))), r = S_0/S_inf.
    tau = 6.0
    t, s = render(lambda x: np.exp(-x / tau), fps=60.0)
    cmp = fit_recovery_models(t, s.astype(float), T0, 105.0, replicates=0)
    kv = cmp.fit("kelvin_voigt")
    r = S0_PX / S_INF_PX
    whole = tau * math.log((1.0 - r) / (1.0 - F))
    assert curve_recovery_time_s(kv, F) == pytest.approx(whole, rel=2e-3)
    for horizon in (15.0, 30.0):
        eps = math.exp(-horizon / tau)
        part = tau * math.log((1.0 - r) / ((1.0 - F) + F * (1.0 - r) * eps))
        assert curve_recovery_time_s(kv, F, horizon) == pytest.approx(part, rel=2e-3)


def test_models_with_weight_are_those_within_an_evidence_ratio_of_8() -> None:
    t, s = render(lambda x: np.exp(-((x / 1.0) ** 0.4)), noise_px=20.0)
    cmp = fit_recovery_models(t, s, T0, 105.0, replicates=0)
    kept = {f.model for f in supported_fits(cmp)}
    weights = {f.model: f.qaicc_weight for f in cmp.fits if f.qaicc_weight is not None}
    best = max(weights.values())
    assert kept == {m for m, w in weights.items() if w >= SUPPORT_RATIO * best}
    assert cmp.best_model in kept and "kelvin_voigt" not in kept  # KV rejected


def test_the_early_stop_check_refuses_a_power_law_and_allows_a_kelvin_voigt_plateau() -> None:
    # Findley (1 + t/1 s)^-1 recorded for 40 s still rises 1.5 % of S_inf to 105 s.
    t, s = render(lambda x: (1.0 + x) ** -1.0, end_s=40.0, fps=60.0)
    keep = t >= T0
    check = early_stop_check(
        t[keep], s[keep], T0, T0 + 105.0, settle_fraction=F, bias_fraction=0.005
    )
    assert not check.allowed and "keeps recording" in check.reason
    t, s = render(lambda x: np.exp(-x / 5.0), end_s=60.0, fps=60.0)
    keep = t >= T0
    check = early_stop_check(
        t[keep], s[keep], T0, T0 + 105.0, settle_fraction=F, bias_fraction=0.005
    )
    assert check.allowed, check.reason


# --------------------------------------------------------------------------- the rules


def test_a_stretched_exponential_with_a_rising_tail_flags_tr_against_the_models() -> None:
    # KWW exp(-(t/1 s)^0.4): the measured S_max sits off the level the best model (power
    # law) reads; T_r and what follows from it are flagged with the amount, never valid.
    res = analyse(*render(lambda x: np.exp(-((x / 1.0) ** 0.4))))
    assert res.models is not None and res.models.kelvin_voigt_rejected
    v = validity(res)
    assert v["recovery_time_s"]["status"] == "flagged"
    fired = {c.flag for c in res.checks}
    assert fired & {Flag.SETTLED_LEVEL_OFF_MODEL, Flag.RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL}
    reason = str(v["recovery_time_s"]["reason"])
    assert re.search(r"[+-]?\d+\.\d\d s", reason), reason
    assert v["viscosity_n_s_per_mm2"]["status"] != "valid"
    assert v["severity"]["status"] != "valid"


def test_a_recording_that_ends_before_the_power_law_settles_is_invalid() -> None:
    # Findley (1 + t/1 s)^-1 reaches 98 % of S_inf at t = 1 s x (A/(0.02 S_inf) - 1) = 35 s;
    # recorded for 10 s, S_max is 1/11 of the rise short and F_r (Eq. 5) 7 % low.
    t, s = render(lambda x: (1.0 + x) ** -1.0, end_s=10.0)
    res = analyse(t, s)
    truth_n = (S_INF_PX - CAL.c1_px) / CAL.c2_px_per_n
    assert abs(res.pitting.rebound_force_n / truth_n - 1.0) > 0.05
    v = validity(res)
    for q in ("recovery_time_s", "rebound_force_n", "viscosity_n_s_per_mm2", "severity"):
        assert v[q]["status"] == "invalid", (q, v[q])
    assert Flag.MODEL_NOT_SETTLED in {c.flag for c in res.checks}


def test_a_recovery_stopped_16_s_in_invalidates_fr_by_the_settled_level_rule() -> None:
    # Kelvin-Voigt tau 7.5 s stopped (Ctrl-C) 16 s after T_0: S_max is e^(-16/7.5) of the
    # rise short, F_r 9 % low.
    t, s = render(lambda x: np.exp(-x / 7.5), end_s=16.0)
    res = analyse(t, s)
    truth_n = (S_INF_PX - CAL.c1_px) / CAL.c2_px_per_n
    assert res.pitting.rebound_force_n / truth_n - 1.0 < -0.05
    v = validity(res)
    assert v["rebound_force_n"]["status"] == "invalid"
    assert v["recovery_time_s"]["status"] == "invalid"
    assert "settle" in str(v["rebound_force_n"]["reason"])


def test_a_kelvin_voigt_recovery_with_noise_stays_valid() -> None:
    res = analyse(*render(lambda x: np.exp(-x / 7.5), noise_px=20.0))
    assert not res.checks, res.checks
    v = validity(res)
    for q in ("depth_mm", "rebound_force_n", "recovery_time_s", "elasticity_kpa", "tau_s"):
        assert v[q]["status"] == "valid", (q, v[q])


# --------------------------------------------------------------------------- uncertainty


def _without(
    t: np.ndarray, s: np.ndarray, lo_s: float, hi_s: float
) -> tuple[np.ndarray, np.ndarray]:
    keep = ~((t > lo_s) & (t < hi_s))
    return t[keep], s[keep]


@pytest.mark.parametrize(("gap_s", "status"), [(1.0, "flagged"), (6.0, "invalid")])
def test_a_gap_at_the_crossing_beyond_tolerance_makes_tr_invalid(gap_s: float, status: str) -> None:
    t, s = render(lambda x: np.exp(-x / 7.5), fps=60.0)
    ts = analyse(t, s, replicates=0).pitting.ts_s
    assert ts is not None
    res = analyse(*_without(t, s, ts - gap_s / 2, ts + gap_s / 2), replicates=0)
    v = validity(res)["recovery_time_s"]
    assert Flag.FRAME_GAP_AT_SETTLING in res.flags
    assert v["status"] == status, v
    if status == "invalid":
        assert re.search(
            r"uncertain by 6\.\d\d s, beyond its tolerance 1\.\d\d s", str(v["reason"])
        )


def _iii_iv_boundary_s() -> float:
    """T_r [s] at which exp(-t/T_r) is as close (RMS over 1..50 s) to grade III as to IV,
    from Table II's E and eta (T_r = eta/E)."""
    grid = np.arange(1.0, 51.0)
    t3, t4 = 6.08 / 220.61 * 1e3, 8.70 / 196.32 * 1e3

    def d(a: float, b: float) -> float:
        return float(np.sqrt(np.mean(np.square(np.exp(-grid / a) - np.exp(-grid / b)))))

    lo, hi = t3, t4
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if d(mid, t3) < d(mid, t4) else (lo, mid)
    return 0.5 * (lo + hi)


def test_a_class_the_uncertainty_could_move_is_not_named() -> None:
    # T_r at the grade III / IV boundary with a 1.2 s gap over its crossing (less than its
    # tolerance: T_r is only flagged), so either grade is possible.
    tr = _iii_iv_boundary_s()
    r = S0_PX / S_INF_PX
    tau = tr / math.log((1.0 - r) / (1.0 - F))
    t, s = render(lambda x: np.exp(-x / tau), fps=60.0)
    res = analyse(*_without(t, s, T0 + tr - 0.6, T0 + tr + 0.6))
    v = validity(res)
    assert v["recovery_time_s"]["status"] == "flagged"
    assert v["severity"]["status"] == "invalid"
    assert "grades III, IV" in str(v["severity"]["reason"])


# --------------------------------------------------------------------------- public API edges


def test_a_flat_noisy_series_has_no_valid_time_constant() -> None:
    t = np.arange(0.0, 120.0, 1.0 / 30.0)
    s = np.where(t < T0, 40000.0, 9000.0) + np.random.default_rng(3).normal(0.0, 20.0, t.size)
    fit = fit_recovery(t, s, T0)
    assert Flag.TIME_CONSTANT_UNCERTAIN in fit.flags
    v = validity(analyse(t, s, replicates=0))
    assert v["tau_s"]["status"] == "invalid"
    assert "standard error" in str(v["tau_s"]["reason"])


def test_an_all_zero_series_has_no_valid_depth() -> None:
    t = np.arange(0.0, 120.0, 1.0 / 30.0)
    res = analyse(t, np.zeros(t.size), replicates=0)
    assert res.pitting.depth_mm == pytest.approx(CAL.indenter_length_mm)  # Eq. 4 at S = 0
    v = validity(res)
    assert v["depth_mm"]["status"] == "invalid"
    assert "S_0 = 0 px" in str(v["depth_mm"]["reason"])
    assert all(v[q]["status"] == "invalid" for q in ("elasticity_kpa", "severity"))
