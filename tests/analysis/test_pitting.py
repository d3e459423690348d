"""Tests of stipi_daemon.analysis.pitting: Eqs. (3), (5), (6) and their edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import (
    compute_pitting_parameters,
    detect_recovery_start,
    pitting_depth_mm,
    rebound_force_n,
    recovery_time,
    validate_series,
)
from stipi_daemon.analysis.recovery_fit import settling_time_from_time_constant
from stipi_daemon.errors import AnalysisError
from tests.analysis.synthetic import kv_series

CAL = Calibration(alpha1_mm_per_px2=1e-9, alpha2_mm_per_px=2e-4, c1_px=1000.0, c2_px_per_n=2000.0)
FRAME_S = 1.0 / 60.0


# --- Eq. (3) ---------------------------------------------------------------------------------


def test_depth_is_indenter_length_minus_depth_change() -> None:
    r = pitting_depth_mm(8.02)
    assert r.value == pytest.approx(12.0 - 8.02)
    assert r.flags == frozenset()
    assert pitting_depth_mm(0.0).value == 12.0
    assert pitting_depth_mm(12.0).value == 0.0
    assert pitting_depth_mm(3.0, indenter_length_mm=10.0).value == 7.0


@pytest.mark.parametrize(("d_s", "expected"), [(-0.5, 12.0), (12.5, 0.0), (1e300, 0.0)])
def test_depth_change_outside_0_l_is_clipped_and_flagged(d_s: float, expected: float) -> None:
    r = pitting_depth_mm(d_s)
    assert r.value == expected
    assert r.flags == {Flag.DEPTH_CLIPPED}


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_depth_change_raises(bad: float) -> None:
    with pytest.raises(AnalysisError, match="depth_change_mm must be finite"):
        pitting_depth_mm(bad)


@pytest.mark.parametrize("length", [0.0, -1.0, math.nan])
def test_bad_indenter_length_raises(length: float) -> None:
    with pytest.raises(AnalysisError, match="indenter_length_mm"):
        pitting_depth_mm(1.0, indenter_length_mm=length)


# --- Eq. (5) ---------------------------------------------------------------------------------


def test_rebound_force_follows_eq5() -> None:
    r = rebound_force_n(13000.0, CAL)
    assert r.value == pytest.approx((13000.0 - 1000.0) / 2000.0)
    assert r.flags == frozenset()


@pytest.mark.parametrize("s_max", [0.0, 500.0, 1000.0])
def test_rebound_force_at_or_below_c1_is_zero_and_flagged(s_max: float) -> None:
    r = rebound_force_n(s_max, CAL)
    assert r.value == 0.0
    assert r.flags == {Flag.REBOUND_BELOW_OFFSET}


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_rebound_force_rejects_bad_s_max(bad: float) -> None:
    with pytest.raises(AnalysisError, match="s_max_px"):
        rebound_force_n(bad, CAL)


# --- series validation -----------------------------------------------------------------------


def test_validate_series_errors_name_the_problem() -> None:
    with pytest.raises(AnalysisError, match="same length"):
        validate_series([0.0, 1.0], [1.0])
    with pytest.raises(AnalysisError, match="one-dimensional"):
        validate_series([[0.0, 1.0]], [[1.0, 2.0]])
    with pytest.raises(AnalysisError, match=r"times_s\[2\] = 1.0 follows"):
        validate_series([0.0, 1.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(AnalysisError, match=r"times_s\[1\] is nan"):
        validate_series([0.0, math.nan], [1.0, 2.0])
    with pytest.raises(AnalysisError, match=r"s_px\[1\] = -2.0 is negative"):
        validate_series([0.0, 1.0], [1.0, -2.0])
    with pytest.raises(AnalysisError, match="at least 2 finite samples"):
        validate_series([0.0, 1.0], [math.nan, 1.0])


def test_validate_series_drops_non_finite_values() -> None:
    s = validate_series([0.0, 1.0, 2.0, 3.0], [1.0, math.inf, math.nan, 4.0])
    assert s.dropped == 2
    np.testing.assert_array_equal(s.times_s, [0.0, 3.0])


# --- Eq. (6) ---------------------------------------------------------------------------------


@pytest.mark.parametrize("tau_s", [0.5, 3.0, 12.0])
def test_recovery_time_of_ideal_recovery_matches_closed_form(tau_s: float) -> None:
    t, s = kv_series(tau_s=tau_s, s0_px=3000.0, s_inf_px=13000.0)
    r = recovery_time(t, s, 15.0)
    s_max = 13000.0 - 10000.0 * math.exp(-(t[-1] - 15.0) / tau_s)  # last frame
    # S(T) = 0.98 S_max  <=>  T = tau ln((S_inf - S_0) / (S_inf - 0.98 S_max))
    expected = tau_s * math.log(10000.0 / (13000.0 - 0.98 * s_max))
    assert r.flags == frozenset()
    assert r.s0_px == 3000.0
    # The robust S_max (running median, cut at the window's end) lies below the plain
    # maximum by at most the last frame's rise: a fraction of a pixel here.
    assert s_max - 1.0 <= r.s_max_px <= s_max
    assert r.recovery_time_s is not None
    # Linear interpolation between frames on a smooth curve: error << one frame.
    assert r.recovery_time_s == pytest.approx(expected, abs=0.01 * FRAME_S)
    assert r.ts_s == pytest.approx(15.0 + r.recovery_time_s)


def test_s0_is_the_first_frame_at_or_after_t0_never_interpolated_across_the_release() -> None:
    # Frames before T_0 show the pitting phase: mixing them into S_0 biases D_p.
    t = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    s = np.array([10.0, 0.0, 50.0, 100.0, 100.0, 100.0])
    r = recovery_time(t, s, 0.25, persist_frames=1)
    assert r.s0_px == pytest.approx(0.0)
    # level 98 px, between (2, 50) and (3, 100): 2 + 48/50
    assert r.ts_s == pytest.approx(2.96)
    assert r.recovery_time_s == pytest.approx(2.71)
    assert recovery_time(t, s, 1.0, persist_frames=1).s0_px == 0.0


def test_single_noisy_frame_crossing_early_is_skipped_and_flagged() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    true_tr = settling_time_from_time_constant(3.0, 3000.0, 13000.0)
    spike = int(np.searchsorted(t, 17.0))
    s[spike : spike + 4] = 12900.0  # above 0.98 * 13000 = 12740 for four frames only
    r = recovery_time(t, s, 15.0, persist_frames=5)
    assert r.flags == {Flag.EARLY_NOISY_CROSSING}
    assert r.recovery_time_s == pytest.approx(true_tr, abs=0.01)
    paper_rule = recovery_time(t, s, 15.0, persist_frames=1)
    assert paper_rule.recovery_time_s is not None
    assert paper_rule.recovery_time_s < 2.1  # the plain first crossing takes the excursion
    assert Flag.EARLY_NOISY_CROSSING not in paper_rule.flags


def test_single_outlier_frame_is_left_out_flagged_and_counted() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    true_tr = settling_time_from_time_constant(3.0, 3000.0, 13000.0)
    spike = int(np.searchsorted(t, 17.0))
    s[spike] = 12900.0  # one frame above the settling level, far above its neighbours
    r = recovery_time(t, s, 15.0)
    assert r.flags == {Flag.OUTLIER_FRAMES}
    assert r.observed.outlier_times_s == (float(t[spike]),)
    assert r.recovery_time_s == pytest.approx(true_tr, abs=0.01)


def test_still_rising_series_reports_a_flagged_lower_bound() -> None:
    # tau = 500 s in a 60 s window: S_k rises all the way, so 98 % of the window's S_max is
    # reached shortly before the window ends; the final-slope check flags it.
    t, s = kv_series(tau_s=500.0, s0_px=3000.0, s_inf_px=13000.0)
    r = recovery_time(t, s, 15.0, window_s=60.0)
    assert r.flags == {Flag.NOT_SETTLED}
    assert r.recovery_time_s is not None
    assert 50.0 < r.recovery_time_s < 60.0
    unchecked = recovery_time(t, s, 15.0, window_s=60.0, end_slope_fraction=0.0)
    assert unchecked.flags == frozenset()
    assert unchecked.recovery_time_s == r.recovery_time_s


def test_recovery_settling_well_inside_the_window_is_not_flagged_rising() -> None:
    # tau = 20 s: 98 % of S_inf at 73 s, 32 s before the 105 s window ends.
    t, s = kv_series(tau_s=20.0, s0_px=3000.0, s_inf_px=13000.0, noise_px=20.0)
    r = recovery_time(t, s, 15.0)
    assert Flag.NOT_SETTLED not in r.flags


def test_never_reaching_level_lower_bound_is_last_window_frame() -> None:
    t = np.arange(0.0, 10.0, 0.5)
    s = np.where(t < 1.0, 50.0, 10.0)
    s[8:12] = 100.0  # a four-frame excursion sets S_max; nothing else comes near it
    r = recovery_time(t, s, 1.0, persist_frames=5)
    assert r.flags == {Flag.EARLY_NOISY_CROSSING, Flag.NOT_SETTLED}
    assert r.ts_s == t[-1]
    assert r.recovery_time_s == pytest.approx(t[-1] - 1.0)


def test_recovery_within_one_frame_reports_the_frame_period_as_upper_bound() -> None:
    t, s = kv_series(tau_s=1e-3, s0_px=3000.0, s_inf_px=13000.0, t0_s=15.0)
    t0 = float(t[900])  # exactly a frame time (15 s)
    r = recovery_time(t, s, t0)
    assert r.flags == {Flag.SETTLED_WITHIN_ONE_FRAME}
    assert r.recovery_time_s == pytest.approx(t[901] - t0)


@pytest.mark.parametrize("shape", ["flat", "falling"])
def test_no_rise_after_t0_is_no_recovery(shape: str) -> None:
    t = np.arange(0.0, 30.0, FRAME_S)
    s = np.full(t.size, 5000.0) if shape == "flat" else 9000.0 - 100.0 * t
    r = recovery_time(t, s, 10.0)
    assert r.flags == {Flag.NO_RECOVERY}
    assert r.recovery_time_s is None
    assert r.ts_s is None


def test_all_zero_series_is_no_recovery() -> None:
    t = np.arange(0.0, 5.0, 0.1)
    r = recovery_time(t, np.zeros(t.size), 1.0)
    assert r.flags == {Flag.NO_RECOVERY}


def test_non_finite_frames_are_dropped_and_flagged() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    clean = recovery_time(t, s, 15.0)
    s[[1000, 1200, 1500]] = [math.nan, math.inf, math.nan]
    r = recovery_time(t, s, 15.0)
    assert r.flags == {Flag.NON_FINITE_INPUT}
    assert r.recovery_time_s == pytest.approx(clean.recovery_time_s, abs=FRAME_S)


def test_a_bright_outlier_on_the_plateau_does_not_set_s_max() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    s[-100] = 20000.0  # one bright frame on the plateau
    plain = recovery_time(t, s, 15.0)
    robust = recovery_time(t, s, 15.0, s_max_top_frames=5)
    for r in (plain, robust):
        assert r.s_max_px == pytest.approx(13000.0, rel=1e-6)
        assert r.flags == {Flag.OUTLIER_FRAMES}


def test_window_limits_the_frames_considered() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    s[t > 40.0] = 30000.0  # a second press after the window
    r = recovery_time(t, s, 15.0, window_s=25.0)
    assert r.s_max_px == pytest.approx(13000.0, rel=1e-3)
    assert r.n_frames == int(np.sum((t > 15.0) & (t <= 40.0)))


def test_recovery_time_rejects_bad_arguments() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    with pytest.raises(AnalysisError, match="outside the series"):
        recovery_time(t, s, 200.0)
    with pytest.raises(AnalysisError, match="t0_s must be finite"):
        recovery_time(t, s, math.nan)
    with pytest.raises(AnalysisError, match="settle_fraction"):
        recovery_time(t, s, 15.0, settle_fraction=1.5)
    with pytest.raises(AnalysisError, match="window_s"):
        recovery_time(t, s, 15.0, window_s=0.0)
    with pytest.raises(AnalysisError, match="persist_frames"):
        recovery_time(t, s, 15.0, persist_frames=0)
    with pytest.raises(AnalysisError, match="s_max_top_frames"):
        recovery_time(t, s, 15.0, s_max_top_frames=0)
    with pytest.raises(AnalysisError, match="no finite frame in the recovery window"):
        recovery_time(t, s, float(t[-1]))


# --- T_0 detection ---------------------------------------------------------------------------


def test_detect_recovery_start_finds_the_release() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, pit_px=40000.0)
    s[t < 2.0] = 0.0  # probe in air before the press: the global minimum is not T_0
    assert detect_recovery_start(t, s) == pytest.approx(15.0, abs=FRAME_S)


def test_detect_recovery_start_with_noise_and_smoothing() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, pit_px=40000.0, noise_px=200.0)
    t0 = detect_recovery_start(t, s, smooth_frames=9)
    assert t0 == pytest.approx(15.0, abs=0.2)


def test_detect_recovery_start_with_bounds_and_errors() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, pit_px=40000.0)
    assert detect_recovery_start(t, s, search_start_s=10.0, search_end_s=30.0) == pytest.approx(
        15.0, abs=FRAME_S
    )
    with pytest.raises(AnalysisError, match="no recovery follows"):
        detect_recovery_start(t, 40000.0 - 10.0 * t)
    with pytest.raises(AnalysisError, match="no finite frame between"):
        detect_recovery_start(t, s, search_start_s=500.0)
    with pytest.raises(AnalysisError, match="smooth_frames"):
        detect_recovery_start(t, s, smooth_frames=0)


# --- compute_pitting_parameters ----------------------------------------------------------------


def test_compute_pitting_parameters_chains_eqs_3_to_6() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    p = compute_pitting_parameters(t, s, 15.0, CAL)
    d_s = -1e-9 * 3000.0**2 + 2e-4 * 3000.0
    assert p.depth_change_mm == pytest.approx(d_s)
    assert p.depth_mm == pytest.approx(12.0 - d_s)
    assert p.rebound_force_n == pytest.approx((13000.0 - 1000.0) / 2000.0, rel=1e-6)
    assert p.recovery_time_s == pytest.approx(
        settling_time_from_time_constant(3.0, 3000.0, 13000.0), abs=0.01 * FRAME_S
    )
    assert (p.t0_s, p.s0_px) == (15.0, 3000.0)
    assert p.flags == frozenset()


def test_compute_pitting_parameters_collects_flags() -> None:
    # S_0 = 99000 px gives d_s = -1e-9 * 99000^2 + 2e-4 * 99000 = 10.0 mm (in range); at
    # S_0 = 150000 px, past the vertex (100000 px), Eq. (4) is extrapolated.
    t, s = kv_series(tau_s=3.0, s0_px=150000.0, s_inf_px=150500.0)
    p = compute_pitting_parameters(t, s, 15.0, CAL)
    assert Flag.CALIBRATION_EXTRAPOLATED in p.flags
    cal_far = Calibration(alpha1_mm_per_px2=0.0, alpha2_mm_per_px=1e-3, c1_px=2e6, c2_px_per_n=1.0)
    t, s = kv_series(tau_s=3.0, s0_px=20000.0, s_inf_px=30000.0)
    p = compute_pitting_parameters(t, s, 15.0, cal_far)
    assert p.depth_mm == 0.0  # d_s = 20 mm > l = 12 mm
    assert p.rebound_force_n == 0.0
    assert {Flag.DEPTH_CLIPPED, Flag.REBOUND_BELOW_OFFSET} <= p.flags


def test_compute_pitting_parameters_flags_s0_outside_calibrated_range() -> None:
    cal = Calibration(
        alpha1_mm_per_px2=1e-9,
        alpha2_mm_per_px=2e-4,
        c1_px=1000.0,
        c2_px_per_n=2000.0,
        s0_valid_range_px=(5000.0, 60000.0),
        force_valid_range_n=(1.0, 20.0),
    )
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0)
    assert compute_pitting_parameters(t, s, 15.0, cal).flags == {Flag.CALIBRATION_EXTRAPOLATED}
    t, s = kv_series(tau_s=3.0, s0_px=6000.0, s_inf_px=13000.0)
    assert compute_pitting_parameters(t, s, 15.0, cal).flags == frozenset()
