"""Validity of each reported quantity and the session's verdict (analysis/validity.py)."""

from __future__ import annotations

import json

import numpy as np

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.results import AnalysisSettings, MeasurementResult, analyze_recovery
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import (
    FLAG_RULES,
    PRIMARY_QUANTITIES,
    SECONDARY_QUANTITIES,
    assess_validity,
)

CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)


def kv_measurement(
    tau_s: float = 7.5, depth_mm: float = 3.0, f_inf_n: float = 6.5, fps: float = 30.0
) -> tuple[np.ndarray, np.ndarray]:
    """A Kelvin-Voigt recovery (T_0 = 15 s) as S_k [px] at ``fps``."""
    s0 = CAL.s0_for_depth_change(CAL.indenter_length_mm - depth_mm)
    s_inf = CAL.area_for_force_px(f_inf_n)
    t = np.arange(0.0, 15.0 + 105.0 + 1e-9, 1.0 / fps)
    s = np.where(t < 15.0, 40000.0, s_inf - (s_inf - s0) * np.exp(-(t - 15.0) / tau_s))
    return t, s


def analyse(t: np.ndarray, s: np.ndarray, t0_s: float = 15.0) -> MeasurementResult:
    return analyze_recovery(t, s, t0_s, CAL, 16.0, AnalysisSettings(), load_reference())


def test_every_flag_has_a_rule() -> None:
    missing = [f for f in Flag if f not in FLAG_RULES]
    assert not missing


def test_clean_recovery_is_complete_and_valid() -> None:
    out = assess_validity(analyse(*kv_measurement()), ended_done=True)
    json.dumps(out)
    assert set(out["validity"]) == {*PRIMARY_QUANTITIES, *SECONDARY_QUANTITIES}
    assert all(v["status"] == "valid" for v in out["validity"].values()), out["validity"]
    assert out["verdict"]["status"] == "complete"


def test_session_not_done_is_incomplete() -> None:
    out = assess_validity(analyse(*kv_measurement()), ended_done=False, end_reason="aborted")
    assert out["verdict"]["status"] == "incomplete"
    assert "aborted" in out["verdict"]["line"]


def test_no_result_makes_every_quantity_invalid_with_the_error() -> None:
    out = assess_validity(None, ended_done=True, analysis_error="no frame after T_0")
    assert {v["status"] for v in out["validity"].values()} == {"invalid"}
    assert "no frame after T_0" in out["validity"]["depth_mm"]["reason"]
    assert out["verdict"]["status"] == "invalid"


def test_no_recovery_invalidates_tr_and_what_is_derived_from_it() -> None:
    t = np.arange(0.0, 60.0, 1 / 30)
    s = np.where(t < 15.0, 40000.0, 5000.0)
    out = assess_validity(analyse(t, s), ended_done=True)
    v = out["validity"]
    assert v["recovery_time_s"]["status"] == "invalid"
    assert v["viscosity_n_s_per_mm2"]["status"] == "invalid"
    assert v["severity"]["status"] == "invalid"
    assert v["depth_mm"]["status"] == "valid"
    assert out["verdict"]["status"] == "invalid"
    assert all(x["reason"] for x in v.values() if x["status"] != "valid")
