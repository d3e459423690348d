"""Common ground of the tissue models: parameters with units and domains, the recovery API.

This module owns :class:`Parameter` (name with its unit, domain, meaning),
:class:`RecoveryModel` (the interface every tissue model implements) and the rules shared
by all of them: how parameters are validated, how the time at which a recovery reaches a
level is found when a model has no closed form, and how the effective time constant of a
curve that is not a single exponential is defined. It computes no model itself.

What a model describes. Every model is the *recovery function* of the pit under the
probe: ``remaining(t)`` is the fraction of the recovery still ahead at ``t`` seconds after
the release T_0 (1 at t = 0, decreasing to 0). The physics (:mod:`..physics`) makes the
depth, the tip force and the occluded area affine in it,
``D(t) = D_inf + (D_p - D_inf) remaining(t - T_0)``, and likewise F(t) and S(t), so one
function fixes the shape of all three. A model's time parameters are those of that
recovery as the probe sees it (the tissue and the PDMS tip together). For a flat
cylindrical indenter the contact radius does not change, so by the elastic-viscoelastic
correspondence the pit follows the material's own recovery function (Lee & Radok 1960;
Ting 1966, J. Appl. Mech. 33:845, for the general case of a changing contact).

Effective time constant (``effective_time_constant_s``): the time after T_0 at which
``1 - 1/e`` (63.2 %) of the whole recovery (S_inf - S_0) is done, i.e.
``remaining(tau_eff) = 1/e``. Why this definition: it equals tau exactly for a Kelvin-Voigt
recovery, so the Kelvin-Voigt ground truth is what it was; it exists, is finite and unique
for every monotone recovery, including one with an instantaneous part (0 when the jump
already exceeds 63.2 %) and a power-law tail whose mean recovery time
``integral remaining dt`` diverges; and it depends neither on the recording window nor on
the sampling, unlike what a least-squares Kelvin-Voigt fit of the curve finds, which is an
estimator's answer (the thing under test), not a property of the tissue.

Domains. Every time parameter lies in [1e-6, 1e6] s (1 us to 11.6 days): wide enough for
any tissue and frame rate, narrow enough that no derived time, rate or power overflows.
Times given to ``remaining`` must be finite and >= 0 [s]; the result is finite and in
[0, 1] for every valid parameter set (tests/sim/tissue: hypothesis over the domains).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.errors import ConfigError

__all__ = [
    "EFFECTIVE_TAU_FRACTION",
    "MAX_TIME_S",
    "MIN_TIME_S",
    "Parameter",
    "RecoveryModel",
    "as_times",
    "time_parameter",
]

FloatArray = NDArray[np.float64]

#: Smallest time parameter of any model [s].
MIN_TIME_S = 1e-6
#: Largest time parameter of any model [s].
MAX_TIME_S = 1e6
#: Recovered fraction that defines the effective time constant, 1 - 1/e [-].
EFFECTIVE_TAU_FRACTION = 1.0 - math.exp(-1.0)


@dataclass(frozen=True)
class Parameter:
    """One model parameter: its name (unit suffix), unit, domain and meaning.

    Attributes
    ----------
    name : str
        Key in a scene's ``tissue.model`` mapping and in the ground truth (ends in its unit,
        ``_s`` for seconds, none for a dimensionless number).
    unit : str
        Unit (``"s"``, ``"1"`` for dimensionless).
    description : str
        What it is, in one line.
    lower, upper : float
        Domain bounds (finite).
    lower_inclusive, upper_inclusive : bool
        Whether each bound belongs to the domain.
    """

    name: str
    unit: str
    description: str
    lower: float
    upper: float
    lower_inclusive: bool = True
    upper_inclusive: bool = True

    @property
    def domain(self) -> str:
        """The domain in interval notation, e.g. ``[1e-06, 1e+06]``."""
        left = "[" if self.lower_inclusive else "("
        right = "]" if self.upper_inclusive else ")"
        return f"{left}{self.lower:g}, {self.upper:g}{right}"

    def contains(self, value: float) -> bool:
        """Whether ``value`` is finite and inside the domain."""
        if not math.isfinite(value):
            return False
        above = value >= self.lower if self.lower_inclusive else value > self.lower
        below = value <= self.upper if self.upper_inclusive else value < self.upper
        return above and below

    def check(self, model: str, value: object) -> float:
        """``value`` as a float, or :class:`ConfigError` naming the model and parameter."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{model}: {self.name} must be a number, got {value!r}")
        v = float(value)
        if not self.contains(v):
            unit = "" if self.unit == "1" else f" {self.unit}"
            raise ConfigError(
                f"{model}: {self.name} = {v:g}{unit} is outside its domain {self.domain}"
            )
        return v


def time_parameter(name: str, description: str, *, lower: float = MIN_TIME_S) -> Parameter:
    """A time parameter [s] with the shared domain [``lower``, 1e6] s."""
    return Parameter(name, "s", description, lower, MAX_TIME_S)


def as_times(t_s: ArrayLike) -> FloatArray:
    """``t_s`` as a float array of times since the release, or :class:`ConfigError`.

    Raises
    ------
    ConfigError
        A time is NaN, infinite or negative (the models are defined for t >= 0 only).
    """
    t = np.asarray(t_s, dtype=np.float64)
    flat = t.ravel()
    bad = np.flatnonzero(~(np.isfinite(flat) & (flat >= 0.0)))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(
            f"t_s[{i}] = {flat[i]}: recovery times must be finite and >= 0 s (since T_0)"
        )
    return t


