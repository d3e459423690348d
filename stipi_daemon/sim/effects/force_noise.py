"""Effect ``force_noise``: white Gaussian noise on the load cell's output, before the ADC.

Owns only the noise model (``sigma_n`` newtons, independent per sample).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, ForceEffect


class Params(EffectParams):
    """``sigma_n``: standard deviation of the force noise [N]."""

    name: Literal["force_noise"] = "force_noise"
    sigma_n: float = Field(default=0.05, ge=0.0, le=100.0)


class Effect(ForceEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def apply_force(
        self, t_s: NDArray[np.float64], force_n: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        return force_n + rng.normal(0.0, self.params.sigma_n, size=force_n.shape)
