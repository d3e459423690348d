"""Effect ``led_flicker``: the LEDs' brightness varies (PWM beat, supply ripple, random).

Owns the brightness factor g(t) = 1 + depth * sin(2 pi f t) + sigma * N(0, 1) per frame,
applied to the whole image (the occluded region is lit by the same LEDs). Flicker changes
S_k when it moves background or edge pixels across the threshold p.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


class Params(EffectParams):
    """Sinusoidal ``depth`` [-] at ``frequency_hz`` [Hz] plus random ``sigma`` [-] per frame."""

    name: Literal["led_flicker"] = "led_flicker"
    depth: float = Field(default=0.02, ge=0.0, le=1.0)
    frequency_hz: float = Field(default=3.3, ge=0.0, le=1000.0)
    sigma: float = Field(default=0.005, ge=0.0, le=1.0)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def gain(self, t_s: float, rng: np.random.Generator) -> float:
        """Brightness factor at ``t_s`` [-] (>= 0)."""
        p = self.params
        g = 1.0 + p.depth * math.sin(2.0 * math.pi * p.frequency_hz * t_s)
        g += p.sigma * float(rng.standard_normal())
        return max(g, 0.0)

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        g = self.gain(t_s, rng)
        lut = np.clip(np.rint(np.arange(256, dtype=np.float64) * g), 0, 255).astype(np.uint8)
        out: NDArray[np.uint8] = np.asarray(cv2.LUT(image, lut), dtype=np.uint8)
        return out
