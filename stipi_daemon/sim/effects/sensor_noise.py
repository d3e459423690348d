"""Effect ``sensor_noise``: Gaussian read noise of the camera sensor, per pixel and channel.

Owns only the noise model (zero-mean Gaussian, ``sigma_levels`` gray levels, rounded and
clipped to 0..255; one draw per pixel, shared by the three channels of a BGR frame so
that the gray conversion sees the full sigma). Pixels near the edge of the occluded
disc cross the threshold p, so S_k scatters by about the edge pixels within sigma of p.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


class Params(EffectParams):
    """``sigma_levels``: standard deviation of the read noise [gray levels]."""

    name: Literal["sensor_noise"] = "sensor_noise"
    sigma_levels: float = Field(default=2.0, ge=0.0, le=128.0)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        noise = rng.standard_normal(image.shape[:2], dtype=np.float32)
        noise *= np.float32(self.params.sigma_levels)
        n16 = np.rint(noise).astype(np.int16)
        if image.ndim == 3:
            n16 = n16[:, :, None]
        out: NDArray[np.uint8] = np.clip(image + n16, 0, 255).astype(np.uint8)
        return out
