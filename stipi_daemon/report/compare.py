"""Comparison of several sessions (``report --compare``): values, mean and spread.

Each session's parameters side by side with their validity and flags, and the mean, sample
standard deviation and coefficient of variation per grade (the sessions sharing a label,
i.e. repeated trials of one phantom, or without labels the nearest grade found), as the
paper's Tables I and II; and each session's S_k and force against the time since its own
T_0, for the overlay figures. Nothing of different grades, nor of a session whose verdict
is not ``complete``, is averaged: such sessions are listed one by one with the reason. It
is pure: the sessions come as :class:`~.inputs.ReportInput`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np

from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.inputs import FloatArray, ReportInput, flags_at, number_at, value_at
from stipi_daemon.report.verdict import VerdictView, combined, read_validity, session_verdict

__all__ = [
    "COMPARE_PARAMETERS",
    "COMPARE_VALIDITY",
    "CompareGroup",
    "CompareSession",
    "CompareStat",
    "CompareTable",
    "OverlaySeries",
    "SessionValue",
    "compare_table",
    "overlay_force",
    "overlay_s_k",
    "recovery_model_text",
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
        "η_τ = E·τ",
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
class SessionValue:
    """One session's value of one parameter, with its validity in that session.

    Attributes
    ----------
    value : float or None
        The value (None: the session has none).
    status : str
        ``valid``, ``flagged``, ``invalid`` or ``unknown`` (recorded before validity was
        kept).
    flags : tuple of str
        The flags that concern it.
    reason : str or None
        Why it is flagged or invalid.
    """

    value: float | None
    status: str
    flags: tuple[str, ...] = ()
    reason: str | None = None


@dataclass(frozen=True)
class CompareSession:
    """One session of a comparison.

    Attributes
    ----------
    session_id, label : str
        The session and the label it was given (its id without one).
    group : str
        The grade it is grouped under: its label, or without labels the nearest grade its
        analysis found (``"grade II (nearest)"``); ``""`` when it has neither.
    verdict : VerdictView
        Its verdict.
    severity : str or None
        The paper estimator's class and nearest grade (``"severe (III)"``), None without
        one or when it is invalid.
    flags : tuple of str
        Every flag of its results and its measurement.
    subject : str or None
        The ``subject`` of its metadata.
    values : dict of str to SessionValue
        Parameter key (:data:`COMPARE_PARAMETERS`) -> its value.
    left_out : str or None
        Why the session enters no mean (None: it does).
    recovery_model : str
        The best recovery model and whether Kelvin-Voigt is rejected
        (:func:`recovery_model_text`).
    """

    session_id: str
    label: str
    group: str
    verdict: VerdictView
    severity: str | None
    flags: tuple[str, ...]
    subject: str | None
    values: dict[str, SessionValue]
    left_out: str | None
    recovery_model: str = "-"


@dataclass(frozen=True)
class CompareStat:
    """Mean and spread of one parameter over the sessions a group averages.

    Attributes
    ----------
    key, symbol, unit : str
        The parameter.
    n : int
        Values that enter the mean (valid ones).
    n_excluded : int
        Values of averaged sessions left out because they are not valid (a flagged or
        invalid secondary quantity of a complete session).
    mean : float or None
        Mean over the valid values.
    sd : float or None
        Sample standard deviation (n - 1), None for n < 2.
    cv_percent : float or None
        100 sd / |mean| [%].
    """

    key: str
    symbol: str
    unit: str
    n: int
    n_excluded: int
    mean: float | None
    sd: float | None
    cv_percent: float | None


@dataclass(frozen=True)
class CompareGroup:
    """The sessions of one grade: the mean and spread of those that may be averaged.

    Attributes
    ----------
    label : str
        The grade (a label given, or the nearest grade found).
    session_ids : tuple of str
        The sessions averaged: those whose verdict is ``complete``.
    left_out : tuple of (str, str)
        (session id, why) of the group's other sessions: flagged, invalid, incomplete or
        of unknown validity. They are shown one by one, never averaged.
    stats : tuple of CompareStat
        One per parameter of :data:`COMPARE_PARAMETERS`, over :attr:`session_ids`.
    severe_count, classified_count : int
        Averaged sessions classified severe, and classified at all.
    """

    label: str
    session_ids: tuple[str, ...]
    left_out: tuple[tuple[str, str], ...]
    stats: tuple[CompareStat, ...]
    severe_count: int
    classified_count: int


@dataclass(frozen=True)
class CompareTable:
    """Each session's values and, per grade, the mean and spread (Tables I and II).

    Attributes
    ----------
    sessions : tuple of CompareSession
        The sessions in the order given.
    groups : tuple of CompareGroup
        One per grade, in first-appearance order. Sessions of different grades are never
        averaged together, and no mean is taken over all sessions.
    grouped_by : {"label", "nearest grade"}
        Whether the grades are the labels given or the grades the analysis found.
    ungrouped : tuple of (str, str)
        (session id, why) of sessions in no group (no label and no valid class).
    """

    sessions: tuple[CompareSession, ...]
    groups: tuple[CompareGroup, ...]
    grouped_by: Literal["label", "nearest grade"]
    ungrouped: tuple[tuple[str, str], ...] = ()

    @property
    def session_ids(self) -> tuple[str, ...]:
        """The sessions' ids, in the order given."""
        return tuple(s.session_id for s in self.sessions)

    @property
    def labels(self) -> tuple[str, ...]:
        """The sessions' labels, in the order given."""
        return tuple(s.label for s in self.sessions)

    @property
    def verdicts(self) -> tuple[VerdictView, ...]:
        """The sessions' verdicts, in the order given."""
        return tuple(s.verdict for s in self.sessions)


