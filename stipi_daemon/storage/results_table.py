"""One row per session: the results table a statistician opens directly.

This module owns the table ``sessions table`` writes (and the one-row ``session.<fmt>`` of
every export): per session its id, creation time, status, metadata (subject, site,
operator, note; :mod:`.metadata`), label, the verdict, the duration and row counts, then
for each reported quantity of the validity schema (:data:`~.reader.QUANTITY_PATHS`) its
value, ``<q>_status`` (``valid``/``flagged``/``invalid``/``unknown``), ``<q>_flags``
(``;``-separated) and ``<q>_reason``; then the recovery models fitted side by side
(summary.json ``results.recovery_models``; docs/analysis.md, "Recovery models, model
selection and intervals"): the best model, the Kelvin-Voigt rejection flag, and per model
its AICc, AICc (Akaike) weight, tau, T_r, F_r and eta with their 95 % interval bounds
(``<model>_<q>_ci95_low``/``_high``) and its flags. It reads what the sessions recorded and
computes nothing.

Units: every numeric column's name ends in its unit (``depth_mm``, ``rebound_force_n``,
``elasticity_kpa``, ``viscosity_n_s_per_mm2`` [N·s/mm²], ``duration_s``...); the Parquet
file also carries it in each field's metadata (``unit``, ``doc``) and, for the whole
table, in the schema metadata ``units`` (JSON: column -> unit).

Never a number without its validity: an ``invalid`` quantity's value is left empty (its
status and reason say why); a ``flagged`` one keeps its value beside its flags. A recovery
model's numbers stand beside that model's flags (``<model>_flags``) and the comparison's
(``recovery_models_flags``); its eta (= E T_r) and eta's interval are left empty when E
(``elasticity_kpa``) is invalid, since they are computed with that E. A session
that cannot be read is a row with only ``session_id``, ``directory``, ``status`` =
``error`` and ``error`` (why), so that no session disappears from a study silently.
CSV: header of column names, floats in Python's shortest round-trip form, booleans as
``True``/``False``, empty for null.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final, Literal

from stipi_daemon.errors import SessionError
from stipi_daemon.storage.metadata import FIELD_DOCS, METADATA_FIELDS, matches
from stipi_daemon.storage.reader import (
    QUANTITY_PATHS,
    SessionReader,
    quantity_status,
    quantity_value,
    session_dirs,
    session_label,
    verdict_of,
)
from stipi_daemon.storage.schema import FORCE_SAMPLES, FRAMES

#: Recovery models in summary.json's ``results.recovery_models.models`` (the analysis'
#: registry, stipi_daemon.analysis.recovery_models.known_models(); a test keeps them equal).
RECOVERY_MODELS: Final[tuple[str, ...]] = ("kelvin_voigt", "two_exponential", "power_law")
#: Quantity of a recovery model -> (its key in summary.json, unit, doc).
_MODEL_QUANTITIES: Final[dict[str, tuple[str, str]]] = {
    "tau_s": ("s", "effective time constant (1 - 1/e of the recovery done) of the fitted curve"),
    "recovery_time_s": ("s", "T_r (Eq. 6) on the fitted curve"),
    "rebound_force_n": ("N", "F_r (Eq. 5) at the fitted curve's S_max"),
    "viscosity_n_s_per_mm2": (
        "N*s/mm^2",
        "eta = E*T_r (Eq. 8) with this model's T_r (not a Kelvin-Voigt eta_tau = E*tau)",
    ),
}

TableFormat = Literal["csv", "parquet"]
TABLE_FORMATS: Final[tuple[TableFormat, ...]] = ("csv", "parquet")

#: Doc of each quantity's value column.
_QUANTITY_DOCS: Final[dict[str, str]] = {
    "depth_mm": "pitting depth D_p (Eq. 3)",
    "rebound_force_n": "rebound force F_r (Eq. 5)",
    "recovery_time_s": "recovery time T_r (Eq. 6)",
    "elasticity_kpa": "elasticity E (Eq. 7), paper estimator",
    "viscosity_n_s_per_mm2": "viscosity eta = E*T_r (Eq. 8), paper estimator",
    "severity": "severity class (mild/severe, Sec. IV.C), paper estimator",
    "tau_s": "fitted Kelvin-Voigt recovery time constant",
    "viscosity_fit_n_s_per_mm2": (
        "viscosity eta_tau = E*tau from the fitted Kelvin-Voigt tau (not the paper's eta)"
    ),
    "applied_force_n": "applied force F_a during the pitting hold",
}


def _columns() -> tuple[tuple[str, str, str, str], ...]:
    """(name, kind: text|real|int|bool, unit, doc) of every column, in order."""
    cols: list[tuple[str, str, str, str]] = [
        ("session_id", "text", "", "session directory name"),
        ("directory", "text", "", "session directory"),
        ("created_utc", "text", "", "creation time, ISO 8601 UTC"),
        ("status", "text", "", "complete, aborted, fault, interrupted, recording or error"),
    ]
    cols += [(f, "text", "", FIELD_DOCS[f]) for f in METADATA_FIELDS]
    cols += [
        ("label", "text", "", "the note's first line, or scene:<name> for simulated devices"),
        ("verdict", "text", "", "complete, flagged, invalid, incomplete or unknown"),
        ("verdict_line", "text", "", "the verdict in one sentence"),
        ("duration_s", "real", "s", "span of the recorded samples and frames"),
        ("n_frames", "int", "", "frames recorded"),
        ("n_force_samples", "int", "", "force samples recorded"),
        ("severity_grade", "text", "", "nearest reference grade (normalised curve shape)"),
    ]
    for q, (_, unit) in QUANTITY_PATHS.items():
        kind = "text" if q == "severity" else "real"
        cols += [
            (q, kind, unit, _QUANTITY_DOCS.get(q, q) + "; empty when invalid"),
            (f"{q}_status", "text", "", f"validity of {q}: valid, flagged, invalid, unknown"),
            (f"{q}_flags", "text", "", f"flags that concern {q}, separated by ';'"),
            (f"{q}_reason", "text", "", f"why {q} is flagged or invalid"),
        ]
    cols += _model_columns()
    cols.append(("error", "text", "", "why the session could not be read (else empty)"))
    return tuple(cols)


def _model_columns() -> list[tuple[str, str, str, str]]:
    """The recovery-model columns (summary.json ``results.recovery_models``)."""
    cols: list[tuple[str, str, str, str]] = [
        (
            "recovery_models_best",
            "text",
            "",
            "recovery model with the highest QAICc weight; empty when none was compared",
        ),
        (
            "kelvin_voigt_rejected",
            "bool",
            "",
            "the data reject Kelvin-Voigt: its QAICc exceeds the best by more than 10",
        ),
        ("kelvin_voigt_delta_qaicc", "real", "", "QAICc(Kelvin-Voigt) - min QAICc"),
        (
            "recovery_models_flags",
            "text",
            "",
            "flags of the model comparison, separated by ';'",
        ),
    ]
    for m in RECOVERY_MODELS:
        cols += [
            (f"{m}_aicc", "real", "", f"{m}: AICc of the fit (lower is better)"),
            (f"{m}_aicc_weight", "real", "", f"{m}: Akaike weight from AICc, 0..1"),
        ]
        for q, (unit, doc) in _MODEL_QUANTITIES.items():
            cols += [
                (f"{m}_{q}", "real", unit, f"{m}: {doc}"),
                (f"{m}_{q}_ci95_low", "real", unit, f"{m}: {q} 95 % interval, lower bound"),
                (f"{m}_{q}_ci95_high", "real", unit, f"{m}: {q} 95 % interval, upper bound"),
            ]
        cols.append((f"{m}_flags", "text", "", f"{m}: flags of its fit, separated by ';'"))
    return cols


#: The table's columns: (name, kind, unit, doc).
COLUMNS: Final = _columns()
COLUMN_NAMES: Final = tuple(c[0] for c in COLUMNS)

Row = dict[str, Any]


def _grade(summary: dict[str, Any] | None) -> str | None:
    results = (summary or {}).get("results")
    severity = results.get("severity") if isinstance(results, dict) else None
    paper = severity.get("paper_estimator") if isinstance(severity, dict) else None
    grade = paper.get("nearest_grade") if isinstance(paper, dict) else None
    return None if grade is None else str(grade)


def quantity_cells(summary: dict[str, Any] | None) -> Row:
    """The verdict and every quantity's value, status, flags and reason of one summary."""
    validity = (summary or {}).get("validity")
    validity = validity if isinstance(validity, dict) else {}
    verdict = (summary or {}).get("verdict")
    row: Row = {
        "verdict": verdict_of(summary),
        "verdict_line": verdict.get("line") if isinstance(verdict, dict) else None,
    }
    for q in QUANTITY_PATHS:
        status = quantity_status(summary, q)
        value = quantity_value(summary, q)
        entry = validity.get(q)
        entry = entry if isinstance(entry, dict) else {}
        if status == "invalid":
            value = None
        elif q == "severity":
            value = None if value is None else str(value)
        elif isinstance(value, bool) or not isinstance(value, int | float):
            value = None
        row[q] = float(value) if isinstance(value, int | float) else value
        row[f"{q}_status"] = status
        row[f"{q}_flags"] = ";".join(str(f) for f in entry.get("flags") or []) or None
        row[f"{q}_reason"] = entry.get("reason")
    row["severity_grade"] = None if row["severity"] is None else _grade(summary)
    return row


