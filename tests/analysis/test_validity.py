"""Validity of each reported quantity and the session's verdict (analysis/validity.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.results import AnalysisSettings, MeasurementResult, analyze_recovery
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import (
    FLAG_RULES,
    PRIMARY_QUANTITIES,
    SECONDARY_QUANTITIES,
    QuantityValidity,
    assess_validity,
    verdict,
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


# --- issue 14 case 3: a camera gap over the release, gaps in the recovery -------------------


def gap(t: np.ndarray, s: np.ndarray, lo_s: float, hi_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The series without the frames strictly between lo_s and hi_s (lost by the camera)."""
    keep = ~((t > lo_s) & (t < hi_s))
    return t[keep], s[keep]


def noisy_kv(
    tau_s: float, t0_s: float = 19.5, noise_px: float = 20.0, seed: int = 0, fps: float = 60.0
) -> tuple[np.ndarray, np.ndarray]:
    """A 3 mm pit recovering to 6.5 N with time constant tau [s], from T_0 for 105 s."""
    s0 = CAL.s0_for_depth_change(CAL.indenter_length_mm - 3.0)
    s_inf = CAL.area_for_force_px(6.5)
    t = np.arange(0.0, t0_s + 105.0 + 1e-9, 1.0 / fps)
    x = np.clip(t - t0_s, 0.0, None)
    s = np.where(t < t0_s, 40000.0, s_inf - (s_inf - s0) * np.exp(-x / tau_s))
    return t, np.clip(s + np.random.default_rng(seed).normal(0.0, noise_px, t.size), 0.0, None)


def test_gap_over_the_release_invalidates_depth_and_what_follows_with_the_gap_named() -> None:
    t, s = gap(*noisy_kv(7.5), 18.8, 20.0)
    res = analyse(t, s, 19.5)
    out = assess_validity(res, ended_done=True)
    v = out["validity"]
    assert Flag.RELEASE_NOT_OBSERVED in res.flags
    for q in ("depth_mm", "elasticity_kpa", "viscosity_n_s_per_mm2", "severity"):
        assert v[q]["status"] == "invalid", q
    assert (
        "no frame between 18.80 and 20.00 s around the release at 19.50 s"
        in (v["depth_mm"]["reason"])
    )
    assert "18.80" in v["elasticity_kpa"]["reason"]
    assert v["rebound_force_n"]["status"] == "valid"
    assert out["verdict"]["status"] == "invalid"
    assert "18.80" in out["verdict"]["line"]
    assert res.to_dict()["pitting"]["observation"]["release_gap_s"] == [
        pytest.approx(18.8, abs=0.02),
        pytest.approx(20.0, abs=0.02),
    ]


def test_a_nan_frame_at_t0_is_not_interpolated_across_the_release() -> None:
    t, s = noisy_kv(7.5, noise_px=0.0)
    clean = analyse(t, s, 19.5)
    s = s.copy()
    s[int(np.searchsorted(t, 19.5))] = np.nan
    res = analyse(t, s, 19.5)
    # S_0 is extrapolated back to T_0 from the next two frames, never mixed with the
    # pitting frame before T_0.
    assert res.pitting.depth_mm == pytest.approx(clean.pitting.depth_mm, rel=0.005)
    assert Flag.RELEASE_NOT_OBSERVED not in res.flags
    assert Flag.S0_EXTRAPOLATED in res.flags


@pytest.mark.parametrize("lost", [1, 2])
def test_frames_lost_just_after_a_fast_release_do_not_bias_the_depth(lost: int) -> None:
    t, s = noisy_kv(0.56, noise_px=0.0)
    clean = analyse(t, s, 19.5)
    i = int(np.searchsorted(t, 19.5))
    keep = np.ones(t.size, dtype=bool)
    keep[i : i + lost] = False  # the frame at T_0 (and the next) lost by the camera
    res = analyse(t[keep], s[keep], 19.5)
    # Without the extrapolation D_p is 14 % (one frame late) to 27 % (two) low here; the
    # line through the next two frames leaves the curvature: 0.4 % and 1.3 %.
    assert res.pitting.depth_mm == pytest.approx(clean.pitting.depth_mm, rel=0.02)
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["depth_mm"]["status"] == "flagged"
    assert "s0_extrapolated" in v["depth_mm"]["flags"]


