"""An instantaneous spring-back at the release: the residual pit is reported apart from the
indentation depth (analysis/pitting.py, results.py, validity.py).

The recovery is a standard linear solid written here from its law (Fung, Biomechanics,
Sec. 2.11: removing a stress held to equilibrium, the strain jumps by tau_eps / tau_sig of
its value, then decays as exp(-t / tau_sig)): S(T_0) = S_0 at the release frame, then
S(t) = S_inf - (S_inf - S_0) (1 - f) exp(-(t - T_0) / tau_sig) for t > T_0.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.results import AnalysisSettings, analyze_recovery
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import assess_validity

CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)
T0, S0, S_INF, TAU_SIG, FPS = 15.0, 6000.0, 17750.0, 8.31, 60.0


def zener(f: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, T0 + 105.0 + 1e-9, 1.0 / FPS)
    x = t - T0
    rec = S_INF - (S_INF - S0) * (1.0 - f) * np.exp(-np.clip(x, 0.0, None) / TAU_SIG)
    s = np.where(x < 0.0, 41500.0, np.where(x <= 1e-9, S0, rec))
    return t, np.round(s)


def l_minus_ds(s_px: float) -> float:
    """Eqs. (3)-(4) written out: D = l - (-alpha1 S^2 + alpha2 S)."""
    return 12.0 - (-1.42e-7 * s_px**2 + 2.556e-3 * s_px)


def test_a_spring_back_spanning_a_frame_reports_the_residual_pit_apart() -> None:
    f = 0.25
    t, s = zener(f)
    r = analyze_recovery(
        t, s, T0, CAL, 16.0, AnalysisSettings(bootstrap_replicates=0), load_reference()
    )
    p = r.pitting
    assert Flag.RELEASE_STEP in p.flags
    after = float(s[np.searchsorted(t, T0) + 1])
    assert p.depth_mm == pytest.approx(l_minus_ds(S0), abs=1e-9)  # indentation depth
    assert p.residual_depth_mm == pytest.approx(l_minus_ds(after), abs=1e-9)
    assert p.spring_back_px == pytest.approx(after - S0)
    # the jump is about f of the recovery (minus one frame's decay)
    expected_jump = (S_INF - S0) * (1 - (1 - f) * math.exp(-1 / FPS / TAU_SIG))
    assert p.spring_back_px == pytest.approx(expected_jump, abs=1.0)
    out = assess_validity(r, ended_done=True)
    d = out["validity"]["depth_mm"]
    assert d["status"] == "flagged"
    assert "spring-back" in d["reason"] and "residual pit" in d["reason"]
    e = out["validity"]["elasticity_kpa"]
    assert e["status"] == "flagged"
    summary = r.to_dict()["pitting"]
    assert summary["indentation_depth_mm"] == p.depth_mm
    assert summary["residual_depth_mm"] == p.residual_depth_mm


def test_without_a_step_there_is_no_residual_depth() -> None:
    t, s = zener(0.0)
    r = analyze_recovery(
        t, s, T0, CAL, 16.0, AnalysisSettings(bootstrap_replicates=0), load_reference()
    )
    assert Flag.RELEASE_STEP not in r.pitting.flags
    assert r.pitting.residual_depth_mm is None and r.pitting.spring_back_px is None
    assert r.to_dict()["pitting"]["residual_depth_mm"] is None
