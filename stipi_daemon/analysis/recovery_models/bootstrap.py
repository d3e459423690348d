"""Block length, variance inflation and moving-block resampling of fit residuals.

Residuals of a recovery fitted to a 60 fps series are autocorrelated (frame-to-frame
rendering and sensor noise, LED flicker at a few hertz, hand tremor): a bootstrap that
draws residuals one by one would treat them as independent and give intervals far too
narrow. The moving-block bootstrap (Kuensch 1989) draws whole blocks of consecutive
residuals instead, keeping the dependence inside each block. This module owns

* :func:`block_length`: the block length from the residuals' own autocorrelation by the
  automatic rule of Politis & White (2004) with the correction of Patton, Politis & White
  (2009), circular/moving-block constant; computed exactly as the reference implementation
  ``arch.bootstrap.optimal_block_length`` (``circular``), which the tests compare against.
  The same flat-top-kernel estimate gives the long-run variance of the residuals, and its
  ratio to their variance is the *variance inflation* c (>= 1) that
  :mod:`.selection` uses for QAICc;
* :func:`moving_block_indices`: the resampling (seeded numpy ``Generator``), or its draws
  (:func:`moving_block_starts`) expanded a few resamples at a time (:func:`block_indices`).

Domain: at least :data:`MIN_SERIES` residuals (shorter series get block length 1 and
inflation 1: too few lags to estimate a dependence); a constant residual series (a perfect
fit) has no dependence to estimate and gets the same. No I/O, no randomness without a
caller's generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.analysis.recovery_models.base import FloatArray

__all__ = [
    "MIN_SERIES",
    "BlockLength",
    "block_indices",
    "block_length",
    "moving_block_indices",
    "moving_block_starts",
]

#: Fewest residuals for which the block length is estimated [-].
MIN_SERIES = 12


@dataclass(frozen=True)
class BlockLength:
    """The residuals' dependence as the bootstrap uses it.

    Attributes
    ----------
    optimal : float
        Politis-White optimal block length for the circular / moving-block bootstrap
        [samples] (``arch``'s ``circular``), capped at min(3 sqrt(n), n/3).
    length : int
        The block length used, ceil(optimal) clipped to [1, n // 3] (at least 1) [samples].
    lag_window : int
        M, the flat-top kernel's width [lags].
    variance_inflation : float
        Long-run variance over variance of the residuals, at least 1 [-].
    """

    optimal: float
    length: int
    lag_window: int
    variance_inflation: float


def _autocovariances(eps: FloatArray, m_max: int) -> tuple[FloatArray, FloatArray]:
    """Autocovariances (divisor n) and arch's absolute autocorrelations up to lag m_max."""
    n = eps.size
    acv = np.zeros(m_max + 1)
    acorr = np.zeros(m_max + 1)
    for i in range(m_max + 1):
        cross = float(eps[i:] @ eps[: n - i])
        v1 = float(eps[i + 1 :] @ eps[i + 1 :])
        v2 = float(eps[: n - i - 1] @ eps[: n - i - 1])
        acv[i] = cross / n
        acorr[i] = abs(cross) / math.sqrt(v1 * v2) if v1 > 0.0 and v2 > 0.0 else 0.0
    return acv, acorr


def block_length(residuals: FloatArray) -> BlockLength:
    """Block length and variance inflation of a residual series (module docstring).

    Parameters
    ----------
    residuals : ndarray, shape (n,)
        Finite residuals in time order.
    """
    x = np.asarray(residuals, dtype=np.float64)
    n = int(x.size)
    eps = x - x.mean() if n else x
    if n < MIN_SERIES or not float(eps @ eps) > 0.0:
        return BlockLength(1.0, 1, 1, 1.0)
    b_max = math.ceil(min(3.0 * math.sqrt(n), n / 3.0))
    kn = max(5, int(math.log10(n)))
    m_max = min(math.ceil(math.sqrt(n)) + kn, n - 2)
    cv = 2.0 * math.sqrt(math.log10(n) / n)
    acv, acorr = _autocovariances(eps, m_max)
    opt_m: int | None = None
    for i in range(kn, m_max + 1):
        if np.all(acorr[i - kn : i] < cv):
            opt_m = i - kn
            break
    m = 2 * max(opt_m, 1) if opt_m is not None else m_max
    m = min(m, m_max)
    k = np.arange(1, m + 1)
    lam = np.where(k / m <= 0.5, 1.0, 2.0 * (1.0 - k / m))
    g = float(np.sum(2.0 * lam * k * acv[1 : m + 1]))
    long_run = float(acv[0] + np.sum(2.0 * lam * acv[1 : m + 1]))
    if long_run > 0.0 and g != 0.0:
        d_cb = 4.0 / 3.0 * long_run**2
        optimal = min((2.0 * g * g / d_cb) ** (1.0 / 3.0) * n ** (1.0 / 3.0), float(b_max))
    else:  # no usable dependence estimate: independent draws
        optimal = 1.0
    length = int(min(max(1, math.ceil(optimal)), max(1, n // 3)))
    inflation = max(1.0, long_run / float(acv[0])) if long_run > 0.0 else 1.0
    return BlockLength(optimal, length, m, inflation)


def moving_block_starts(
    n: int, length: int, replicates: int, rng: np.random.Generator
) -> tuple[NDArray[np.int64], int]:
    """The block starts of ``replicates`` moving-block resamples of a series of ``n``
    samples, shape (replicates, ceil(n / length)), each uniform in [0, n - length], and the
    block length used (``length`` within [1, n]); :func:`block_indices` expands them."""
    length = max(1, min(length, n))
    blocks = -(-n // length)
    return rng.integers(0, n - length + 1, size=(replicates, blocks)), length


def block_indices(starts: NDArray[np.int64], length: int, n: int) -> NDArray[np.intp]:
    """Indices of the resamples with block ``starts`` (rows of :func:`moving_block_starts`):
    each concatenates its blocks of ``length`` consecutive indices, cut to ``n``. Rows can be
    expanded a few at a time: a whole bootstrap's indices (200 x n) need not exist at once."""
    idx = (starts[:, :, None] + np.arange(length)[None, None, :]).reshape(starts.shape[0], -1)
    return idx[:, :n]


def moving_block_indices(
    n: int, length: int, replicates: int, rng: np.random.Generator
) -> NDArray[np.intp]:
    """Indices of ``replicates`` moving-block resamples of a series of ``n`` samples.

    Each resample concatenates ceil(n / length) blocks of ``length`` consecutive indices,
    each starting uniformly in [0, n - length], and is cut to ``n``.
    """
    starts, length = moving_block_starts(n, length, replicates, rng)
    return block_indices(starts, length, n)
