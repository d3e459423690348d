"""The report's parameter table: every result of a session, as data and as rows.

:data:`PARAMETER_ROWS` lists the table's fixed lines as :class:`RowSpec` records (symbol,
words, key, unit, where in ``summary["results"]`` the value, its standard error and its
flags are, and how it is to be read); :func:`parameter_table` renders them for one
``summary.json``, adds the severity lines of each estimator and, for a simulated session,
the ground truth and the error against it. :func:`flag_descriptions` gives the meaning of
every flag (:data:`~stipi_daemon.analysis.flags.FLAG_DESCRIPTIONS`) for the page's legend.
It is pure; the page's markup and number formatting are :mod:`.html`'s.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final

from stipi_daemon.analysis.flags import FLAG_DESCRIPTIONS, Flag
from stipi_daemon.analysis.truth_comparison import compare_ground_truth
from stipi_daemon.report.inputs import flags_at, number_at, value_at
from stipi_daemon.report.verdict import QuantityStatus, combined, read_validity

__all__ = [
    "FIT",
    "PARAMETER_ROWS",
    "PITTING",
    "SEVERITY",
    "SEVERITY_ESTIMATORS",
    "VPR",
    "ParameterRow",
    "RowSpec",
    "flag_descriptions",
    "parameter_table",
]

#: Sections of the table, in page order.
PITTING: Final = "Pitting parameters (Eqs. 3-6)"
VPR: Final = "VPR model, paper estimator (Eqs. 7-8, 10)"
FIT: Final = "Kelvin-Voigt recovery fit (η_τ = E·τ)"
SEVERITY: Final = "Edema severity (Section IV.C)"

#: Estimators whose severity class is tabulated: key in ``results.severity``, label.
SEVERITY_ESTIMATORS: Final = (("paper_estimator", "paper estimator"), ("fitted_recovery", "fit"))

#: Rows whose ground truth the simulator records but :func:`compare_ground_truth` does not
#: compare (scene-clock times are left out: the session clock differs).
_TRUTH_READ_DIRECTLY: Final = ("depth_change_mm", "s0_px", "s_max_px")

_UNDEFINED: Final = "undefined (see notes)"


@dataclass(frozen=True)
class ParameterRow:
    """One line of the parameter table.

    Attributes
    ----------
    group : str
        Section of the table (pitting, VPR model, fit, severity).
    symbol, name : str
        Symbol as the paper writes it and a few words.
    key : str
        Stable identifier (unit in the name, ground-truth key where one exists).
    value : float or str or None
        The value (None: not available, see ``note``).
    uncertainty : float or None
        One standard error, in the value's unit (only the fit reports them).
    unit : str
        Unit of value and uncertainty.
    flags : tuple of str
        Quality flags of the value.
    note : str
        Why a value is missing or how it is to be read.
    truth : float or None
        Simulator ground truth, when the session has one.
    error_percent : float or None
        100 (value - truth)/|truth| [%].
    validity : QuantityStatus or None
        The validity of the quantities the value depends on (the worst of them; None: the
        row reports no assessed quantity, e.g. T_0 or R). An ``invalid`` value is recorded
        here but never shown as a result.
    """

    group: str
    symbol: str
    name: str
    key: str
    value: float | str | None
    uncertainty: float | None
    unit: str
    flags: tuple[str, ...] = ()
    note: str = ""
    truth: float | None = None
    error_percent: float | None = None
    validity: QuantityStatus | None = None

    @property
    def shown_as_result(self) -> bool:
        """False when the value is not valid (the page shows it only greyed, as not valid)."""
        return self.validity is None or self.validity.status != "invalid"


def _viscosity_from_tau_se(results: Mapping[str, Any]) -> float | None:
    """SE of eta_tau = E tau [N s/mm^2] from tau's alone (E has none): E [kPa] SE(tau) [s] / 1e3."""
    tau = number_at(results, "fitted_recovery", "tau_s")
    tau_se = number_at(results, "fitted_recovery", "tau_se_s")
    e_kpa = number_at(results, "fitted_recovery", "model", "elasticity_kpa")
    return None if tau is None or tau_se is None or e_kpa is None else e_kpa * tau_se / 1e3


@dataclass(frozen=True)
class RowSpec:
    """One fixed line of the parameter table, as data.

    Paths name a place in ``summary["results"]`` with dots (``"pitting.depth_mm"``).

    Attributes
    ----------
    group, symbol, name, key, unit : str
        As in :class:`ParameterRow`.
    value : str
        Path of the value (a finite number, else None); empty: the key itself.
    uncertainty : str or callable or None
        Path of its standard error, or a function of the results that propagates one;
        None: no standard error.
    flags : str or None
        Path of the section whose flags the value carries; None: no flags.
    note : str
        How the value is to be read.
    note_if_absent : str
        The note instead when the value is missing (or, with ``requires``, that section).
    requires : str or None
        Path of the section whose absence ``note_if_absent`` explains.
    note_if_flag : tuple of (str, str) or None
        (flag, note): the note instead when the value carries that flag.
    validity : tuple of str
        The quantities of ``summary["validity"]`` the value depends on (empty: none).
    """

    group: str
    symbol: str
    name: str
    key: str
    unit: str
    value: str = ""
    uncertainty: str | Callable[[Mapping[str, Any]], float | None] | None = None
    flags: str | None = None
    note: str = ""
    note_if_absent: str = ""
    requires: str | None = None
    note_if_flag: tuple[str, str] | None = None
    validity: tuple[str, ...] = ()


