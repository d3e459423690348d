"""Power-law recovery: the modified power law, a Kelvin-Voigt start and a t^-n tail.

Tissues with a broad spectrum of retardation times recover with a power-law tail (the
fractional Kelvin-Voigt solid's Mittag-Leffler recovery E_a(-(t/tau)^a) decays as
t^-a / Gamma(1 - a); Mainardi 2010, Ch. 3). The model here is the modified power law

    remaining(t) = (1 + t / (n tau_s))^(-n)

which has that tail, remaining ~ (t / (n tau))^-n, with a closed form. It is a linear
viscoelastic recovery (completely monotone): the Laplace transform of a gamma
distribution of retardation rates, shape n and mean 1/tau,
remaining(t) = integral Gamma(lambda; n, n tau) exp(-lambda t) d lambda, i.e. a
generalised Kelvin-Voigt solid with a continuous spectrum. Its defining relation is the
constant log-log slope, d ln remaining / d ln(1 + t/(n tau)) = -n. At the start it falls
like Kelvin-Voigt with the same tau (remaining'(0) = -1/tau); Kelvin-Voigt is the limit
n -> inf (remaining -> exp(-t/tau)). Parameters are those of the recovery the probe sees
(base module).

Computed as exp(-n log1p(t / (n tau))): no overflow for any t >= 0 in the domain.

Paper's quantities: T_r (98 % rule) = n tau expm1(-ln(1 - x) / n) with x the fraction of
the recovery that 98 % of S_max means; effective tau (1 - 1/e recovered) =
n tau expm1(1/n), which grows without bound as n -> 0 (e.g. 2.7e45 tau at n = 0.01, the
domain's edge; still finite); eta = E T_r (Eq. 8).

Source: M. L. Williams, AIAA J. 2 (1964) 785-808 (the modified power law); F. Mainardi,
Fractional Calculus and Waves in Linear Viscoelasticity (Imperial College Press, 2010),
Ch. 3 (fractional Kelvin-Voigt, power-law creep and recovery); T. C. T. Ting,
J. Appl. Mech. 33 (1966) 845-854 (viscoelastic indentation); M. L. Oyen, J. Mater. Res.
20 (2005) 2094 (power-law ramp-hold indentation).
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numpy.typing import ArrayLike

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.tissue.base import (
    FloatArray,
    Parameter,
    RecoveryModel,
    as_times,
    time_parameter,
)

__all__ = ["PowerLaw"]

#: Largest argument of exp() that stays finite (ln of the largest float).
_MAX_EXP = math.log(sys.float_info.max)


class PowerLaw(RecoveryModel):
    """Modified power law, remaining(t) = (1 + t/(n tau))^-n."""

    NAME = "power_law"
    TITLE = "power-law recovery (modified power law)"
    EQUATION = "remaining(t) = (1 + t/(exponent_n tau_s))^(-exponent_n)"
    SOURCE = (
        "Williams, AIAA J. 2 (1964) 785 (modified power law); Mainardi, Fractional Calculus "
        "and Waves in Linear Viscoelasticity (2010), Ch. 3; Ting, J. Appl. Mech. 33 (1966) "
        "845; Oyen, J. Mater. Res. 20 (2005) 2094"
    )
    PARAMETERS = (
        time_parameter("tau_s", "initial time constant, -1/remaining'(0)"),
        Parameter(
            "exponent_n", "1", "exponent of the late t^-n tail (inf: Kelvin-Voigt)", 0.01, 1e6
        ),
    )

    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """exp(-n log1p(t / (n tau))) [-]."""
        t = as_times(t_s)
        n, tau = self.parameters["exponent_n"], self.parameters["tau_s"]
        with np.errstate(under="ignore", over="ignore"):
            result: FloatArray = np.exp(-n * np.log1p(t / (n * tau)))
        return result

    def time_scale_s(self) -> float:
        """tau [s]."""
        return self.parameters["tau_s"]

    def time_to_recover(self, fraction: float) -> float:
        """n tau expm1(-ln(1 - fraction) / n) [s] (closed form).

        Raises
        ------
        ConfigError
            ``fraction`` outside [0, 1), or the time exceeds what a float holds (a small
            exponent and a fraction near 1: e.g. 99.999 % at n = 0.01 takes e^1151 tau).
        """
        if not (math.isfinite(fraction) and 0.0 <= fraction < 1.0):
            return super().time_to_recover(fraction)
        n, tau = self.parameters["exponent_n"], self.parameters["tau_s"]
        power = -math.log1p(-fraction) / n
        t = n * tau * math.expm1(power) if power < _MAX_EXP else math.inf
        if not math.isfinite(t):
            raise ConfigError(
                f"{self.NAME}: {fraction:g} of the recovery is reached only after more than "
                f"{sys.float_info.max:.3g} s (exponent_n = {n:g}, tau_s = {tau:g} s)"
            )
        return t
