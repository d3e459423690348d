"""Effect ``hand_tremor``: the operator's physiological tremor (about 8-12 Hz).

Owns the tremor model: a sinusoid at ``frequency_hz`` with a slowly wandering phase,
moving the occluded disc by ``position_amplitude_mm`` (the probe shifts against the
indenter) and adding ``force_amplitude_n`` to the load cell's reading. The tissue's
mechanics are not changed: tremor perturbs the measurements, not the pit.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, ForceEffect, RenderEffect


class Params(EffectParams):
    """Amplitudes of position [mm] and force [N] at ``frequency_hz`` [Hz]."""

    name: Literal["hand_tremor"] = "hand_tremor"
    frequency_hz: float = Field(default=9.0, gt=0.0, le=50.0)
    position_amplitude_mm: float = Field(default=0.1, ge=0.0, le=10.0)
    force_amplitude_n: float = Field(default=0.3, ge=0.0, le=20.0)


class Effect(RenderEffect, ForceEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        self._amp_px = params.position_amplitude_mm * context.px_per_mm

    def offset_px(self, t_s: float, rng: np.random.Generator) -> tuple[float, float]:
        w = 2.0 * math.pi * self.params.frequency_hz * t_s
        jitter = 0.2 * float(rng.standard_normal())
        return (
            self._amp_px * math.sin(w + jitter),
            self._amp_px * math.cos(1.3 * w + jitter),
        )

    def apply_force(
        self, t_s: NDArray[np.float64], force_n: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        w = 2.0 * math.pi * self.params.frequency_hz * t_s
        phase = np.cumsum(rng.normal(0.0, 0.05, size=t_s.shape))
        return force_n + self.params.force_amplitude_n * np.sin(w + phase)