_DP: Final = ("depth_mm",)
_FR: Final = ("rebound_force_n",)
_TR: Final = ("recovery_time_s",)
_TAU: Final = ("tau_s",)

# fmt: off
#: The table's fixed lines, in page order (the severity lines follow them).
PARAMETER_ROWS: Final[tuple[RowSpec, ...]] = (
    RowSpec(PITTING, "T_0", "start of recovery", "t0_s", "s", "pitting.t0_s"),
    RowSpec(
        PITTING, "T_s", "S_k settled (98 %)", "ts_s", "s", "pitting.ts_s", flags="pitting",
        validity=_TR,
    ),
    RowSpec(PITTING, "S_0", "S_k at T_0", "s0_px", "px", "pitting.s0_px", validity=_DP),
    RowSpec(
        PITTING, "S_max", "largest S_k", "s_max_px", "px", "pitting.s_max_px", validity=_FR
    ),
    RowSpec(
        PITTING, "d_s", "depth change (Eq. 4)", "depth_change_mm", "mm",
        "pitting.depth_change_mm", flags="pitting", validity=_DP,
    ),
    RowSpec(
        PITTING, "D_p", "pitting depth (Eq. 3)", "depth_mm", "mm", "pitting.depth_mm",
        flags="pitting", validity=_DP,
    ),
    RowSpec(
        PITTING, "F_r", "rebound force (Eq. 5)", "rebound_force_n", "N",
        "pitting.rebound_force_n", flags="pitting", validity=_FR,
    ),
    RowSpec(
        PITTING, "T_r", "recovery time (Eq. 6)", "recovery_time_s", "s",
        "pitting.recovery_time_s", flags="pitting", note="98 % settling time",
        note_if_flag=(Flag.NOT_SETTLED.value, "lower bound: S_k had not settled"),
        validity=_TR,
    ),
    RowSpec(
        VPR, "F_a", "applied force (mean over the hold)", "applied_force_n", "N",
        validity=("applied_force_n",),
    ),
    RowSpec(VPR, "R", "indenter radius", "indenter_radius_mm", "mm"),
    RowSpec(
        VPR, "E", "elasticity (Eq. 7)", "elasticity_kpa", "kPa", "paper_estimator.elasticity_kpa",
        flags="pitting", note_if_absent=_UNDEFINED, requires="paper_estimator",
        validity=("elasticity_kpa",),
    ),
    RowSpec(
        VPR, "η", "viscosity E·T_r (Eq. 8)", "viscosity_n_s_per_mm2", "N·s/mm²",
        "paper_estimator.viscosity_n_s_per_mm2", flags="pitting", note_if_absent=_UNDEFINED,
        requires="paper_estimator", validity=("viscosity_n_s_per_mm2",),
    ),
    RowSpec(
        FIT, "τ", "time constant", "time_constant_s", "s", "fitted_recovery.tau_s",
        uncertainty="fitted_recovery.tau_se_s", flags="fitted_recovery",
        note_if_absent="no fit (see flags and notes)", validity=_TAU,
    ),
    RowSpec(
        FIT, "A", "amplitude S_∞ - S_0", "amplitude_px", "px", "fitted_recovery.amplitude_px",
        uncertainty="fitted_recovery.amplitude_se_px", flags="fitted_recovery", validity=_TAU,
    ),
    RowSpec(
        FIT, "S_∞", "offset (settled S_k)", "offset_px", "px", "fitted_recovery.offset_px",
        uncertainty="fitted_recovery.offset_se_px", flags="fitted_recovery", validity=_TAU,
    ),
    RowSpec(
        FIT, "η_τ", "viscosity E·τ", "viscosity_from_time_constant_n_s_per_mm2", "N·s/mm²",
        "fitted_recovery.model.viscosity_n_s_per_mm2", uncertainty=_viscosity_from_tau_se,
        flags="fitted_recovery", note="SE from τ only", validity=("tau_s", "elasticity_kpa"),
    ),
    RowSpec(
        FIT, "RMSE", "residual RMS", "rmse_px", "px", "fitted_recovery.rmse_px", validity=_TAU
    ),
    RowSpec(
        FIT, "R²", "coefficient of determination", "r_squared", "-", "fitted_recovery.r_squared",
        validity=_TAU,
    ),
    RowSpec(FIT, "n", "frames fitted", "n_points", "-", "fitted_recovery.n_points"),
)
# fmt: on


