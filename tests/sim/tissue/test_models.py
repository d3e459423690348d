"""Tissue models against checks nobody here wrote: ODEs integrated by scipy, the diffusion
equation by the method of lines, the gamma spectrum by quadrature, and the limits where a
model reduces to Kelvin-Voigt. Specs: Fung, Biomechanics Sec. 2.11 (standard form of the
standard linear solid); Findley, Lai & Onaran Sec. 5.4 (generalised Kelvin model);
Terzaghi/Biot consolidation (Wang, Theory of Linear Poroelasticity, Sec. 6.2); Williams
1964 (modified power law). Also: every registered model's metadata and parameter domains
at their edges."""

from __future__ import annotations

import importlib
import math
import re

import numpy as np
import pytest
from scipy import integrate, stats

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.tissue import (
    DEFAULT_TISSUE_MODEL,
    TISSUE_MODELS,
    build_tissue_model,
    known_tissue_models,
    tissue_model_class,
)
from stipi_daemon.sim.tissue.base import EFFECTIVE_TAU_FRACTION, RecoveryModel
from stipi_daemon.sim.tissue.kelvin_voigt import KelvinVoigt
from stipi_daemon.sim.tissue.poroelastic import SWITCH_T, Poroelastic, degree_of_consolidation
from stipi_daemon.sim.tissue.power_law import PowerLaw
from stipi_daemon.sim.tissue.prony import Prony
from stipi_daemon.sim.tissue.zener import Zener

#: A valid parameter set of every model (grade III-like scenes' values).
VALID: dict[str, dict[str, float]] = {
    "kelvin_voigt": {"tau_s": 7.65},
    "zener": {"tau_sigma_s": 8.31, "tau_epsilon_s": 2.08},
    "prony": {"tau_1_s": 1.0, "tau_2_s": 8.92, "weight_1": 0.4},
    "poroelastic": {"tau_p_s": 20.0},
    "power_law": {"tau_s": 2.07, "exponent_n": 1.5},
}
UNIT_SUFFIX = {"s": "_s", "1": ""}


def test_registry_names_every_model_and_defaults_to_kelvin_voigt() -> None:
    assert set(known_tissue_models()) == set(VALID) == set(TISSUE_MODELS)
    assert DEFAULT_TISSUE_MODEL == "kelvin_voigt"
    with pytest.raises(ConfigError, match=r"unknown tissue model 'maxwell' \(known: .*zener"):
        tissue_model_class("maxwell")


@pytest.mark.parametrize("name", sorted(TISSUE_MODELS))
def test_metadata_of_every_model(name: str) -> None:
    cls = tissue_model_class(name)
    assert cls.NAME == name
    meta = cls.metadata()
    assert meta["title"] and meta["equation"]
    # A literature source: an author and a year.
    assert re.search(r"[A-Z][a-z]+.*\(?(19|20)\d\d\)?", str(meta["source"])), meta["source"]
    module = importlib.import_module(cls.__module__)
    assert module.__doc__ is not None and "Source:" in module.__doc__
    assert "Paper's quantities" in module.__doc__
    assert cls.PARAMETERS
    for p in cls.PARAMETERS:
        assert p.unit in UNIT_SUFFIX, p
        if UNIT_SUFFIX[p.unit]:
            assert p.name.endswith(UNIT_SUFFIX[p.unit]), p
        else:
            assert not p.name.endswith("_s"), p
        assert p.description
        assert math.isfinite(p.lower) and math.isfinite(p.upper) and p.lower < p.upper
        assert re.fullmatch(r"[\[(].+, .+[\])]", p.domain)
    model = build_tissue_model(name, VALID[name])
    assert model.parameters == VALID[name]


def _other_params(name: str, pname: str, value: float) -> dict[str, float]:
    params = dict(VALID[name])
    params[pname] = value
    if name == "zener" and pname == "tau_epsilon_s":
        params["tau_sigma_s"] = 1e6
    if name == "zener" and pname == "tau_sigma_s":
        params["tau_epsilon_s"] = 0.0
    return params


