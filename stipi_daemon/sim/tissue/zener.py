"""Standard linear solid (Zener): an instantaneous elastic recovery, then one exponential.

Constitutive law in Fung's standard form (Biomechanics, Sec. 2.11, Eq. 2.11:3):

    sigma + tau_epsilon sigma' = E_R (eps + tau_sigma eps')

with E_R the relaxed modulus, tau_epsilon the relaxation time under constant strain and
tau_sigma the retardation time under constant stress (tau_epsilon < tau_sigma for a
solid). Removing a stress sigma_0 held to equilibrium (eps = sigma_0 / E_R) makes the
strain jump by tau_epsilon / tau_sigma of its value (integrate the law across the step),
after which eps + tau_sigma eps' = 0. Hence

    remaining(0) = 1,  remaining(t) = (1 - tau_epsilon / tau_sigma) exp(-t / tau_sigma), t > 0

Parameters are those of the recovery the probe sees (tissue and tip together; base
module). Kelvin-Voigt is the limit tau_epsilon_s = 0 (no instantaneous part), with
tau = tau_sigma_s. The jump falls between the T_0 frame (which still shows the pit, S_0)
and the next frame.

Paper's quantities: T_r (98 % rule) = tau_sigma ln((1 - f)/(1 - x)) with
f = tau_epsilon / tau_sigma and x the fraction of the recovery that 98 % of S_max means,
0 when the jump covers it; effective tau = tau_sigma (1 + ln(1 - f)), 0 when f >= 1 - 1/e;
eta = E T_r (Eq. 8).

Source: Y. C. Fung, Biomechanics: Mechanical Properties of Living Tissues, 2nd ed.
(Springer, 1993), Sec. 2.11 (standard linear solid); W. N. Findley, J. S. Lai,
K. Onaran, Creep and Relaxation of Nonlinear Viscoelastic Materials (North-Holland,
1976), Sec. 5.3 (three-parameter solid), creep recovery.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.tissue.base import (
    MAX_TIME_S,
    FloatArray,
    Parameter,
    RecoveryModel,
    as_times,
    time_parameter,
)

__all__ = ["Zener"]


class Zener(RecoveryModel):
    """Standard linear solid recovery: jump of tau_eps/tau_sigma, then exp(-t/tau_sigma)."""

    NAME = "zener"
    TITLE = "standard linear solid (Zener)"
    EQUATION = (
        "remaining(t) = (1 - tau_epsilon_s/tau_sigma_s) exp(-t/tau_sigma_s) for t > 0, "
        "remaining(0) = 1"
    )
    SOURCE = (
        "Fung, Biomechanics (2nd ed., Springer 1993), Sec. 2.11, standard linear solid; "
        "Findley, Lai & Onaran, Creep and Relaxation of Nonlinear Viscoelastic Materials "
        "(1976), Sec. 5.3"
    )
    PARAMETERS = (
        time_parameter("tau_sigma_s", "retardation time under constant stress"),
        Parameter(
            "tau_epsilon_s",
            "s",
            "relaxation time under constant strain (0: Kelvin-Voigt)",
            0.0,
            MAX_TIME_S,
        ),
    )
    JOINT_DOMAIN = "tau_epsilon_s < tau_sigma_s (a solid: the jump is less than the recovery)"

    def _check_joint(self) -> None:
        if not self.parameters["tau_epsilon_s"] < self.parameters["tau_sigma_s"]:
            raise ConfigError(
                f"{self.NAME}: tau_epsilon_s = {self.parameters['tau_epsilon_s']:g} s must be "
                f"< tau_sigma_s = {self.parameters['tau_sigma_s']:g} s"
            )

    @property
    def instant_fraction(self) -> float:
        """Fraction of the recovery done instantly at T_0, tau_epsilon / tau_sigma [-]."""
        return self.parameters["tau_epsilon_s"] / self.parameters["tau_sigma_s"]

    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """(1 - f) exp(-t / tau_sigma) for t > 0, 1 at t = 0 [-]."""
        t = as_times(t_s)
        with np.errstate(under="ignore", over="ignore"):
            decay = (1.0 - self.instant_fraction) * np.exp(-(t / self.parameters["tau_sigma_s"]))
        result: FloatArray = np.where(t > 0.0, decay, 1.0)
        return result

    def time_scale_s(self) -> float:
        """tau_sigma [s]."""
        return self.parameters["tau_sigma_s"]

    def time_to_recover(self, fraction: float) -> float:
        """tau_sigma ln((1 - f)/(1 - fraction)), 0 when the jump covers it [s]."""
        if not (math.isfinite(fraction) and 0.0 <= fraction < 1.0):
            return super().time_to_recover(fraction)
        f = self.instant_fraction
        if fraction <= f:
            return 0.0
        return self.parameters["tau_sigma_s"] * (math.log1p(-f) - math.log1p(-fraction))
