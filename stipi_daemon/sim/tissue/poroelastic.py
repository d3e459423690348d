"""Poroelastic recovery: fluid flows back into the pit; early sqrt(t), late exponential.

Biot's linear poroelasticity reduces, for a layer drained on one face, to the diffusion of
the pore pressure (Terzaghi's consolidation): p_t = c p_zz on 0 < z < H, p = 0 at the
drained face z = 0, no flux at z = H, p = 1 initially. The degree of consolidation U(T) is
the fraction of the volume change done at the dimensionless time T = c t / H^2; the
swelling of a pit after the release is the same linear problem. The model is

    remaining(t) = 1 - U(t / tau_p_s),  tau_p_s = H^2 / c

with the two exact forms of U (Carslaw & Jaeger, Sec. 3.3; Wang, Sec. 6.2):

* T <= 1/4 (images): U = 2 sqrt(T/pi) + 4 sqrt(T) sum_{m>=1} (-1)^m ierfc(m / sqrt(T)),
  ierfc(x) = exp(-x^2)/sqrt(pi) - x erfc(x); the early recovery is 2 sqrt(T/pi);
* T > 1/4 (Fourier): 1 - U = sum_{m>=0} (2/M^2) exp(-M^2 T), M = pi (2m + 1)/2; the late
  recovery is the single exponential (8/pi^2) exp(-pi^2 T / 4), time constant
  4 tau_p / pi^2.

Four image terms and eight Fourier terms leave truncation errors below 1e-16 at the switch
(the terms fall as exp(-(2m/sqrt(T))^2) and exp(-M^2/4)); tests check both forms against
each other and against a method-of-lines solution of the diffusion equation.
tau_p_s is the drainage time of the recovery the probe sees (base module); for
indentation H is about the contact radius a (Hu et al. 2010 scale time by D t / a^2, and
their flat-punch and spherical relaxation curves share the early sqrt(t) and the
exponential-like late decay).

Paper's quantities: T_r (98 % rule) and the effective tau (1 - 1/e recovered, at
T = 0.4348...) by Brent's method; eta = E T_r (Eq. 8).

Source: M. A. Biot, J. Appl. Phys. 12 (1941) 155-164 (general theory of consolidation);
K. Terzaghi (1925); H. F. Wang, Theory of Linear Poroelasticity (Princeton, 2000),
Sec. 6.2; H. S. Carslaw, J. C. Jaeger, Conduction of Heat in Solids, 2nd ed. (Oxford,
1959), Sec. 3.3; Y. Hu, X. Zhao, J. J. Vlassak, Z. Suo, Appl. Phys. Lett. 96 (2010)
121904 (poroelastic indentation); M. L. Oyen, J. Mater. Res. 23 (2008) 1307.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import erfcx

from stipi_daemon.sim.tissue.base import FloatArray, RecoveryModel, as_times, time_parameter

__all__ = ["SWITCH_T", "Poroelastic", "degree_of_consolidation"]

#: Dimensionless time at which U switches from the image to the Fourier series [-].
SWITCH_T = 0.25
_IMAGE_TERMS = 4
_FOURIER_TERMS = 8
_SQRT_PI = math.sqrt(math.pi)


def _ierfc(x: FloatArray) -> FloatArray:
    """Integrated complementary error function for x >= 2 (no cancellation to speak of)."""
    with np.errstate(under="ignore", over="ignore", invalid="ignore"):
        out: FloatArray = np.exp(-(x * x)) * (1.0 / _SQRT_PI - x * erfcx(x))
    return np.where(np.isfinite(out), out, 0.0)


def _consolidation(big_t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(U, 1 - U) at T >= 0, each from the series that gives it without cancellation."""
    with np.errstate(under="ignore", over="ignore"):  # terms flush to 0 (T up to inf)
        return _consolidation_series(big_t)


def _consolidation_series(big_t: FloatArray) -> tuple[FloatArray, FloatArray]:
    early = big_t <= SWITCH_T
    u = np.empty_like(big_t)
    rest = np.empty_like(big_t)
    root = np.sqrt(big_t[early])
    ue = 2.0 * root / _SQRT_PI
    safe = np.where(root > 0.0, root, 1.0)
    for m in range(1, _IMAGE_TERMS + 1):
        term = np.where(root > 0.0, _ierfc(m / safe), 0.0)
        ue = ue + (4.0 * root) * ((-1.0) ** m) * term
    u[early] = ue
    rest[early] = 1.0 - ue
    tl = big_t[~early]
    rl = np.zeros_like(tl)
    with np.errstate(under="ignore"):
        for m in range(_FOURIER_TERMS):
            big_m2 = (math.pi * (2 * m + 1) / 2.0) ** 2
            rl = rl + (2.0 / big_m2) * np.exp(-big_m2 * tl)
    rest[~early] = rl
    u[~early] = 1.0 - rl
    return np.clip(u, 0.0, 1.0), np.clip(rest, 0.0, 1.0)


def degree_of_consolidation(t_dimensionless: ArrayLike) -> FloatArray:
    """Terzaghi's degree of consolidation U(T) [-] for T >= 0 (module docstring)."""
    return _consolidation(np.asarray(t_dimensionless, dtype=np.float64))[0]


class Poroelastic(RecoveryModel):
    """Consolidation-type recovery, remaining(t) = 1 - U(t / tau_p)."""

    NAME = "poroelastic"
    TITLE = "poroelastic recovery (early sqrt(t), late exponential)"
    EQUATION = (
        "remaining(t) = 1 - U(t/tau_p_s); U ~ 2 sqrt(T/pi) early, "
        "1 - U ~ (8/pi^2) exp(-pi^2 T/4) late (Terzaghi/Biot consolidation)"
    )
    SOURCE = (
        "Biot, J. Appl. Phys. 12 (1941) 155; Terzaghi (1925); Wang, Theory of Linear "
        "Poroelasticity (2000), Sec. 6.2; Carslaw & Jaeger, Conduction of Heat in Solids "
        "(1959), Sec. 3.3; Hu et al., Appl. Phys. Lett. 96 (2010) 121904; Oyen, "
        "J. Mater. Res. 23 (2008) 1307"
    )
    PARAMETERS = (
        time_parameter("tau_p_s", "drainage time H^2/c (drainage length^2 / diffusivity)"),
    )

    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """1 - U(t / tau_p) [-]."""
        t = as_times(t_s)
        with np.errstate(over="ignore", under="ignore"):
            big_t = t / self.parameters["tau_p_s"]
        return _consolidation(big_t)[1]

    def time_scale_s(self) -> float:
        """tau_p [s]."""
        return self.parameters["tau_p_s"]

    @property
    def late_time_constant_s(self) -> float:
        """Time constant of the late exponential, 4 tau_p / pi^2 [s]."""
        return 4.0 * self.parameters["tau_p_s"] / math.pi**2
