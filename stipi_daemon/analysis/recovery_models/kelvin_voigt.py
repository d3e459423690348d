"""Kelvin-Voigt recovery: one exponential, the model the paper's VPR model assumes (Eq. 10).

    g(x) = exp(-x / tau_s),   y(t) = offset - amplitude exp(-(t - T_0)/tau_s)

A spring and a dashpot in parallel recover from a held stress as eta eps' + E eps = 0,
so the strain decays with the retardation time tau = eta / E. Its effective time constant
(1 - 1/e of the recovery done) is tau itself.

The fit is :mod:`~stipi_daemon.analysis.recovery_fit`'s (the second estimator of
``summary.json``'s ``fitted_recovery``): its start-value rule (a log-spaced tau grid with
offset and amplitude by linear least squares, :func:`~stipi_daemon.analysis.recovery_fit.
grid_start`) and its solver (:func:`~stipi_daemon.analysis.recovery_fit.solve_scaled`), so
the Kelvin-Voigt entry of the model comparison is that very fit.

Source: W. N. Findley, J. S. Lai, K. Onaran, Creep and Relaxation of Nonlinear
Viscoelastic Materials (North-Holland, 1976), Sec. 5.2 (Kelvin model, creep recovery);
Y. C. Fung, Biomechanics (2nd ed., Springer, 1993), Sec. 2.11.
"""

from __future__ import annotations

import math

import numpy as np

from stipi_daemon.analysis.recovery_fit import grid_start
from stipi_daemon.analysis.recovery_models.base import FloatArray, RecoveryModel, time_parameter

__all__ = ["KelvinVoigt"]


class KelvinVoigt(RecoveryModel):
    """Single exponential, g(x) = exp(-x / tau_s)."""

    NAME = "kelvin_voigt"
    TITLE = "Kelvin-Voigt (single exponential)"
    EQUATION = "g(x) = exp(-x/tau_s)"
    SOURCE = (
        "Findley, Lai & Onaran, Creep and Relaxation of Nonlinear Viscoelastic Materials "
        "(1976), Sec. 5.2; Fung, Biomechanics (2nd ed., 1993), Sec. 2.11"
    )
    SHAPE_PARAMETERS = (time_parameter("tau_s", "retardation time eta/E"),)
    TAU_MEANING = "tau_s itself"

    def shape(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        """exp(-x e^-u) and its derivative in u = ln tau."""
        with np.errstate(under="ignore"):
            rate = np.exp(-u[:, 0])  # 1/tau, finite: u is bounded
            arg = x[None, :] * rate[:, None]
            g: FloatArray = np.exp(-arg)
            dg = (g * arg)[:, :, None]
        return g, dg

    def start(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """The Kelvin-Voigt fit's grid start (recovery_fit.grid_start)."""
        return np.asarray(grid_start(x, z), dtype=np.float64)

    def time_to_remaining(self, u: FloatArray, level: float) -> float:
        """tau ln(1/level) [s]."""
        return math.exp(float(u[0])) * -math.log(level)
