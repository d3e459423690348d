"""Kelvin-Voigt recovery: a single exponential, the paper's VPR model (Eqs. 9-10).

Constitutive law (Eq. 9): sigma = E eps + eta eps'. Free recovery from the pit (sigma = 0
after T_0) gives Eq. (10), D(t) = D_p exp(-t / tau) with tau = eta / E, so the fraction of
the recovery still ahead is

    remaining(t) = exp(-t / tau_s)

Under the probe the recovering tissue presses the indenter into the PDMS tip (a spring
k_p in parallel with the tissue's k = pi^2 R E / 3): c D' + (k + k_p) D = const, which is
again a single exponential with tau_r = tau k / (k + k_p) (:func:`recovery_time_constant_s`;
a scene's legacy ``tissue`` form, grade or E with tau/eta, is this model with that tau_r).
The model's ``tau_s`` is the time constant of the recovery the probe sees.

Paper's quantities: T_r (98 % rule) = tau ln((S_inf - S_0)/(S_inf - 0.98 S_max)), about
3.9 tau; the effective tau is tau itself; eta = E T_r (Eq. 8), while the tissue's eta is
E tau (the paper's Eq. 10 with eta from Eq. 8 decays at 1/T_r, not 1/tau).

Source: Y. C. Fung, Biomechanics: Mechanical Properties of Living Tissues, 2nd ed.
(Springer, 1993), Sec. 2.11 (Kelvin/Voigt model); W. N. Findley, J. S. Lai, K. Onaran,
Creep and Relaxation of Nonlinear Viscoelastic Materials (North-Holland, 1976), Ch. 5;
the paper's Eqs. (9)-(10).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.sim.tissue.base import FloatArray, RecoveryModel, as_times, time_parameter

__all__ = ["KelvinVoigt", "recovery_time_constant_s"]


def recovery_time_constant_s(
    tissue_tau_s: float, stiffness_n_per_mm: float, tip_stiffness_n_per_mm: float
) -> float:
    """Time constant of the recovery under the tip, tau k / (k + k_p) [s]."""
    k, kp = stiffness_n_per_mm, tip_stiffness_n_per_mm
    return tissue_tau_s * k / (k + kp)


class KelvinVoigt(RecoveryModel):
    """Single-exponential recovery, remaining(t) = exp(-t / tau_s)."""

    NAME = "kelvin_voigt"
    TITLE = "Kelvin-Voigt (single exponential)"
    EQUATION = "remaining(t) = exp(-t / tau_s)"
    SOURCE = (
        "Fung, Biomechanics (2nd ed., Springer 1993), Sec. 2.11; Findley, Lai & Onaran, "
        "Creep and Relaxation of Nonlinear Viscoelastic Materials (1976), Ch. 5; "
        "the paper's Eqs. (9)-(10)"
    )
    PARAMETERS = (time_parameter("tau_s", "time constant of the recovery under the probe"),)

    @property
    def tau_s(self) -> float:
        """tau [s]."""
        return self.parameters["tau_s"]

    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """exp(-t / tau) [-] (the physics' historical expression, bit for bit)."""
        dt = as_times(t_s)
        with np.errstate(under="ignore", over="ignore"):
            result: FloatArray = np.exp(-(dt / self.tau_s))
        return result

    def time_scale_s(self) -> float:
        """tau [s]."""
        return self.tau_s

    def time_to_recover(self, fraction: float) -> float:
        """-tau ln(1 - fraction) [s] (closed form)."""
        if not (math.isfinite(fraction) and 0.0 <= fraction < 1.0):
            return super().time_to_recover(fraction)  # raises the common error
        return -self.tau_s * math.log1p(-fraction)

    def settling_time_s(self, start: float, end: float, level: float) -> float:
        """tau ln((end - start)/(end - level)) [s] (the ground truth's historical form)."""
        return self.tau_s * math.log((end - start) / (end - level))

    def effective_time_constant_s(self) -> float:
        """tau [s] exactly."""
        return self.tau_s
