"""The load cell and the MCU's ADC: force [N] to raw counts, as the probe would read them.

This module owns the FC22-like transfer function (ratiometric output, zero at
``zero_fraction`` and full scale at ``zero_fraction + span_fraction`` of the supply), the
divider to the MCU's ADC reference, the ADC's quantisation and clipping, and the inverse
the host applies (``force = (adc - zero_counts) * span``). It does not schedule samples or
apply effects (see :mod:`.pipeline`). Everything is pure and vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.sim.scene import LoadCellSpec

__all__ = ["LoadCellModel"]


@dataclass(frozen=True)
class LoadCellModel:
    """Force to ADC counts and back for one :class:`LoadCellSpec`.

    With the defaults (FC22 10 lbf = 44.48 N, 0.5-4.5 V at 5 V, divider 0.66 to a 3.3 V,
    10-bit ADC): zero at 102.4 counts, 819.2 counts for full scale, 54.3 mN per count.
    """

    spec: LoadCellSpec

    @property
    def full_counts(self) -> int:
        """Number of ADC codes, 2^bits."""
        return 1 << self.spec.adc_bits

    @property
    def counts_per_volt(self) -> float:
        """ADC counts per volt of load-cell output (before the divider) [1/V]."""
        s = self.spec
        return s.divider_ratio / s.adc_reference_v * self.full_counts

    @property
    def zero_counts(self) -> float:
        """Counts at zero force (fractional: the ideal transfer function) [counts]."""
        s = self.spec
        return s.supply_v * s.zero_fraction * self.counts_per_volt

    @property
    def newton_per_count(self) -> float:
        """Force per ADC count [N/count]."""
        s = self.spec
        return s.range_n / (s.supply_v * s.span_fraction * self.counts_per_volt)

    @property
    def span_un_per_count(self) -> int:
        """Span as the protocol's GET_INFO reports it [uN/count], rounded."""
        return round(self.newton_per_count * 1e6)

    def ideal_counts(self, force_n: ArrayLike) -> NDArray[np.float64]:
        """Unquantised ADC reading for ``force_n`` [N] (not clipped) [counts]."""
        f = np.asarray(force_n, dtype=np.float64)
        result: NDArray[np.float64] = self.zero_counts + f / self.newton_per_count
        return result

    def counts(self, force_n: ArrayLike) -> NDArray[np.int64]:
        """Quantised (rounded) and clipped ADC codes for ``force_n`` [N]."""
        c = np.rint(self.ideal_counts(force_n))
        return np.clip(c, 0, self.full_counts - 1).astype(np.int64)

    def force_n(self, counts: ArrayLike) -> NDArray[np.float64]:
        """The host's conversion of ADC codes back to force [N]."""
        c = np.asarray(counts, dtype=np.float64)
        result: NDArray[np.float64] = (c - self.zero_counts) * self.newton_per_count
        return result

    def saturated(self, counts: ArrayLike) -> NDArray[np.bool_]:
        """Whether each code is at an end of the ADC range (force outside the range)."""
        c = np.asarray(counts)
        result: NDArray[np.bool_] = (c <= 0) | (c >= self.full_counts - 1)
        return result
