"""Mapping of the probe's microsecond clock onto the host's monotonic clock.

This module owns the online fit ``host_s ≈ offset_s + (1 + drift) * mcu_s`` between the
probe's unwrapped ``t_us`` (docs/protocol.md, "Timestamps and wrap-around") and the host
time at which the frame carrying it was received, and its offline replay from stored
(raw ``t_us``, host) pairs. It does not unwrap the u32 counter itself (that is
:mod:`stipi_daemon.protocol.timestamps`), read any clock, or do I/O.

Estimator. A received time is the true host time of the MCU timestamp plus a transport
delay that is never negative (BLE connection-event batching, radio retries, the host's
scheduler), so the fitted line is a *lower envelope* of the observations:

* observations are bucketed by MCU time (``bucket_s``); each bucket keeps only its least
  delayed observation under the current slope (the minimum-delay filter);
* the drift ``b = k - 1`` is the slope of a weighted least-squares line through those
  bucket minima, refitted on the lower half of their residuals (the points nearest the
  envelope), with exponential forgetting weights ``w_i = exp(-(x_last - x_i) /
  forgetting_s)`` so slow drift changes are followed, buckets older than ``window_s``
  dropped, a ridge prior towards zero drift (``drift_prior_ppm``, ``delay_noise_s``) that
  only matters while the data span a few seconds, and a clamp to ``±max_drift_ppm``;
* the offset puts the line through the least delayed observation of the last
  ``forgetting_s`` (every recent observation lies on or above it).

A pure convex-hull (linear-programming) envelope was tried first: with delays spread over
tens of ms its slope comes from two hull vertices and was off by >1000 ppm after 10 s at
10 Hz; the least-squares slope through many bucket minima is far steadier.

Latency common to *every* observation (a fixed minimum transport delay) cannot be told
from the clock offset; give it as ``min_latency_s`` if it is known, otherwise the mapped
times are late by it. The caller pairs each frame with the MCU time of its *last* sample
(``t_us + (count - 1) * period_us``), which was taken just before the frame was sent.

Domain and edges: ``mcu_us`` is any Python ``int`` (unwrapped, 64-bit; may be negative),
``host_s`` finite and non-decreasing. Before the second observation the model is
offset-only (drift 0); with two or more, the slope comes from the hull. All arithmetic is
relative to the first observation of a segment (an integer epoch in µs and its host time),
so values near 2^40 µs and beyond lose no precision.

MCU reset (or any jump of the MCU clock against the host clock): an observation whose
residual against the current model exceeds ``reset_threshold_s`` in magnitude is held
back, not fitted. If ``reset_confirm_n`` consecutive observations spanning at least
``reset_confirm_s`` of host time are all held back, the clock has jumped: the fit restarts
from those observations and :meth:`ClockSync.observe` returns a :class:`ClockReset`
naming the jump and the model that was valid before. A transport stall that delivers a
backlog late is not a reset: the backlog's residuals fall back under the threshold as it
drains and the held observations are dropped (counted in ``n_rejected``). The caller may
also call :meth:`ClockSync.reset` when it knows the probe restarted (e.g. ``first_index``
going backwards).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from stipi_daemon.protocol.timestamps import TimestampUnwrapper

__all__ = [
    "ClockModel",
    "ClockReset",
    "ClockSync",
    "ClockSyncConfig",
    "ResidualStats",
    "fit_offline",
    "fit_offline_segments",
]

_US = 1e-6


class ClockSyncConfig(BaseModel):
    """Parameters of the lower-envelope clock fit; immutable.

    Parameters
    ----------
    bucket_s : float
        Width of the MCU-time buckets; one observation (least delayed) is kept per bucket [s].
    window_s : float
        Observations older than this (MCU time, before the latest) are forgotten [s].
    forgetting_s : float
        Time constant of the exponential weights that place the evaluation point [s].
    max_drift_ppm : float
        Largest |drift| the fit may report [ppm]; the estimate is clamped to it.
    drift_prior_ppm : float
        Prior spread of the drift around 0 [ppm] (resonator spec 0.5 % = 5000 ppm).
    delay_noise_s : float
        Typical spread of the per-bucket minimum delays [s]; with ``drift_prior_ppm`` it
        sets how much MCU-time span the data need before they outweigh the prior.
    min_latency_s : float
        Known latency common to every observation, subtracted from host times [s].
    reset_threshold_s : float
        |residual| above which an observation is held back as a possible clock jump [s].
    reset_confirm_n : int
        Consecutive held-back observations that confirm a jump.
    reset_confirm_s : float
        Host time the held-back observations must span to confirm a jump [s].
    residual_history : int
        Number of recent observations kept for :attr:`ClockSync.residual_stats`.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    bucket_s: float = Field(0.25, gt=0.0, allow_inf_nan=False)
    window_s: float = Field(120.0, gt=0.0, allow_inf_nan=False)
    forgetting_s: float = Field(30.0, gt=0.0, allow_inf_nan=False)
    max_drift_ppm: float = Field(10_000.0, ge=0.0, lt=1e6, allow_inf_nan=False)
    drift_prior_ppm: float = Field(5_000.0, gt=0.0, allow_inf_nan=False)
    delay_noise_s: float = Field(0.005, gt=0.0, allow_inf_nan=False)
    min_latency_s: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    reset_threshold_s: float = Field(0.5, gt=0.0, allow_inf_nan=False)
    reset_confirm_n: int = Field(3, ge=1)
    reset_confirm_s: float = Field(1.0, ge=0.0, allow_inf_nan=False)
    residual_history: int = Field(1000, ge=1)