@pytest.mark.parametrize(("half_gap_s", "status"), [(0.5, "flagged"), (1.0, "invalid")])
def test_gap_over_the_settling_crossing_flags_tr_with_the_gap_length(
    half_gap_s: float, status: str
) -> None:
    # T_r = 7.5 s ln((1 - r)/0.02) = 27.0 s: tolerance 5 % = 1.35 s. A 1 s gap is a
    # caveat; a 2 s gap is an uncertainty beyond the tolerance: invalid, not flagged.
    t, s = noisy_kv(7.5, noise_px=0.0)
    clean = analyse(t, s, 19.5)
    ts = clean.pitting.ts_s
    assert ts is not None
    t2, s2 = gap(t, s, ts - half_gap_s, ts + half_gap_s)
    res = analyse(t2, s2, 19.5)
    v = assess_validity(res, ended_done=True)["validity"]["recovery_time_s"]
    assert Flag.FRAME_GAP_AT_SETTLING in res.flags
    assert v["status"] == status
    assert f"uncertain by {2 * half_gap_s:.1f}" in v["reason"]
    assert res.pitting.observed.settling_gap is not None
    assert (
        res.pitting.observed.settling_gap.start_s <= ts <= res.pitting.observed.settling_gap.end_s
    )


def test_gap_beside_the_maximum_flags_fr_and_long_gaps_flag_the_fit() -> None:
    t, s = noisy_kv(7.5, noise_px=0.0)
    t2, s2 = gap(t, s, 100.0, t[-1] - 0.01)  # the last frame (the maximum) after a gap
    v = assess_validity(analyse(t2, s2, 19.5), ended_done=True)["validity"]
    assert v["rebound_force_n"]["status"] == "flagged"
    assert "frame_gap_at_maximum" in v["rebound_force_n"]["flags"]
    assert "frame_gaps_in_fit" in v["tau_s"]["flags"]


def test_a_short_gap_away_from_release_crossing_and_maximum_changes_nothing() -> None:
    t, s = noisy_kv(7.5)
    t2, s2 = gap(t, s, 70.0, 71.5)
    res = analyse(t2, s2, 19.5)
    assert len(res.pitting.observed.gaps) == 1
    out = assess_validity(res, ended_done=True)
    assert out["verdict"]["status"] == "complete", out


def test_a_complete_verdict_never_calls_a_flagged_secondary_quantity_valid() -> None:
    # 15 s of frames missing late in the recovery: only the fit of tau is concerned (a
    # secondary quantity), so the verdict stays complete, and its line says what is not valid
    t, s = noisy_kv(7.5)
    out = assess_validity(analyse(*gap(t, s, 60.0, 75.0), 19.5), ended_done=True)
    v = out["validity"]
    # what the fitted recovery gives beside tau (eta = E*tau, its severity) follows tau
    from_tau = {"tau_s", "viscosity_fit_n_s_per_mm2", "severity_fit"}
    assert {q for q, e in v.items() if e["status"] != "valid"} == from_tau
    for q in from_tau - {"tau_s"}:
        assert v[q]["status"] == "flagged" and "frame_gaps_in_fit" in v[q]["flags"]
        assert v[q]["reason"].startswith("tau is flagged: frame gaps cover"), v[q]
    # the line names tau, not what follows from it
    assert out["verdict"] == {
        "status": "complete",
        "line": "Complete: every primary result is valid (tau flagged).",
    }


def test_a_complete_verdict_names_each_secondary_quantity_that_is_not_valid() -> None:
    ok = QuantityValidity("valid", (), None)
    validity = dict.fromkeys(PRIMARY_QUANTITIES, ok) | {
        "tau_s": QuantityValidity("invalid", ("fit_not_converged",), "the fit did not converge"),
        "applied_force_n": QuantityValidity("flagged", ("x",), "y"),
    }
    v = verdict(validity, ended_done=True)
    assert (v.status, v.line) == (
        "complete",
        "Complete: every primary result is valid (tau invalid, F_a flagged).",
    )
    clean = verdict(validity | dict.fromkeys(SECONDARY_QUANTITIES, ok), ended_done=True)
    assert clean.line == "Complete: every result is valid."


