"""Effect ``outlier_frames``: single frames far darker or brighter than their neighbours.

A real camera delivers such a frame when the illumination or the exposure jumps for one
frame: an LED driver brown-out or a loose LED connector (the waveguide goes dark), an
auto-exposure or gain step, ambient light or a flash reaching the sensor (the image
saturates). A dark frame sets every ROI pixel below the threshold p, so its S_k is the
whole ROI; a bright one clips every pixel at 255, so its S_k is 0 and the frame is
counted as saturated. The frame nearest each listed time (``k = round(t fps)``) is
replaced by a uniform image at ``dark_level`` or ``bright_level``; effects applied later
(``sensor_noise``, ``jpeg_compression``) still act on it, as on a real sensor.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_validator

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect


class Params(EffectParams):
    """Scene times [s] of dark and bright frames and their gray levels [gray level]."""

    name: Literal["outlier_frames"] = "outlier_frames"
    dark_times_s: tuple[float, ...] = ()
    bright_times_s: tuple[float, ...] = ()
    dark_level: int = Field(default=4, ge=0, le=255)
    bright_level: int = Field(default=255, ge=0, le=255)

    @field_validator("dark_times_s", "bright_times_s")
    @classmethod
    def _finite(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        for t in v:
            if not (np.isfinite(t) and t >= 0.0):
                raise ValueError(f"times must be finite and >= 0, got {t}")
        return v

    @model_validator(mode="after")
    def _levels(self) -> Params:
        if self.dark_level >= self.bright_level:
            raise ValueError(
                f"dark_level {self.dark_level} must be below bright_level {self.bright_level}"
            )
        return self


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        self._fps = context.fps
        #: Gray level of each outlier frame by camera index (bright wins a tie).
        self.levels: dict[int, int] = {
            round(t * context.fps): params.dark_level for t in params.dark_times_s
        }
        self.levels.update(
            {round(t * context.fps): params.bright_level for t in params.bright_times_s}
        )

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        level = self.levels.get(round(t_s * self._fps))
        if level is None:
            return image
        image[...] = level
        return image
