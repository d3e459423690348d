"""Effect ``ble_link``: the BLE link loses and delays the load-cell sample batches.

Owns the link model between the probe's ``SAMPLES`` frames and the host. Samples are
grouped as the firmware sends them: consecutive indices in batches of ``batch_size``
(sample i in batch i // batch_size), a batch being ready when its last sample is taken.

* Loss, per batch: independent with ``loss_probability``, or bursty with ``burst``, a
  Gilbert-Elliott chain over batches (good -> bad with ``p_good_to_bad``, bad -> good with
  ``p_bad_to_good``; a batch is lost with ``loss_good`` or ``loss_bad`` in that state;
  the first batch's state is drawn from the chain's stationary distribution). A lost
  batch loses all its samples; :attr:`stipi_daemon.sim.ForceBatch.lost_index` lists them.
* Delay: notifications leave at connection events, every ``connection_interval_s`` from
  an anchor drawn uniformly in [0, interval) once per run. A batch goes at the first event
  at or after it is ready (so the wait is uniform in [0, interval)), plus
  floor(X / interval) further events with X ~ Exp(``retry_mean_s``) (radio retries: an
  exponential tail quantised to connection intervals), plus ``host_latency_s`` (the host's
  stack). Notifications arrive in order: a delivered batch never arrives before the one
  delivered before it. A lost batch's time is when it would have arrived, unordered.

The host receive time of every delivered sample (that of its batch) is
:attr:`stipi_daemon.sim.ForceBatch.t_host_s`; :meth:`Effect.schedule` gives the
per-batch view. Per-event throughput is not limited (39 bytes per 10-sample batch is far
below what one connection event carries). Forces and true times are not changed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, SampleClockEffect

__all__ = ["BurstLoss", "Effect", "LinkSchedule", "Params"]


class BurstLoss(BaseModel):
    """Gilbert-Elliott loss over batches: transition probabilities per batch [-] and the
    loss probability in each state [-]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    p_good_to_bad: float = Field(default=0.01, gt=0.0, le=1.0)
    p_bad_to_good: float = Field(default=0.3, gt=0.0, le=1.0)
    loss_good: float = Field(default=0.0, ge=0.0, le=1.0)
    loss_bad: float = Field(default=0.8, ge=0.0, le=1.0)

    @property
    def stationary_bad(self) -> float:
        """Long-run fraction of batches sent in the bad state [-]."""
        return self.p_good_to_bad / (self.p_good_to_bad + self.p_bad_to_good)

    @property
    def mean_loss(self) -> float:
        """Long-run fraction of batches lost [-]."""
        b = self.stationary_bad
        return (1.0 - b) * self.loss_good + b * self.loss_bad


class Params(EffectParams):
    """Batching (``batch_size`` samples), loss (``loss_probability`` [-] per batch or
    ``burst``) and delay (``connection_interval_s``, ``retry_mean_s``, ``host_latency_s`` [s])."""

    name: Literal["ble_link"] = "ble_link"
    batch_size: int = Field(default=10, ge=1, le=24)
    loss_probability: float = Field(default=0.01, ge=0.0, lt=1.0)
    burst: BurstLoss | None = None
    connection_interval_s: float = Field(default=0.03, ge=0.0075, le=4.0)
    retry_mean_s: float = Field(default=0.01, ge=0.0, le=10.0)
    host_latency_s: float = Field(default=0.002, ge=0.0, le=1.0)

    @model_validator(mode="after")
    def _one_loss_model(self) -> Params:
        if self.burst is not None and "loss_probability" in self.model_fields_set:
            raise ValueError("give either loss_probability or burst, not both")
        return self