@pytest.mark.parametrize(
    ("name", "pname"),
    [(n, p.name) for n in sorted(TISSUE_MODELS) for p in tissue_model_class(n).PARAMETERS],
)
def test_domain_edges(name: str, pname: str) -> None:
    cls = tissue_model_class(name)
    (p,) = [q for q in cls.PARAMETERS if q.name == pname]
    for edge, inside in ((p.lower, p.lower_inclusive), (p.upper, p.upper_inclusive)):
        params = _other_params(name, pname, edge)
        if name == "zener" and pname == "tau_epsilon_s" and edge == p.upper:
            params["tau_sigma_s"] = edge  # jointly invalid: tau_epsilon must be < tau_sigma
            inside = False
        if inside:
            model = cls(**params)
            t = np.array([0.0, 1e-9, 1.0, 1e3, 1e7])
            r = model.remaining(t)
            assert np.all(np.isfinite(r)) and np.all((r >= 0.0) & (r <= 1.0))
            assert math.isfinite(model.effective_time_constant_s())
        else:
            with pytest.raises(ConfigError, match=pname):
                cls(**params)
    for outside in (np.nextafter(p.lower, -math.inf), np.nextafter(p.upper, math.inf)):
        with pytest.raises(ConfigError, match=f"{pname} = .* outside its domain"):
            cls(**_other_params(name, pname, float(outside)))
    for bad in (math.nan, math.inf, -math.inf, True, "1.0"):
        with pytest.raises(ConfigError, match=pname):
            cls(**_other_params(name, pname, bad))  # type: ignore[arg-type]


@pytest.mark.parametrize("name", sorted(TISSUE_MODELS))
def test_missing_unknown_parameters_and_bad_times(name: str) -> None:
    cls = tissue_model_class(name)
    with pytest.raises(ConfigError, match="missing parameter"):
        cls()
    with pytest.raises(ConfigError, match="unknown parameter 'tau_x'"):
        cls(**VALID[name], tau_x=1.0)
    model = cls(**VALID[name])
    for bad in (-1e-12, math.nan, math.inf):
        with pytest.raises(ConfigError, match=r"t_s\[1\] = .*finite and >= 0"):
            model.remaining([0.0, bad])
    for f in (-0.1, 1.0, math.nan):
        with pytest.raises(ConfigError, match=r"fraction must be in \[0, 1\)"):
            model.time_to_recover(f)


@pytest.mark.parametrize("name", sorted(TISSUE_MODELS))
def test_time_to_recover_inverts_remaining(name: str) -> None:
    model = build_tissue_model(name, VALID[name])
    assert float(model.remaining(0.0)) == 1.0
    for x in (1e-6, 0.3, EFFECTIVE_TAU_FRACTION, 0.98, 1 - 1e-9):
        t = model.time_to_recover(x)
        if name == "zener" and x <= 2.08 / 8.31:
            assert t == 0.0  # the instantaneous part covers it
            continue
        assert float(model.recovered(t)) == pytest.approx(x, rel=1e-9, abs=1e-12)
        # The generic search (Brent) agrees with a model's closed form.
        assert RecoveryModel.time_to_recover(model, x) == pytest.approx(t, rel=1e-9)
    tau = model.effective_time_constant_s()
    assert float(model.remaining(tau)) == pytest.approx(math.exp(-1.0), rel=1e-9)


def test_kelvin_voigt_against_solve_ivp() -> None:
    model = KelvinVoigt(tau_s=7.65)
    t = np.linspace(0.0, 60.0, 61)
    sol = integrate.solve_ivp(
        lambda _t, y: -y / 7.65, (0.0, 60.0), [1.0], t_eval=t, rtol=1e-11, atol=1e-14
    )
    np.testing.assert_allclose(model.remaining(t), sol.y[0], rtol=1e-8, atol=1e-12)
    assert model.effective_time_constant_s() == 7.65


def test_zener_against_funds_standard_form_integrated() -> None:
    """sigma + tau_eps sigma' = E_R (eps + tau_sig eps') (Fung, Eq. 2.11:3), the stress
    removed linearly over 1e-7 tau_sigma from equilibrium; the strain's recovery."""
    tau_sig, tau_eps, e_r, sigma0 = 8.31, 2.08, 3.0, 1.0
    ramp = 1e-7 * tau_sig

    def rhs(t: float, y: np.ndarray, dsigma: float) -> list[float]:
        sigma = sigma0 * max(0.0, 1.0 - t / ramp)
        return [(sigma + tau_eps * dsigma - e_r * y[0]) / (e_r * tau_sig)]

    eps0 = sigma0 / e_r
    ramp_sol = integrate.solve_ivp(
        rhs, (0.0, ramp), [eps0], args=(-sigma0 / ramp,), method="Radau", rtol=1e-12, atol=1e-15
    )
    t = np.linspace(ramp, 50.0, 200)
    sol = integrate.solve_ivp(
        rhs, (ramp, 50.0), ramp_sol.y[:, -1], args=(0.0,), t_eval=t, rtol=1e-11, atol=1e-15
    )
    model = Zener(tau_sigma_s=tau_sig, tau_epsilon_s=tau_eps)
    np.testing.assert_allclose(model.remaining(t), sol.y[0] / eps0, rtol=1e-6, atol=1e-9)
    assert model.instant_fraction == pytest.approx(tau_eps / tau_sig)


