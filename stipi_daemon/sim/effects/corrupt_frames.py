"""Effect ``corrupt_frames``: single frames arrive corrupt and cannot be measured.

A real camera path now and then hands over a frame it cannot decode: a truncated MJPEG
(USB packet loss), a torn or short DMA buffer. The daemon's V4L2 camera skips such a
frame (its ``seq`` is lost and counted; :meth:`stipi_daemon.cameras.v4l2.V4L2Camera`),
so an unmeasurable frame reaches the measurement as a one-frame gap, never as an S_k; an
offline S_k series marks it NaN instead. This effect loses, at each of ``times_s``, the
frame whose nominal time ``k / fps`` is nearest (``k = round(t fps)``), as that camera
path does; the frames around it keep their index and timestamp.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameDropEffect


class Params(EffectParams):
    """Scene times [s] of the corrupt frames (the frame nearest each time)."""

    name: Literal["corrupt_frames"] = "corrupt_frames"
    times_s: tuple[float, ...] = Field(default=())

    @field_validator("times_s")
    @classmethod
    def _finite(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for t in v:
            if not (np.isfinite(t) and t >= 0.0):
                raise ValueError(f"times must be finite and >= 0, got {t}")
        return v


class Effect(FrameDropEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        #: Camera indices of the corrupt frames.
        self.indices = frozenset(round(t * context.fps) for t in params.times_s)

    def keep(self, index: int, t_s: float, rng: np.random.Generator) -> bool:
        return index not in self.indices