def _at(results: Mapping[str, Any], path: str) -> Any:
    return value_at(results, *path.split("."))


def _render(
    spec: RowSpec, results: Mapping[str, Any], validity: Mapping[str, QuantityStatus] | None
) -> ParameterRow:
    """The line ``spec`` describes, read from ``results``, with its quantities' validity."""
    value = number_at(results, *(spec.value or spec.key).split("."))
    if spec.uncertainty is None:
        se = None
    elif isinstance(spec.uncertainty, str):
        se = number_at(results, *spec.uncertainty.split("."))
    else:
        se = spec.uncertainty(results)
    flags = () if spec.flags is None else flags_at(_at(results, spec.flags))
    absent = value is None if spec.requires is None else _at(results, spec.requires) is None
    note = spec.note_if_absent if absent and spec.note_if_absent else spec.note
    if spec.note_if_flag is not None and spec.note_if_flag[0] in flags:
        note = spec.note_if_flag[1]
    return ParameterRow(
        spec.group,
        spec.symbol,
        spec.name,
        spec.key,
        value,
        se,
        spec.unit,
        flags,
        note,
        validity=combined(validity, spec.validity),
    )


#: Quantities each estimator's severity depends on (its class and recovered percentage).
_SEVERITY_VALIDITY: Final = {"paper_estimator": ("severity",), "fitted_recovery": ("tau_s",)}


def _severity_rows(
    results: Mapping[str, Any], validity: Mapping[str, QuantityStatus] | None
) -> list[ParameterRow]:
    """Class and recovered percentage of each estimator of :data:`SEVERITY_ESTIMATORS`."""
    rows: list[ParameterRow] = []
    for est, label in SEVERITY_ESTIMATORS:
        name, key = f"severity ({label})", f"severity_{est}"
        s = value_at(results, "severity", est)
        valid = combined(validity, _SEVERITY_VALIDITY[est])
        if not isinstance(s, Mapping):
            rows.append(
                ParameterRow(
                    SEVERITY, "class", name, key, None, None, "", (), _UNDEFINED, validity=valid
                )
            )
            continue
        w = value_at(s, "window_s")
        window = f"{w[0]:g}-{w[1]:g} s" if isinstance(w, list) and len(w) == 2 else "?"
        thr = number_at(s, "threshold_recovered_percent")
        flags = flags_at(s)
        grade = f"{s.get('severity')} (nearest grade {s.get('nearest_grade')})"
        rows += [
            ParameterRow(SEVERITY, "class", name, key, grade, None, "", flags, validity=valid),
            ParameterRow(
                SEVERITY,
                "recovered",
                f"recovered over {window} ({label})",
                f"recovered_percent_{est}",
                number_at(s, "recovered_percent"),
                None,
                "%",
                flags,
                "" if thr is None else f"severe below {thr:.1f} %",
                validity=valid,
            ),
        ]
    return rows


def _with_ground_truth(
    rows: Sequence[ParameterRow], summary: Mapping[str, Any], truth: Mapping[str, Any]
) -> list[ParameterRow]:
    """``rows`` with the simulator's ground truth and the error against it [%]."""
    comparisons = {c.name: c for c in compare_ground_truth(summary, truth)}
    out = []
    for r in rows:
        c = comparisons.get(r.key)
        t_value = c.truth if c is not None else None
        if c is None and r.key in _TRUTH_READ_DIRECTLY:
            t_value = number_at(truth, r.key)
        err = c.error_percent if c is not None else None
        if err is None and t_value not in (None, 0.0) and isinstance(r.value, float):
            assert t_value is not None
            err = 100.0 * (r.value - t_value) / abs(t_value)
        out.append(replace(r, truth=t_value, error_percent=err))
    return out


def parameter_table(summary: Mapping[str, Any] | None) -> tuple[ParameterRow, ...]:
    """Every result of the session's summary, with uncertainties, flags, validity and truth.

    The lines of :data:`PARAMETER_ROWS`, then each estimator's severity. The standard
    error of eta_tau = E tau is propagated from tau's alone (E has none). Each row carries the
    validity of the quantities it depends on (``unknown`` for a session recorded before
    validity was kept). Empty when the summary has no results.
    """
    res = value_at(summary, "results")
    if not isinstance(res, Mapping):
        return ()
    validity = read_validity(summary)
    rows = [_render(spec, res, validity) for spec in PARAMETER_ROWS]
    rows += _severity_rows(res, validity)
    truth = value_at(summary, "ground_truth")
    if isinstance(truth, Mapping):
        rows = _with_ground_truth(rows, summary or {}, truth)
    return tuple(rows)


def flag_descriptions() -> dict[str, str]:
    """Flag value -> what it means (:data:`~stipi_daemon.analysis.flags.FLAG_DESCRIPTIONS`)."""
    return {flag.value: text for flag, text in FLAG_DESCRIPTIONS.items()}
