"""Effect ``force_dropout``: the probe's link delivers no load-cell samples over a span.

A real probe loses a stretch of samples when its link drops out for a moment: a USB
cable that disconnects and reconnects, a BLE link out of range, a host that stops reading
long enough for the firmware's 64-sample ring to overflow. Every sample taken at a true
time in ``[t_start_s, t_end_s)`` is taken but not delivered: it appears in
:attr:`stipi_daemon.sim.ForceBatch.lost_index`, and the delivered samples keep their
index, so the host sees one index gap (the daemon records it as a ``force`` gap). Sample
times, forces and the other samples are unchanged.

The emulated probe (:class:`stipi_daemon.sim.feather.SceneAdc` under the firmware model,
serial and BLE alike) plays the same span: the samples it takes at a true time in it are
counted (their indices are used) and left out of its SAMPLES frames, whose sequence numbers
are used as by frames lost on the link, so the daemon records one ``force`` gap with
cause ``link`` and exactly these samples missing.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.sim.effects.base import EffectContext, SampleClockEffect, SpanParams


class Params(SpanParams):
    """Span ``[t_start_s, t_end_s)`` of true time without delivered samples [s] (default:
    empty)."""

    name: Literal["force_dropout"] = "force_dropout"


class Effect(SampleClockEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        self._rate_hz = context.sample_rate_hz
        self._t_true_s: NDArray[np.float64] | None = None

    def true_time_s(
        self, t_nominal_s: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        # Remember the true times of the samples (as the previous clock effects left them)
        # for delivered(), which is given only the indices.
        self._t_true_s = t_nominal_s
        return t_nominal_s

    def delivered(self, index: NDArray[np.int64], rng: np.random.Generator) -> NDArray[np.bool_]:
        p = self.params
        t = self._t_true_s
        if t is None or t.shape != index.shape:
            t = index / self._rate_hz  # the nominal schedule
        lost: NDArray[np.bool_] = (t >= p.t_start_s) & (t < p.t_end_s)
        return ~lost
