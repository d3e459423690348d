"""Tissue models of the simulator: registry of names to recovery models, imported lazily.

This package owns the tissue models (one module each, with its equation, parameters with
units and domains, and its literature source; :mod:`.base` states what a model is and how
the effective time constant of a non-exponential recovery is defined) and this registry.
A scene names its model in ``tissue.model`` (:class:`.spec.TissueModelSpec`); only that
model's module is imported. Without ``tissue.model`` a scene is Kelvin-Voigt, as before.

| name | module | recovery function remaining(t) |
|---|---|---|
| ``kelvin_voigt`` | :mod:`.kelvin_voigt` | exp(-t/tau) |
| ``zener`` | :mod:`.zener` | jump tau_eps/tau_sigma, then exp(-t/tau_sigma) |
| ``prony`` | :mod:`.prony` | w exp(-t/tau_1) + (1 - w) exp(-t/tau_2) |
| ``poroelastic`` | :mod:`.poroelastic` | 1 - U(t/tau_p), Terzaghi/Biot consolidation |
| ``power_law`` | :mod:`.power_law` | (1 + t/(n tau))^-n |
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.tissue.base import RecoveryModel

__all__ = [
    "DEFAULT_TISSUE_MODEL",
    "TISSUE_MODELS",
    "build_tissue_model",
    "known_tissue_models",
    "tissue_model_class",
]

#: Model of a scene that names none.
DEFAULT_TISSUE_MODEL = "kelvin_voigt"

#: Scene name -> "module:class" under this package.
TISSUE_MODELS: dict[str, str] = {
    "kelvin_voigt": "kelvin_voigt:KelvinVoigt",
    "zener": "zener:Zener",
    "prony": "prony:Prony",
    "poroelastic": "poroelastic:Poroelastic",
    "power_law": "power_law:PowerLaw",
}


def known_tissue_models() -> tuple[str, ...]:
    """Names of all tissue models, sorted."""
    return tuple(sorted(TISSUE_MODELS))


def tissue_model_class(name: str) -> type[RecoveryModel]:
    """Import and return the class of tissue model ``name``.

    Raises
    ------
    ConfigError
        ``name`` is not a known model; the message lists the known ones.
    """
    target = TISSUE_MODELS.get(name)
    if target is None:
        raise ConfigError(
            f"unknown tissue model {name!r} (known: {', '.join(known_tissue_models())})"
        )
    module, attr = target.split(":")
    cls = getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    assert isinstance(cls, type) and issubclass(cls, RecoveryModel)
    return cls


def build_tissue_model(name: str, parameters: Mapping[str, object]) -> RecoveryModel:
    """Model ``name`` with ``parameters`` (validated against its domains).

    Raises
    ------
    ConfigError
        Unknown model, or a parameter missing, unknown, not a number or out of its domain.
    """
    cls = tissue_model_class(name)
    return cls(**parameters)  # type: ignore[arg-type]
