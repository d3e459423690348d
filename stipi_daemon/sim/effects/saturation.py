"""Effect ``saturation``: too much gain or exposure; bright pixels clip at 255.

Owns only the gain-and-clip model, out = min(255, gain * in). A strong gain saturates the
lit waveguide (the analysis flags saturated frames) and lifts the occluded level toward
the threshold p, so S_k collapses.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


class Params(EffectParams):
    """``gain`` applied before the 8-bit clip [-]."""

    name: Literal["saturation"] = "saturation"
    gain: float = Field(default=1.3, gt=0.0, le=20.0)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        self._lut = np.clip(np.rint(np.arange(256) * params.gain), 0, 255).astype(np.uint8)

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        out: NDArray[np.uint8] = self._lut[image]
        return out