def _number(value: Any) -> float | None:
    """A finite recorded number as a float, else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def model_cells(summary: dict[str, Any] | None) -> Row:
    """The recovery-model columns of one summary (all None when it has no comparison)."""
    results = (summary or {}).get("results")
    rm = results.get("recovery_models") if isinstance(results, dict) else None
    row: Row = {name: None for name, *_ in _model_columns()}
    if not isinstance(rm, dict):
        return row
    best = rm.get("best_model")
    rejected = rm.get("kelvin_voigt_rejected")
    row["recovery_models_best"] = best if isinstance(best, str) else None
    row["kelvin_voigt_rejected"] = rejected if isinstance(rejected, bool) else None
    row["kelvin_voigt_delta_qaicc"] = _number(rm.get("kelvin_voigt_delta_qaicc"))
    row["recovery_models_flags"] = ";".join(str(f) for f in rm.get("flags") or []) or None
    models = rm.get("models")
    models = models if isinstance(models, dict) else {}
    e_invalid = quantity_status(summary, "elasticity_kpa") == "invalid"
    for m in RECOVERY_MODELS:
        fit = models.get(m)
        if not isinstance(fit, dict):
            continue
        row[f"{m}_aicc"] = _number(fit.get("aicc"))
        row[f"{m}_aicc_weight"] = _number(fit.get("akaike_weight"))
        row[f"{m}_flags"] = ";".join(str(f) for f in fit.get("flags") or []) or None
        ci = fit.get("ci95")
        ci = ci if isinstance(ci, dict) else {}
        for q in _MODEL_QUANTITIES:
            if q == "viscosity_n_s_per_mm2" and e_invalid:
                continue
            row[f"{m}_{q}"] = _number(fit.get(q))
            bounds = ci.get(q)
            if isinstance(bounds, list | tuple) and len(bounds) == 2:
                lo, hi = _number(bounds[0]), _number(bounds[1])
                if lo is not None and hi is not None:
                    row[f"{m}_{q}_ci95_low"], row[f"{m}_{q}_ci95_high"] = lo, hi
    return row


def session_row(reader: SessionReader) -> Row:
    """The row of one open session (see the module doc)."""
    metadata = reader.metadata
    row: Row = dict.fromkeys(COLUMN_NAMES)
    row |= {
        "session_id": reader.session_id,
        "directory": str(reader.directory),
        "created_utc": str(reader.manifest["created_utc"]),
        "status": reader.status.value,
        "label": session_label(reader.manifest, metadata),
        "duration_s": reader.duration_s(),
        "n_frames": reader.count(FRAMES),
        "n_force_samples": reader.count(FORCE_SAMPLES),
        **metadata,
    }
    try:
        summary = reader.summary
    except SessionError as exc:
        row |= quantity_cells(None) | model_cells(None)
        row["error"] = f"summary unreadable: {exc}"
        return row
    return row | quantity_cells(summary) | model_cells(summary)


def error_row(directory: Path, error: str) -> Row:
    """The row of a session directory that cannot be read."""
    row: Row = dict.fromkeys(COLUMN_NAMES)
    row |= {
        "session_id": directory.name,
        "directory": str(directory),
        "status": "error",
        "error": error,
    }
    return row


def collect_rows(root: Path | str, where: dict[str, str | None] | None = None) -> list[Row]:
    """One row per session directory under ``root`` (sorted by id) whose metadata equals
    every given value of ``where``; unreadable sessions are always included."""
    rows: list[Row] = []
    for directory in session_dirs(root):
        try:
            with SessionReader(directory) as reader:
                metadata = reader.metadata
                if where and not matches(metadata, where):
                    continue
                rows.append(session_row(reader))
        except SessionError as exc:
            rows.append(error_row(directory, str(exc)))
    return rows


def table_format(path: Path) -> TableFormat:
    """The format a results file's name asks for (``.csv`` or ``.parquet``)."""
    suffix = path.suffix.lower().lstrip(".")
    if suffix == "csv":
        return "csv"
    if suffix in ("parquet", "pq"):
        return "parquet"
    raise SessionError(f"--out {path}: give a file name ending in .csv or .parquet")


def _csv_cell(value: Any) -> str:
    if value is None:
        return ""
    return repr(value) if isinstance(value, float) else str(value)


def write_rows(path: Path, rows: Sequence[Row], fmt: TableFormat) -> None:
    """Write ``rows`` (dicts keyed by :data:`COLUMN_NAMES`) as CSV or Parquet."""
    if fmt == "csv":
        with open(path, "w", encoding="utf-8", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow(COLUMN_NAMES)
            writer.writerows([_csv_cell(row.get(c)) for c in COLUMN_NAMES] for row in rows)
        return
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"int": pa.int64(), "real": pa.float64(), "text": pa.string(), "bool": pa.bool_()}
    fields, arrays = [], []
    for name, kind, unit, doc in COLUMNS:
        fields.append(pa.field(name, types[kind], metadata={"unit": unit, "doc": doc}))
        arrays.append(pa.array([row.get(name) for row in rows], type=types[kind]))
    units = {name: unit for name, _, unit, _ in COLUMNS if unit}
    schema = pa.schema(
        fields,
        metadata={
            "table": "sessions",
            "doc": "one row per session: metadata, verdict, each quantity's value and validity",
            "units": json.dumps(units),
        },
    )
    pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path)
