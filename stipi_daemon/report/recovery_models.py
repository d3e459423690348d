"""The recovery models side by side: their table, its plain text, and the curves' figure data.

The analysis fits Kelvin-Voigt, two time constants and a power law to the same recovery
frames and writes ``summary["results"]["recovery_models"]`` (docs/analysis.md, "Recovery
models, model selection and intervals"). This module turns that record into

* :class:`RecoveryModelsView`: one :class:`ModelRow` per model with its Akaike weight
  (AICc), its QAICc weight and Delta QAICc (the QAICc decides the Kelvin-Voigt rejection
  and the best model), tau, T_r, F_r and eta each with its 95 % interval, the best model
  marked, what tau means for the model, and the rejection line with its rule and flag
  text; every number as text by the report's one rule (:mod:`.numbers`, a value to 4
  significant figures; an interval's bounds are values too). A missing interval reads
  ``n/a`` with the reason (:func:`interval_reason`);
* :func:`recovery_models_text`: the same table in plain text (``stipi-daemon report``);
* :class:`RecoveryModelsFigure`: the recovery S_k frames with each model's curve, evaluated
  by the model's own function (:meth:`~stipi_daemon.analysis.recovery_models.RecoveryModel.
  curve`) at the frame times, never re-derived here.

A summary written before the models were compared has no ``recovery_models``; one whose
analysis refused the series holds None (its reason in the notes). Either gives no view,
only :func:`absence_line`. Pure: no I/O, no drawing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from stipi_daemon.analysis.flags import FLAG_DESCRIPTIONS, Flag
from stipi_daemon.analysis.recovery_models import MODELS
from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.figures import recorded_outliers
from stipi_daemon.report.inputs import FloatArray, ReportInput, number_at, value_at
from stipi_daemon.report.numbers import value_text

__all__ = [
    "INTERVAL_QUANTITIES",
    "NOT_AVAILABLE",
    "ModelCurve",
    "ModelRow",
    "RecoveryModelsFigure",
    "RecoveryModelsView",
    "absence_line",
    "interval_reason",
    "interval_text",
    "recovery_models_figure",
    "recovery_models_text",
    "recovery_models_view",
]

#: Quantities with a 95 % interval shown in the table: key -> (symbol, unit).
INTERVAL_QUANTITIES: Final[dict[str, tuple[str, str]]] = {
    "tau_s": ("τ", "s"),
    "recovery_time_s": ("T_r", "s"),
    "rebound_force_n": ("F_r", "N"),
    # the paper's eta = E T_r with the model's T_r (a Kelvin-Voigt row's is not its E tau)
    "viscosity_n_s_per_mm2": ("η (E·T_r)", "N·s/mm²"),
}
#: A missing interval.
NOT_AVAILABLE: Final = "n/a"
#: Plain names of the registered models, for legends and the text table.
_SHORT_NAMES: Final[dict[str, str]] = {
    "kelvin_voigt": "Kelvin-Voigt",
    "two_exponential": "two exponentials",
    "power_law": "power law",
}


def _short(name: str) -> str:
    return _SHORT_NAMES.get(name, name)


@dataclass(frozen=True)
class ModelRow:
    """One model of the table, its numbers as the report writes them.

    Attributes
    ----------
    name, title, equation, tau_meaning : str
        Registry name, human-readable name, g(x) and what the model's tau is.
    best : bool
        The model with the highest QAICc weight.
    akaike_weight, qaicc_weight, delta_qaicc : str
        AICc weight, QAICc weight and QAICc - min QAICc (``-`` when not computed).
    values : dict of str to str
        Key of :data:`INTERVAL_QUANTITIES` -> the value's text (``-`` when missing).
    intervals : dict of str to str
        Same keys -> ``[low, high]`` text, or ``n/a (<reason>)``.
    block_length : int or None
        Block length of the bootstrap [samples].
    flags : tuple of str
        The model's flags.
    """

    name: str
    title: str
    equation: str
    tau_meaning: str
    best: bool
    akaike_weight: str
    qaicc_weight: str
    delta_qaicc: str
    values: dict[str, str]
    intervals: dict[str, str]
    block_length: int | None
    flags: tuple[str, ...]

    @property
    def short_name(self) -> str:
        """Plain name (legend, text table)."""
        return _short(self.name)


@dataclass(frozen=True)
class RecoveryModelsView:
    """The recovery-models section of a report (:func:`recovery_models_view`).

    Attributes
    ----------
    rows : tuple of ModelRow
        In the analysis' order (Kelvin-Voigt first).
    best_model : str or None
        Registry name of the best model (highest QAICc weight).
    kelvin_voigt_rejected : bool
        Whether the analysis raised ``kelvin_voigt_rejected``.
    rejection_line : str
        Kelvin-Voigt's Delta QAICc against the rule, and the decision.
    flag_text : str
        The flag's meaning (:data:`~stipi_daemon.analysis.flags.FLAG_DESCRIPTIONS`) when
        raised, else empty.
    selection, intervals : str
        The selection rule and the interval method, as recorded.
    window_text : str
        Fitted samples, span, bootstrap replicates and seed, variance inflation c.
    flags : tuple of str
        The comparison's own flags.
    """

    rows: tuple[ModelRow, ...]
    best_model: str | None
    kelvin_voigt_rejected: bool
    rejection_line: str
    flag_text: str
    selection: str
    intervals: str
    window_text: str
    flags: tuple[str, ...]


def absence_line(results: Mapping[str, Any] | None, notes: Sequence[str] = ()) -> str | None:
    """One line saying why a session shows no recovery models; None when it has them."""
    if results is None:
        return "Recovery models: not shown, the session has no results."
    if "recovery_models" not in results:
        return (
            "Recovery models: not in this session's summary (analysed before the models were "
            "compared); stipi-daemon analyze SESSION computes them."
        )
    if not isinstance(results.get("recovery_models"), Mapping):
        why = next((n for n in notes if n.startswith("recovery models not compared")), "")
        return "Recovery models: not compared" + (
            why.removeprefix("recovery models not compared") + "."
            if why
            else " (the analysis recorded none)."
        )
    return None


def interval_reason(entry: Mapping[str, Any], key: str, replicates: Any) -> str:
    """Why model ``entry`` has no 95 % interval on ``key`` (a ``ci95`` key)."""
    if number_at(entry, key) is None:
        return "no value"
    flags = entry.get("flags")
    if isinstance(flags, list) and Flag.NO_CONFIDENCE_INTERVALS.value in flags:
        return "not computed: fewer than 12 samples, or over 10 % of bootstrap refits failed"
    boot = value_at(entry, "bootstrap", "replicates")
    if replicates == 0 or boot == 0:
        return "no bootstrap (analysis.bootstrap_replicates = 0)"
    return "unbounded: some bootstrap replicates have no finite value"


def interval_text(entry: Mapping[str, Any], key: str, replicates: Any) -> str:
    """``[low, high]`` of ``entry["ci95"][key]`` by the rounding rule, or ``n/a (why)``."""
    ci = value_at(entry, "ci95", key)
    if isinstance(ci, list) and len(ci) == 2:
        lo, hi = (number_at({"v": v}, "v") for v in ci)
        if lo is not None and hi is not None:
            return f"[{value_text(lo)}, {value_text(hi)}]"
    return f"{NOT_AVAILABLE} ({interval_reason(entry, key, replicates)})"


def _row(name: str, entry: Mapping[str, Any], best: str | None, replicates: Any) -> ModelRow:
    block = value_at(entry, "bootstrap", "block_length")
    flags = entry.get("flags")
    return ModelRow(
        name=name,
        title=str(entry.get("title") or name),
        equation=str(entry.get("equation") or ""),
        tau_meaning=str(entry.get("tau_meaning") or ""),
        best=name == best,
        akaike_weight=value_text(number_at(entry, "akaike_weight")),
        qaicc_weight=value_text(number_at(entry, "qaicc_weight")),
        delta_qaicc=value_text(number_at(entry, "delta_qaicc")),
        values={k: value_text(number_at(entry, k)) for k in INTERVAL_QUANTITIES},
        intervals={k: interval_text(entry, k, replicates) for k in INTERVAL_QUANTITIES},
        block_length=block if isinstance(block, int) and not isinstance(block, bool) else None,
        flags=tuple(str(f) for f in flags) if isinstance(flags, list) else (),
    )


def recovery_models_view(results: Mapping[str, Any] | None) -> RecoveryModelsView | None:
    """The section's content from ``results["recovery_models"]``; None when there is none."""
    rm = value_at(results, "recovery_models")
    models = value_at(rm, "models")
    if not isinstance(rm, Mapping) or not isinstance(models, Mapping):
        return None
    best = rm.get("best_model") if isinstance(rm.get("best_model"), str) else None
    replicates = rm.get("bootstrap_replicates")
    rows = tuple(
        _row(str(name), entry, best, replicates)
        for name, entry in models.items()
        if isinstance(entry, Mapping)
    )
    rejected = rm.get("kelvin_voigt_rejected") is True
    rule = str(rm.get("kelvin_voigt_rejection_rule") or "")
    delta = value_text(number_at(rm, "kelvin_voigt_delta_qaicc"))
    if rejected:
        decision = f"Kelvin-Voigt rejected ({Flag.KELVIN_VOIGT_REJECTED.value})"
    elif delta == "-":
        decision = "Kelvin-Voigt neither confirmed nor rejected (no QAICc)"
    else:
        decision = "Kelvin-Voigt not rejected"
    window = value_at(rm, "window_s")
    span = (
        f" over {value_text(float(window[1]) - float(window[0]), 's')}"
        if isinstance(window, list) and len(window) == 2 and all(_number(w) for w in window)
        else ""
    )
    flags = rm.get("flags")
    return RecoveryModelsView(
        rows=rows,
        best_model=best,
        kelvin_voigt_rejected=rejected,
        rejection_line=(
            f"{decision}: QAICc(Kelvin-Voigt) - min QAICc = {delta}; rule: {rule or '-'}."
        ),
        flag_text=FLAG_DESCRIPTIONS[Flag.KELVIN_VOIGT_REJECTED] if rejected else "",
        selection=str(rm.get("selection") or ""),
        intervals=str(rm.get("intervals") or ""),
        window_text=(
            f"{value_text(number_at(rm, 'n_points'))} frames{span}; variance inflation c = "
            f"{value_text(number_at(rm, 'variance_inflation'))}; bootstrap: "
            f"{value_text(number_at(rm, 'bootstrap_replicates'))} replicates, seed "
            f"{value_text(number_at(rm, 'bootstrap_seed'))}"
        ),
        flags=tuple(str(f) for f in flags) if isinstance(flags, list) else (),
    )


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


