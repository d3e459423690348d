"""``mcu_clock_drift``: the samples' MCU stamps run at the drifted rate, true times stay;
the host maps them with the real ClockSync and the analysis runs on the host's times.

Scene: grade 1, 4 s hold, 8 s recovery, 640x480 at 30 fps (as tests/sim/effects/test_effects.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from stipi_daemon.sim import Pipeline, ground_truth
from stipi_daemon.sim.effects.mcu_clock_drift import Params
from tests.sim._analysis import analyse, host_timed
from tests.sim.effects.test_effects import _scene


def _run(effects: list[dict[str, Any]]) -> tuple[float, float, float, Any]:
    s = _scene(effects)
    gt = ground_truth(s)
    pipe = Pipeline(s)
    batch = pipe.force_batch()
    hb, sync = host_timed(batch)
    a = analyse(pipe.frames(gt.t0_s - 0.5), hb, gt, 1.0)
    time_err_s = float(np.max(np.abs(hb.t_true_s - batch.t_true_s)))
    return abs(a.e_kpa / gt.elasticity_kpa - 1.0), time_err_s, sync.drift_ppm, a


def test_stamps_run_at_the_drifted_rate_and_true_times_stay() -> None:
    clean = Pipeline(_scene([])).force_batch()
    ppm, jitter = 5000.0, 4.0
    b = Pipeline(_scene([{"name": "mcu_clock_drift", "rate_error_ppm": ppm, "jitter_us": jitter}]))
    batch = b.force_batch()
    np.testing.assert_array_equal(batch.t_true_s, clean.t_true_s)
    np.testing.assert_array_equal(batch.adc_counts, clean.adc_counts)
    resid = batch.t_mcu_us - (1.0 + ppm * 1e-6) * clean.t_mcu_us
    assert abs(float(np.mean(resid))) < 0.5
    assert float(np.std(resid)) == pytest.approx(np.hypot(jitter, 1 / np.sqrt(12)), rel=0.1)
    slope = np.polyfit(batch.t_true_s, batch.t_mcu_us * 1e-6, 1)[0]
    assert (slope - 1.0) * 1e6 == pytest.approx(ppm, abs=1.0)
    assert np.all(np.diff(batch.t_mcu_us) > 0)


@pytest.mark.parametrize("ppm", [5000.0, -5000.0])
def test_resonator_tolerance_is_absorbed_by_clock_sync(ppm: float) -> None:
    """+-0.5 % (a ceramic resonator's tolerance) with 20 us jitter: ClockSync finds the
    drift, sample times are right within 1 ms and E within 0.1 % of the clean run's."""
    e_clean, _, _, _ = _run([])
    e_err, t_err, drift, a = _run(
        [{"name": "mcu_clock_drift", "rate_error_ppm": ppm, "jitter_us": 20.0}]
    )
    assert t_err < 1e-3
    assert drift == pytest.approx(-ppm, abs=150.0)  # ClockSync: + means the MCU is slow
    assert abs(e_err - e_clean) < 1e-3
    assert not a.flags


def test_too_fast_clock_biases_e_with_no_flag() -> None:
    """5 % (beyond ClockSync's +-10000 ppm clamp): the fit is clamped, hold samples are
    mis-timed by up to ~0.5 s and after-release samples enter the hold mean: E is off by
    > 3 % and the analysis has no clock-quality flag (ClockSync's drift sits at its clamp)."""
    e_err, t_err, drift, a = _run([{"name": "mcu_clock_drift", "rate_error_ppm": 50_000.0}])
    assert drift == pytest.approx(-10_000.0)
    assert t_err > 0.3
    assert e_err > 0.03
    assert not a.flags


def test_params_bounds() -> None:
    with pytest.raises(ValueError, match="less than or equal"):
        Params(rate_error_ppm=60_000.0)
    with pytest.raises(ValueError, match="Extra inputs"):
        Params.model_validate({"name": "mcu_clock_drift", "ppm": 1.0})
