"""Effect ``mcu_clock_drift``: the MCU's resonator runs off its nominal rate, with jitter.

Owns the MCU timestamps of the load-cell samples: a sample taken at true (scene) time t
is stamped ``t_mcu_us = boot + 1e6 (1 + rate_error_ppm 1e-6) t + j`` before rounding to
the microsecond, with j ~ N(0, ``jitter_us``) independent per sample (interrupt latency
and ``micros()`` granularity). Positive ``rate_error_ppm`` is an MCU clock that runs
fast (the sign convention of :class:`stipi_daemon.sim.feather.McuClock`); a ceramic
resonator is within +-5000 ppm (0.5 %). The true times and the forces stay those of the
clean scene; only the clock the host must map onto its own
(:class:`stipi_daemon.protocol.clocksync.ClockSync`) changes. (On the probe the timer that
schedules samples runs on the same resonator, so real samples are evenly spaced in MCU
time; here they are evenly spaced in true time. The two differ by the rate error times
the interval, under 0.5 us across a 10-sample batch at 100 Hz and 5000 ppm.)
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, SampleClockEffect


class Params(EffectParams):
    """Rate error of the MCU clock (``rate_error_ppm`` [ppm], + fast) and the standard
    deviation of the timestamp jitter (``jitter_us`` [us])."""

    name: Literal["mcu_clock_drift"] = "mcu_clock_drift"
    rate_error_ppm: float = Field(default=2000.0, ge=-50_000.0, le=50_000.0)
    jitter_us: float = Field(default=4.0, ge=0.0, le=1000.0)


class Effect(SampleClockEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def mcu_time_us(
        self, t_true_s: NDArray[np.float64], mcu_us: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        k = 1.0 + self.params.rate_error_ppm * 1e-6
        out: NDArray[np.float64] = mcu_us * k
        if self.params.jitter_us > 0.0:
            out = out + rng.normal(0.0, self.params.jitter_us, size=out.shape)
        return out
