"""The registry of recovery models: name -> model (one instance each, stateless).

| name | module | g(x), x = t - T_0 |
|---|---|---|
| ``kelvin_voigt`` | :mod:`.kelvin_voigt` | exp(-x/tau) |
| ``two_exponential`` | :mod:`.two_exponential` | w exp(-x/tau_fast) + (1 - w) exp(-x/tau_slow) |
| ``power_law`` | :mod:`.power_law` | (1 + x/(n tau))^-n |

Kelvin-Voigt comes first: it is the paper's model and the reference of the rejection rule.
A new model is a module with a :class:`~.base.RecoveryModel` subclass and a line here; the
metadata test covers it without change.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final

from stipi_daemon.analysis.recovery_models.base import RecoveryModel
from stipi_daemon.analysis.recovery_models.kelvin_voigt import KelvinVoigt
from stipi_daemon.analysis.recovery_models.power_law import PowerLaw
from stipi_daemon.analysis.recovery_models.two_exponential import TwoExponential

__all__ = ["MODELS", "known_models"]

#: Registry name -> model, Kelvin-Voigt first.
MODELS: Final[Mapping[str, RecoveryModel]] = MappingProxyType(
    {m.NAME: m for m in (KelvinVoigt(), TwoExponential(), PowerLaw())}
)


def known_models() -> tuple[str, ...]:
    """Registry names in registry order."""
    return tuple(MODELS)
