"""Effect ``frame_gap``: the camera delivers no frames over one span of scene time.

A real camera stops delivering for a while when its USB link resets, the host's driver
starves (bus bandwidth, a suspended hub) or the capture thread is held up: every frame
whose nominal time ``k / fps`` lies in ``[t_start_s, t_end_s)`` is lost, and the frames
around the span keep their index and timestamp, so the loss shows as one ``seq`` gap of
about ``(t_end_s - t_start_s) * fps`` frames (the daemon records it as a ``frames`` gap).
Unlike ``dropped_frames`` (independent random losses) the span is deterministic. List the
effect once per span for several gaps.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from stipi_daemon.sim.effects.base import EffectContext, FrameDropEffect, SpanParams


class Params(SpanParams):
    """Span ``[t_start_s, t_end_s)`` of scene time without frames [s] (default: empty)."""

    name: Literal["frame_gap"] = "frame_gap"


class Effect(FrameDropEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def keep(self, index: int, t_s: float, rng: np.random.Generator) -> bool:
        return not self.params.t_start_s <= t_s < self.params.t_end_s
