"""Effect ``force_drift``: zero offset and linear drift of the load cell (temperature, creep).

Owns only the deterministic drift F' = F + offset_n + rate_n_per_s * t.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, ForceEffect


class Params(EffectParams):
    """``offset_n`` [N] at t = 0 and ``rate_n_per_s`` [N/s]."""

    name: Literal["force_drift"] = "force_drift"
    offset_n: float = Field(default=0.0, ge=-100.0, le=100.0)
    rate_n_per_s: float = Field(default=0.002, ge=-10.0, le=10.0)


class Effect(ForceEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def apply_force(
        self, t_s: NDArray[np.float64], force_n: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        return force_n + self.params.offset_n + self.params.rate_n_per_s * t_s
