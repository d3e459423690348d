"""Comparison of several sessions (``report --compare``): values, mean and spread.

Each session's parameters side by side, their mean, sample standard deviation and
coefficient of variation per group of sessions sharing a label (repeated trials of one
phantom) and over all of them, as the paper's Tables I and II; and each session's S_k and
force against the time since its own T_0, for the overlay figures. It is pure: the sessions
come as :class:`~.inputs.ReportInput`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.inputs import FloatArray, ReportInput, number_at, value_at
from stipi_daemon.report.verdict import VerdictView, combined, read_validity, session_verdict

__all__ = [
    "COMPARE_PARAMETERS",
    "COMPARE_VALIDITY",
    "CompareGroup",
    "CompareStat",
    "CompareTable",
    "OverlaySeries",
    "compare_table",
    "overlay_force",
    "overlay_s_k",
    "value_status",
]

#: Parameters tabulated by :func:`compare_table`: (key, symbol, unit, path in the results).
#: Their validity is that of the quantities in :data:`COMPARE_VALIDITY`.
COMPARE_PARAMETERS: Final[tuple[tuple[str, str, str, tuple[str, ...]], ...]] = (
    ("depth_mm", "D_p", "mm", ("pitting", "depth_mm")),
    ("rebound_force_n", "F_r", "N", ("pitting", "rebound_force_n")),
    ("recovery_time_s", "T_r", "s", ("pitting", "recovery_time_s")),
    ("applied_force_n", "F_a", "N", ("applied_force_n",)),
    ("elasticity_kpa", "E", "kPa", ("paper_estimator", "elasticity_kpa")),
    ("viscosity_n_s_per_mm2", "η = E·T_r", "N·s/mm²", ("paper_estimator", "viscosity_n_s_per_mm2")),
    ("time_constant_s", "τ", "s", ("fitted_recovery", "tau_s")),
    (
        "viscosity_from_time_constant_n_s_per_mm2",
        "η = E·τ",
        "N·s/mm²",
        ("fitted_recovery", "model", "viscosity_n_s_per_mm2"),
    ),
)
#: Parameter key -> the ``summary["validity"]`` quantities its value depends on.
COMPARE_VALIDITY: Final[dict[str, tuple[str, ...]]] = {
    "depth_mm": ("depth_mm",),
    "rebound_force_n": ("rebound_force_n",),
    "recovery_time_s": ("recovery_time_s",),
    "applied_force_n": ("applied_force_n",),
    "elasticity_kpa": ("elasticity_kpa",),
    "viscosity_n_s_per_mm2": ("viscosity_n_s_per_mm2",),
    "time_constant_s": ("tau_s",),
    "viscosity_from_time_constant_n_s_per_mm2": ("tau_s", "elasticity_kpa"),
}


@dataclass(frozen=True)
class CompareStat:
    """Mean and spread of one parameter over a group of sessions.

    Attributes
    ----------
    key, symbol, unit : str
        The parameter.
    values : tuple of float or None
        Each session's value, in the group's order (None: the session has none).
    statuses : tuple of str
        Each value's validity (``valid``, ``flagged``, ``invalid``, ``unknown``: recorded
        before validity was kept).
    n : int
        Sessions whose value enters the mean (a value that is not invalid).
    n_excluded : int
        Values left out of the mean because they are invalid.
    n_flagged : int
        Flagged values included in the mean.
    n_unknown : int
        Values of unknown validity included in the mean.
    mean : float or None
        Mean over the values that are not invalid.
    sd : float or None
        Sample standard deviation (n - 1), None for n < 2.
    cv_percent : float or None
        100 sd / |mean| [%].
    """

    key: str
    symbol: str
    unit: str
    values: tuple[float | None, ...]
    statuses: tuple[str, ...]
    n: int
    n_excluded: int
    n_flagged: int
    n_unknown: int
    mean: float | None
    sd: float | None
    cv_percent: float | None


@dataclass(frozen=True)
class CompareGroup:
    """Sessions sharing a label (e.g. repeated trials of one phantom) and their statistics."""

    label: str
    session_ids: tuple[str, ...]
    stats: tuple[CompareStat, ...]
    severe_count: int
    classified_count: int


@dataclass(frozen=True)
class CompareTable:
    """Per-session values and per-group and overall mean and spread (Tables I and II).

    Attributes
    ----------
    session_ids, labels : tuple of str
        The sessions and their labels, in the order given.
    severities : tuple of str or None
        Each session's class and nearest grade from the paper estimator (``"severe
        (III)"``), None without one or when it is invalid.
    verdicts : tuple of VerdictView
        Each session's verdict.
    groups : tuple of CompareGroup
        One per distinct label, in first-appearance order.
    overall : CompareGroup
        All sessions together.
    """

    session_ids: tuple[str, ...]
    labels: tuple[str, ...]
    severities: tuple[str | None, ...]
    verdicts: tuple[VerdictView, ...]
    groups: tuple[CompareGroup, ...]
    overall: CompareGroup


def _stat(
    key: str,
    symbol: str,
    unit: str,
    values: tuple[float | None, ...],
    statuses: tuple[str, ...],
) -> CompareStat:
    """Mean and spread of the values that are not invalid (invalid ones are counted)."""
    kept = [x for x, st in zip(values, statuses, strict=True) if x is not None and st != "invalid"]
    v = np.asarray(kept, dtype=np.float64)
    mean = float(np.mean(v)) if v.size else None
    sd = float(np.std(v, ddof=1)) if v.size >= 2 else None
    cv = None if sd is None or mean is None or mean == 0.0 else 100.0 * sd / abs(mean)
    present = [st for x, st in zip(values, statuses, strict=True) if x is not None]
    return CompareStat(
        key,
        symbol,
        unit,
        values,
        statuses,
        int(v.size),
        present.count("invalid"),
        present.count("flagged"),
        present.count("unknown"),
        mean,
        sd,
        cv,
    )


def value_status(inp: ReportInput, key: str) -> str:
    """The validity of parameter ``key`` of a session (``unknown`` without a record)."""
    v = combined(read_validity(inp.summary), COMPARE_VALIDITY[key])
    return "unknown" if v is None else v.status


def _severity_class(inp: ReportInput) -> str | None:
    """The paper estimator's class, None when there is none or it is invalid."""
    v = combined(read_validity(inp.summary), ("severity",))
    if v is not None and v.status == "invalid":
        return None
    cls = value_at(inp.results, "severity", "paper_estimator", "severity")
    return None if cls is None else str(cls)