@dataclass(frozen=True)
class LinkSchedule:
    """What the link did with each batch.

    Attributes
    ----------
    first_index : numpy.ndarray
        Index of each batch's first sample (int64).
    count : numpy.ndarray
        Samples in each batch (int64; the last batch may be short).
    ready_s : numpy.ndarray
        When each batch was ready to send: its last sample's time [s].
    lost : numpy.ndarray
        Whether each batch was lost (bool).
    arrival_s : numpy.ndarray
        Host receive time of each batch [s] (lost ones: when they would have arrived).
    """

    first_index: NDArray[np.int64]
    count: NDArray[np.int64]
    ready_s: NDArray[np.float64]
    lost: NDArray[np.bool_]
    arrival_s: NDArray[np.float64]


class Effect(SampleClockEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params

    def _batches(self, index: NDArray[np.int64]) -> NDArray[np.int64]:
        out: NDArray[np.int64] = index // self.params.batch_size
        return out

    def losses(self, n_batches: int, rng: np.random.Generator) -> NDArray[np.bool_]:
        """Which of ``n_batches`` consecutive batches are lost."""
        p = self.params
        u = rng.random(n_batches)
        if p.burst is None:
            lost: NDArray[np.bool_] = u < p.loss_probability
            return lost
        ge = p.burst
        flip = rng.random(n_batches)
        bad = bool(rng.random() < ge.stationary_bad)
        out = np.empty(n_batches, dtype=np.bool_)
        for b in range(n_batches):
            out[b] = u[b] < (ge.loss_bad if bad else ge.loss_good)
            bad = flip[b] >= ge.p_bad_to_good if bad else flip[b] < ge.p_good_to_bad
        return out

    def arrivals(
        self, ready_s: NDArray[np.float64], lost: NDArray[np.bool_], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        """Host receive times [s] of batches ready at ``ready_s`` [s] (sorted)."""
        p = self.params
        ci = p.connection_interval_s
        anchor = rng.uniform(0.0, ci)
        event = np.ceil((ready_s - anchor) / ci - 1e-9)
        if p.retry_mean_s > 0.0:
            event += np.floor(rng.exponential(p.retry_mean_s, size=ready_s.shape) / ci)
        arrival: NDArray[np.float64] = anchor + event * ci + p.host_latency_s
        kept = ~lost
        arrival[kept] = np.maximum.accumulate(arrival[kept]) if kept.any() else arrival[kept]
        return arrival

    def schedule(
        self, index: NDArray[np.int64], t_ready_s: NDArray[np.float64], rng: np.random.Generator
    ) -> LinkSchedule:
        """Batches, losses and arrival times of the samples ``index`` (0, 1, 2, ...) taken
        at ``t_ready_s`` [s]; draws the losses, then the delays, from ``rng``."""
        batch = self._batches(index)
        n_b = int(batch[-1]) + 1 if batch.size else 0
        first = np.arange(n_b, dtype=np.int64) * self.params.batch_size
        count = np.bincount(batch, minlength=n_b).astype(np.int64)
        last = np.minimum(first + count - 1, index.size - 1)
        ready = t_ready_s[last]
        lost = self.losses(n_b, rng)
        return LinkSchedule(first, count, ready, lost, self.arrivals(ready, lost, rng))

    def delivered(self, index: NDArray[np.int64], rng: np.random.Generator) -> NDArray[np.bool_]:
        batch = self._batches(index)
        n_b = int(batch[-1]) + 1 if batch.size else 0
        kept: NDArray[np.bool_] = ~self.losses(n_b, rng)[batch]
        return kept

    def host_time_s(
        self,
        index: NDArray[np.int64],
        t_host_s: NDArray[np.float64],
        delivered: NDArray[np.bool_],
        rng: np.random.Generator,
    ) -> NDArray[np.float64]:
        batch = self._batches(index)
        n_b = int(batch[-1]) + 1 if batch.size else 0
        last = np.minimum((np.arange(n_b) + 1) * self.params.batch_size - 1, index.size - 1)
        # A batch counts as lost for the ordering when none of its samples got through.
        lost = ~np.bincount(batch, weights=delivered, minlength=n_b).astype(np.bool_)
        arrival = self.arrivals(t_host_s[last], lost, rng)
        out: NDArray[np.float64] = arrival[batch]
        return out