#: Column headings of the table (HTML and text), after the model's name.
COLUMNS: Final = (
    "Akaike weight (AICc)",
    "QAICc weight (decides)",
    "ΔQAICc",
    "τ [s]",
    "T_r [s]",
    "F_r [N]",
    "η = E·T_r [N·s/mm²]",
)


def quantity_cell(row: ModelRow, key: str) -> str:
    """``value [low, high]`` or ``value n/a (why)`` of one quantity."""
    return f"{row.values[key]} {row.intervals[key]}"


def row_cells(row: ModelRow) -> tuple[str, ...]:
    """The cells of :data:`COLUMNS` for ``row``."""
    return (
        row.akaike_weight,
        row.qaicc_weight,
        row.delta_qaicc,
        *(quantity_cell(row, k) for k in INTERVAL_QUANTITIES),
    )


def recovery_models_text(view: RecoveryModelsView | None, absence: str | None = None) -> str:
    """The table as plain text (``stipi-daemon report``), or the one absence line."""
    if view is None:
        return absence or "Recovery models: none recorded."
    lines = ["recovery models (value [95 % interval]; the best model marked *):"]
    for row in view.rows:
        mark = "*" if row.best else " "
        lines.append(
            f" {mark} {row.short_name}: Akaike weight {row.akaike_weight}, QAICc weight "
            f"{row.qaicc_weight}, ΔQAICc {row.delta_qaicc}"
            + (f" [{', '.join(row.flags)}]" if row.flags else "")
        )
        lines.append(
            "     "
            + "; ".join(
                f"{sym} = {quantity_cell(row, k)} {unit}"
                for k, (sym, unit) in INTERVAL_QUANTITIES.items()
            )
        )
        lines.append(f"     τ: {row.tau_meaning}")
    lines.append("  " + view.rejection_line)
    if view.flag_text:
        lines.append(f"  {Flag.KELVIN_VOIGT_REJECTED.value}: {view.flag_text}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The figure: recovery S_k with every model's curve
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelCurve:
    """One model's curve of the figure.

    Attributes
    ----------
    name : str
        Registry name.
    label : str
        Legend text: the model and its weights.
    t_since_t0_s, model_px : numpy.ndarray
        Frame times since T_0 [s] and the model's curve there [px] (empty: not drawn).
    best : bool
        The best model (drawn widest).
    not_drawn : str
        Why the curve is empty.
    """

    name: str
    label: str
    t_since_t0_s: FloatArray
    model_px: FloatArray
    best: bool
    not_drawn: str = ""


@dataclass(frozen=True)
class RecoveryModelsFigure:
    """The recovery S_k frames of the models' window and every model's curve.

    Attributes
    ----------
    t0_s : float
        T_0 [s] (the curves' time origin).
    t_since_t0_s, s_k_px : numpy.ndarray
        Fitted frames (window of ``recovery_models``, outliers left out) [s since T_0], [px].
    rejected_t_since_t0_s, rejected_s_k_px : numpy.ndarray
        Frames of the window the analysis left out as outliers.
    curves : tuple of ModelCurve
        One per model, in the analysis' order.
    rejection_line : str
        The Kelvin-Voigt decision (title).
    """

    t0_s: float
    t_since_t0_s: FloatArray
    s_k_px: FloatArray
    rejected_t_since_t0_s: FloatArray
    rejected_s_k_px: FloatArray
    curves: tuple[ModelCurve, ...]
    rejection_line: str


def model_curve_px(
    name: str, parameters: Mapping[str, Any], t_s: FloatArray, t0_s: float
) -> FloatArray:
    """Model ``name``'s curve at ``t_s`` [s] from its recorded ``parameters`` [px, s, 1].

    The recorded keys ``offset_px`` and ``amplitude_px`` are the model function's
    ``offset`` and ``amplitude``; the function is the model's own.

    Raises
    ------
    AnalysisError
        An unknown model, or parameters the model refuses (missing, out of bounds).
    """
    model = MODELS.get(name)
    if model is None:
        raise AnalysisError(f"recovery model {name!r} is not known to this version")
    kw = {
        k.removesuffix("_px") if k in ("offset_px", "amplitude_px") else k: float(v)
        for k, v in parameters.items()
        if _number(v)
    }
    return model.curve(t_s, t0_s, **kw)


def _legend(row: ModelRow) -> str:
    return (
        f"{row.short_name}{' (best)' if row.best else ''}: Akaike w = {row.akaike_weight}, "
        f"QAICc w = {row.qaicc_weight}; τ = {row.values['tau_s']} s"
    )


def recovery_models_figure(inp: ReportInput) -> RecoveryModelsFigure | None:
    """The figure's data; None when the session has no recovery models or no T_0."""
    view = recovery_models_view(inp.results)
    rm = value_at(inp.results, "recovery_models")
    window = value_at(rm, "window_s")
    t0 = number_at(inp.results, "pitting", "t0_s")
    if view is None or t0 is None or not isinstance(window, list) or len(window) != 2:
        return None
    if not all(_number(w) for w in window):
        return None
    lo, hi = float(window[0]), float(window[1])
    t, s = inp.frame_times_s, inp.s_k_px
    sel = (t >= lo) & (t <= hi) & (t >= t0) & np.isfinite(s)
    rejected = sel & recorded_outliers(inp)
    sel &= ~rejected
    ts = t[sel]
    curves: list[ModelCurve] = []
    for row in view.rows:
        params = value_at(rm, "models", row.name, "parameters")
        empty = np.zeros(0)
        if not isinstance(params, Mapping):
            reason = "not fitted" + (f" ({', '.join(row.flags)})" if row.flags else "")
            curves.append(
                ModelCurve(row.name, f"{row.short_name}: {reason}", empty, empty, row.best, reason)
            )
            continue
        try:
            y = model_curve_px(row.name, params, ts, t0)
        except AnalysisError as exc:
            curves.append(
                ModelCurve(
                    row.name,
                    f"{row.short_name}: not drawn ({exc})",
                    empty,
                    empty,
                    row.best,
                    str(exc),
                )
            )
            continue
        curves.append(ModelCurve(row.name, _legend(row), ts - t0, y, row.best))
    return RecoveryModelsFigure(
        t0_s=t0,
        t_since_t0_s=ts - t0,
        s_k_px=s[sel],
        rejected_t_since_t0_s=t[rejected] - t0,
        rejected_s_k_px=s[rejected],
        curves=tuple(curves),
        rejection_line=view.rejection_line,
    )