def _group(label: str, members: Sequence[ReportInput]) -> CompareGroup:
    stats = tuple(
        _stat(
            key,
            symbol,
            unit,
            tuple(number_at(m.results, *path) for m in members),
            tuple(value_status(m, key) for m in members),
        )
        for key, symbol, unit, path in COMPARE_PARAMETERS
    )
    classes = [_severity_class(m) for m in members]
    return CompareGroup(
        label=label,
        session_ids=tuple(m.session_id for m in members),
        stats=stats,
        severe_count=sum(c == "severe" for c in classes),
        classified_count=sum(c is not None for c in classes),
    )


def compare_table(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> CompareTable:
    """Tabulate several sessions: each one's values, mean and spread per label and overall.

    A value that is invalid in its session's ``summary["validity"]`` is listed but left
    out of every mean and spread (counted in :attr:`CompareStat.n_excluded`); flagged
    values and those of older sessions without validity enter them, counted.

    Parameters
    ----------
    inputs : sequence of ReportInput
        The sessions (at least one).
    labels : sequence of str, optional
        One label per session (e.g. the grade); sessions with the same label form a group
        (repeated trials). Default: each session's id.

    Raises
    ------
    AnalysisError
        No session, or a label count that differs from the session count.
    """
    if not inputs:
        raise AnalysisError("nothing to compare: no session given")
    names = tuple(labels) if labels is not None else tuple(i.session_id for i in inputs)
    if len(names) != len(inputs):
        raise AnalysisError(f"{len(names)} labels for {len(inputs)} sessions")
    order: dict[str, list[ReportInput]] = {}
    for name, inp in zip(names, inputs, strict=True):
        order.setdefault(name, []).append(inp)
    severities: list[str | None] = []
    for inp in inputs:
        sev = value_at(inp.results, "severity", "paper_estimator")
        cls, grade = _severity_class(inp), value_at(sev, "nearest_grade")
        severities.append(None if cls is None else f"{cls} ({grade})")
    return CompareTable(
        session_ids=tuple(i.session_id for i in inputs),
        labels=names,
        severities=tuple(severities),
        verdicts=tuple(session_verdict(i.summary, i.status) for i in inputs),
        groups=tuple(_group(name, members) for name, members in order.items()),
        overall=_group("all sessions", list(inputs)),
    )


@dataclass(frozen=True)
class OverlaySeries:
    """One session's series against time since its T_0, for overlays.

    Attributes
    ----------
    label : str
        Legend text.
    t_since_t0_s : numpy.ndarray
        Times since the session's T_0 [s].
    values : numpy.ndarray
        The series (S_k [px] or force [N]).
    """

    label: str
    t_since_t0_s: FloatArray
    values: FloatArray


def _overlay(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None, which: str
) -> tuple[OverlaySeries, ...]:
    names = list(labels) if labels is not None else [i.session_id for i in inputs]
    out = []
    for name, inp in zip(names, inputs, strict=True):
        t0 = inp.t0_s
        if t0 is None:
            continue
        t, v = (
            (inp.frame_times_s, inp.s_k_px) if which == "s_k" else (inp.force_times_s, inp.force_n)
        )
        out.append(OverlaySeries(name, t - t0, v))
    return tuple(out)


def overlay_s_k(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> tuple[OverlaySeries, ...]:
    """Each session's S_k [px] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "s_k")


def overlay_force(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> tuple[OverlaySeries, ...]:
    """Each session's force [N] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "force")
