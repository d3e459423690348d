"""Model selection: AICc, QAICc, Akaike weights and the Kelvin-Voigt rejection rule.

For Gaussian residuals the maximised log-likelihood of a least-squares fit with residual sum
of squares RSS on n samples is -n/2 ln(RSS/n) + const, so (Hurvich & Tsai 1989; Burnham &
Anderson 2002, Eq. 2.2 and Sec. 2.4)

    AICc = n ln(RSS/n) + 2k + 2k(k + 1)/(n - k - 1)

where k counts the curve's parameters **and the noise variance** (Kelvin-Voigt k = 4,
two time constants k = 6, power law k = 5). It needs n >= k + 2. Akaike weights are
w_i = exp(-Delta_i/2) / sum_j exp(-Delta_j/2), Delta_i = AICc_i - min AICc.

RSS floor: an RMS residual below 1e-6 of the series' range counts as 1e-6 of it (a fit
better than 1 ppm of the range is a tie; S_k itself is counted in whole pixels), so
noiseless curves compare by their parameter counts instead of by rounding errors.

Why the decision uses QAICc. AICc assumes independent residuals; a 60 fps series' are
autocorrelated, which inflates the log-likelihood ratio between nested models by about
the ratio c of the residuals' long-run variance to their variance (an AR(1) noise with
lag-1 correlation 0.8 gives c ~ 9), so plain AICc would "reject" Kelvin-Voigt on a
Kelvin-Voigt tissue whenever the noise is correlated. Burnham & Anderson's quasi-likelihood
form (2002, Sec. 6.2) divides the log-likelihood term by c:

    QAICc = n ln(RSS/n) / c + 2K + 2K(K + 1)/(n - K - 1),  K = k + 1

(the +1 counts c). c is estimated from the residuals of the model with the smallest RSS
(the best-fitting, as B&A estimate it from the global model) by the flat-top kernel of
:func:`.bootstrap.block_length`, and is at least 1.

Rejection rule: Kelvin-Voigt is rejected when its QAICc exceeds the best model's by more
than :data:`KV_REJECTION_DELTA` = 10, i.e. an evidence ratio of the best model over
Kelvin-Voigt above e^5 ~ 148 (Burnham & Anderson 2002, Sec. 2.6: Delta > 10 means
essentially no support).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = [
    "KV_REJECTION_DELTA",
    "RMS_FLOOR",
    "aicc",
    "akaike_weights",
    "floored_rss",
    "qaicc",
]

#: QAICc difference above which Kelvin-Voigt is rejected (evidence ratio e^5) [-].
KV_REJECTION_DELTA = 10.0
#: RMS residual floor as a fraction of the series' range [-].
RMS_FLOOR = 1e-6


def floored_rss(rss: float, n: int, y_span: float) -> float:
    """RSS with the RMS floor applied (module docstring), > 0 for a non-constant series."""
    return max(rss, n * (RMS_FLOOR * y_span) ** 2)


def aicc(rss: float, n: int, k: int) -> float | None:
    """AICc = n ln(RSS/n) + 2k + 2k(k+1)/(n-k-1); None when n < k + 2 or RSS <= 0."""
    return qaicc(rss, n, k, 1.0, extra_parameters=0)


def qaicc(
    rss: float, n: int, k: int, inflation: float, *, extra_parameters: int = 1
) -> float | None:
    """QAICc with variance inflation c; K = k + ``extra_parameters``. None when undefined."""
    big_k = k + extra_parameters
    if n - big_k - 1 <= 0 or not (rss > 0.0 and math.isfinite(rss)) or not inflation >= 1.0:
        return None
    return n * math.log(rss / n) / inflation + 2 * big_k + 2 * big_k * (big_k + 1) / (n - big_k - 1)


def akaike_weights(values: Sequence[float | None]) -> list[float | None]:
    """Akaike weights of (Q)AICc values; None stays None (the model takes no part)."""
    finite = [v for v in values if v is not None]
    if not finite:
        return [None for _ in values]
    best = min(finite)
    rel = [None if v is None else math.exp(-0.5 * (v - best)) for v in values]
    total = sum(r for r in rel if r is not None)
    return [None if r is None else r / total for r in rel]
