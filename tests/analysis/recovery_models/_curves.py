"""Recovery series from the simulator's tissue models (stipi_daemon.sim.tissue, an
independent implementation of each recovery function) with the noise of a rendered scene.

Noise model ("realistic"): measured on tissue_kelvin_voigt.yaml and tissue_zener.yaml rendered
at 640x480, 60 fps with sensor_noise (2 levels) and led_flicker (2 %, 3.3 Hz) and counted
with FrameProcessor: S_k minus the closed-form S(t) has SD 15 px, autocorrelation 0.80 at
lag 1 and a 3.3 Hz periodic part (-0.76 at lag 10, +0.68 at lag 20). Reproduced as an
AR(1) series (rho 0.6, SD 8 px) plus a 3.3 Hz sinusoid of 15 px amplitude and random phase.
"""

from __future__ import annotations

import math

import numpy as np

from stipi_daemon.sim.tissue import build_tissue_model

FPS = 60.0
S0_PX, S_INF_PX = 4862.0, 17851.0
T0_S = 15.0
#: The scenes' models (configs/scenes/tissue_*.yaml).
SCENE_MODELS: dict[str, dict[str, float]] = {
    "kelvin_voigt": {"tau_s": 7.65},
    "zener": {"tau_sigma_s": 8.31, "tau_epsilon_s": 2.08},
    "prony": {"tau_1_s": 1.0, "tau_2_s": 8.92, "weight_1": 0.4},
    "poroelastic": {"tau_p_s": 20.0},
    "power_law": {"tau_s": 2.07, "exponent_n": 1.5},
}
#: Which fitted model is the true one for each tissue (None: no fitted model is).
TRUE_FIT = {
    "kelvin_voigt": "kelvin_voigt",
    "zener": "two_exponential",
    "prony": "two_exponential",
    "poroelastic": None,
    "power_law": "power_law",
}


def realistic_noise(n: int, rng: np.random.Generator) -> np.ndarray:
    """AR(1) (rho 0.6, SD 8 px) plus a 3.3 Hz, 15 px flicker of random phase [px]."""
    rho, sd = 0.6, 8.0
    e = rng.standard_normal(n) * sd * math.sqrt(1.0 - rho**2)
    ar = np.empty(n)
    ar[0] = rng.standard_normal() * sd
    for i in range(1, n):
        ar[i] = rho * ar[i - 1] + e[i]
    k = np.arange(n)
    out: np.ndarray = ar + 15.0 * np.sin(
        2.0 * math.pi * 3.3 * k / FPS + rng.uniform(0, 2 * math.pi)
    )
    return out


def series(
    tissue: str,
    params: dict[str, float] | None = None,
    *,
    window_s: float = 105.0,
    fps: float = FPS,
    noise: str | float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """(t [s], S_k [px], truth) of one recovery from T_0 = 15 s.

    truth: ``tau_s`` (effective, 1 - 1/e recovered), ``recovery_time_s`` (98 % of S at the
    window's last sample), ``s_max`` [px], all from the tissue model.
    """
    model = build_tissue_model(tissue, params or SCENE_MODELS[tissue])
    x = np.arange(0.0, window_s + 1e-9, 1.0 / fps)
    s = S_INF_PX - (S_INF_PX - S0_PX) * model.remaining(x)
    s_max = float(s[-1])
    level = 0.98 * s_max
    tr = 0.0 if level <= S0_PX else model.settling_time_s(S0_PX, S_INF_PX, level)
    truth = {"tau_s": model.effective_time_constant_s(), "recovery_time_s": tr, "s_max": s_max}
    rng = np.random.default_rng(seed)
    if noise == "realistic":
        s = s + realistic_noise(x.size, rng)
    elif noise:
        s = s + float(noise) * rng.standard_normal(x.size)
    return x + T0_S, s, truth
