"""Effect ``motion_blur``: the probe moves during the exposure, so the disc is smeared.

Owns the exposure's sub-frame times and the slow sway of the operator's hand. A frame is
stamped at the start of its exposure: the frame at t integrates the scene over
[t, t + ``exposure_s``], the pipeline rendering ``sub_frames`` sub-frames at
t + exposure_s (j + 1/2) / n, j = 0..n-1, each with
the disc offset of every render effect at that time (this effect's sway
x = A sin(2 pi f t), y = A sin(1.7 pi f t + 1), amplitude A = ``sway_amplitude_mm``, plus
the tremor of ``hand_tremor`` if the scene lists it, whose random phase is drawn once per
frame so the motion inside one exposure is smooth) and averages them (rounded to uint8).
The change of S during the exposure is integrated the same way (so S_k lags S(t) by
about half an exposure while S changes; a frame whose exposure straddled the instant
release would mix both states, which the start-of-exposure stamp avoids for the frame at
T_0 on the frame grid). Smearing turns the sharp edge ramp into a wider one; a pixel is
counted when the time-averaged level is <= p.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.effects.base import EffectContext, EffectParams, RenderEffect


class Params(EffectParams):
    """Exposure (``exposure_s`` [s], default the camera's), its ``sub_frames``, and the hand's
    sway (``sway_amplitude_mm`` [mm] at ``sway_frequency_hz`` [Hz])."""

    name: Literal["motion_blur"] = "motion_blur"
    exposure_s: float | None = Field(default=None, gt=0.0, le=1.0)
    sub_frames: int = Field(default=8, ge=2, le=32)
    sway_amplitude_mm: float = Field(default=0.0, ge=0.0, le=10.0)
    sway_frequency_hz: float = Field(default=1.0, gt=0.0, le=50.0)


class Effect(RenderEffect):
    """Raises :class:`~stipi_daemon.errors.ConfigError` if the exposure exceeds the frame period."""

    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        self.exposure_s = context.exposure_s if params.exposure_s is None else params.exposure_s
        period_s = 1.0 / context.fps
        if self.exposure_s > period_s * (1.0 + 1e-9):
            raise ConfigError(
                f"motion_blur.exposure_s: {self.exposure_s} s is longer than the frame period "
                f"{period_s:.6g} s"
            )
        self._amp_px = params.sway_amplitude_mm * context.px_per_mm
        n = params.sub_frames
        self._fractions = tuple((j + 0.5) / n for j in range(n))

    def sub_times_s(self, t_s: float) -> tuple[float, ...]:
        return tuple(t_s + self.exposure_s * f for f in self._fractions)

    def offset_px(self, t_s: float, rng: np.random.Generator) -> tuple[float, float]:
        if self._amp_px == 0.0:
            return (0.0, 0.0)
        w = 2.0 * math.pi * self.params.sway_frequency_hz * t_s
        return (self._amp_px * math.sin(w), self._amp_px * math.sin(0.85 * w + 1.0))