def test_prony_against_two_kelvin_voigt_elements_integrated() -> None:
    """Two Kelvin-Voigt elements in series, eta_i eps_i' + E_i eps_i = sigma, sigma removed
    at t = 0 from equilibrium (Findley, Lai & Onaran Sec. 5.4)."""
    e1, e2, eta1, eta2, sigma0 = 2.0, 0.5, 2.0, 4.46, 1.0
    t = np.linspace(0.0, 80.0, 161)
    sol = integrate.solve_ivp(
        lambda _t, y: [-e1 * y[0] / eta1, -e2 * y[1] / eta2],
        (0.0, 80.0),
        [sigma0 / e1, sigma0 / e2],
        t_eval=t,
        rtol=1e-11,
        atol=1e-15,
    )
    total = sol.y.sum(axis=0) / (sigma0 / e1 + sigma0 / e2)
    w = (1 / e1) / (1 / e1 + 1 / e2)
    model = Prony(tau_1_s=eta1 / e1, tau_2_s=eta2 / e2, weight_1=w)
    np.testing.assert_allclose(model.remaining(t), total, rtol=1e-8, atol=1e-12)


def test_poroelastic_against_method_of_lines() -> None:
    """p_t = p_zz on (0, 1), p(0) = 0, p_z(1) = 0, p = 1 at T = 0; U = 1 - mean p.
    Cell-centred finite volumes (n = 400): p' = A p with A symmetric tridiagonal, integrated
    exactly in time through LAPACK's eigendecomposition of A (p(T) = V exp(Lambda T) V' p0);
    error O(1/n^2) once T >> 1/n^2. (A BDF integration of the same system once returned NaN
    in a loaded test run and never again in hundreds alone: the exact exponential leaves no
    step-size control to go wrong.)"""
    n = 400
    h = 1.0 / n
    t_eval = np.array([0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0])
    main = -2.0 * np.ones(n)
    main[-1] = -1.0  # no flux at z = 1
    main[0] = -3.0  # ghost cell: p = 0 at the drained face
    from scipy.linalg import eigh_tridiagonal

    lam, vec = eigh_tridiagonal(main / h**2, np.ones(n - 1) / h**2)
    assert np.all(lam < 0.0)  # a decaying (dissipative) system
    p = vec @ (np.exp(np.outer(lam, t_eval)) * (vec.T @ np.ones(n))[:, None])
    assert p.shape == (n, len(t_eval)) and np.all(np.isfinite(p))
    u_mol = 1.0 - p.mean(axis=0)
    np.testing.assert_allclose(degree_of_consolidation(t_eval), u_mol, atol=2e-4)
    model = Poroelastic(tau_p_s=20.0)
    np.testing.assert_allclose(model.recovered(20.0 * t_eval), u_mol, atol=2e-4)


def test_poroelastic_early_sqrt_and_late_exponential() -> None:
    model = Poroelastic(tau_p_s=20.0)
    early = np.array([1e-12, 1e-8, 1e-5, 1e-3]) * 20.0
    np.testing.assert_allclose(
        model.recovered(early), 2.0 * np.sqrt(early / 20.0 / math.pi), rtol=1e-12, atol=1e-15
    )
    # Early slope in log-log is 1/2 (U itself: no 1 - (1 - U) rounding).
    u = degree_of_consolidation(early / 20.0)
    slope = np.diff(np.log(u)) / np.diff(np.log(early))
    np.testing.assert_allclose(slope, 0.5, atol=1e-12)
    late = np.array([1.0, 2.0, 5.0, 10.0]) * 20.0
    np.testing.assert_allclose(
        model.remaining(late),
        8.0 / math.pi**2 * np.exp(-(math.pi**2) * late / 20.0 / 4.0),
        rtol=1e-7,
    )
    assert model.late_time_constant_s == pytest.approx(4 * 20.0 / math.pi**2)
    # Both series agree around the switch.
    big_t = np.linspace(0.5 * SWITCH_T, 2.0 * SWITCH_T, 50)
    fourier = 1.0 - sum(
        2.0 / (math.pi * (2 * m + 1) / 2) ** 2 * np.exp(-((math.pi * (2 * m + 1) / 2) ** 2) * big_t)
        for m in range(400)
    )
    np.testing.assert_allclose(degree_of_consolidation(big_t), fourier, atol=1e-15)


