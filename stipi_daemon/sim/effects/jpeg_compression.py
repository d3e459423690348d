"""Effect ``jpeg_compression``: the frame goes through a JPEG encoder (phone video, MJPG).

Owns only the round trip through OpenCV's JPEG codec at ``quality``; ringing and 8x8
blocking move edge pixels across the threshold p.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


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
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.params.quality])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise RuntimeError("OpenCV failed to JPEG-encode a frame")
        flag = cv2.IMREAD_COLOR if image.ndim == 3 else cv2.IMREAD_GRAYSCALE
        out: NDArray[np.uint8] = np.asarray(cv2.imdecode(buf, flag), dtype=np.uint8)
        return out
