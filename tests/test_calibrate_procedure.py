"""Calibration points from recordings: force plateaus, displacement intervals, fit report."""

from __future__ import annotations

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import (
    calibration_from_fits,
    fit_depth_calibration,
    fit_force_calibration,
)
from stipi_daemon.analysis.calibration_procedure import (
    DisplacementInterval,
    displacement_points,
    find_force_plateaus,
    fit_report,
    force_points,
)
from stipi_daemon.errors import CalibrationError

C1, C2 = 1500.0, 2500.0


def staircase(
    levels: list[float], hold_s: float = 3.0, ramp_s: float = 0.5, rate_hz: float = 100.0
) -> tuple[np.ndarray, np.ndarray]:
    """Force held at each level, linear ramps between, starting and ending unloaded."""
    knots_t, knots_f = [0.0], [0.0]
    t = 1.0
    knots_t.append(t)
    knots_f.append(0.0)
    for level in levels:
        t += ramp_s
        knots_t.append(t)
        knots_f.append(level)
        t += hold_s
        knots_t.append(t)
        knots_f.append(level)
    t += ramp_s
    knots_t += [t, t + 1.0]
    knots_f += [0.0, 0.0]
    times = np.arange(0.0, knots_t[-1], 1.0 / rate_hz)
    return times, np.interp(times, knots_t, knots_f)


def test_plateaus_of_a_noisy_staircase() -> None:
    levels = [4.0, 8.0, 12.0, 16.0, 20.0]
    t, f = staircase(levels)
    rng = np.random.default_rng(1)
    noisy = f + rng.normal(0.0, 0.05, f.size)
    noisy[700] += 3.0  # one spike inside the second plateau
    noisy[1350:1353] = np.nan  # lost samples in the middle of the fourth (12.0-15.0 s)
    found = find_force_plateaus(t, noisy)
    # The loss splits the fourth plateau into two halves shorter than 2 s: not used.
    means = [float(np.nanmean(noisy[(t >= a) & (t <= b)])) for a, b in found]
    assert [round(m) for m in means] == [4, 8, 12, 20]
    for a, b in found:
        assert b - a >= 2.0
    # Without the gap, every level is found, and nothing at 0 N (unloaded probe).
    found = find_force_plateaus(t, f + rng.normal(0.0, 0.05, f.size))
    assert len(found) == 5


def test_a_slow_ramp_is_not_a_plateau() -> None:
    t = np.arange(0.0, 20.0, 0.01)
    f = 2.0 + 0.2 * t  # 0.2 N/s: 0.5 N band spans 2.5 s
    assert find_force_plateaus(t, f) == []


def test_force_points_average_force_and_area() -> None:
    t, f = staircase([5.0, 10.0, 15.0])
    rng = np.random.default_rng(2)
    frame_t = np.arange(0.0, t[-1], 1 / 30)
    s = C1 + C2 * np.interp(frame_t, t, f) + rng.normal(0.0, 50.0, frame_t.size)
    pts = force_points(t, f, frame_t, s, find_force_plateaus(t, f))
    assert [p.force_n for p in pts] == pytest.approx([5.0, 10.0, 15.0], abs=1e-9)
    for p in pts:
        assert p.s_px == pytest.approx(C1 + C2 * p.force_n, abs=4 * 50 / np.sqrt(p.n_frames))
        assert p.n_frames >= 70 and p.t_end_s - p.t_start_s == pytest.approx(2.5, abs=0.1)
    fit = fit_force_calibration([p.s_px for p in pts], [p.force_n for p in pts])
    assert fit.c2_px_per_n == pytest.approx(C2, rel=0.01)
    with pytest.raises(CalibrationError, match=r"holds 0 frame\(s\)"):
        force_points(t, f, frame_t[:10], s[:10], [(5.0, 8.0)])
    with pytest.raises(CalibrationError, match="shorter than twice the trim"):
        force_points(t, f, frame_t, s, [(5.0, 5.4)])


def test_displacement_points() -> None:
    frame_t = np.arange(0.0, 10.0, 0.1)
    s = np.where(frame_t < 5.0, 1000.0, 3000.0)
    pts = displacement_points(
        frame_t,
        s,
        [DisplacementInterval(1.0, 4.0, 2.5), DisplacementInterval(6.0, 9.0, 7.0)],
    )
    assert [(p.s0_px, p.interval.depth_change_mm) for p in pts] == [(1000.0, 2.5), (3000.0, 7.0)]
    with pytest.raises(CalibrationError, match=r"interval 1: t_end_s 1\.0 is not after"):
        displacement_points(frame_t, s, [DisplacementInterval(2.0, 1.0, 3.0)])
    with pytest.raises(CalibrationError, match=r"interval 1 \[20, 30\] s holds 0 frame"):
        displacement_points(frame_t, s, [DisplacementInterval(20.0, 30.0, 3.0)])


def test_fit_report_lists_coefficients_errors_and_residuals() -> None:
    s0 = np.array([1000.0, 2000.0, 3000.0, 4000.0, 5000.0])
    d = -1.4e-7 * s0**2 + 2.5e-3 * s0 + np.array([0.01, -0.02, 0.0, 0.02, -0.01])
    f = np.array([2.0, 6.0, 10.0, 14.0])
    s = C1 + C2 * f + np.array([10.0, -20.0, 15.0, -5.0])
    cal = calibration_from_fits(fit_depth_calibration(s0, d), fit_force_calibration(s, f))
    text = "\n".join(fit_report(cal))
    assert "alpha1 = " in text and "+-" in text and "R^2 = " in text
    assert "residuals [mm]: " in text and "residuals [px]: " in text
    assert "threshold p = not recorded" in text
