"""Effect ``dropped_frames``: the camera or the link loses frames at random.

Owns only the decision per frame (independent, probability ``probability``); the frames
that are kept keep their index and timestamp, so gaps are visible.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameDropEffect


class Params(EffectParams):
    """``probability`` that a frame is lost [-]."""

    name: Literal["dropped_frames"] = "dropped_frames"
    probability: float = Field(default=0.02, ge=0.0, lt=1.0)


class Effect(FrameDropEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def keep(self, index: int, t_s: float, rng: np.random.Generator) -> bool:
        return bool(rng.random() >= self.params.probability)
