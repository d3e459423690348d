"""Viscoelastic Pitting Recovery (VPR) model, the paper's estimator: Eqs. (7)-(10).

This module owns tissue elasticity from the pitting depth (Eq. 7), viscosity from the
recovery time (Eq. 8), the Kelvin-Voigt depth recovery D(t) = D_p exp(-(E/eta) t) (Eq. 10,
from the constitutive law Eq. 9) and the :class:`VPRModel` record, together with the single
F_a/R ratio that reproduces the paper's Table II. It does not own the pitting parameters
(see ``pitting``), the fitted time-constant estimator (see ``recovery_fit``) nor the
severity classification (see ``severity``).

Units: elasticity in kPa, viscosity in N*s/mm^2 (as the paper's Table II), so that
1 kPa = 1e-3 N/mm^2, kPa*s = 1e-3 N*s/mm^2 and the decay rate E/eta is
``1e-3 * E_kpa / eta_n_s_per_mm2`` [1/s].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.errors import AnalysisError, require_finite

if TYPE_CHECKING:
    from stipi_daemon.analysis.pitting import PittingParameters

__all__ = [
    "KPA_PER_N_PER_MM2",
    "PAPER_APPLIED_FORCE_N",
    "PAPER_FORCE_RADIUS_RATIO_N_PER_MM",
    "PAPER_IMPLIED_RADIUS_MM",
    "VPRModel",
    "decay_rate_per_s",
    "elasticity_kpa",
    "viscosity_n_s_per_mm2",
    "vpr_depth_mm",
]

#: 1 N/mm^2 = 1 MPa = 1000 kPa.
KPA_PER_N_PER_MM2 = 1000.0

#: Applied pitting force stated in the paper (16 +/- 1.5 N, Section IV.B) [N].
PAPER_APPLIED_FORCE_N = 16.0

PAPER_FORCE_RADIUS_RATIO_N_PER_MM = 4.928
"""F_a/R [N/mm] that makes Eq. (7) reproduce Table II's STIP-I elasticities.

