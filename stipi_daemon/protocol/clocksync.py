"""Mapping of the probe's microsecond clock onto the host's monotonic clock.

This module owns the online fit ``host_s ≈ offset_s + (1 + drift) * mcu_s`` between the
probe's unwrapped ``t_us`` (docs/protocol.md, "Timestamps and wrap-around") and the host
time at which the frame carrying it was received, and its offline replay from stored
(raw ``t_us``, host) pairs. It does not unwrap the u32 counter itself (that is
:mod:`stipi_daemon.protocol.timestamps`), read any clock, or do I/O.

Estimator. A received time is the true host time of the MCU timestamp plus a transport
delay that is never negative (serial buffering, BLE connection-event batching, radio
retries, the host's scheduler). The noise is one-sided and heavy-tailed: most frames are
late by tens of ms, a stall delivers a backlog hundreds of ms late, and the least delay
(the *floor*) itself moves by a few ms when the host gets loaded. So the line sought is
the *lower envelope* of the observations, and a mean-based fit is biased by whatever the
delays do:

* observations are bucketed by MCU time (``bucket_s``); each bucket keeps only its least
  delayed observation under the current drift (the minimum-delay filter); buckets older
  than ``window_s`` are dropped;
* the drift ``b = k - 1`` is the slope of a *low-quantile regression* line through the
  bucket minima: it minimises the check loss ``sum(rho_tau(z_i - c - b x_i))`` with
  ``tau = quantile`` (0.2), ``z = host - mcu``, so a fifth of the minima lie below it.
  Its slope follows the lower part of the delay distribution and cannot be tilted by
  whatever happens above it: a start-up burst, a loaded stretch or a stall's backlog
  (bucket minima further above the previous line than three times their median plus
  ``delay_noise_s`` are left out first) would need to fill most of the buckets. The loss,
  minimised over ``c``, is convex in ``b``: a golden-section search finds it (first within
  1000 ppm of the previous drift). A ridge prior towards zero drift (``drift_prior_ppm``
  against ``delay_noise_s``) shrinks it while the data span a few seconds, and it is
  clamped to ``±max_drift_ppm``. It is refitted when a new bucket opens;
* the offset puts the line through the least delayed bucket of the last ``anchor_s``
  under that drift (every recent observation lies on or above it), so a mapped time is
  late only by the floor delay of that window plus the drift error times at most
  ``anchor_s``.

Three other estimators were measured on observations recorded through the real links
(ProbeLink over the pty and over BLE with a 30 ms connection interval, ±5000 ppm, with
and without two CPU hogs; docs/reliability.md): a weighted least-squares line through the
bucket minima (the previous version) follows a start-up burst or a rising floor with
drift errors of 1000-3000 ppm, which the offset turns into 5-55 ms; a least-trimmed-squares
line through per-segment minima gets stuck on a biased subset after a slow start (BLE,
up to 8 ms); the pure convex-hull (linear-programming) envelope takes its slope from two
nearby hull vertices and is off by >1000 ppm after 10 s at 10 Hz. What remains is the
floor itself: delay common to every observation of the anchor window cannot be told from
the clock offset, and a floor that rises by a few ms for several seconds within the
first 10 s still tilts the drift by a few hundred ppm.

Latency common to *every* observation (a fixed minimum transport delay) cannot be told
from the clock offset; give it as ``min_latency_s`` if it is known, otherwise the mapped
times are late by it. The caller pairs each frame with the MCU time of its *last* sample
(``t_us + (count - 1) * period_us``), which was taken just before the frame was sent.

Domain and edges: ``mcu_us`` is any Python ``int`` (unwrapped, 64-bit; may be negative),
``host_s`` finite and non-decreasing. Before the second observation the model is
offset-only (drift 0); with two or more, the drift comes from the quantile fit. All
arithmetic is relative to the first observation of a segment (an integer epoch in µs and
its host time), so values near 2^40 µs and beyond lose no precision.

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
from collections.abc import Callable, Iterable
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
    quantile : float
        Quantile of the bucket minima's delays that the drift's regression line follows
        (``tau`` of the check loss).
    anchor_s : float
        The offset is set by the least delayed observation of this last span of MCU time [s].
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
    quantile: float = Field(0.2, gt=0.0, lt=1.0, allow_inf_nan=False)
    anchor_s: float = Field(10.0, gt=0.0, allow_inf_nan=False)
    max_drift_ppm: float = Field(10_000.0, ge=0.0, lt=1e6, allow_inf_nan=False)
    drift_prior_ppm: float = Field(5_000.0, gt=0.0, allow_inf_nan=False)
    delay_noise_s: float = Field(0.003, gt=0.0, allow_inf_nan=False)
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
    """Online lower-envelope fit of offset and drift (see the module docstring).

    :meth:`observe` costs about 70 µs when the observation opens a new bucket (the drift is
    refitted over at most ``window_s / bucket_s`` buckets), less otherwise.
    """

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
        self._unsorted = False
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
        if kept is not None and (y - self._k * x) >= (kept[1] - self._k * kept[0]):
            return  # not below its bucket's minimum: the envelope is unchanged
        if kept is None and idx < self._max_bucket:
            self._unsorted = True  # MCU time went back (within the reset threshold)
        self._buckets[idx] = (x, y)
        new_bucket = idx > self._max_bucket
        if new_bucket:
            self._max_bucket = idx
            oldest = idx - math.ceil(cfg.window_s / cfg.bucket_s)
            if self._unsorted or next(iter(self._buckets)) < oldest:
                keys = sorted(i for i in self._buckets if i >= oldest)
                self._buckets = {i: self._buckets[i] for i in keys}
                self._unsorted = False
        buckets = list(self._buckets.values())
        if self._unsorted:
            buckets.sort()
        pts = np.array(buckets, dtype=np.float64)
        bx, by = pts[:, 0], pts[:, 1]
        if new_bucket or len(buckets) <= 3:
            self._k = 1.0 + self._fit_drift(bx, by)
        recent = bx >= bx[-1] - cfg.anchor_s
        self._a = float(np.min(by[recent] - self._k * bx[recent]))

    def _fit_drift(self, x: np.ndarray, y: np.ndarray) -> float:
        """Drift of the ``quantile`` regression line through the bucket minima (x, y) [s]."""
        cfg = self.config
        z = y - x  # host - mcu = offset + drift * x + delay [s]
        if x.size >= 3:
            # backlogs (a stall's late frames) are left out: far above the previous line
            r = y - (self._a + self._k * x)
            keep = r <= 3.0 * float(np.median(r)) + cfg.delay_noise_s
            if int(keep.sum()) >= 2:
                x, z = x[keep], z[keep]
        n = x.size
        dx = x - x.mean()
        sxx = float(dx @ dx)
        if n < 2 or sxx <= 0.0:
            return self._k - 1.0
        tau = cfg.quantile
        j = min(n - 1, int(tau * n))

        def loss(b: float) -> float:
            # check loss of the best intercept (the tau-quantile of the residuals) [s]
            d = z - b * x
            d -= np.partition(d, j)[j]
            return tau * float(d.sum()) - float(d[d < 0.0].sum())

        # The loss is convex in the drift: golden-section search, first within 1000 ppm of
        # the previous drift, over twice the clamp if the minimum is at that bracket's edge.
        lim = cfg.max_drift_ppm * 1e-6
        wide = min(2.0 * lim, 0.5)
        b_prev = self._k - 1.0
        b = _golden_min(loss, max(b_prev - 1e-3, -wide), min(b_prev + 1e-3, wide))
        if abs(b - b_prev) > 1e-3 - 1e-5:
            b = _golden_min(loss, -wide, wide)
        # ridge prior on the drift: shrink by sxx / (sxx + (noise / prior)^2) [s^2]
        lam = (cfg.delay_noise_s / (cfg.drift_prior_ppm * 1e-6)) ** 2
        return min(max(b * sxx / (sxx + lam), -lim), lim)

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


def _golden_min(f: Callable[[float], float], lo: float, hi: float, tol: float = 4e-6) -> float:
    """Minimiser of the convex function ``f`` on [lo, hi], to within ``tol``."""
    g = 0.5 * (3.0 - math.sqrt(5.0))
    m1, m2 = lo + g * (hi - lo), hi - g * (hi - lo)
    f1, f2 = f(m1), f(m2)
    while hi - lo > tol:
        if f1 <= f2:
            hi, m2, f2 = m2, m1, f1
            m1 = lo + g * (hi - lo)
            f1 = f(m1)
        else:
            lo, m1, f1 = m1, m2, f2
            m2 = hi - g * (hi - lo)
            f2 = f(m2)
    return 0.5 * (lo + hi)


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
