"""Two time constants: the standard linear solid and the bi-exponential (two-term Prony) recovery.

    g(x) = weight_fast exp(-x / tau_fast_s) + (1 - weight_fast) exp(-x / tau_slow_s)

Two Kelvin-Voigt elements in series recover each on its own, so the recovery is a sum of
two exponentials (a generalised Kelvin-Voigt solid, two-term Prony series). The standard
linear solid (Zener), whose recovery jumps by tau_epsilon/tau_sigma at the release and then
decays with tau_sigma, is the limit tau_fast_s -> 0: a fast term shorter than one frame
period is a jump between the T_0 frame and the next (with tau_fast_s at its 1 ms bound,
exp(-x/tau_fast) < 6e-8 one frame of 60 fps after T_0). Kelvin-Voigt is the limit
weight_fast = 0 or 1, or tau_fast_s = tau_slow_s. Nothing divides by the difference of the
time constants, so nearly equal ones are harmless; the weight is then undetermined (the
solver keeps it where it is) but the curve, its effective tau and T_r are not.

Effective time constant (1 - 1/e recovered) and T_r: the root of g(x) = level, bracketed by
[tau_fast ln(1/level), tau_slow ln(1/level)] (each exponential alone reaches the level at
its end of the bracket), by Brent's method.

Source: W. N. Findley, J. S. Lai, K. Onaran, Creep and Relaxation of Nonlinear
Viscoelastic Materials (North-Holland, 1976), Secs. 5.3-5.4 (three-parameter solid,
generalised Kelvin model); Y. C. Fung, Biomechanics (2nd ed., Springer, 1993), Sec. 2.11
(standard linear solid); S. W. Park, R. A. Schapery, Int. J. Solids Struct. 36 (1999)
1653 (Prony series).
"""

from __future__ import annotations

import math

import numpy as np

from stipi_daemon.analysis.recovery_models.base import (
    FloatArray,
    ModelParameter,
    RecoveryModel,
    time_parameter,
)

__all__ = ["TwoExponential"]

_GRID_TAU = 29