class RecoveryModel(ABC):
    """A tissue model: the pit's recovery function after the release (module docstring).

    Subclasses set the class attributes and implement :meth:`remaining`; they may override
    :meth:`time_to_recover` with a closed form. Construct with keyword parameters
    (``Zener(tau_sigma_s=12.0, tau_epsilon_s=3.0)``); every parameter is checked against
    its domain, and :meth:`_check_joint` checks constraints between parameters.

    Raises
    ------
    ConfigError
        A parameter is missing, unknown, not a number or outside its domain.
    """

    #: Registry name (a scene's ``tissue.model.name``).
    NAME: ClassVar[str]
    #: Human-readable name.
    TITLE: ClassVar[str]
    #: The recovery function in plain text.
    EQUATION: ClassVar[str]
    #: Literature source of the model.
    SOURCE: ClassVar[str]
    #: The parameters, in order.
    PARAMETERS: ClassVar[tuple[Parameter, ...]]
    #: Constraints between parameters beyond each one's domain (text; "" if none).
    JOINT_DOMAIN: ClassVar[str] = ""

    def __init__(self, **parameters: float) -> None:
        known = {p.name for p in self.PARAMETERS}
        unknown = sorted(set(parameters) - known)
        if unknown:
            raise ConfigError(
                f"{self.NAME}: unknown parameter {unknown[0]!r} "
                f"(parameters: {', '.join(p.name for p in self.PARAMETERS)})"
            )
        missing = [p.name for p in self.PARAMETERS if p.name not in parameters]
        if missing:
            raise ConfigError(f"{self.NAME}: missing parameter {missing[0]!r}")
        self.parameters: dict[str, float] = {
            p.name: p.check(self.NAME, parameters[p.name]) for p in self.PARAMETERS
        }
        self._check_joint()

    def _check_joint(self) -> None:
        """Raise :class:`ConfigError` when the parameters violate :attr:`JOINT_DOMAIN`."""
        return None

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.parameters.items())
        return f"{type(self).__name__}({args})"

    @abstractmethod
    def remaining(self, t_s: ArrayLike) -> FloatArray:
        """Fraction of the recovery still ahead at ``t_s`` after T_0 [-], in [0, 1].

        ``t_s`` [s] finite and >= 0 (:class:`ConfigError` otherwise); 1 at t = 0.
        """

    def recovered(self, t_s: ArrayLike) -> FloatArray:
        """Fraction of the recovery done at ``t_s`` after T_0 [-]: 1 - remaining."""
        out: FloatArray = 1.0 - self.remaining(t_s)
        return out

    @abstractmethod
    def time_scale_s(self) -> float:
        """A characteristic time of the model [s] (used to bracket :meth:`time_to_recover`)."""

    def time_to_recover(self, fraction: float) -> float:
        """Earliest time after T_0 at which ``fraction`` of the recovery is done [s].

        For a jump at T_0 (an instantaneous part) the infimum is returned: 0 when the jump
        already covers ``fraction``. Without a closed form: Brent's method on the monotone
        ``remaining(t) = 1 - fraction``, bracketed by doubling from :meth:`time_scale_s`.

        Parameters
        ----------
        fraction : float
            In [0, 1) (the whole recovery, 1, is reached only as t -> inf).

        Raises
        ------
        ConfigError
            ``fraction`` outside [0, 1).
        """
        f = _check_fraction(self.NAME, fraction)
        if f == 0.0:
            return 0.0
        target = 1.0 - f
        if float(self.remaining(0.0)) <= target:
            return 0.0
        lo, hi = 0.0, self.time_scale_s()
        while float(self.remaining(hi)) > target:
            lo, hi = hi, 2.0 * hi
            if not math.isfinite(hi):  # pragma: no cover - excluded by the domains
                raise ConfigError(f"{self}: recovery never reaches {f:g}")
        from scipy.optimize import brentq

        root = brentq(lambda t: float(self.remaining(t)) - target, lo, hi, xtol=1e-300, rtol=1e-14)
        return float(root)

    def settling_time_s(self, start: float, end: float, level: float) -> float:
        """Time after T_0 at which a curve from ``start`` to ``end`` reaches ``level`` [s].

        The curve is ``end - (end - start) remaining(t)`` (S, F or D of the physics);
        ``level`` must lie in [start, end) in the curve's direction.
        """
        return self.time_to_recover((level - start) / (end - start))

    def effective_time_constant_s(self) -> float:
        """Time at which 1 - 1/e of the recovery is done [s] (module docstring: why)."""
        return self.time_to_recover(EFFECTIVE_TAU_FRACTION)

    @classmethod
    def metadata(cls) -> dict[str, object]:
        """Name, title, equation, source and parameters (name, unit, domain, meaning)."""
        return {
            "name": cls.NAME,
            "title": cls.TITLE,
            "equation": cls.EQUATION,
            "source": cls.SOURCE,
            "joint_domain": cls.JOINT_DOMAIN,
            "parameters": [
                {
                    "name": p.name,
                    "unit": p.unit,
                    "domain": p.domain,
                    "description": p.description,
                }
                for p in cls.PARAMETERS
            ],
        }


def _check_fraction(model: str, fraction: float) -> float:
    f = float(fraction)
    if not (math.isfinite(f) and 0.0 <= f < 1.0):
        raise ConfigError(f"{model}: recovered fraction must be in [0, 1), got {fraction!r}")
    return f
