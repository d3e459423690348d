"""Effect ``exposure_drift``: the image brightness drifts slowly over the run.

Owns the gain g(t) of a camera whose auto-exposure or gain wanders, or of LEDs warming
up: ``linear`` g = (1 + s) (1 + r t / 60) or ``exponential`` g = (1 + s) (1 + r)^(t / 60),
with ``start_percent`` s and ``rate_percent_per_min`` r in percent, t the scene time [s];
g is clipped at 0 and applied to the whole frame through a 256-entry lookup table, like
:mod:`.led_flicker` (which owns fast fluctuations; this owns the slow trend). A gain moves
the disc's edge ramp and the lit background against the fixed threshold p, so S_k drifts.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


class Params(EffectParams):
    """Brightness at t = 0 (``start_percent`` [%]) and its drift (``rate_percent_per_min``
    [%/min], ``linear`` or compounding ``exponential``)."""

    name: Literal["exposure_drift"] = "exposure_drift"
    mode: Literal["linear", "exponential"] = "linear"
    rate_percent_per_min: float = Field(default=2.0, ge=-1000.0, le=1000.0)
    start_percent: float = Field(default=0.0, ge=-100.0, le=1000.0)

    @model_validator(mode="after")
    def _exponential_rate(self) -> Params:
        if self.mode == "exponential" and self.rate_percent_per_min <= -100.0:
            raise ValueError("an exponential drift needs rate_percent_per_min > -100")
        return self


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def gain(self, t_s: float) -> float:
        """Brightness factor at scene time ``t_s`` [s] (>= 0) [-]."""
        p = self.params
        r = p.rate_percent_per_min / 100.0
        if p.mode == "linear":
            trend = 1.0 + r * t_s / 60.0
        else:
            trend = math.exp(math.log1p(r) * t_s / 60.0)
        return max((1.0 + p.start_percent / 100.0) * trend, 0.0)

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        g = self.gain(t_s)
        lut = np.clip(np.rint(np.arange(256, dtype=np.float64) * g), 0, 255).astype(np.uint8)
        out: NDArray[np.uint8] = np.asarray(cv2.LUT(image, lut), dtype=np.uint8)
        return out
