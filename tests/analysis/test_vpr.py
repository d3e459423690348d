"""Tests of stipi_daemon.analysis.vpr: Eqs. (7), (8) and (10) and VPRModel."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import PittingParameters
from stipi_daemon.analysis.vpr import (
    PAPER_APPLIED_FORCE_N,
    PAPER_FORCE_RADIUS_RATIO_N_PER_MM,
    PAPER_IMPLIED_RADIUS_MM,
    VPRModel,
    decay_rate_per_s,
    elasticity_kpa,
    viscosity_n_s_per_mm2,
    vpr_depth_mm,
)
from stipi_daemon.errors import AnalysisError


def test_elasticity_eq7_with_unit_conversion() -> None:
    # 3/(pi^2 * 7.5 mm) * 16 N / 4 mm = 0.16211 N/mm^2 = 162.11 kPa
    expected = 3.0 / (math.pi**2 * 7.5) * 16.0 / 4.0 * 1000.0
    assert elasticity_kpa(16.0, 4.0, 7.5) == pytest.approx(expected, rel=1e-15)
    assert elasticity_kpa(16.0, 4.0, 7.5) == pytest.approx(162.1139, rel=1e-6)


def test_elasticity_scales_with_force_and_inversely_with_depth_and_radius() -> None:
    e = elasticity_kpa(10.0, 5.0, 3.0)
    assert elasticity_kpa(20.0, 5.0, 3.0) == pytest.approx(2 * e)
    assert elasticity_kpa(10.0, 10.0, 3.0) == pytest.approx(e / 2)
    assert elasticity_kpa(10.0, 5.0, 6.0) == pytest.approx(e / 2)


@pytest.mark.parametrize(
    ("force", "depth", "radius", "match"),
    [
        (16.0, 0.0, 7.5, "elasticity .Eq. 7. is undefined"),
        (16.0, -1.0, 7.5, "depth_mm must be > 0"),
        (16.0, math.nan, 7.5, "depth_mm must be finite"),
        (0.0, 4.0, 7.5, "applied_force_n must be > 0"),
        (math.inf, 4.0, 7.5, "applied_force_n must be finite"),
        (16.0, 4.0, 0.0, "indenter_radius_mm must be > 0"),
        (16.0, 5e-324, 7.5, "elasticity overflows"),
    ],
)
def test_elasticity_domain_errors(force: float, depth: float, radius: float, match: str) -> None:
    with pytest.raises(AnalysisError, match=match):
        elasticity_kpa(force, depth, radius)


def test_viscosity_eq8_units() -> None:
    # 1000 kPa * 1 s = 1 N/mm^2 * s
    assert viscosity_n_s_per_mm2(1000.0, 1.0) == pytest.approx(1.0)
    assert viscosity_n_s_per_mm2(376.37, 2.19) == pytest.approx(0.8242503)


@pytest.mark.parametrize(("e", "t"), [(0.0, 1.0), (100.0, 0.0), (100.0, -1.0), (math.nan, 1.0)])
def test_viscosity_domain_errors(e: float, t: float) -> None:
    with pytest.raises(AnalysisError):
        viscosity_n_s_per_mm2(e, t)


def test_decay_rate_is_inverse_recovery_time() -> None:
    eta = viscosity_n_s_per_mm2(250.0, 8.0)
    assert decay_rate_per_s(250.0, eta) == pytest.approx(1 / 8.0)


def test_vpr_depth_eq10() -> None:
    e, t_r, d_p = 316.02, 8.95, 4.74
    eta = viscosity_n_s_per_mm2(e, t_r)
    t = np.array([0.0, t_r, 2 * t_r])
    d = vpr_depth_mm(t, d_p, e, eta)
    np.testing.assert_allclose(d, d_p * np.exp(-t / t_r), rtol=1e-14)
    assert d[0] == d_p
    assert d[1] == pytest.approx(d_p / math.e)


def test_vpr_depth_is_vectorised_and_underflows_quietly() -> None:
    t = np.linspace(0.0, 1e6, 12).reshape(3, 4)
    d = vpr_depth_mm(t, 5.0, 300.0, 1e-6)  # rate 300 /s: exp(-3e8) underflows to 0
    assert d.shape == (3, 4)
    assert d[0, 0] == 5.0
    assert np.all(d.ravel()[1:] == 0.0)
    assert vpr_depth_mm(2.0, 1.0, 1000.0, 1.0).shape == ()


@pytest.mark.parametrize("bad_t", [-1.0, math.nan, math.inf])
def test_vpr_depth_rejects_bad_times(bad_t: float) -> None:
    with pytest.raises(AnalysisError, match=r"t_s\[1\]"):
        vpr_depth_mm([0.0, bad_t], 1.0, 100.0, 1.0)


def test_vpr_depth_rejects_negative_depth_and_allows_zero() -> None:
    with pytest.raises(AnalysisError, match="depth_mm must be >= 0"):
        vpr_depth_mm([0.0], -1.0, 100.0, 1.0)
    np.testing.assert_array_equal(vpr_depth_mm([0.0, 1.0], 0.0, 100.0, 1.0), [0.0, 0.0])


def test_model_from_values_and_properties() -> None:
    m = VPRModel.from_values(4.74, 8.95, applied_force_n=16.0, indenter_radius_mm=3.2467)
    assert m.time_constant_s == pytest.approx(8.95)
    assert m.decay_rate_per_s == pytest.approx(1 / 8.95)
    assert m.depth_at(0.0) == pytest.approx(4.74)
    assert m.normalised_depth(8.95) == pytest.approx(1 / math.e)
    assert m.flags == frozenset()


def _params(recovery_time_s: float | None, flags: frozenset[Flag]) -> PittingParameters:
    return PittingParameters(
        depth_mm=4.74,
        depth_change_mm=7.26,
        rebound_force_n=6.22,
        recovery_time_s=recovery_time_s,
        t0_s=15.0,
        ts_s=None if recovery_time_s is None else 15.0 + recovery_time_s,
        s0_px=3000.0,
        s_max_px=13000.0,
        flags=flags,
    )


def test_model_from_pitting_carries_flags() -> None:
    m = VPRModel.from_pitting(
        _params(105.0, frozenset({Flag.NOT_SETTLED})),
        applied_force_n=16.0,
        indenter_radius_mm=7.5,
    )
    assert m.flags == {Flag.NOT_SETTLED}
    assert m.viscosity_n_s_per_mm2 == pytest.approx(m.elasticity_kpa * 105.0 / 1000.0)


def test_model_from_pitting_without_recovery_raises() -> None:
    with pytest.raises(AnalysisError, match="no_recovery"):
        VPRModel.from_pitting(
            _params(None, frozenset({Flag.NO_RECOVERY})),
            applied_force_n=16.0,
            indenter_radius_mm=7.5,
        )


def test_paper_constants_are_consistent() -> None:
    assert PAPER_APPLIED_FORCE_N / PAPER_IMPLIED_RADIUS_MM == pytest.approx(
        PAPER_FORCE_RADIUS_RATIO_N_PER_MM
    )
    assert PAPER_IMPLIED_RADIUS_MM == pytest.approx(3.247, abs=5e-4)
    assert PAPER_FORCE_RADIUS_RATIO_N_PER_MM * 7.5 == pytest.approx(36.96, abs=0.01)
