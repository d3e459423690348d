"""``sensor_noise``'s table-based generator: the rounded-Gaussian statistics it documents,
exact clipping, channels shared, and determinism per (seed, frame)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from stipi_daemon.sim import Pipeline
from stipi_daemon.sim.effects.base import EffectContext
from stipi_daemon.sim.effects.sensor_noise import Effect, Params, noise_table
from tests.sim.effects.test_effects import _scene

CTX = EffectContext(640, 480, 30.0, 0.008, 128, 100.0, 44.48, 8.64)


@pytest.mark.parametrize("sigma", [0.5, 2.0, 12.0])
def test_noise_is_a_rounded_gaussian(sigma: float) -> None:
    n = Effect(Params(sigma_levels=sigma), CTX).noise((600, 800), np.random.default_rng(1))
    assert abs(float(n.mean())) < 0.01 * max(sigma, 1.0)
    # rounding adds 1/12 level^2 of variance (for sigma >~ 1)
    expect = np.sqrt(sigma**2 + 1 / 12) if sigma >= 1 else None
    if expect is not None:
        assert float(n.std()) == pytest.approx(expect, rel=0.01)
    # probability of each value within 2^-16 of the rounded Gaussian's (plus sampling noise)
    k = np.arange(-3, 4)
    p_model = norm.cdf((k + 0.5) / sigma) - norm.cdf((k - 0.5) / sigma)
    p_seen = np.array([np.mean(n == v) for v in k])
    np.testing.assert_allclose(p_seen, p_model, atol=0.003)
    assert int(np.abs(n).max()) <= round(4.3249 * sigma)


def test_table_tails_are_cut_at_4_32_sigma() -> None:
    t = noise_table(50.0)
    assert -int(t.min()) == int(t.max()) == round(50.0 * 4.3249)
    assert np.all(np.diff(t) >= 0)
    assert int(noise_table(100.0).max()) == 255  # beyond 255 the clip makes no difference


def test_apply_equals_clipped_sum_and_shares_channels() -> None:
    e = Effect(Params(sigma_levels=30.0), CTX)
    img = np.random.default_rng(0).integers(0, 256, (60, 80, 3)).astype(np.uint8)
    out = e.apply_frame(img.copy(), 0.0, np.random.default_rng(7))
    n = e.noise((60, 80), np.random.default_rng(7))
    np.testing.assert_array_equal(out, np.clip(img.astype(np.int16) + n[:, :, None], 0, 255))
    gray = img[:, :, 0].copy()
    out_g = e.apply_frame(gray, 0.0, np.random.default_rng(7))
    np.testing.assert_array_equal(out_g, out[:, :, 0] * 0 + np.clip(gray + n.astype(int), 0, 255))


def test_frames_are_deterministic_per_seed_and_frame() -> None:
    s = _scene([{"name": "sensor_noise", "sigma_levels": 2.0}]).with_camera(width=320, height=240)
    whole = {f.index: f.image for f in Pipeline(s, 5).frames(0.0, 0.5)}
    window = list(Pipeline(s, 5).frames(0.3, 0.4))
    assert window
    for f in window:
        np.testing.assert_array_equal(f.image, whole[f.index])
    other = next(iter(Pipeline(s, 6).frames(0.3, 0.3)))
    assert not np.array_equal(other.image, whole[other.index])