# --- issue 14 case 4: one outlier frame ------------------------------------------------------


@pytest.mark.parametrize("value", [70000.0, 0.0])  # a dark frame (whole ROI), a bright one
@pytest.mark.parametrize("at_s", [20.0, 30.0, 49.5, 110.0])
def test_one_outlier_frame_changes_no_result_and_is_flagged(value: float, at_s: float) -> None:
    t, s = noisy_kv(7.5)
    clean = analyse(t, s, 19.5)
    s = s.copy()
    s[int(np.searchsorted(t, at_s))] = value
    res = analyse(t, s, 19.5)
    p, c = res.pitting, clean.pitting
    assert p.rebound_force_n == pytest.approx(c.rebound_force_n, rel=1e-3)
    assert p.recovery_time_s == pytest.approx(c.recovery_time_s, abs=0.1)
    assert p.depth_mm == pytest.approx(c.depth_mm, rel=1e-3)
    assert res.fit.tau_s == pytest.approx(7.5, rel=0.01)
    assert res.fit.r_squared is not None and res.fit.r_squared > 0.999
    assert Flag.OUTLIER_FRAMES in res.flags
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["rebound_force_n"]["status"] == "flagged"
    assert "1 outlier frame" in v["rebound_force_n"]["reason"]


def test_a_recovery_the_model_does_not_describe_is_a_poor_fit_and_tau_invalid() -> None:
    # Two time scales: half the rise in 1 s, half linearly over the whole window.
    t = np.arange(0.0, 125.0, 1 / 60)
    x = np.clip(t - 19.5, 0.0, None)
    s = np.where(t < 19.5, 40000.0, 5000.0 + 6000.0 * (1 - np.exp(-x / 1.0)) + 60.0 * x)
    res = analyse(t, s, 19.5)
    assert Flag.POOR_FIT in res.fit.flags
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["tau_s"]["status"] == "invalid"
    assert "R^2" in v["tau_s"]["reason"]


# --- issue 14 case 5: tissue that barely recovers --------------------------------------------


