"""Property tests: the analysis core never returns NaN/inf, never overflows or warns.

Over time constants 1 ms..1e4 s, S_k up to 1e8 px, depths down to the smallest float,
noisy and constant series and NaN/inf samples, every call either returns finite (possibly
flagged) numbers or raises AnalysisError. pytest turns any warning into an error.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import compute_pitting_parameters, recovery_time
from stipi_daemon.analysis.recovery_fit import fit_recovery
from stipi_daemon.analysis.severity import classify_decay_rate, load_reference
from stipi_daemon.analysis.vpr import VPRModel, elasticity_kpa, vpr_depth_mm
from stipi_daemon.errors import AnalysisError

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CAL = Calibration(alpha1_mm_per_px2=1e-9, alpha2_mm_per_px=2e-4, c1_px=1000.0, c2_px_per_n=2000.0)
REFERENCE = load_reference()

log_tau = st.floats(min_value=math.log(1e-3), max_value=math.log(1e4))
s_scale = st.floats(min_value=0.0, max_value=1e8)


@st.composite
def recovery_series(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A pitting-then-recovery series at 10 fps (fewer frames keep the tests fast)."""
    tau = math.exp(draw(log_tau))
    s_inf = draw(s_scale)
    s0 = s_inf * draw(st.floats(min_value=0.0, max_value=1.2))
    noise = draw(st.sampled_from([0.0, 1e-3, 0.02, 0.2])) * max(s_inf, 1.0)
    t0 = 5.0
    t = np.arange(0.0, 110.0, 0.1)
    x = np.clip(t - t0, 0.0, None)
    with np.errstate(under="ignore"):
        s = np.where(t < t0, 1.5 * s_inf, s_inf - (s_inf - s0) * np.exp(-x / tau))
    if noise > 0.0:
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        s = np.clip(s + rng.normal(0.0, noise, t.size), 0.0, None)
    for i in draw(st.lists(st.integers(0, t.size - 1), max_size=4)):
        s[i] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    return t, s, t0, tau


def _finite_or_none(*values: float | None) -> None:
    for v in values:
        assert v is None or math.isfinite(v), values


@SETTINGS
@given(recovery_series())
def test_recovery_time_is_finite_or_typed_error(
    data: tuple[np.ndarray, np.ndarray, float, float],
) -> None:
    t, s, t0, _ = data
    try:
        r = recovery_time(t, s, t0)
    except AnalysisError:
        return
    _finite_or_none(r.recovery_time_s, r.ts_s, r.s0_px, r.s_max_px, r.level_px)
    if r.recovery_time_s is None:
        assert Flag.NO_RECOVERY in r.flags
    else:
        assert 0.0 <= r.recovery_time_s <= 105.0 + 1e-9
    if np.any(~np.isfinite(s)):
        assert Flag.NON_FINITE_INPUT in r.flags


@SETTINGS
@given(recovery_series())
def test_pitting_parameters_are_finite_or_typed_error(
    data: tuple[np.ndarray, np.ndarray, float, float],
) -> None:
    t, s, t0, _ = data
    try:
        p = compute_pitting_parameters(t, s, t0, CAL)
    except AnalysisError:
        return
    _finite_or_none(p.depth_mm, p.depth_change_mm, p.rebound_force_n, p.recovery_time_s)
    assert 0.0 <= p.depth_mm <= 12.0
    assert p.rebound_force_n >= 0.0
    try:
        m = VPRModel.from_pitting(p, applied_force_n=16.0, indenter_radius_mm=7.5)
    except AnalysisError:
        return
    _finite_or_none(m.elasticity_kpa, m.viscosity_n_s_per_mm2, m.time_constant_s)