class TwoExponential(RecoveryModel):
    """Bi-exponential recovery; the standard linear solid is its tau_fast -> 0 limit."""

    NAME = "two_exponential"
    TITLE = "standard linear solid / two time constants (bi-exponential)"
    EQUATION = (
        "g(x) = weight_fast exp(-x/tau_fast_s) + (1 - weight_fast) exp(-x/tau_slow_s); "
        "standard linear solid: tau_fast_s -> 0"
    )
    SOURCE = (
        "Findley, Lai & Onaran, Creep and Relaxation of Nonlinear Viscoelastic Materials "
        "(1976), Secs. 5.3-5.4; Fung, Biomechanics (2nd ed., 1993), Sec. 2.11; Park & "
        "Schapery, Int. J. Solids Struct. 36 (1999) 1653"
    )
    SHAPE_PARAMETERS = (
        time_parameter("tau_fast_s", "shorter retardation time (below a frame: a jump)"),
        time_parameter("tau_slow_s", "longer retardation time"),
        ModelParameter("weight_fast", "1", "share of the recovery with tau_fast_s", 0.0, 1.0),
    )
    TAU_MEANING = "root of g(x) = 1/e (1 - 1/e of the recovery done)"

    def shape(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        """g and its derivatives in (ln tau_1, ln tau_2, w)."""
        with np.errstate(under="ignore"):
            a1 = x[None, :] * np.exp(-u[:, 0])[:, None]
            a2 = x[None, :] * np.exp(-u[:, 1])[:, None]
            e1, e2 = np.exp(-a1), np.exp(-a2)
            w = u[:, 2][:, None]
            g: FloatArray = np.minimum(w * e1 + (1.0 - w) * e2, 1.0)
            dg = np.empty((*g.shape, 3))
            dg[:, :, 0] = w * e1 * a1
            dg[:, :, 1] = (1.0 - w) * e2 * a2
            dg[:, :, 2] = e1 - e2
        return g, dg

    def canonical(self, u: FloatArray) -> FloatArray:
        """Order the terms so that tau_fast <= tau_slow."""
        if u[0] <= u[1]:
            return u
        return np.array([u[1], u[0], 1.0 - u[2]])

    def nested_start(self, kelvin_voigt: FloatArray) -> FloatArray | None:
        """Both terms at the Kelvin-Voigt tau, weight 1/2: the same curve."""
        o, a, lt = (float(v) for v in kelvin_voigt)
        return np.array([o, a, lt, lt, 0.5])

    def start(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """Best pair of a log-spaced tau grid (29 values over the bounds), linear part exact.

        For each pair tau_i < tau_j, z ~ c0 + c1 exp(-x/tau_i) + c2 exp(-x/tau_j) by
        linear least squares (a 1e-12 ridge keeps coincident columns solvable); pairs
        whose c1, c2 differ in sign (a weight outside [0, 1]) are skipped. The
        single-exponential grid point (weight 1/2, both at the best one-tau grid point) is
        a candidate too, so a Kelvin-Voigt series starts where Kelvin-Voigt would.
        """
        lo, hi = self.SHAPE_PARAMETERS[0].solver_bounds
        log_tau = np.linspace(lo, hi, _GRID_TAU)
        with np.errstate(under="ignore"):
            e = np.exp(-x[None, :] / np.exp(log_tau)[:, None])  # (G, n)
        n = float(x.size)
        s, gram, ez, zz = e.sum(axis=1), e @ e.T, e @ z, float(z @ z)
        i, j = np.triu_indices(_GRID_TAU, k=1)
        m = np.empty((i.size, 3, 3))
        m[:, 0, 0] = n
        m[:, 0, 1] = m[:, 1, 0] = s[i]
        m[:, 0, 2] = m[:, 2, 0] = s[j]
        m[:, 1, 1], m[:, 2, 2] = gram[i, i], gram[j, j]
        m[:, 1, 2] = m[:, 2, 1] = gram[i, j]
        rhs = np.stack([np.full(i.size, z.sum()), ez[i], ez[j]], axis=1)
        ridge = 1e-12 * np.einsum("pii->p", m)[:, None, None] * np.eye(3)[None]
        c = np.linalg.solve(m + ridge, rhs[:, :, None])[:, :, 0]
        ssr = zz - np.einsum("pi,pi->p", c, rhs)  # normal equations: z.z - c.(X^T z)
        same_sign = c[:, 1] * c[:, 2] > 0.0
        # The one-exponential candidate from the same basis.
        z_mean = float(z.mean())
        db = e - e.mean(axis=1, keepdims=True)
        var_b = np.einsum("ij,ij->i", db, db)
        cov = db @ (z - z_mean)
        ok1 = var_b > 1e-12 * n
        slope = np.where(ok1, cov / np.where(ok1, var_b, 1.0), 0.0)
        k = int(np.argmax(np.where(ok1, slope * cov, -np.inf)))
        best_one = (float(((z - z_mean) ** 2).sum() - slope[k] * cov[k]), k)
        if same_sign.any() and float(np.min(ssr[same_sign])) < best_one[0]:
            q = int(np.flatnonzero(same_sign)[np.argmin(ssr[same_sign])])
            c0, c1, c2 = c[q]
            return np.array([c0, -(c1 + c2), log_tau[i[q]], log_tau[j[q]], c1 / (c1 + c2)])
        amp = -float(slope[k])
        offset = z_mean + amp * float(e[k].mean())
        return np.array([offset, amp, log_tau[k], log_tau[k], 0.5])

    def time_to_remaining(self, u: FloatArray, level: float) -> float:
        """Root of g(x) = level (Brent), bracketed by the two single-term roots [s]."""
        t1, t2, w = math.exp(float(u[0])), math.exp(float(u[1])), float(u[2])
        ln = -math.log(level)
        lo, hi = min(t1, t2) * ln, max(t1, t2) * ln
        if hi - lo <= 1e-12 * hi or w in (0.0, 1.0):
            return t2 * ln if w == 0.0 else (t1 * ln if w == 1.0 else lo)

        def h(xx: float) -> float:
            return w * math.exp(-xx / t1) + (1.0 - w) * math.exp(-xx / t2) - level

        if h(lo) <= 0.0:
            return lo
        if h(hi) >= 0.0:
            return hi
        from scipy.optimize import brentq  # scipy: imported where used

        return float(brentq(h, lo, hi, xtol=1e-12 * hi, rtol=1e-12))
