"""``study diff``: what changed between two analysis versions of a study.

Both versions' ``results`` rows are read (DuckDB over the dataset, :mod:`.query`) and
paired by ``session_uid``. Reported:

* the sessions whose **verdict** (complete, flagged, invalid, incomplete, unknown) or
  **severity class** (mild, severe; Sec. IV.C) differs, with both values; a session with
  an ``error`` in a version has no verdict there (shown as ``error``);
* per numeric quantity of the results table (``depth_mm`` [mm], ``rebound_force_n`` [N],
  ``recovery_time_s`` [s], ``elasticity_kpa`` [kPa], ``viscosity_n_s_per_mm2``
  [N*s/mm^2], ``tau_s`` [s], ``applied_force_n`` [N]) the distribution of the change
  ``V2 - V1`` over the sessions where both values exist (an invalid quantity has none):
  n, median, 5th and 95th percentiles (linear interpolation, numpy's default) and the
  largest absolute change, in the quantity's unit; and how many sessions changed the
  quantity's status (valid, flagged, invalid, unknown). With n = 0 the statistics are
  empty, never 0.

:meth:`VersionDiff.write_csv` writes one row per session present in either version:
uid, site, probe, whether it is in each version, verdict, severity class and error in
each, and per quantity both values and the change (empty when either is missing).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from stipi_daemon.study.dataset import RESULTS_COLUMNS, StudyError

__all__ = ["QuantityChange", "VersionDiff", "diff_versions", "numeric_quantities"]

_NONE: Final = "-"


def numeric_quantities() -> list[tuple[str, str]]:
    """(column, unit) of every numeric quantity of the results table (it has a status)."""
    names = {c.name for c in RESULTS_COLUMNS}
    return [
        (c.name, c.unit)
        for c in RESULTS_COLUMNS
        if str(c.type) == "double" and f"{c.name}_status" in names
    ]


@dataclass(frozen=True)
class QuantityChange:
    """The changes ``V2 - V1`` of one quantity over the sessions both versions value.

    Attributes
    ----------
    quantity, unit : str
    n : int
        Sessions with a value in both versions.
    status_changed : int
        Sessions in both versions whose status of the quantity differs.
    median, p5, p95, max_abs : float or None
        Median, 5th and 95th percentile and largest absolute change [unit]; None if n = 0.
    """

    quantity: str
    unit: str
    n: int
    status_changed: int
    median: float | None
    p5: float | None
    p95: float | None
    max_abs: float | None


def _change_stats(
    quantity: str, unit: str, pairs: list[tuple[Any, Any]], status: int
) -> QuantityChange:
    deltas = np.array(
        [b - a for a, b in pairs if a is not None and b is not None], dtype=np.float64
    )
    deltas = deltas[np.isfinite(deltas)]
    if deltas.size == 0:
        return QuantityChange(quantity, unit, 0, status, None, None, None, None)
    p5, median, p95 = (float(v) for v in np.percentile(deltas, [5.0, 50.0, 95.0]))
    return QuantityChange(
        quantity, unit, int(deltas.size), status, median, p5, p95, float(np.max(np.abs(deltas)))
    )


@dataclass
class VersionDiff:
    """Two analysis versions compared (see the module doc).

    Attributes
    ----------
    dataset : Path
    v1, v2 : str
    sessions : list of dict
        One row per session in either version (the CSV's columns).
    quantities : list of QuantityChange
    """

    dataset: Path
    v1: str
    v2: str
    sessions: list[dict[str, Any]]
    quantities: list[QuantityChange]

    def changed(self) -> list[dict[str, Any]]:
        """Sessions in both versions whose verdict or severity class changed."""
        return [r for r in self.sessions if r["verdict_changed"] or r["severity_changed"]]

    def lines(self, max_rows: int = 50) -> list[str]:
        """The comparison as text: counts, changed sessions, the change distributions."""
        both = sum(1 for r in self.sessions if r["in_v1"] and r["in_v2"])
        only1 = sum(1 for r in self.sessions if r["in_v1"] and not r["in_v2"])
        only2 = sum(1 for r in self.sessions if r["in_v2"] and not r["in_v1"])
        err1 = sum(1 for r in self.sessions if r["error_v1"] is not None)
        err2 = sum(1 for r in self.sessions if r["error_v2"] is not None)
        changed = self.changed()
        n_verdict = sum(1 for r in changed if r["verdict_changed"])
        n_severity = sum(1 for r in changed if r["severity_changed"])
        out = [
            f"{self.dataset}: {self.v1} -> {self.v2}: {both} sessions in both, "
            f"{only1} only in {self.v1}, {only2} only in {self.v2}; errors {err1} -> {err2}",
            f"verdict changed in {n_verdict} sessions, severity class in {n_severity}",
        ]
        if changed:
            width = max(12, *(len(r["session_uid"]) for r in changed))
            out += ["", f"{'session':<{width}}  {'verdict':<26}  severity class"]
            for r in changed[:max_rows]:
                verdict = f"{_text(r['verdict_v1'])} -> {_text(r['verdict_v2'])}"
                severity = f"{_text(r['severity_class_v1'])} -> {_text(r['severity_class_v2'])}"
                out.append(f"{r['session_uid']:<{width}}  {verdict:<26}  {severity}")
            if len(changed) > max_rows:
                out.append(f"... and {len(changed) - max_rows} more (--out FILE.csv lists all)")
        out += [
            "",
            f"change {self.v2} - {self.v1}, sessions valued in both:",
            f"{'quantity':<24}{'unit':>10}{'n':>7}{'status chg':>11}"
            f"{'median':>12}{'p5':>12}{'p95':>12}{'max |chg|':>12}",
        ]
        for q in self.quantities:
            out.append(
                f"{q.quantity:<24}{q.unit:>10}{q.n:>7}{q.status_changed:>11}"
                + "".join(f"{_num(v):>12}" for v in (q.median, q.p5, q.p95, q.max_abs))
            )
        return out

    def write_csv(self, path: Path) -> None:
        """One row per session (see the module doc), written atomically.

        Raises
        ------
        StudyError
            The file cannot be written or does not end in ``.csv``.
        """
        if path.suffix.lower() != ".csv":
            raise StudyError(f"--out {path}: give a file name ending in .csv")
        columns = list(self.sessions[0]) if self.sessions else ["session_uid"]
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "w", newline="", encoding="utf-8") as f:
                writer = csv.DictWriter(f, fieldnames=columns)
                writer.writeheader()
                for row in self.sessions:
                    writer.writerow({k: "" if v is None else v for k, v in row.items()})
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise StudyError(f"--out {path}: cannot write: {exc.strerror or exc}") from None


def _text(value: Any) -> str:
    return _NONE if value is None else str(value)


def _num(value: float | None) -> str:
    return _NONE if value is None or not math.isfinite(value) else f"{value:.4g}"


def _rows(dataset: Path, version: str, known: list[str]) -> dict[str, dict[str, Any]]:
    from stipi_daemon.study.query import run_query

    if version not in known:
        there = ", ".join(known) or "none"
        raise StudyError(f"{dataset}: no analysis version {version!r} (there are: {there})")
    literal = "'" + version.replace("'", "''") + "'"
    table = run_query(dataset, f"SELECT * FROM results WHERE analysis = {literal}")
    return {r["session_uid"]: r for r in table.to_pylist()}


def _versions(dataset: Path) -> list[str]:
    from stipi_daemon.study.query import run_query

    table = run_query(dataset, "SELECT DISTINCT analysis FROM results ORDER BY analysis")
    return [str(v) for v in table.column(0).to_pylist() if v is not None]


def diff_versions(dataset: Path, v1: str, v2: str) -> VersionDiff:
    """Compare analysis versions ``v1`` and ``v2`` of ``dataset``.

    Raises
    ------
    StudyError
        Not a study dataset, or a version has no results in it (one line, naming those
        there are).
    """
    known = _versions(dataset)
    a, b = _rows(dataset, v1, known), _rows(dataset, v2, known)
    quantities = numeric_quantities()
    sessions: list[dict[str, Any]] = []
    for uid in sorted(a.keys() | b.keys()):
        r1, r2 = a.get(uid), b.get(uid)
        any_row = r1 if r1 is not None else r2
        assert any_row is not None
        row: dict[str, Any] = {
            "session_uid": uid,
            "site": any_row.get("site"),
            "probe": any_row.get("probe"),
            "in_v1": r1 is not None,
            "in_v2": r2 is not None,
        }
        for key in ("verdict", "severity_class", "error"):
            row[f"{key}_v1"] = _cell(r1, key)
            row[f"{key}_v2"] = _cell(r2, key)
        both = r1 is not None and r2 is not None
        row["verdict_changed"] = both and row["verdict_v1"] != row["verdict_v2"]
        row["severity_changed"] = both and row["severity_class_v1"] != row["severity_class_v2"]
        for q, _unit in quantities:
            x, y = _cell(r1, q), _cell(r2, q)
            row[f"{q}_v1"], row[f"{q}_v2"] = x, y
            row[f"{q}_change"] = None if x is None or y is None else y - x
        sessions.append(row)
    changes = []
    for q, unit in quantities:
        pairs = [(a[u].get(q), b[u].get(q)) for u in a.keys() & b.keys()]
        status = sum(
            1 for u in a.keys() & b.keys() if a[u].get(f"{q}_status") != b[u].get(f"{q}_status")
        )
        changes.append(_change_stats(q, unit, pairs, status))
    return VersionDiff(dataset, v1, v2, sessions, changes)


def _cell(row: dict[str, Any] | None, key: str) -> Any:
    """A value of a results row; the verdict of a row with an error is ``error``."""
    if row is None:
        return None
    if key == "verdict" and row.get("error") is not None:
        return "error"
    value = row.get(key)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
