"""Two time constants: a generalised Kelvin-Voigt solid (two-term Prony series).

Two Kelvin-Voigt elements in series (compliances J_1, J_2, retardation times tau_1,
tau_2) have the creep compliance J(t) = sum_i J_i (1 - exp(-t / tau_i)); removing a stress
held to equilibrium, each element recovers on its own, eta_i eps_i' + E_i eps_i = 0, so

    remaining(t) = w exp(-t / tau_1_s) + (1 - w) exp(-t / tau_2_s),  w = J_1 / (J_1 + J_2)

Parameters are those of the recovery the probe sees (tissue and tip together; base
module). Kelvin-Voigt is the limit weight_1 = 1 (or 0, or tau_1_s = tau_2_s). Nearly
equal time constants need no special care: nothing divides by their difference. An
edematous tissue's fast elastic rebound and slow refilling are the two terms.

Paper's quantities: T_r (98 % rule) and the effective tau (1 - 1/e recovered) by Brent's
method on the monotone remaining(t) (no closed form); eta = E T_r (Eq. 8).

Source: W. N. Findley, J. S. Lai, K. Onaran, Creep and Relaxation of Nonlinear
Viscoelastic Materials (North-Holland, 1976), Sec. 5.4 (generalised Kelvin model);
S. W. Park, R. A. Schapery, Int. J. Solids Struct. 36 (1999) 1653-1675 (Prony series).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.sim.tissue.base import (
    FloatArray,
    Parameter,
    RecoveryModel,
    as_times,
    time_parameter,
)

__all__ = ["Prony"]


class Prony(RecoveryModel):
    """Bi-exponential recovery, w exp(-t/tau_1) + (1 - w) exp(-t/tau_2)."""

    NAME = "prony"
    TITLE = "two time constants (generalised Kelvin-Voigt, Prony series)"
    EQUATION = "remaining(t) = weight_1 exp(-t/tau_1_s) + (1 - weight_1) exp(-t/tau_2_s)"
    SOURCE = (
        "Findley, Lai & Onaran, Creep and Relaxation of Nonlinear Viscoelastic Materials "
        "(1976), Sec. 5.4 (generalised Kelvin model); Park & Schapery, Int. J. Solids "
        "Struct. 36 (1999) 1653 (Prony series)"
    )
    PARAMETERS = (
        time_parameter("tau_1_s", "first retardation time"),
        time_parameter("tau_2_s", "second retardation time"),
        Parameter("weight_1", "1", "share of the recovery with tau_1_s, J_1/(J_1+J_2)", 0, 1),
    )

    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """w exp(-t / tau_1) + (1 - w) exp(-t / tau_2) [-]."""
        t = as_times(t_s)
        p = self.parameters
        w = p["weight_1"]
        with np.errstate(under="ignore", over="ignore"):
            result: FloatArray = w * np.exp(-(t / p["tau_1_s"])) + (1.0 - w) * np.exp(
                -(t / p["tau_2_s"])
            )
        return np.minimum(result, 1.0)

    def time_scale_s(self) -> float:
        """The smaller time constant [s] (the numeric search doubles from it)."""
        return min(self.parameters["tau_1_s"], self.parameters["tau_2_s"])
