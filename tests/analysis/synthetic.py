"""Synthetic S_k series for the analysis tests: an ideal Kelvin-Voigt recovery after a pit."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def kv_series(
    *,
    tau_s: float,
    s0_px: float,
    s_inf_px: float,
    t0_s: float = 15.0,
    duration_s: float = 120.0,
    fps: float = 60.0,
    pit_px: float | None = None,
    noise_px: float = 0.0,
    seed: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Frame times [s] and S_k [px]: flat ``pit_px`` before T_0, then
    S(t) = S_inf - (S_inf - S_0) exp(-(t - T_0)/tau), plus Gaussian noise."""
    t = np.arange(0.0, duration_s, 1.0 / fps)
    pit = 2.0 * s_inf_px if pit_px is None else pit_px
    x = np.clip(t - t0_s, 0.0, None)
    with np.errstate(under="ignore"):
        rec = s_inf_px - (s_inf_px - s0_px) * np.exp(-x / tau_s)
    s = np.where(t < t0_s, pit, rec)
    if noise_px > 0.0:
        s = s + np.random.default_rng(seed).normal(0.0, noise_px, s.size)
        s = np.clip(s, 0.0, None)
    return t, s
