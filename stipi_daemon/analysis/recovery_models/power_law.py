"""Power-law recovery: the modified power law, an exponential start and a t^-n tail.

    g(x) = (1 + x / (exponent_n tau_s))^(-exponent_n)

Tissues with a broad spectrum of retardation times recover with a power-law tail; the
modified power law has that tail, g ~ (x / (n tau))^-n, and starts like a Kelvin-Voigt
recovery of the same tau (g'(0) = -1/tau). It is completely monotone (a gamma
distribution of retardation rates, shape n, mean 1/tau), and Kelvin-Voigt is its limit
n -> inf: the search stops at n = 1000, where it differs from exp(-x/tau) by less than
x^2/(2000 tau^2) relative. Exponents near 0 give a recovery that barely progresses
(n = 0.01 needs e^100 tau to reach 1 - 1/e); near 1 a tail like 1/t.

Computed as exp(-n log1p(x/(n tau))), which cannot overflow: x/(n tau) <= 1e4/1e-5.
Effective time constant (1 - 1/e recovered): n tau expm1(1/n), finite over the bounds
(at most 2.7e43 tau at n = 0.01). T_r and the like from the closed-form inverse
x = n tau expm1(-ln(level)/n), ``inf`` when it overflows.

Source: M. L. Williams, AIAA J. 2 (1964) 785-808 (modified power law); F. Mainardi,
Fractional Calculus and Waves in Linear Viscoelasticity (Imperial College Press, 2010),
Ch. 3; M. L. Oyen, J. Mater. Res. 20 (2005) 2094 (power-law ramp-hold indentation).
"""

from __future__ import annotations

import math

import numpy as np

from stipi_daemon.analysis.recovery_models.base import (
    FloatArray,
    ModelParameter,
    RecoveryModel,
    linear_least_squares_grid,
    time_parameter,
)

__all__ = ["EXPONENT_RANGE", "PowerLaw"]

#: Search range of the exponent n [-].
EXPONENT_RANGE = (0.01, 1000.0)
_GRID_TAU = 31
#: Grid rows computed at once [-] (a block's arrays: 5 MB at 105 s of 60 fps).
_GRID_BLOCK = 100
_GRID_N = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 20.0, 200.0)


class PowerLaw(RecoveryModel):
    """Modified power law, g(x) = (1 + x/(n tau))^-n."""

    NAME = "power_law"
    TITLE = "power law (modified power law)"
    EQUATION = "g(x) = (1 + x/(exponent_n tau_s))^(-exponent_n)"
    SOURCE = (
        "Williams, AIAA J. 2 (1964) 785 (modified power law); Mainardi, Fractional Calculus "
        "and Waves in Linear Viscoelasticity (2010), Ch. 3; Oyen, J. Mater. Res. 20 (2005) 2094"
    )
    SHAPE_PARAMETERS = (
        time_parameter("tau_s", "initial time constant, -1/g'(0)"),
        ModelParameter(
            "exponent_n",
            "1",
            "exponent of the late x^-n tail (large: Kelvin-Voigt)",
            *EXPONENT_RANGE,
            transform="log",
        ),
    )
    TAU_MEANING = "n tau expm1(1/n), the time at which 1 - 1/e of the recovery is done"

    def shape(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        """g = exp(-n log1p(q)), q = x/(n tau); derivatives in (ln tau, ln n)."""
        with np.errstate(under="ignore", over="ignore"):
            n = np.exp(u[:, 1])[:, None]
            q = x[None, :] / (n * np.exp(u[:, 0])[:, None])
            lq = np.log1p(q)
            g: FloatArray = np.exp(-n * lq)
            ratio = q / (1.0 + q)
            dg = np.empty((*g.shape, 2))
            dg[:, :, 0] = g * n * ratio
            dg[:, :, 1] = g * n * (ratio - lq)
        return g, dg

    def nested_start(self, kelvin_voigt: FloatArray) -> FloatArray | None:
        """The Kelvin-Voigt tau with the largest exponent (the exponential limit)."""
        o, a, lt = (float(v) for v in kelvin_voigt)
        return np.array([o, a, lt, math.log(EXPONENT_RANGE[1])])

    def start(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """Best (tau, n) of a grid (31 log-spaced tau x 10 exponents), linear part exact."""
        log_tau = np.linspace(
            math.log(self.SHAPE_PARAMETERS[0].lower),
            math.log(self.SHAPE_PARAMETERS[0].upper),
            _GRID_TAU,
        )
        u = np.array([(lt, math.log(n)) for lt in log_tau for n in _GRID_N])
        # g of shape() without its derivatives, in place, a block of the grid's rows at a
        # time: the whole grid is 310 rows x the recovery's frames, 16 MB per array at 105 s
        # of 60 fps, and it made the analysis's peak memory (each row is solved on its own:
        # the same numbers in blocks)
        parts = [
            self._grid_fit(u[k : k + _GRID_BLOCK], x, z) for k in range(0, len(u), _GRID_BLOCK)
        ]
        ssr, offset, amplitude = (np.concatenate(a) for a in zip(*parts, strict=True))
        i = int(np.argmin(ssr))
        return np.array([offset[i], amplitude[i], *u[i]])

    @staticmethod
    def _grid_fit(u: FloatArray, x: FloatArray, z: FloatArray) -> tuple[FloatArray, ...]:
        """:func:`linear_least_squares_grid` of the grid rows ``u`` (log tau, log n)."""
        with np.errstate(under="ignore", over="ignore"):
            n = np.exp(u[:, 1])[:, None]
            basis = x[None, :] / (n * np.exp(u[:, 0])[:, None])
            np.log1p(basis, out=basis)
            np.multiply(-n, basis, out=basis)
            np.exp(basis, out=basis)
        return linear_least_squares_grid(basis, z)

    def time_to_remaining(self, u: FloatArray, level: float) -> float:
        """n tau expm1(-ln(level)/n) [s]; inf past the float range."""
        tau, n = math.exp(float(u[0])), math.exp(float(u[1]))
        arg = -math.log(level) / n
        if arg > 700.0:
            return math.inf
        return n * tau * math.expm1(arg)
