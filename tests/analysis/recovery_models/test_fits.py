"""Fits against curves from the simulator's tissue models (an independent implementation of
each recovery): parameters recovered on noiseless curves, AICc picking the true model,
Kelvin-Voigt rejected under realistic noise exactly when the tissue is not Kelvin-Voigt,
intervals covering the truth at about their nominal rate, the block length equal to the
reference implementation's (arch), the batch solver equal to scipy's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.recovery_fit import fit_recovery
from stipi_daemon.analysis.recovery_models import MODELS, fit_recovery_models
from stipi_daemon.analysis.recovery_models.base import solve_batch, solve_scaled
from stipi_daemon.analysis.recovery_models.bootstrap import block_length
from stipi_daemon.errors import AnalysisError

from ._curves import SCENE_MODELS, T0_S, TRUE_FIT, realistic_noise, series


@pytest.mark.parametrize("tissue", sorted(SCENE_MODELS))
def test_noiseless_curves_recover_the_truth_and_aicc_picks_the_true_model(tissue: str) -> None:
    t, s, truth = series(tissue, window_s=60.0, fps=30.0)
    c = fit_recovery_models(t, s, T0_S, replicates=0)
    true = TRUE_FIT[tissue]
    assert c.fits[0].model == "kelvin_voigt"
    if true is None:  # poroelastic: no fitted model is true; Kelvin-Voigt is rejected
        assert c.kelvin_voigt_rejected
        return
    fit = c.fit(true)
    assert fit.quantities["tau_s"] == pytest.approx(truth["tau_s"], rel=1e-5)
    assert fit.quantities["recovery_time_s"] == pytest.approx(truth["recovery_time_s"], rel=1e-5)
    assert fit.quantities["s_max"] == pytest.approx(truth["s_max"], rel=1e-7)
    assert fit.parameters is not None
    p = fit.parameters
    assert p["offset"] == pytest.approx(17851.0, rel=1e-6)
    assert p["offset"] - p["amplitude"] == pytest.approx(4862.0, rel=1e-6)
    weights = {f.model: f.akaike_weight for f in c.fits}
    assert max(weights, key=lambda m: weights[m] or 0.0) == true
    others = [f.aicc for f in c.fits if f.model != true and f.aicc is not None]
    assert fit.aicc is not None
    # Nested models can only lose by their extra parameters (2 per parameter); others lose big.
    assert min(others) - fit.aicc >= 1.9
    if tissue == "kelvin_voigt":
        assert not c.kelvin_voigt_rejected
        assert fit.akaike_weight is not None and fit.akaike_weight > 0.6
    else:
        assert c.kelvin_voigt_rejected
        assert fit.akaike_weight is not None and fit.akaike_weight > 0.999
        assert min(others) - fit.aicc > 100.0


def test_parameters_of_each_model_are_recovered() -> None:
    t, s, _ = series("prony", window_s=60.0, fps=30.0)
    p = fit_recovery_models(t, s, T0_S, replicates=0).fit("two_exponential").parameters
    assert p is not None
    assert p["tau_fast_s"] == pytest.approx(1.0, rel=1e-5)
    assert p["tau_slow_s"] == pytest.approx(8.92, rel=1e-5)
    assert p["weight_fast"] == pytest.approx(0.4, rel=1e-5)
    t, s, _ = series("zener", window_s=60.0, fps=30.0)
    z = fit_recovery_models(t, s, T0_S, replicates=0).fit("two_exponential")
    assert z.parameters is not None
    assert z.parameters["tau_slow_s"] == pytest.approx(8.31, rel=1e-4)
    assert z.parameters["weight_fast"] == pytest.approx(2.08 / 8.31, rel=1e-3)  # the jump
    assert z.parameters["tau_fast_s"] < 1.0 / 30.0
    t, s, _ = series("power_law", window_s=60.0, fps=30.0)
    p = fit_recovery_models(t, s, T0_S, replicates=0).fit("power_law").parameters
    assert p is not None
    assert p["tau_s"] == pytest.approx(2.07, rel=1e-5)
    assert p["exponent_n"] == pytest.approx(1.5, rel=1e-5)


def test_kelvin_voigt_entry_is_the_fitted_recovery() -> None:
    t, s, _ = series("zener", noise=15.0, window_s=40.0, fps=30.0)
    kv = fit_recovery_models(t, s, T0_S, 40.0, replicates=0).fit("kelvin_voigt")
    ref = fit_recovery(t, s, T0_S, 40.0)
    assert kv.parameters is not None
    assert kv.parameters["tau_s"] == ref.tau_s
    assert kv.parameters["offset"] == ref.offset and kv.parameters["amplitude"] == ref.amplitude


@pytest.mark.parametrize("tissue", sorted(SCENE_MODELS))
def test_kelvin_voigt_rejected_exactly_on_non_kelvin_voigt_tissue(tissue: str) -> None:
    for seed in (1, 2):
        t, s, _ = series(tissue, noise="realistic", seed=seed, window_s=105.0)
        c = fit_recovery_models(t, s, T0_S, replicates=0)
        assert c.kelvin_voigt_rejected == (tissue != "kelvin_voigt"), (seed, c.to_dict())
        assert (Flag.KELVIN_VOIGT_REJECTED in c.flags) == (tissue != "kelvin_voigt")


def test_intervals_cover_the_truth_at_about_the_nominal_rate() -> None:
    """20 seeded noisy recoveries per true model: the 95 % intervals of tau and T_r of the
    true model cover the tissue model's values in >= 80 % of them (P(<= 15 of 20) ~ 1.6 %
    at a true 95 %)."""
    cases = [("kelvin_voigt", "kelvin_voigt"), ("prony", "two_exponential")]
    for tissue, fitted in cases:
        covered = {"tau_s": 0, "recovery_time_s": 0}
        for seed in range(20):
            t, s, truth = series(tissue, noise="realistic", seed=seed, window_s=20.0, fps=60.0)
            f = fit_recovery_models(t, s, T0_S, 20.0, replicates=100, seed=seed).fit(fitted)
            for k in covered:
                ci = f.ci95[k]
                assert ci is not None
                covered[k] += ci[0] <= truth[k] <= ci[1]
        assert covered["tau_s"] >= 16 and covered["recovery_time_s"] >= 16, (tissue, covered)


def test_intervals_are_deterministic() -> None:
    t, s, _ = series("power_law", noise="realistic", seed=3, window_s=20.0)
    a = fit_recovery_models(t, s, T0_S, 20.0, replicates=40, seed=7).to_dict()
    b = fit_recovery_models(t, s, T0_S, 20.0, replicates=40, seed=7).to_dict()
    assert a == b
    c = fit_recovery_models(t, s, T0_S, 20.0, replicates=40, seed=8).to_dict()
    assert c["models"]["power_law"]["ci95"] != a["models"]["power_law"]["ci95"]


def test_block_length_equals_arch_reference() -> None:
    from arch.bootstrap import optimal_block_length

    rng = np.random.default_rng(0)
    for n in (50, 600, 6300):
        for kind in ("white", "ar", "realistic"):
            if kind == "white":
                x = rng.standard_normal(n)
            elif kind == "ar":
                x = np.zeros(n)
                for i in range(1, n):
                    x[i] = 0.7 * x[i - 1] + rng.standard_normal()
            else:
                x = realistic_noise(n, rng)
            ref = float(optimal_block_length(x)["circular"].iloc[0])
            got = block_length(x)
            assert got.optimal == pytest.approx(max(ref, 0.0), rel=1e-9) or (
                ref < 1.0 and got.length == 1
            ), (n, kind, ref, got)
            assert got.length == max(1, min(math.ceil(got.optimal), n // 3))


@pytest.mark.parametrize("name", ["kelvin_voigt", "two_exponential", "power_law"])
def test_batch_solver_agrees_with_scipy(name: str) -> None:
    model = MODELS[name]
    tissue = {"kelvin_voigt": "kelvin_voigt", "two_exponential": "prony"}.get(name, "power_law")
    t, s, _ = series(tissue, window_s=30.0, fps=30.0)
    x = t - T0_S
    z = (s - s.min()) / np.ptp(s)
    rng = np.random.default_rng(1)
    zs = z[None, :] + 0.003 * rng.standard_normal((6, z.size))
    p0 = solve_scaled(model, x, z, model.start(x, z))
    assert p0 is not None
    batch, ok = solve_batch(model, x, zs, p0)
    assert ok.all()
    for b in range(zs.shape[0]):
        ref = solve_scaled(model, x, zs[b], p0)
        assert ref is not None
        rb, _ = model.residuals_batch(batch[b][None], x, zs[b][None], with_jacobian=False)
        rr, _ = model.residuals_batch(ref[None], x, zs[b][None], with_jacobian=False)
        assert float(rb[0] @ rb[0]) <= float(rr[0] @ rr[0]) * (1.0 + 1e-5)
        u = math.exp(-1.0)
        assert model.time_to_remaining(batch[b][2:], u) == pytest.approx(
            model.time_to_remaining(ref[2:], u), rel=1e-3
        )


def test_eta_interval_carries_the_depth_uncertainty() -> None:
    # E = c/D_p (Eq. 7): with D_p uncertain by 1 %, eta's 95 % interval spans at least
    # +-1.96 % around eta (the T_r part adds to it); the other intervals do not change.
    t, s, _ = series("kelvin_voigt", noise="realistic", seed=1, window_s=30.0)
    kw = {"replicates": 200, "seed": 3, "elasticity_kpa": 200.0}
    fixed = fit_recovery_models(t, s, T0_S, 30.0, **kw).fit("kelvin_voigt")  # type: ignore[arg-type]
    drawn = fit_recovery_models(t, s, T0_S, 30.0, depth_rel_sd=0.01, **kw)  # type: ignore[arg-type]
    f = drawn.fit("kelvin_voigt")
    assert drawn.to_dict()["depth_relative_sd"] == 0.01
    for k in ("tau_s", "recovery_time_s", "rebound_force_n", "s_max"):
        assert f.ci95[k] == fixed.ci95[k], k
    eta = f.quantities["viscosity_n_s_per_mm2"]
    lo, hi = f.ci95["viscosity_n_s_per_mm2"] or (math.nan, math.nan)
    flo, fhi = fixed.ci95["viscosity_n_s_per_mm2"] or (math.nan, math.nan)
    assert eta is not None and lo < flo and hi > fhi
    assert (hi - lo) / eta == pytest.approx(2 * 1.96 * 0.01, rel=0.25)
    with pytest.raises(AnalysisError, match="depth_rel_sd"):
        fit_recovery_models(t, s, T0_S, 30.0, depth_rel_sd=math.nan)
