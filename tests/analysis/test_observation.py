"""Frame gaps, outlier frames and the robust S_max (analysis/observation.py, pitting.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.observation import (
    FrameGap,
    find_frame_gaps,
    find_outlier_frames,
    noise_sigma,
    release_gap,
    running_median,
)
from stipi_daemon.analysis.pitting import recovery_time
from tests.analysis.synthetic import kv_series

NOISE_PX = 20.0


def test_gaps_are_intervals_over_one_and_a_half_median_periods() -> None:
    t = np.arange(100) * 0.1
    t = np.delete(t, [31, 32, 62])  # two frames lost (3.0 -> 3.3), then one (6.1 -> 6.3)
    gaps = find_frame_gaps(t)
    assert [(round(g.start_s, 2), round(g.end_s, 2)) for g in gaps] == [(3.0, 3.3), (6.1, 6.3)]
    assert gaps[0].describe() == "no frame between 3.00 and 3.30 s"
    assert find_frame_gaps(np.arange(0.0, 1.0, 0.1)) == ()


def test_release_is_observed_unless_frames_around_t0_are_over_three_periods_apart() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    assert release_gap(t, 5.0, 0.1) is None  # T_0 on a frame
    assert release_gap(t, 5.05, 0.1) is None  # between two frames
    assert release_gap(np.delete(t, 50), 5.0, 0.1) is None  # the T_0 frame lost
    lost = t[(t < 4.5) | (t > 5.5)]
    assert release_gap(lost, 5.0, 0.1) == FrameGap(pytest.approx(4.4), pytest.approx(5.6))
    # T_0 on the first frame after a gap: the release may have been anywhere in it
    assert release_gap(lost, float(lost[lost > 5.0][0]), 0.1) is not None


def test_a_monotone_series_is_its_own_running_median_and_has_no_outlier() -> None:
    _, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, t0_s=0.0, duration_s=20.0)
    np.testing.assert_array_equal(running_median(s, 2)[:-2], s[:-2])
    np.testing.assert_allclose(running_median(s, 2)[-2:], s[-2:], atol=0.1)  # cut windows
    assert not find_outlier_frames(s).any()


@pytest.mark.parametrize("value", [0.0, 70000.0])
@pytest.mark.parametrize("where", [1, 500, -2, -1])
def test_an_outlier_frame_is_found_anywhere_after_the_first(where: int, value: float) -> None:
    _, s = kv_series(
        tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, t0_s=0.0, duration_s=20.0, noise_px=NOISE_PX
    )
    s[where] = value
    found = np.flatnonzero(find_outlier_frames(s))
    assert found.tolist() == [where % s.size]


def test_noise_sigma_measures_the_frame_noise_not_the_recovery() -> None:
    t, s = kv_series(tau_s=3.0, s0_px=3000.0, s_inf_px=13000.0, noise_px=NOISE_PX)
    assert noise_sigma(s[t >= 15.0]) == pytest.approx(NOISE_PX, rel=0.1)


@settings(max_examples=60, deadline=None)
@given(
    tau_s=st.floats(0.05, 500.0),
    s0_px=st.floats(0.0, 20000.0),
    rise_px=st.floats(1.0, 50000.0),
    fps=st.sampled_from([15.0, 30.0, 60.0, 120.0]),
    window_s=st.floats(5.0, 105.0),
)
def test_robust_s_max_is_the_plain_maximum_on_a_clean_kelvin_voigt_recovery(
    tau_s: float, s0_px: float, rise_px: float, fps: float, window_s: float
) -> None:
    t = np.arange(0.0, window_s + 1e-9, 1.0 / fps)
    s = s0_px + rise_px * (1.0 - np.exp(-t / tau_s))
    r = recovery_time(t, s, 0.0, window_s=window_s, persist_frames=1)
    # Never above the plain maximum, never below it by more than the last frame's rise:
    # within 1 px whenever S_k rises by at most 1 px per frame at the end of the window.
    w = s[(t > 0.0) & (t <= window_s)]
    last_rise = float(w[-1] - w[-2]) if w.size > 1 else 0.0
    assert 0.0 <= float(np.max(w)) - r.s_max_px <= max(last_rise, 0.0) + 1e-6
    if last_rise <= 1.0:
        assert abs(r.s_max_px - float(np.max(w))) <= 1.0


_CLEAN_T, _CLEAN_S = kv_series(
    tau_s=5.0, s0_px=3000.0, s_inf_px=13000.0, noise_px=NOISE_PX, duration_s=60.0, seed=4
)
_CLEAN = recovery_time(_CLEAN_T, _CLEAN_S, 15.0, window_s=40.0)


@settings(max_examples=80, deadline=None)
@given(
    index=st.integers(int(15.0 * 60) + 1, int(55.0 * 60)),
    value=st.floats(0.0, 100000.0),
)
def test_a_single_outlier_anywhere_changes_s_max_by_less_than_the_noise(
    index: int, value: float
) -> None:
    s = _CLEAN_S.copy()
    s[index] = value
    r = recovery_time(_CLEAN_T, s, 15.0, window_s=40.0)
    assert abs(r.s_max_px - _CLEAN.s_max_px) < NOISE_PX