def _stat(key: str, symbol: str, unit: str, values: Sequence[SessionValue]) -> CompareStat:
    """Mean and spread of the valid values (the others are counted, never averaged)."""
    kept = [v.value for v in values if v.value is not None and v.status == "valid"]
    x = np.asarray(kept, dtype=np.float64)
    mean = float(np.mean(x)) if x.size else None
    sd = float(np.std(x, ddof=1)) if x.size >= 2 else None
    cv = None if sd is None or mean is None or mean == 0.0 else 100.0 * sd / abs(mean)
    excluded = sum(v.value is not None and v.status != "valid" for v in values)
    return CompareStat(key, symbol, unit, int(x.size), excluded, mean, sd, cv)


def _session_value(inp: ReportInput, key: str, path: tuple[str, ...]) -> SessionValue:
    v = combined(read_validity(inp.summary), COMPARE_VALIDITY[key])
    value = number_at(inp.results, *path)
    if v is None:
        return SessionValue(value, "unknown")
    return SessionValue(value, v.status, v.flags, v.reason)


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


def _session_flags(inp: ReportInput) -> tuple[str, ...]:
    """Every flag of the session's results, measurement and validity, sorted, once each."""
    found = [*flags_at(inp.results), *flags_at(value_at(inp.results, "pitting"))]
    found += flags_at(value_at(inp.results, "fitted_recovery"))
    for est in ("paper_estimator", "fitted_recovery"):
        found += flags_at(value_at(inp.results, "severity", est))
    measured = value_at(inp.summary, "measurement_flags")
    if isinstance(measured, list):
        found += [str(f) for f in measured]
    for q in (read_validity(inp.summary) or {}).values():
        found += q.flags
    return tuple(sorted(set(found)))


def _left_out(verdict: VerdictView) -> str | None:
    """Why a session with this verdict enters no mean (None: it does)."""
    if verdict.status == "complete":
        return None
    named = "; ".join(
        f"{p.symbol} {p.status}" + (f" ({', '.join(p.flags)})" if p.flags else "")
        for p in verdict.problems
    )
    return f"verdict {verdict.status}" + (f": {named}" if named else f": {verdict.line}")


def _subject(inp: ReportInput) -> str | None:
    s = value_at(inp.metadata, "subject")
    return None if s is None else str(s)


def _grade_of(inp: ReportInput) -> str:
    """The nearest grade of the session's valid severity class, ``""`` without one."""
    if _severity_class(inp) is None:
        return ""
    grade = value_at(inp.results, "severity", "paper_estimator", "nearest_grade")
    return "" if grade is None else f"grade {grade} (nearest)"


def recovery_model_text(results: Mapping[str, Any] | None) -> str:
    """The best recovery model and the Kelvin-Voigt decision, in a few words.

    ``two_exponential; kelvin_voigt_rejected``, ``kelvin_voigt; Kelvin-Voigt not rejected``,
    or why there is none (no results, a summary from before the comparison, not compared).
    """
    if results is None:
        return "- (no results)"
    if "recovery_models" not in results:
        return "- (summary predates the recovery models)"
    rm = results.get("recovery_models")
    if not isinstance(rm, Mapping):
        return "- (not compared)"
    best = rm.get("best_model")
    best_text = str(best) if isinstance(best, str) else "none"
    if rm.get("kelvin_voigt_rejected") is True:
        return f"{best_text}; kelvin_voigt_rejected"
    if value_at(rm, "kelvin_voigt_delta_qaicc") is None:
        return f"{best_text}; Kelvin-Voigt not weighed"
    return f"{best_text}; Kelvin-Voigt not rejected"


def _session(inp: ReportInput, label: str, group: str) -> CompareSession:
    verdict = session_verdict(inp.summary, inp.status)
    cls = _severity_class(inp)
    grade = value_at(inp.results, "severity", "paper_estimator", "nearest_grade")
    return CompareSession(
        session_id=inp.session_id,
        label=label,
        group=group,
        verdict=verdict,
        severity=None if cls is None else f"{cls} ({grade})",
        flags=_session_flags(inp),
        subject=_subject(inp),
        values={key: _session_value(inp, key, path) for key, _, _, path in COMPARE_PARAMETERS},
        left_out=_left_out(verdict),
        recovery_model=recovery_model_text(inp.results),
    )


