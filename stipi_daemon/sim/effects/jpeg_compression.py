"""Effect ``jpeg_compression``: the camera's frames are JPEGs (phone video, an MJPG camera).

Owns the effect's parameter (``quality``). Naming it makes the scene a Motion-JPEG scene
(:func:`stipi_daemon.sim.jpeg.scene_encoding`): the pipeline encodes each frame once, after
every other image effect, at this quality, and the frame the analysis sees is the decode of
that JPEG, which travels with it (``SimFrame.packet``) into the simulated camera and the
written video. Ringing and 8x8 blocking move edge pixels across the threshold p.
:meth:`Effect.apply_frame` is the same round trip for a lone image.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect
from stipi_daemon.sim.jpeg import decode_jpeg, encode_jpeg


class Params(EffectParams):
    """``quality``: JPEG quality, 1 (worst) .. 100."""

    name: Literal["jpeg_compression"] = "jpeg_compression"
    quality: int = Field(default=80, ge=1, le=100)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        """``image`` through the JPEG encoder at ``quality`` and back (same layout)."""
        channels = 3 if image.ndim == 3 else 1
        return decode_jpeg(encode_jpeg(image, self.params.quality), channels)