@pytest.mark.parametrize("tau_s", [300.0, 1000.0, 1e4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_recovery_slower_than_the_window_is_never_a_confident_result(
    tau_s: float, seed: int
) -> None:
    res = analyse(*noisy_kv(tau_s, seed=seed), 19.5)
    out = assess_validity(res, ended_done=True)
    v = out["validity"]
    assert v["recovery_time_s"]["status"] == "invalid"
    assert "did not settle" in v["recovery_time_s"]["reason"]
    assert v["severity"]["status"] == "invalid"
    assert v["viscosity_n_s_per_mm2"]["status"] == "invalid"
    assert out["verdict"]["status"] == "invalid"


def test_no_recovery_at_all_with_noise_is_never_mild() -> None:
    t, s = noisy_kv(7.5)
    s = np.where(t < 19.5, 40000.0, 5000.0 + np.random.default_rng(3).normal(0.0, 20.0, t.size))
    out = assess_validity(analyse(t, s, 19.5), ended_done=True)
    assert out["validity"]["recovery_time_s"]["status"] == "invalid"
    assert out["validity"]["severity"]["status"] == "invalid"


def test_a_rise_within_the_settling_band_cannot_be_timed() -> None:
    t = np.arange(0.0, 125.0, 1 / 60)
    x = np.clip(t - 19.5, 0.0, None)
    s = np.where(t < 19.5, 40000.0, 10000.0 + 100.0 * (1 - np.exp(-x / 5.0)))  # 1 % rise
    res = analyse(t, s, 19.5)
    assert Flag.RISE_WITHIN_SETTLING_BAND in res.flags
    assert assess_validity(res, ended_done=True)["validity"]["recovery_time_s"]["status"] == (
        "invalid"
    )


@pytest.mark.parametrize("tau_s", [1.0, 3.0, 7.5, 10.0])
def test_kelvin_voigt_recoveries_that_settle_are_complete(tau_s: float) -> None:
    out = assess_validity(analyse(*noisy_kv(tau_s), 19.5), ended_done=True)
    assert out["verdict"]["status"] == "complete", out


def test_facts_from_outside_the_result_invalidate_or_flag_and_propagate() -> None:
    res = analyse(*kv_measurement())
    out = assess_validity(
        res,
        ended_done=True,
        invalid_reasons={"depth_mm": "S_0 not observed"},
        extra_flags=("s0_not_observed",),
    )
    v = out["validity"]
    assert v["depth_mm"] == {
        "status": "invalid",
        "flags": ["s0_not_observed"],
        "reason": "S_0 not observed",
    }
    assert v["severity"]["reason"] == "D_p is invalid: S_0 not observed"
    assert v["severity"]["flags"] == ["s0_not_observed"]
    # eta = E*tau through E (Eq. 7 needs D_p); the fitted severity, from the curve alone, not
    assert v["viscosity_fit_n_s_per_mm2"]["status"] == "invalid"
    assert v["viscosity_fit_n_s_per_mm2"]["reason"] == "D_p is invalid: S_0 not observed"
    assert v["severity_fit"]["status"] == "valid"
    out = assess_validity(
        res,
        ended_done=True,
        caveats={"recovery_time_s": "image and force disagree on T_0"},
        extra_flags=("t0_image_force_disagree",),
    )
    v = out["validity"]
    assert v["recovery_time_s"]["status"] == "flagged"
    assert v["viscosity_n_s_per_mm2"]["status"] == "flagged"
    assert "image and force disagree" in v["viscosity_n_s_per_mm2"]["reason"]
    assert v["depth_mm"]["status"] == "valid"
    assert out["verdict"]["status"] == "flagged"


def test_a_gap_over_the_early_rise_flags_the_fit_even_when_short_against_the_window() -> None:
    t, s = gap(*noisy_kv(1.0), 19.6, 21.0)  # 1.4 s of a 105 s window, most of the rise
    v = assess_validity(analyse(t, s, 19.5), ended_done=True)["validity"]
    assert "frame_gaps_in_fit" in v["tau_s"]["flags"]


@pytest.mark.parametrize("value", [0.0, 70000.0])
@pytest.mark.parametrize("tau_s", [0.6, 7.5])
def test_an_outlier_on_the_s0_frame_is_not_taken_as_s0(value: float, tau_s: float) -> None:
    t, s = noisy_kv(tau_s)
    clean = analyse(t, s, 19.5)
    s = s.copy()
    s[int(np.searchsorted(t, 19.5))] = value  # the frame at T_0 itself
    res = analyse(t, s, 19.5)
    assert Flag.S0_EXTRAPOLATED in res.flags
    # S_0 from the next frame: one frame period into the recovery.
    assert res.pitting.depth_mm == pytest.approx(clean.pitting.depth_mm, rel=0.05)
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["depth_mm"]["status"] == "flagged"
    assert "missing or an outlier" in v["depth_mm"]["reason"]


def test_a_release_step_within_one_frame_keeps_its_s0_and_flags_depth() -> None:
    t = np.arange(0.0, 125.0, 1 / 60)
    s = np.where(t < 19.5, 40000.0, 17000.0)
    s[int(np.searchsorted(t, 19.5))] = 5000.0  # S_0 on one frame, settled on the next
    res = analyse(t, s, 19.5)
    assert res.pitting.s0_px == 5000.0
    assert Flag.SETTLED_WITHIN_ONE_FRAME in res.flags
    assert Flag.S0_EXTRAPOLATED not in res.flags
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["depth_mm"]["status"] == "flagged"


def spring_back(
    jump: float, t0_s: float, noise_px: float = 20.0, tau_sigma_s: float = 8.31
) -> tuple[np.ndarray, np.ndarray, float]:
    """A standard linear solid's recovery (Fung 1993 Sec. 2.11): the share ``jump`` of it
    at once, the rest exponential; 60 fps from 0 s, T_0 ``t0_s`` [s]. Returns t, S_k, S_0."""
    s0 = CAL.s0_for_depth_change(CAL.indenter_length_mm - 3.0)
    s_inf = CAL.area_for_force_px(6.5)
    t = np.arange(0.0, 125.0, 1 / 60)
    x = t - t0_s
    after = s_inf - (s_inf - s0) * (1.0 - jump) * np.exp(-np.clip(x, 0.0, None) / tau_sigma_s)
    s = np.where(t < t0_s, 40000.0, after)
    s[int(np.searchsorted(t, t0_s))] = s0  # the release frame still shows the pit
    noise = np.random.default_rng(3).normal(0.0, noise_px, t.size)
    return t, np.clip(s + noise, 0.0, None), s0


@pytest.mark.parametrize("jump", [0.1, 0.25, 0.6])
@pytest.mark.parametrize("t0_s", [19.5, 19.505])  # T_0 on a frame, and between two
def test_a_spring_back_at_the_release_keeps_s0_from_the_release_frame(
    jump: float, t0_s: float
) -> None:
    # A standard linear solid recovers the share tau_eps/tau_sig at once, between the
    # release frame and the next: the release frame is then an outlier of the frames
    # after it, but the pit it shows is S_0. Read from the frames after the jump, D_p
    # was 79 % low and E 390 % high on the Zener scene.
    t, s, s0 = spring_back(jump, t0_s)
    res = analyse(t, s, t0_s)
    assert res.pitting.s0_px == pytest.approx(s0, abs=80.0)
    assert res.pitting.depth_mm == pytest.approx(3.0, rel=0.01)
    assert Flag.RELEASE_STEP in res.flags
    assert Flag.S0_EXTRAPOLATED not in res.flags
    v = assess_validity(res, ended_done=True)["validity"]
    for q in ("depth_mm", "elasticity_kpa"):
        assert v[q]["status"] == "flagged", q
        assert "spring-back" in v[q]["reason"], q


def test_kelvin_voigt_recoveries_show_no_release_step() -> None:
    for tau_s in (0.05, 0.3, 7.5, 30.0):
        res = analyse(*noisy_kv(tau_s, noise_px=20.0), 19.5)
        assert Flag.RELEASE_STEP not in res.flags, tau_s


def test_a_bright_frame_at_a_spring_back_is_still_an_outlier() -> None:
    # below the contact floor C1 (Eq. 5) no image shows the pit: an outlier, extrapolated
    t, s, _ = spring_back(0.25, 19.5)
    s[int(np.searchsorted(t, 19.5))] = 0.0
    res = analyse(t, s, 19.5)
    assert Flag.RELEASE_STEP not in res.flags
    assert Flag.S0_EXTRAPOLATED in res.flags


def test_a_dark_frame_just_before_t0_flags_depth_and_tr() -> None:
    # The dark frame at the release looks like one more pitting frame: T_0 placed at the
    # image's step (the next frame) may be a frame late.
    t, s = noisy_kv(0.56)
    i = int(np.searchsorted(t, 19.5))
    s = s.copy()
    s[i] = 70000.0
    res = analyse(t, s, float(t[i + 1]))
    assert Flag.RELEASE_FRAME_OUTLIER in res.flags
    v = assess_validity(res, ended_done=True)["validity"]
    assert v["depth_mm"]["status"] == "flagged"
    assert v["recovery_time_s"]["status"] == "flagged"
    clean = assess_validity(analyse(*noisy_kv(0.56), 19.5), ended_done=True)
    assert "release_frame_outlier" not in clean["validity"]["depth_mm"]["flags"]


def test_depth_uncertainty_is_the_calibration_slope_times_the_frame_noise() -> None:
    # checked against a central difference of Eqs. (3)-(4) through Calibration itself
    from stipi_daemon.analysis.results import depth_relative_sd

    t, s = noisy_kv(7.5, noise_px=20.0)
    res = analyse(t, s, 19.5)
    p = res.pitting
    h = 1.0
    slope = (CAL.depth_change_mm(p.s0_px + h) - CAL.depth_change_mm(p.s0_px - h)) / (2 * h)
    rel = depth_relative_sd(t, s, p, CAL)
    assert rel == pytest.approx(abs(slope) * 20.0 / p.depth_mm, rel=0.15)  # noise SD 20 px
    assert res.models is not None and res.models.depth_rel_sd == rel
    clean = analyse(*noisy_kv(7.5, noise_px=0.0), 19.5)
    assert clean.models is not None and clean.models.depth_rel_sd < 1e-4  # no noise
