"""Effect ``vignetting``: the lens darkens the image radially from the optical axis.

Owns the static falloff map f(r) = clip(1 - strength (r / R)^2, 0, 1), r the distance
from the frame centre [px], R = ``radius_fraction`` times the half-diagonal [px] (the
distance at which ``strength`` of the light is lost; a quadratic approximation of the
cos^4 law). The map is computed once per scene, stored as a uint8 fraction of 255 (its
factor resolution is 1/255) and applied to every frame with OpenCV's saturating multiply;
the whole frame is attenuated, the occluded disc and its edge ramp included, so the edge
crosses the threshold p slightly further in. It is an effect applied per frame rather
than folded into the renderer's background (which has no such hook): the effect-free
rendering path is untouched.
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
    """Fraction of light lost (``strength`` [-]) at ``radius_fraction`` of the half-diagonal."""

    name: Literal["vignetting"] = "vignetting"
    strength: float = Field(default=0.3, ge=0.0, le=1.0)
    radius_fraction: float = Field(default=1.0, gt=0.0, le=4.0)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        h, w = context.height_px, context.width_px
        self.radius_px = params.radius_fraction * 0.5 * math.hypot(w, h)
        yy, xx = np.ogrid[0:h, 0:w]
        r2 = ((xx - (w - 1) / 2.0) ** 2 + (yy - (h - 1) / 2.0) ** 2) / self.radius_px**2
        #: Falloff factor per pixel [-], (H, W) float64.
        self.factor = np.clip(1.0 - params.strength * r2, 0.0, 1.0)
        self._map = np.rint(self.factor * 255.0).astype(np.uint8)
        self._map3 = np.ascontiguousarray(np.repeat(self._map[:, :, None], 3, axis=2))

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        m = self._map3 if image.ndim == 3 else self._map
        out: NDArray[np.uint8] = np.asarray(
            cv2.multiply(image, m, scale=1.0 / 255.0), dtype=np.uint8
        )
        return out
