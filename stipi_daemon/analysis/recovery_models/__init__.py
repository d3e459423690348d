"""Recovery models fitted side by side: Kelvin-Voigt, two time constants, power law.

The paper's VPR model (Eqs. 7-10) assumes a Kelvin-Voigt tissue, whose recovery is one
exponential. Tissue that is not (a standard linear solid with an instantaneous part, two
time scales, a poroelastic or power-law recovery) makes its tau, and the fitted estimator
built on it, describe a curve the tissue does not follow. This package fits every model
of its registry (:mod:`.registry`; one module per model with its equation, parameters with
units and bounds, start-value rule and source) to the recovery, weighs them by AICc
(:mod:`.selection`), flags Kelvin-Voigt when the data reject it, and gives each model
95 % intervals on tau, T_r, F_r and eta by a moving-block bootstrap of its residuals
(:mod:`.bootstrap`, :mod:`.comparison`). Pure: no I/O; docs/analysis.md, "Recovery
models, model selection and intervals".

Entry point: :func:`fit_recovery_models` (times, values, T_0) -> :class:`RecoveryModelComparison`.
"""

from __future__ import annotations

from stipi_daemon.analysis.recovery_models.base import ModelParameter, RecoveryModel
from stipi_daemon.analysis.recovery_models.comparison import (
    CI_QUANTITIES,
    DEFAULT_REPLICATES,
    ModelFit,
    RecoveryModelComparison,
    fit_recovery_models,
)
from stipi_daemon.analysis.recovery_models.registry import MODELS, known_models
from stipi_daemon.analysis.recovery_models.selection import KV_REJECTION_DELTA

__all__ = [
    "CI_QUANTITIES",
    "DEFAULT_REPLICATES",
    "KV_REJECTION_DELTA",
    "MODELS",
    "ModelFit",
    "ModelParameter",
    "RecoveryModel",
    "RecoveryModelComparison",
    "fit_recovery_models",
    "known_models",
]
