"""Whole-measurement analysis on synthetic Kelvin-Voigt recoveries with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.results import (
    AnalysisSettings,
    analyze_recovery,
    applied_force_n_from_samples,
)
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.vpr import elasticity_kpa
from stipi_daemon.errors import AnalysisError

CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)


def _series(tau_s: float, depth_mm: float, f_inf_n: float, fps: float = 60.0, t0: float = 15.0):
    s0 = CAL.s0_for_depth_change(CAL.indenter_length_mm - depth_mm)
    s_inf = CAL.area_for_force_px(f_inf_n)
    t = np.arange(0.0, t0 + 105.0 + 1e-9, 1.0 / fps)
    s = np.where(t < t0, 40000.0, s_inf - (s_inf - s0) * np.exp(-(t - t0) / tau_s))
    return t, s, s0, s_inf


def test_recovers_known_parameters() -> None:
    t, s, _, _ = _series(tau_s=7.5, depth_mm=3.0, f_inf_n=6.5)
    settings = AnalysisSettings(indenter_radius_mm=7.5)
    res = analyze_recovery(t, s, 15.0, CAL, 16.0, settings, load_reference())
    assert res.pitting.depth_mm == pytest.approx(3.0, rel=1e-6)
    assert res.pitting.rebound_force_n == pytest.approx(CAL.rebound_force_n(s[t >= 15.0].max()))
    assert res.fit.tau_s == pytest.approx(7.5, rel=1e-6)
    assert res.paper_model is not None and res.fit_model is not None
    assert res.paper_model.elasticity_kpa == pytest.approx(elasticity_kpa(16.0, 3.0, 7.5))
    # eta of the paper is E*T_r; of the fit, E*tau (kPa*s -> N*s/mm^2).
    assert res.fit_model.viscosity_n_s_per_mm2 == pytest.approx(
        res.paper_model.elasticity_kpa * 7.5 / 1000.0, rel=1e-6
    )
    assert res.severity_paper is not None and res.severity_fit is not None
    d = res.to_dict()
    json.dumps(d)  # JSON-ready
    assert d["pitting"]["depth_mm"] == pytest.approx(3.0, rel=1e-6)
    assert d["notes"] == []


def test_no_recovery_leaves_paper_estimator_undefined_with_note() -> None:
    t = np.arange(0.0, 60.0, 1 / 30)
    s = np.where(t < 15.0, 40000.0, 5000.0)
    res = analyze_recovery(t, s, 15.0, CAL, 16.0, AnalysisSettings(), load_reference())
    assert Flag.NO_RECOVERY in res.pitting.flags
    assert res.paper_model is None
    assert res.severity_paper is None
    assert any("paper estimator undefined" in n for n in res.notes)
    json.dumps(res.to_dict())


def test_slow_recovery_flags_not_settled() -> None:
    t, s, _, _ = _series(tau_s=200.0, depth_mm=3.0, f_inf_n=6.5, fps=30.0)
    res = analyze_recovery(t, s, 15.0, CAL, 16.0, AnalysisSettings(), load_reference())
    assert Flag.NOT_SETTLED in res.flags
    assert res.fit.tau_s is not None and math.isfinite(res.fit.tau_s)


def test_applied_force_is_the_mean_over_the_hold() -> None:
    t = np.arange(0.0, 20.0, 0.01)
    f = np.where((t >= 1.0) & (t <= 16.0), 16.0, 0.5)
    assert applied_force_n_from_samples(t, f, 1.0, 16.0) == pytest.approx(16.0)
    with pytest.raises(AnalysisError, match="no force sample in the pitting hold"):
        applied_force_n_from_samples(t, f, 30.0, 40.0)
    with pytest.raises(AnalysisError, match="not > 0"):
        applied_force_n_from_samples(t, -f, 1.0, 16.0)


def test_bad_applied_force_raises() -> None:
    t, s, _, _ = _series(tau_s=5.0, depth_mm=3.0, f_inf_n=6.0)
    with pytest.raises(AnalysisError, match="applied_force_n"):
        analyze_recovery(t, s, 15.0, CAL, math.nan, AnalysisSettings(), load_reference())
