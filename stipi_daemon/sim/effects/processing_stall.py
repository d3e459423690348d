"""Effect ``processing_stall``: the daemon stops taking frames over one span of scene time.

What a machine busy with something else does to a measurement, on purpose and the same
every run: every frame captured in ``[t_start_s, t_end_s)`` is handed to the daemon only
at ``t_end_s`` (then one after another, in order, a microsecond of session time apart per
second of stall), as a camera that waits for its consumer (a video file, the simulator)
delivers them after the consumer was held up. The daemon's lag
handling then acts as on a real stall: frames later than half of ``run.max_lag_s`` are
stored as ``processing_behind`` gaps, and a lag beyond ``run.max_lag_s`` ends the run
with a fault. The force samples keep coming. In a run on wall time this adds to whatever
the machine itself does; on a simulated run's clock (:class:`stipi_daemon.clock.VirtualClock`)
it is the only lag there is.
"""

from __future__ import annotations

from typing import Literal

from stipi_daemon.sim.effects.base import EffectContext, SpanParams


class Params(SpanParams):
    """Span ``[t_start_s, t_end_s)`` of scene time whose frames wait until ``t_end_s`` [s]."""

    name: Literal["processing_stall"] = "processing_stall"


class Effect:
    """Not run by the frame pipeline: the simulated camera asks it when to hand over."""

    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def handed_over_s(self, t_s: float) -> float | None:
        """Scene time [s] a frame captured at scene time ``t_s`` is handed over at, when
        later than its capture (None: at once)."""
        p = self.params
        return p.t_end_s if p.t_start_s <= t_s < p.t_end_s else None