class ClockModel(BaseModel):
    """Snapshot of a clock fit (``k = 1 + drift_ppm * 1e-6``).

    ``host_s = epoch_host_s + intercept_s + k * (mcu_us - epoch_mcu_us) * 1e-6``.

    Serialisable (``model_dump_json``) so that a session file can store it and the
    alignment can be checked or redone offline.

    Parameters
    ----------
    epoch_mcu_us : int
        Reference MCU time (first observation of the segment) [µs].
    epoch_host_s : float
        Host time received with ``epoch_mcu_us`` (minus ``min_latency_s``) [s].
    intercept_s : float
        Fitted host time at ``epoch_mcu_us``, relative to ``epoch_host_s`` [s] (<= 0).
    drift_ppm : float
        Fitted drift: MCU clock slow (+) or fast (-) against the host [ppm].
    n_observations : int
        Observations fitted in this segment.
    first_mcu_us, last_mcu_us : int
        MCU time span of the fitted observations [µs].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    epoch_mcu_us: int
    epoch_host_s: float = Field(allow_inf_nan=False)
    intercept_s: float = Field(allow_inf_nan=False)
    drift_ppm: float = Field(allow_inf_nan=False)
    n_observations: int = Field(ge=0)
    first_mcu_us: int
    last_mcu_us: int

    @property
    def offset_s(self) -> float:
        """``offset_s`` of ``host_s = offset_s + (1 + drift) * mcu_us * 1e-6`` [s]."""
        k = 1.0 + self.drift_ppm * 1e-6
        return self.epoch_host_s + self.intercept_s - k * (self.epoch_mcu_us * _US)

    def to_host(self, mcu_us: int) -> float:
        """Host time [s] of the unwrapped MCU time ``mcu_us`` [µs]."""
        k = 1.0 + self.drift_ppm * 1e-6
        return self.epoch_host_s + (
            self.intercept_s + k * ((int(mcu_us) - self.epoch_mcu_us) * _US)
        )


@dataclass(frozen=True, slots=True)
class ClockReset:
    """A jump of the MCU clock against the host clock was confirmed and the fit restarted.

    Parameters
    ----------
    host_s : float
        Host time of the first held-back observation (when the jump was first seen) [s].
    mcu_us : int
        Its MCU time [µs].
    jump_s : float
        Median residual of the held-back observations against the old model [s]
        (positive: the MCU clock went back, e.g. a reboot).
    previous : ClockModel
        The model that was valid before the jump.
    """

    host_s: float
    mcu_us: int
    jump_s: float
    previous: ClockModel


@dataclass(frozen=True, slots=True)
class ResidualStats:
    """Delays of recent observations above the fitted line [s] (the transport latency)."""

    n: int
    min_s: float
    median_s: float
    p95_s: float
    max_s: float


class ClockSync:
    """Online lower-envelope fit of offset and drift (see the module docstring)."""

    def __init__(self, config: ClockSyncConfig | None = None) -> None:
        self.config = config if config is not None else ClockSyncConfig()
        self._resets: list[ClockReset] = []
        self._n_rejected = 0
        self._last_host_s = -math.inf
        self._start_segment()

    # ---------------------------------------------------------------- state

    def _start_segment(self) -> None:
        self._epoch_mcu_us: int | None = None
        self._epoch_host_s = 0.0
        self._a = 0.0
        self._k = 1.0
        self._n = 0
        self._first_mcu_us = 0
        self._last_mcu_us = 0
        self._buckets: dict[int, tuple[float, float]] = {}
        self._max_bucket = -(1 << 62)
        self._recent: deque[tuple[float, float]] = deque(maxlen=self.config.residual_history)
        self._held: list[tuple[int, float, float]] = []

    # ---------------------------------------------------------------- public API

    def observe(self, mcu_us: int, host_s: float) -> ClockReset | None:
        """Add one observation.

        Parameters
        ----------
        mcu_us : int
            Unwrapped MCU time of the frame's content [µs].
        host_s : float
            Host monotonic time at which the frame was received [s]; finite, and not
            earlier than the previous observation's.

        Returns
        -------
        ClockReset or None
            A :class:`ClockReset` when this observation confirms a clock jump, else None.

        Raises
        ------
        ValueError
            If ``mcu_us`` is not an int, ``host_s`` is not finite, or ``host_s`` goes back.
        """
        if isinstance(mcu_us, bool) or not isinstance(mcu_us, int | np.integer):
            raise ValueError(f"mcu_us must be an int (unwrapped µs), got {mcu_us!r}")
        if not math.isfinite(host_s):
            raise ValueError(f"host_s must be finite, got {host_s!r}")
        if host_s < self._last_host_s:
            raise ValueError(
                f"host_s went back from {self._last_host_s!r} to {host_s!r}: receive times "
                "must come from a monotonic clock, in arrival order"
            )
        self._last_host_s = host_s
        mcu_us = int(mcu_us)
        y_host = host_s - self.config.min_latency_s
        if self._epoch_mcu_us is None:
            self._epoch_mcu_us, self._epoch_host_s = mcu_us, y_host
            self._first_mcu_us = self._last_mcu_us = mcu_us
            self._add(0.0, 0.0)
            return None
        x = (mcu_us - self._epoch_mcu_us) * _US
        y = y_host - self._epoch_host_s
        residual = y - (self._a + self._k * x)
        if abs(residual) > self.config.reset_threshold_s:
            self._held.append((mcu_us, host_s, residual))
            span_s = self._held[-1][1] - self._held[0][1]
            if len(self._held) >= self.config.reset_confirm_n and (
                span_s >= self.config.reset_confirm_s
            ):
                return self._confirm_reset()
            return None
        if self._held:
            self._n_rejected += len(self._held)
            self._held = []
        self._first_mcu_us = min(self._first_mcu_us, mcu_us)
        self._last_mcu_us = max(self._last_mcu_us, mcu_us)
        self._add(x, y)
        return None

    def reset(self) -> None:
        """Forget the current segment (the caller knows the probe restarted)."""
        self._n_rejected += len(self._held)
        self._start_segment()

    def to_host(self, mcu_us: int) -> float:
        """Host time [s] of the unwrapped MCU time ``mcu_us`` [µs] under the current fit.

        Raises
        ------
        ValueError
            Before the first observation (nothing to map with).
        """
        if self._epoch_mcu_us is None:
            raise ValueError("ClockSync.to_host called before any observation")
        return self._epoch_host_s + (self._a + self._k * ((int(mcu_us) - self._epoch_mcu_us) * _US))

    @property
    def model(self) -> ClockModel:
        """Frozen snapshot of the current fit.

        Raises
        ------
        ValueError
            Before the first observation.
        """
        if self._epoch_mcu_us is None:
            raise ValueError("ClockSync.model requested before any observation")
        return ClockModel(
            epoch_mcu_us=self._epoch_mcu_us,
            epoch_host_s=self._epoch_host_s,
            intercept_s=self._a,
            drift_ppm=(self._k - 1.0) * 1e6,
            n_observations=self._n,
            first_mcu_us=self._first_mcu_us,
            last_mcu_us=self._last_mcu_us,
        )

    @property
    def offset_s(self) -> float:
        """``offset_s`` of ``host_s = offset_s + (1 + drift) * mcu_us * 1e-6`` [s]."""
        return self.model.offset_s

    @property
    def drift_ppm(self) -> float:
        """Fitted drift [ppm]; 0 before the second observation."""
        return (self._k - 1.0) * 1e6

    @property
    def n_observations(self) -> int:
        """Observations fitted in the current segment."""
        return self._n

    @property
    def n_rejected(self) -> int:
        """Observations held back as possible jumps and then dropped (stall backlogs)."""
        return self._n_rejected

    @property
    def resets(self) -> tuple[ClockReset, ...]:
        """Every confirmed clock jump, oldest first."""
        return tuple(self._resets)

    @property
    def residual_stats(self) -> ResidualStats | None:
        """Delays of the last ``residual_history`` fitted observations above the line.

        ``min_s`` is about 0 (the line is their lower envelope); ``median_s`` and ``p95_s``
        describe the transport latency. None before the first observation.
        """
        if not self._recent:
            return None
        xy = np.asarray(self._recent, dtype=np.float64)
        r = xy[:, 1] - (self._a + self._k * xy[:, 0])
        q50, q95 = np.quantile(r, [0.5, 0.95])
        return ResidualStats(
            n=int(r.size),
            min_s=float(r.min()),
            median_s=float(q50),
            p95_s=float(q95),
            max_s=float(r.max()),
        )

    # ---------------------------------------------------------------- fitting

    def _add(self, x: float, y: float) -> None:
        self._n += 1
        self._recent.append((x, y))
        cfg = self.config
        idx = math.floor(x / cfg.bucket_s)
        kept = self._buckets.get(idx)
        changed = kept is None or (y - self._k * x) < (kept[1] - self._k * kept[0])
        if changed:
            self._buckets[idx] = (x, y)
        if idx > self._max_bucket:
            self._max_bucket = idx
            oldest = idx - math.ceil(cfg.window_s / cfg.bucket_s)
            for old in [i for i in self._buckets if i < oldest]:
                del self._buckets[old]
                changed = True
        if changed:
            self._refit()

    def _refit(self) -> None:
        cfg = self.config
        pts = np.array([self._buckets[i] for i in sorted(self._buckets)], dtype=np.float64)
        x, y = pts[:, 0], pts[:, 1]
        x_last = float(x[-1])
        w = np.exp(-(x_last - x) / cfg.forgetting_s)
        z = y - x  # host - mcu: the delay plus offset and drift * x
        # ridge prior on the drift: lam = (noise / prior)^2 in the units of sum(w dx^2) [s^2]
        lam = (cfg.delay_noise_s / (cfg.drift_prior_ppm * 1e-6)) ** 2
        keep = np.ones(x.size, dtype=bool)
        b = 0.0
        for _ in range(2):
            wk, xk, zk = w[keep], x[keep], z[keep]
            sw = float(wk.sum())
            xm, zm = float(wk @ xk) / sw, float(wk @ zk) / sw
            dx = xk - xm
            b = float(wk @ (dx * (zk - zm))) / (float(wk @ (dx * dx)) + lam)
            if x.size < 4:
                break
            # second pass on the lower half of the bucket minima (closest to the envelope)
            r = z - (zm + b * (x - xm))
            keep = r <= np.median(r)
        lim = cfg.max_drift_ppm * 1e-6
        b = min(max(b, -lim), lim)
        k = 1.0 + b
        recent = x >= x_last - cfg.forgetting_s
        self._k = k
        self._a = float(np.min(y[recent] - k * x[recent]))

    def _confirm_reset(self) -> ClockReset:
        held = self._held
        previous = self.model
        jump_s = float(np.median([r for _, _, r in held]))
        event = ClockReset(host_s=held[0][1], mcu_us=held[0][0], jump_s=jump_s, previous=previous)
        self._resets.append(event)
        self._start_segment()
        last = self._last_host_s
        self._last_host_s = -math.inf
        for mcu_us, host_s, _ in held:
            self.observe(mcu_us, host_s)
        self._last_host_s = last
        return event


def _replay(
    pairs: Iterable[tuple[int, float]], config: ClockSyncConfig | None
) -> tuple[ClockSync, list[ClockModel]]:
    sync = ClockSync(config)
    unwrapper = TimestampUnwrapper()
    segments: list[ClockModel] = []
    for i, (raw_us, host_s) in enumerate(pairs):
        try:
            mcu_us = unwrapper.unwrap(int(raw_us))
            event = sync.observe(mcu_us, float(host_s))
        except ValueError as exc:
            raise ValueError(f"clock pair {i} ({raw_us!r}, {host_s!r}): {exc}") from exc
        if event is not None:
            segments.append(event.previous)
    if sync.n_observations == 0:
        raise ValueError("fit_offline needs at least one (raw t_us, host_s) pair")
    segments.append(sync.model)
    return sync, segments


def fit_offline(
    pairs: Iterable[tuple[int, float]], config: ClockSyncConfig | None = None
) -> ClockModel:
    """Redo the alignment from stored (raw u32 ``t_us`` [µs], host receive time [s]) pairs.

    The pairs are unwrapped with :class:`~stipi_daemon.protocol.timestamps.TimestampUnwrapper`
    and replayed through :class:`ClockSync`, so the result equals the online model at the
    end of the recording (with the same config). After a clock jump this is the last
    segment's model; :func:`fit_offline_segments` returns every segment.

    Raises
    ------
    ValueError
        On an empty input or a bad pair (its index is named).
    """
    return _replay(pairs, config)[1][-1]


def fit_offline_segments(
    pairs: Iterable[tuple[int, float]], config: ClockSyncConfig | None = None
) -> list[ClockModel]:
    """Like :func:`fit_offline`, but one model per segment between clock jumps, in order."""
    return _replay(pairs, config)[1]