def _group(label: str, members: Sequence[CompareSession]) -> CompareGroup:
    averaged = [m for m in members if m.left_out is None]
    stats = tuple(
        _stat(key, symbol, unit, [m.values[key] for m in averaged])
        for key, symbol, unit, _ in COMPARE_PARAMETERS
    )
    classes = [None if m.severity is None else m.severity.split(" ")[0] for m in averaged]
    return CompareGroup(
        label=label,
        session_ids=tuple(m.session_id for m in averaged),
        left_out=tuple((m.session_id, m.left_out) for m in members if m.left_out is not None),
        stats=stats,
        severe_count=sum(c == "severe" for c in classes),
        classified_count=sum(c is not None for c in classes),
    )


def compare_table(
    inputs: Sequence[ReportInput], labels: Sequence[str] | None = None
) -> CompareTable:
    """Tabulate several sessions: each one's values, and the mean and spread per grade.

    Sessions are grouped by grade: by their labels when given (``--labels``, e.g. the
    phantom's grade), else by the nearest grade their analysis found. Within a group only
    sessions whose verdict is ``complete`` are averaged, and of them only valid values;
    flagged, invalid, incomplete sessions and those of unknown validity are listed one by
    one with the reason (:attr:`CompareGroup.left_out`). Sessions of different grades are
    never averaged together.

    Parameters
    ----------
    inputs : sequence of ReportInput
        The sessions (at least one).
    labels : sequence of str, optional
        One label per session; sessions with the same label form a group (repeated
        trials of one grade).

    Raises
    ------
    AnalysisError
        No session, or a label count that differs from the session count.
    """
    if not inputs:
        raise AnalysisError("nothing to compare: no session given")
    if labels is not None and len(labels) != len(inputs):
        raise AnalysisError(f"{len(labels)} labels for {len(inputs)} sessions")
    names = tuple(labels) if labels is not None else tuple(i.session_id for i in inputs)
    groups = tuple(labels) if labels is not None else tuple(_grade_of(i) for i in inputs)
    sessions = tuple(
        _session(inp, name, group) for inp, name, group in zip(inputs, names, groups, strict=True)
    )
    order: dict[str, list[CompareSession]] = {}
    for s in sessions:
        if s.group:
            order.setdefault(s.group, []).append(s)
    ungrouped = tuple(
        (s.session_id, "no label and no valid severity class: no grade to group it under")
        for s in sessions
        if not s.group
    )
    return CompareTable(
        sessions=sessions,
        groups=tuple(_group(name, members) for name, members in order.items()),
        grouped_by="label" if labels is not None else "nearest grade",
        ungrouped=ungrouped,
    )


@dataclass(frozen=True)
class OverlaySeries:
    """One session's series against time since its T_0, for overlays.

    Attributes
    ----------
    label : str
        Legend text: the session's grade (or label); sessions sharing it share one entry.
    t_since_t0_s : numpy.ndarray
        Times since the session's T_0 [s].
    values : numpy.ndarray
        The series (S_k [px] or force [N]).
    averaged : bool
        Whether the session enters its grade's means (drawn differently when not).
    """

    label: str
    t_since_t0_s: FloatArray
    values: FloatArray
    averaged: bool = True


def _overlay(
    inputs: Sequence[ReportInput],
    labels: Sequence[str] | None,
    which: str,
    averaged: Sequence[bool] | None,
) -> tuple[OverlaySeries, ...]:
    names = list(labels) if labels is not None else [i.session_id for i in inputs]
    kept = list(averaged) if averaged is not None else [True] * len(inputs)
    out = []
    for name, inp, avg in zip(names, inputs, kept, strict=True):
        t0 = inp.t0_s
        if t0 is None:
            continue
        t, v = (
            (inp.frame_times_s, inp.s_k_px) if which == "s_k" else (inp.force_times_s, inp.force_n)
        )
        out.append(OverlaySeries(name, t - t0, v, avg))
    return tuple(out)


def overlay_s_k(
    inputs: Sequence[ReportInput],
    labels: Sequence[str] | None = None,
    averaged: Sequence[bool] | None = None,
) -> tuple[OverlaySeries, ...]:
    """Each session's S_k [px] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "s_k", averaged)


def overlay_force(
    inputs: Sequence[ReportInput],
    labels: Sequence[str] | None = None,
    averaged: Sequence[bool] | None = None,
) -> tuple[OverlaySeries, ...]:
    """Each session's force [N] against time since its T_0 (sessions without T_0 left out)."""
    return _overlay(inputs, labels, "force", averaged)
