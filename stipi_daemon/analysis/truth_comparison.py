"""Results against a simulator's ground truth, parameter by parameter.

Pure: :func:`compare_ground_truth` sets a summary's D_p, F_r, T_r, tau, F_a, E and eta
(the layout of the live ``summary.json``) beside the values a simulated scene was built
with (``ground_truth.json``, :class:`~stipi_daemon.sim.truth.GroundTruth`'s keys), with the
relative error and the simulator's acceptance tolerance
(:data:`GROUND_TRUTH_TOLERANCES`). Used by ``analyze`` (:mod:`stipi_daemon.app.analyze`)
and the report.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

__all__ = ["GROUND_TRUTH_TOLERANCES", "ParameterComparison", "compare_ground_truth"]

#: Relative tolerances of the simulator's acceptance test (ground truth vs analysis) [1].
GROUND_TRUTH_TOLERANCES: Final[dict[str, float]] = {
    "depth_mm": 0.01,
    "rebound_force_n": 0.01,
    "time_constant_s": 0.02,
    "elasticity_kpa": 0.01,
}


@dataclass(frozen=True)
class ParameterComparison:
    """One parameter of the results against the simulator's ground truth.

    Attributes
    ----------
    name : str
        Ground-truth key (unit in the name).
    label : str
        Symbol as the paper writes it.
    truth, measured : float or None
        Ground-truth and analysed values.
    error_percent : float or None
        ``100 (measured - truth) / |truth|`` [%]; None when either value is missing or
        the truth is 0.
    tolerance_percent : float or None
        The simulator's acceptance tolerance for this parameter [%], if it has one.
    """

    name: str
    label: str
    truth: float | None
    measured: float | None
    error_percent: float | None
    tolerance_percent: float | None

    @property
    def within_tolerance(self) -> bool | None:
        """Whether |error| <= tolerance; None without a tolerance or a value."""
        if self.tolerance_percent is None or self.error_percent is None:
            return None
        return abs(self.error_percent) <= self.tolerance_percent


def _get(d: Any, *keys: str) -> float | None:
    for k in keys:
        if not isinstance(d, Mapping):
            return None
        d = d.get(k)
    if isinstance(d, bool) or not isinstance(d, int | float):
        return None
    return float(d)


def compare_ground_truth(
    summary: Mapping[str, Any], truth: Mapping[str, Any]
) -> list[ParameterComparison]:
    """Compare a summary's results with a simulator ground truth (``ground_truth.json``).

    Parameters
    ----------
    summary : mapping
        A summary as :meth:`ReplayOutcome.summary` builds it.
    truth : mapping
        The ground truth (keys of :class:`~stipi_daemon.sim.truth.GroundTruth`).

    Returns
    -------
    list of ParameterComparison
        D_p, F_r, T_r, tau, F_a, E, eta (paper, E T_r) and eta (fit, E tau); the measured
        value is None when the summary has no results.
    """
    res = summary.get("results") or {}
    rows = [
        ("depth_mm", "D_p [mm]", _get(res, "pitting", "depth_mm")),
        ("rebound_force_n", "F_r [N]", _get(res, "pitting", "rebound_force_n")),
        ("recovery_time_s", "T_r [s]", _get(res, "pitting", "recovery_time_s")),
        ("time_constant_s", "tau [s]", _get(res, "fitted_recovery", "tau_s")),
        ("applied_force_n", "F_a [N]", _get(res, "applied_force_n")),
        ("elasticity_kpa", "E [kPa]", _get(res, "paper_estimator", "elasticity_kpa")),
        (
            "viscosity_n_s_per_mm2",
            "eta = E T_r [N s/mm^2]",
            _get(res, "paper_estimator", "viscosity_n_s_per_mm2"),
        ),
        (
            "viscosity_from_time_constant_n_s_per_mm2",
            "eta = E tau [N s/mm^2]",
            _get(res, "fitted_recovery", "model", "viscosity_n_s_per_mm2"),
        ),
    ]
    out: list[ParameterComparison] = []
    for name, label, measured in rows:
        t = _get(truth, name)
        err: float | None = None
        if t is not None and measured is not None and t != 0.0:
            err = 100.0 * (measured - t) / abs(t)
        tol = GROUND_TRUTH_TOLERANCES.get(name)
        out.append(
            ParameterComparison(
                name=name,
                label=label,
                truth=t,
                measured=measured,
                error_percent=err,
                tolerance_percent=None if tol is None else 100.0 * tol,
            )
        )
    return out
