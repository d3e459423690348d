"""The settling tests shared by the analysis and the state machine (analysis/settling.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.pitting import recovery_time
from stipi_daemon.analysis.settling_rules import (
    LineSums,
    kelvin_voigt_truncation_bias,
    least_squares_slope,
    still_rising,
    truncation_hold_factor,
)

F = 0.98


def kv_series(
    tau_s: float, r: float, s_inf_px: float = 20000.0, fps: float = 60.0, window_s: float = 105.0
) -> tuple[np.ndarray, np.ndarray]:
    """Kelvin-Voigt recovery S(t) = S_inf - (S_inf - S_0) e^(-t/tau), T_0 = 0, frames at k/fps."""
    t = np.arange(0, math.floor(window_s * fps) + 1) / fps
    return t, s_inf_px - (1.0 - r) * s_inf_px * np.exp(-t / tau_s)


def test_still_rising_is_slope_times_horizon_against_the_band() -> None:
    assert still_rising(2.0, 10.0, 19.9)
    assert not still_rising(2.0, 10.0, 20.0)  # exactly at the band: still settled
    assert not still_rising(-5.0, 10.0, 1.0)  # falling is never rising
    assert not still_rising(5.0, 0.0, 0.0)


@given(
    st.lists(
        st.tuples(st.floats(0.0, 100.0), st.floats(-1e5, 1e5)), min_size=2, max_size=60
    ).filter(lambda xy: len({x for x, _ in xy}) > 1)
)
@settings(max_examples=100, deadline=None, derandomize=True)
def test_line_sums_slope_equals_the_batch_least_squares_slope(
    xy: list[tuple[float, float]],
) -> None:
    x = np.array([a for a, _ in xy])
    y = np.array([b for _, b in xy])
    if np.ptp(x) < 1e-3:  # nearly equal times: both forms lose the digits
        return
    sums = LineSums()
    for a, b in xy:
        sums = sums.add(a, b)
    slope = sums.slope_px_per_s
    assert slope is not None
    scale = max(1.0, float(np.ptp(y)) / float(np.ptp(x)))
    assert slope == pytest.approx(least_squares_slope(x, y), abs=1e-7 * scale)


def test_line_sums_since_a_snapshot_is_the_suffix() -> None:
    t = np.linspace(0.0, 50.0, 3001)
    s = 15000.0 + 3.0 * t + 40.0 * np.sin(t)
    sums, snap = LineSums(), LineSums()
    for i, (a, b) in enumerate(zip(t, s, strict=True)):
        if i == 2000:
            snap = sums
        sums = sums.add(float(a), float(b))
    suffix = sums.since(snap)
    assert suffix.n == 1001
    assert suffix.slope_px_per_s == pytest.approx(least_squares_slope(t[2000:], s[2000:]), 1e-9)
    assert LineSums().add(1.0, 5.0).slope_px_per_s is None  # one sample
    assert LineSums().add(1.0, 5.0).add(1.0, 7.0).slope_px_per_s is None  # one time


@pytest.mark.parametrize("r", [0.0, 0.3, 0.6, 0.9])
@pytest.mark.parametrize("window_over_tau", [2.0, 5.0, 8.0])
def test_truncation_bias_formula_matches_eq6_on_a_sampled_recovery(
    r: float, window_over_tau: float
) -> None:
    tau = 4.0
    t, s = kv_series(tau, r, fps=2000.0, window_s=600.0)  # effectively the whole recovery
    full = recovery_time(t, s, 0.0, window_s=600.0, end_slope_fraction=0.0)
    keep = t <= window_over_tau * tau
    part = recovery_time(t[keep], s[keep], 0.0, window_s=600.0, end_slope_fraction=0.0)
    assert full.recovery_time_s is not None and part.recovery_time_s is not None
    measured = 1.0 - part.recovery_time_s / full.recovery_time_s
    # interpolation between frames 0.5 ms apart: ~1e-5 of T_r
    assert measured == pytest.approx(kelvin_voigt_truncation_bias(r, window_over_tau), abs=2e-4)


@pytest.mark.parametrize("r", [0.0, 0.2, 0.4, 0.6, 0.8, 0.9, 0.95, 0.97])
@pytest.mark.parametrize("bias", [0.001, 0.005, 0.01, 0.05])
def test_the_hold_factor_bounds_the_bias(r: float, bias: float) -> None:
    factor = truncation_hold_factor(r, F, bias)
    assert factor is not None and factor > 1.0
    big_l = math.log((1.0 - r) / (1.0 - F))  # T_r = tau L
    got = kelvin_voigt_truncation_bias(r, factor * big_l)
    assert got <= bias
    assert got > 0.9 * bias  # and not much longer than needed (ln(1 + x) <= x)


def test_the_hold_factor_at_the_paper_phantoms_and_its_domain() -> None:
    # Grade I..IV of the simulator have S_0 / S_inf = 0.23..0.40: about 2 T_r.
    assert truncation_hold_factor(0.0, F, 0.005) == pytest.approx(2.001, abs=1e-3)
    assert truncation_hold_factor(0.4, F, 0.005) == pytest.approx(2.192, abs=1e-3)
    assert truncation_hold_factor(0.98, F, 0.005) is None  # the rise is inside the band
    assert truncation_hold_factor(1.5, F, 0.005) is None
    lenient = truncation_hold_factor(0.0, F, 0.9)
    assert lenient is not None and 0.0 < lenient < 1.0  # the plateau start alone suffices
    with pytest.raises(ValueError, match="bias_fraction"):
        truncation_hold_factor(0.3, F, 0.0)
    with pytest.raises(ValueError, match="settle_fraction"):
        truncation_hold_factor(0.3, 1.0, 0.01)
    with pytest.raises(ValueError, match="s0_over_s_max"):
        truncation_hold_factor(math.nan, F, 0.01)
    with pytest.raises(ValueError, match="s0_over_s_inf"):
        kelvin_voigt_truncation_bias(0.99, 5.0)
    with pytest.raises(ValueError, match="window_over_tau"):
        kelvin_voigt_truncation_bias(0.5, -1.0)