In Table II, E_stipi * D_p is the same for the four grades (1497.92-1497.95 kPa*mm, mean
1497.94), so the paper evaluated Eq. (7) with one fixed F_a/R. Eq. (7) gives
E * D_p = 1000 * 3/pi^2 * F_a/R [kPa*mm], hence F_a/R = 1497.94 * pi^2 / 3000 = 4.92802 N/mm;
a least-squares fit of E_i = (3000/pi^2) (F_a/R) / D_p,i over the four grades gives
4.92803 N/mm. Rounded to 4.928 N/mm it reproduces every grade's E within 0.002 %.
The paper does not state F_a and R. This ratio implies F_a = 36.96 N for the stated
15 mm indenter diameter (R = 7.5 mm), or R = 3.247 mm for the stated F_a = 16 N
(:data:`PAPER_IMPLIED_RADIUS_MM`); neither matches both stated values, so use your own
measured F_a and R for new data and this constant only to reproduce the paper.
"""

#: Indenter radius that, with F_a = 16 N, gives :data:`PAPER_FORCE_RADIUS_RATIO_N_PER_MM` [mm].
PAPER_IMPLIED_RADIUS_MM = PAPER_APPLIED_FORCE_N / PAPER_FORCE_RADIUS_RATIO_N_PER_MM


def _positive(name: str, value: float) -> float:
    v = require_finite(name, value)
    if v <= 0.0:
        raise AnalysisError(f"{name} must be > 0, got {v}")
    return v


def _finite_result(name: str, value: float, inputs: str) -> float:
    if not math.isfinite(value):
        raise AnalysisError(f"{name} overflows for {inputs}")
    return value


def elasticity_kpa(applied_force_n: float, depth_mm: float, indenter_radius_mm: float) -> float:
    """Tissue elasticity E = 3/(pi^2 R) * F_a / D_p, Eq. (7).

    Parameters
    ----------
    applied_force_n : float
        Applied pitting force F_a [N], > 0.
    depth_mm : float
        Pitting depth D_p [mm], > 0 (Eq. 7 divides by it).
    indenter_radius_mm : float
        Indenter radius R [mm], > 0.

    Returns
    -------
    float
        E [kPa] (Eq. 7 gives N/mm^2, multiplied by 1000).

    Raises
    ------
    AnalysisError
        An input is NaN/inf or <= 0 (D_p = 0 leaves E undefined), or E overflows.
    """
    force = _positive("applied_force_n", applied_force_n)
    radius = _positive("indenter_radius_mm", indenter_radius_mm)
    depth = require_finite("depth_mm", depth_mm)
    if depth <= 0.0:
        raise AnalysisError(
            f"depth_mm must be > 0, got {depth}: elasticity (Eq. 7) is undefined for a "
            "zero or negative pitting depth"
        )
    e = KPA_PER_N_PER_MM2 * 3.0 / (math.pi**2 * radius) * (force / depth)
    return _finite_result("elasticity", e, f"F_a={force} N, D_p={depth} mm, R={radius} mm")


def viscosity_n_s_per_mm2(elasticity_kpa: float, recovery_time_s: float) -> float:
    """Tissue viscosity eta = E * T_r, Eq. (8).

    Parameters
    ----------
    elasticity_kpa : float
        Elasticity E [kPa], > 0.
    recovery_time_s : float
        Recovery time T_r [s], > 0 (a zero T_r would make the decay rate E/eta infinite).

    Returns
    -------
    float
        eta [N*s/mm^2] (kPa*s = 1e-3 N*s/mm^2). Relative, not absolute, viscosity (paper).

    Raises
    ------
    AnalysisError
        An input is NaN/inf or <= 0, or eta overflows.
    """
    e = _positive("elasticity_kpa", elasticity_kpa)
    t_r = _positive("recovery_time_s", recovery_time_s)
    eta = e * t_r / KPA_PER_N_PER_MM2
    return _finite_result("viscosity", eta, f"E={e} kPa, T_r={t_r} s")


def decay_rate_per_s(elasticity_kpa: float, viscosity_n_s_per_mm2: float) -> float:
    """Decay rate E/eta of Eq. (10) [1/s], i.e. ``1e-3 * E_kpa / eta``.

    With eta from Eq. (8) this is 1/T_r.

    Raises
    ------
    AnalysisError
        An input is NaN/inf or <= 0, or the rate over/underflows to inf/0.
    """
    e = _positive("elasticity_kpa", elasticity_kpa)
    eta = _positive("viscosity_n_s_per_mm2", viscosity_n_s_per_mm2)
    rate = (e / KPA_PER_N_PER_MM2) / eta
    if not math.isfinite(rate) or rate <= 0.0:
        raise AnalysisError(f"decay rate E/eta is not representable for E={e} kPa, eta={eta}")
    return rate


def vpr_depth_mm(
    t_s: ArrayLike,
    depth_mm: float,
    elasticity_kpa: float,
    viscosity_n_s_per_mm2: float,
) -> NDArray[np.float64]:
    """Pitting depth during recovery D(t) = D_p exp(-(E/eta) t), Eq. (10).

    Vectorised over ``t_s``. The exponent is never positive for t >= 0, so the result
    cannot overflow; it underflows quietly to 0 for long times.

    Parameters
    ----------
    t_s : array_like
        Times since the start of recovery T_0 [s], finite and >= 0.
    depth_mm : float
        Pitting depth at T_0, D_p [mm], finite and >= 0.
    elasticity_kpa : float
        Elasticity E [kPa], > 0.
    viscosity_n_s_per_mm2 : float
        Viscosity eta [N*s/mm^2], > 0.

    Returns
    -------
    numpy.ndarray
        D(t) [mm], same shape as ``t_s``, in [0, D_p].

    Raises
    ------
    AnalysisError
        A time is negative or non-finite, or a parameter is outside its domain.
    """
    t = np.asarray(t_s, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(t.ravel()) | (t.ravel() < 0.0))
    if bad.size:
        i = int(bad[0])
        raise AnalysisError(f"t_s[{i}] = {t.ravel()[i]}: times must be finite and >= 0 s")
    d_p = require_finite("depth_mm", depth_mm)
    if d_p < 0.0:
        raise AnalysisError(f"depth_mm must be >= 0, got {d_p}")
    rate = decay_rate_per_s(elasticity_kpa, viscosity_n_s_per_mm2)
    with np.errstate(over="ignore", under="ignore"):
        out: NDArray[np.float64] = d_p * np.exp(-(rate * t))
    return out


@dataclass(frozen=True)
class VPRModel:
    """The VPR model of one measurement, Eqs. (7)-(10).

    Attributes
    ----------
    elasticity_kpa : float
        E [kPa], Eq. (7).
    viscosity_n_s_per_mm2 : float
        eta [N*s/mm^2], Eq. (8) (or E * tau for a fitted time constant).
    depth_mm : float
        D_p [mm], the depth at the start of recovery.
    applied_force_n : float
        F_a used in Eq. (7) [N].
    indenter_radius_mm : float
        R used in Eq. (7) [mm].
    flags : frozenset[Flag]
        Flags carried over from the inputs (e.g. ``NOT_SETTLED``: eta is a lower bound).
    """

    elasticity_kpa: float
    viscosity_n_s_per_mm2: float
    depth_mm: float
    applied_force_n: float
    indenter_radius_mm: float
    flags: frozenset[Flag] = frozenset()

    @property
    def decay_rate_per_s(self) -> float:
        """E/eta [1/s], the exponent's rate in Eq. (10)."""
        return decay_rate_per_s(self.elasticity_kpa, self.viscosity_n_s_per_mm2)

    @property
    def time_constant_s(self) -> float:
        """Retardation time eta/E [s] (equals T_r when eta comes from Eq. 8)."""
        tau = 1.0 / self.decay_rate_per_s
        return _finite_result("time constant", tau, f"decay rate {self.decay_rate_per_s} 1/s")

    def depth_at(self, t_s: ArrayLike) -> NDArray[np.float64]:
        """D(t) [mm] at times ``t_s`` [s] since T_0, Eq. (10)."""
        return vpr_depth_mm(t_s, self.depth_mm, self.elasticity_kpa, self.viscosity_n_s_per_mm2)

    def normalised_depth(self, t_s: ArrayLike) -> NDArray[np.float64]:
        """D(t)/D_p [-]: 1 at T_0, 0 at full recovery (Section IV.C)."""
        return vpr_depth_mm(t_s, 1.0, self.elasticity_kpa, self.viscosity_n_s_per_mm2)

    @classmethod
    def from_values(
        cls,
        depth_mm: float,
        recovery_time_s: float,
        *,
        applied_force_n: float,
        indenter_radius_mm: float,
        flags: frozenset[Flag] = frozenset(),
    ) -> VPRModel:
        """Build the model from D_p [mm] and T_r [s] with Eqs. (7) and (8).

        Raises
        ------
        AnalysisError
            As :func:`elasticity_kpa` and :func:`viscosity_n_s_per_mm2`.
        """
        e = elasticity_kpa(applied_force_n, depth_mm, indenter_radius_mm)
        eta = viscosity_n_s_per_mm2(e, recovery_time_s)
        decay_rate_per_s(e, eta)  # validates that Eq. (10) is representable
        return cls(
            elasticity_kpa=e,
            viscosity_n_s_per_mm2=eta,
            depth_mm=float(depth_mm),
            applied_force_n=float(applied_force_n),
            indenter_radius_mm=float(indenter_radius_mm),
            flags=flags,
        )

    @classmethod
    def from_pitting(
        cls,
        params: PittingParameters,
        *,
        applied_force_n: float,
        indenter_radius_mm: float,
    ) -> VPRModel:
        """Build the model from :class:`~stipi_daemon.analysis.pitting.PittingParameters`.

        The pitting flags are carried over: with ``NOT_SETTLED`` T_r, and so eta, is a lower
        bound; with ``SETTLED_WITHIN_ONE_FRAME`` an upper bound.

        Parameters
        ----------
        params : PittingParameters
            D_p and T_r of the measurement.
        applied_force_n : float
            F_a [N] (the paper states 16 N).
        indenter_radius_mm : float
            R [mm]. To reproduce the paper's Table II use ``applied_force_n / R`` =
            :data:`PAPER_FORCE_RADIUS_RATIO_N_PER_MM`.

        Raises
        ------
        AnalysisError
            The measurement has no recovery time (``NO_RECOVERY``), a zero depth, or an
            input outside the domain of Eqs. (7)-(8).
        """
        if params.recovery_time_s is None:
            raise AnalysisError(
                "no recovery time (flag no_recovery): S_k did not rise after T_0 "
                f"= {params.t0_s} s, so viscosity (Eq. 8) is undefined"
            )
        return cls.from_values(
            params.depth_mm,
            params.recovery_time_s,
            applied_force_n=applied_force_n,
            indenter_radius_mm=indenter_radius_mm,
            flags=params.flags,
        )
