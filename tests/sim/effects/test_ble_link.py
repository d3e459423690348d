"""``ble_link``: batches lost (Bernoulli or Gilbert-Elliott) and delayed on connection
events; losses exactly accountable, host receive times usable by ClockSync.

Scene: grade 1, 4 s hold, 8 s recovery, 640x480 at 30 fps (as tests/sim/effects/test_effects.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.results import applied_force_n_from_samples
from stipi_daemon.errors import AnalysisError
from stipi_daemon.protocol.accounting import SampleAccounting
from stipi_daemon.sim import Pipeline, ground_truth
from stipi_daemon.sim.effects.base import EffectContext
from stipi_daemon.sim.effects.ble_link import BurstLoss, Effect, Params
from tests.sim._analysis import analyse, host_timed
from tests.sim.effects.test_effects import _scene

CTX = EffectContext(640, 480, 30.0, 0.008, 128, 100.0, 44.48, 8.64)


def _batch(effects: list[dict[str, Any]]) -> Any:
    return Pipeline(_scene(effects)).force_batch()


def test_losses_are_whole_batches_and_exactly_accounted() -> None:
    """Lost samples are whole 10-sample batches, listed in ``lost_index``; the protocol's
    SampleAccounting, fed the delivered batches, finds the same gaps."""
    b = _batch([{"name": "ble_link", "loss_probability": 0.2}])
    n = b.index.size + b.lost_index.size
    np.testing.assert_array_equal(np.sort(np.r_[b.index, b.lost_index]), np.arange(n))
    assert b.lost_index.size > 0 and b.lost_index.size % 10 == 0
    lost_batches = np.unique(b.lost_index // 10)
    np.testing.assert_array_equal(np.bincount(b.lost_index // 10)[lost_batches], 10)
    acc = SampleAccounting()
    starts = np.flatnonzero(np.r_[True, b.index[1:] // 10 != b.index[:-1] // 10])
    counts = np.diff(np.r_[starts, b.index.size])
    for i, c in zip(starts, counts, strict=True):
        acc.observe(int(b.index[i]), int(c))
    gap_indices = [g.start_index + k for g in acc.gaps for k in range(g.count)]
    first, last = int(b.index[0]), int(b.index[-1])
    inner = b.lost_index[(b.lost_index > first) & (b.lost_index < last)]
    np.testing.assert_array_equal(gap_indices, inner)
    assert acc.received == b.index.size


def test_delivery_times_are_quantised_ordered_and_late() -> None:
    p = {"name": "ble_link", "connection_interval_s": 0.03, "host_latency_s": 0.002}
    b = _batch([p])
    batch_of = b.index // 10
    ends = np.r_[batch_of[1:] != batch_of[:-1], True]
    arrival = b.t_host_s[ends]
    ready = b.t_true_s[ends]
    # every sample of a batch arrives with it, after its last sample was taken
    for k in np.unique(batch_of):
        assert np.ptp(b.t_host_s[batch_of == k]) == 0.0
    assert np.all(arrival >= ready + 0.002 - 1e-12)
    assert np.all(np.diff(arrival) >= 0.0)
    # on the connection-event grid (plus the host latency)
    steps = (arrival - arrival[0]) / 0.03
    np.testing.assert_allclose(steps, np.rint(steps), atol=1e-6)
    assert float(np.median(arrival - ready)) < 0.03 + 0.002


def test_mild_link_keeps_results_on_the_host_clock() -> None:
    """1 % loss, 30 ms interval, 10 ms retries, with a 0.5 % resonator: the daemon's view
    (ClockSync on (last-sample MCU time, receive time)) puts samples within 15 ms of their
    true time (the envelope keeps the smallest delay, which ClockSync cannot tell from
    the offset) and E stays within 0.2 %."""
    s = _scene([{"name": "ble_link"}, {"name": "mcu_clock_drift", "rate_error_ppm": 5000.0}])
    gt = ground_truth(s)
    pipe = Pipeline(s)
    batch = pipe.force_batch()
    hb, _ = host_timed(batch)
    assert np.all(hb.t_true_s - batch.t_true_s > -1e-3)
    assert np.max(np.abs(hb.t_true_s - batch.t_true_s)) < 0.015
    a = analyse(pipe.frames(gt.t0_s - 0.5), hb, gt, 1.0)
    assert abs(a.e_kpa / gt.elasticity_kpa - 1) < 0.002
    assert not a.flags


def test_total_loss_in_the_hold_raises_analysis_error() -> None:
    """99.9 % loss: no sample survives in the hold. The analysis has no loss flag; its
    applied-force step raises AnalysisError naming the empty hold."""
    b = _batch([{"name": "ble_link", "loss_probability": 0.999}])
    with pytest.raises(AnalysisError, match="no force sample in the pitting hold"):
        applied_force_n_from_samples(b.t_host_s, b.force_n, 1.5, 4.95)


def test_burst_loss_rate_and_burstiness() -> None:
    burst = BurstLoss(p_good_to_bad=0.02, p_bad_to_good=0.25, loss_good=0.0, loss_bad=0.9)
    e = Effect(Params(burst=burst), CTX)
    lost = e.losses(200_000, np.random.default_rng(3))
    assert lost.mean() == pytest.approx(burst.mean_loss, rel=0.05)
    # bursty: a loss follows a loss far more often than the mean rate
    follow = float(np.mean(lost[1:][lost[:-1]]))
    assert follow > 5 * burst.mean_loss


def test_params_reject_two_loss_models_and_unknown_fields() -> None:
    with pytest.raises(ValueError, match="not both"):
        Params.model_validate({"name": "ble_link", "loss_probability": 0.1, "burst": {}})
    with pytest.raises(ValueError, match="Extra inputs"):
        Params.model_validate({"name": "ble_link", "burst": {"p_loss": 0.1}})


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 400),
    batch_size=st.integers(1, 24),
    p=st.floats(0.0, 0.9),
    seed=st.integers(0, 2**32 - 1),
)
def test_schedule_matches_the_pipeline_hooks(n: int, batch_size: int, p: float, seed: int) -> None:
    """``schedule`` and the pipeline's hooks (``delivered`` then ``host_time_s``) draw the
    same losses and arrivals from the same generator; arrivals of kept batches are ordered."""
    e = Effect(Params(batch_size=batch_size, loss_probability=p), CTX)
    index = np.arange(n, dtype=np.int64)
    t = index / 100.0
    sched = e.schedule(index, t, np.random.default_rng(seed))
    g = np.random.default_rng(seed)
    kept = e.delivered(index, g)
    host = e.host_time_s(index, t, kept, g)
    np.testing.assert_array_equal(kept, ~sched.lost[index // batch_size])
    np.testing.assert_array_equal(host, sched.arrival_s[index // batch_size])
    assert int(sched.count.sum()) == n
    assert np.all(np.diff(sched.arrival_s[~sched.lost]) >= 0.0)
    assert np.all(sched.arrival_s >= sched.ready_s)