def test_power_law_defining_relation_and_gamma_spectrum() -> None:
    n, tau = 1.5, 2.07
    model = PowerLaw(tau_s=tau, exponent_n=n)
    t = np.geomspace(1e-3, 1e4, 60)
    x = np.log1p(t / (n * tau))
    slope = np.diff(np.log(model.remaining(t))) / np.diff(x)
    np.testing.assert_allclose(slope, -n, rtol=1e-9)
    # A Laplace transform of gamma-distributed retardation rates (shape n, mean 1/tau).
    rates = stats.gamma(a=n, scale=1.0 / (n * tau))
    for ti in (0.0, 0.5, 3.0, 30.0, 300.0):
        val, _ = integrate.quad(lambda lam, ti=ti: rates.pdf(lam) * math.exp(-lam * ti), 0, np.inf)
        assert float(model.remaining(ti)) == pytest.approx(val, rel=1e-7)
    # It starts like Kelvin-Voigt with the same tau, and its tail is (t / (n tau))^-n.
    h = 1e-7 * tau
    assert (1.0 - float(model.remaining(h))) / h == pytest.approx(1.0 / tau, rel=1e-6)
    assert float(model.remaining(1e8)) == pytest.approx((1e8 / (n * tau)) ** -n, rel=1e-7)


@pytest.mark.parametrize(
    "model",
    [
        Zener(tau_sigma_s=7.65, tau_epsilon_s=0.0),
        Prony(tau_1_s=7.65, tau_2_s=1.0, weight_1=1.0),
        Prony(tau_1_s=1.0, tau_2_s=7.65, weight_1=0.0),
        Prony(tau_1_s=7.65, tau_2_s=7.65, weight_1=0.3),
    ],
    ids=repr,
)
def test_limits_that_are_kelvin_voigt(model: RecoveryModel) -> None:
    kv = KelvinVoigt(tau_s=7.65)
    t = np.concatenate(([0.0], np.geomspace(1e-6, 1e3, 200)))
    np.testing.assert_allclose(model.remaining(t), kv.remaining(t), rtol=1e-15, atol=0.0)
    assert model.effective_time_constant_s() == pytest.approx(7.65, rel=1e-12)
    assert model.time_to_recover(0.98) == pytest.approx(kv.time_to_recover(0.98), rel=1e-12)


def test_power_law_tends_to_kelvin_voigt() -> None:
    kv = KelvinVoigt(tau_s=7.65)
    t = np.linspace(0.0, 3 * 7.65, 50)
    for n, tol in ((1e3, 5e-3), (1e6, 5e-6)):
        pl = PowerLaw(tau_s=7.65, exponent_n=n)
        np.testing.assert_allclose(pl.remaining(t), kv.remaining(t), rtol=tol)


def test_nearly_equal_prony_time_constants_are_smooth() -> None:
    t = np.linspace(0.0, 50.0, 101)
    base = Prony(tau_1_s=5.0, tau_2_s=5.0, weight_1=0.5).remaining(t)
    near = Prony(tau_1_s=5.0, tau_2_s=5.0 * (1 + 1e-12), weight_1=0.5).remaining(t)
    np.testing.assert_allclose(near, base, rtol=1e-11)


def test_power_law_time_beyond_float_range_is_a_typed_error() -> None:
    model = PowerLaw(tau_s=1e-6, exponent_n=0.01)
    # 1 - 1/e is still finite at the domain's edge: n tau expm1(1/n).
    assert model.effective_time_constant_s() == pytest.approx(1e-8 * math.expm1(100.0))
    with pytest.raises(ConfigError, match=r"0.99999 of the recovery is reached only after"):
        model.time_to_recover(0.99999)