@SETTINGS
@given(recovery_series())
def test_recovery_fit_is_finite_or_typed_error(
    data: tuple[np.ndarray, np.ndarray, float, float],
) -> None:
    t, s, t0, _ = data
    try:
        f = fit_recovery(t, s, t0)
    except AnalysisError:
        return
    _finite_or_none(
        f.tau_s, f.amplitude, f.offset, f.tau_se_s, f.amplitude_se, f.offset_se, f.r_squared
    )
    assert math.isfinite(f.rmse)
    if f.tau_s is not None:
        assert 1e-3 * (1 - 1e-9) <= f.tau_s <= 1e4 * (1 + 1e-9)
    else:
        assert f.flags & {Flag.CONSTANT_SERIES, Flag.FIT_NOT_CONVERGED}


@SETTINGS
@given(
    tau=st.floats(min_value=0.3, max_value=40.0),
    s_inf=st.floats(min_value=10.0, max_value=1e8),
    s0_fraction=st.floats(min_value=0.0, max_value=0.7),
)
def test_noise_free_fit_recovers_tau_inside_the_window(
    tau: float, s_inf: float, s0_fraction: float
) -> None:
    t = np.arange(0.0, 105.0, 0.1)
    with np.errstate(under="ignore"):
        s = s_inf - s_inf * (1 - s0_fraction) * np.exp(-t / tau)
    f = fit_recovery(t, s, 0.0)
    assert f.flags == frozenset()
    assert f.tau_s is not None
    assert abs(f.tau_s / tau - 1.0) < 1e-4


@SETTINGS
@given(
    value=st.floats(min_value=0.0, max_value=1e8),
    n=st.integers(min_value=4, max_value=500),
)
def test_constant_series_is_flagged(value: float, n: int) -> None:
    t = np.linspace(0.0, 105.0, n)
    f = fit_recovery(t, np.full(n, value), 0.0)
    assert f.flags == {Flag.CONSTANT_SERIES}
    r = recovery_time(t, np.full(n, value), 0.0)
    assert r.flags == {Flag.NO_RECOVERY}


@SETTINGS
@given(
    depth=st.one_of(
        st.floats(min_value=0.0, max_value=1e3, allow_subnormal=True),
        st.sampled_from([0.0, 5e-324, 1e-308, -0.0, math.nan, math.inf, -1.0]),
    ),
    force=st.floats(min_value=1e-3, max_value=1e3),
    radius=st.floats(min_value=1e-3, max_value=1e2),
    recovery_s=st.floats(min_value=1e-3, max_value=1e4),
)
def test_vpr_chain_is_finite_or_typed_error(
    depth: float, force: float, radius: float, recovery_s: float
) -> None:
    try:
        e = elasticity_kpa(force, depth, radius)
        m = VPRModel.from_values(
            depth, recovery_s, applied_force_n=force, indenter_radius_mm=radius
        )
    except AnalysisError as exc:
        assert str(exc)
        return
    assert math.isfinite(e) and e > 0.0
    t = np.array([0.0, 1e-3, 1.0, 1e4, 1e300])
    d = m.depth_at(t)
    assert np.all(np.isfinite(d))
    assert np.all((d >= 0.0) & (d <= depth))
    assert math.isfinite(m.time_constant_s)


@SETTINGS
@given(
    depth=st.floats(min_value=0.0, max_value=1e6),
    e=st.floats(min_value=1e-6, max_value=1e9),
    eta=st.floats(min_value=1e-9, max_value=1e9),
    t=st.lists(st.floats(min_value=0.0, max_value=1e308), min_size=1, max_size=20),
)
def test_vpr_depth_never_overflows(depth: float, e: float, eta: float, t: list[float]) -> None:
    try:
        d = vpr_depth_mm(t, depth, e, eta)
    except AnalysisError:
        return
    assert np.all(np.isfinite(d))
    assert np.all((d >= 0.0) & (d <= depth))


@SETTINGS
@given(rate=st.floats(min_value=1e-12, max_value=1e12))
def test_classification_is_finite_for_any_positive_rate(rate: float) -> None:
    r = classify_decay_rate(rate, REFERENCE)
    assert 0.0 <= r.window_mean_depth_fraction <= 1.0
    assert math.isfinite(r.recovered_percent)
    assert all(math.isfinite(dist) for _, dist in r.grade_distances)
    assert r.nearest_grade in {"I", "II", "III", "IV"}
