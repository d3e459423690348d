"""One name and symbol per viscosity on every surface (issue 37).

Two viscosities are reported: the paper's eta = E*T_r (Eq. 8; ``eta``, ``η``) and E*tau
from the fitted Kelvin-Voigt time constant (``eta_tau``, ``η_τ``). One session's numbers,
the issue's (eta 6.09, E*tau 1.69 N*s/mm^2), are rendered by the live console panel, the
console's results, the report's parameter table and verdict names, the comparison's rows,
the recovery-model table's heading, and the results table the exports and the study
dataset carry; on each surface the label next to 6.09 is eta's and the one next to 1.69 is
eta_tau's, and neither label is used for the other.
"""

from __future__ import annotations

import io
import re
from typing import Any

import pyarrow as pa
from rich.console import Console

from stipi_daemon.app.console import ETA, ETA_TAU, OperatorConsole, format_results
from stipi_daemon.measurement.pipeline import LiveParameters
from stipi_daemon.measurement.state_machine import MeasurementConfig
from stipi_daemon.report.compare import COMPARE_PARAMETERS
from stipi_daemon.report.parameter_table import parameter_table
from stipi_daemon.report.recovery_models import COLUMNS, INTERVAL_QUANTITIES
from stipi_daemon.report.verdict import QUANTITY_NAMES
from stipi_daemon.storage.results_table import COLUMNS as RESULT_TABLE_COLUMNS
from stipi_daemon.storage.results_table import quantity_cells
from stipi_daemon.study.dataset import arrow_schema

ETA_VALUE = 6.09  # E*T_r [N*s/mm^2]
ETA_TAU_VALUE = 1.69  # E*tau [N*s/mm^2]
E_KPA = 221.5  # E*T_r / E = 27.5 s; E*tau / E = 7.63 s


def _summary() -> dict[str, Any]:
    names = [
        "depth_mm",
        "rebound_force_n",
        "recovery_time_s",
        "elasticity_kpa",
        "viscosity_n_s_per_mm2",
        "severity",
        "tau_s",
        "viscosity_fit_n_s_per_mm2",
        "applied_force_n",
    ]
    sev = {
        "severity": "mild",
        "nearest_grade": "1+",
        "recovered_percent": 90.0,
        "window_s": [0.0, 10.0],
        "threshold_recovered_percent": 80.0,
    }
    return {
        "results": {
            "pitting": {"depth_mm": 0.58, "rebound_force_n": 7.25, "recovery_time_s": 27.5},
            "paper_estimator": {"elasticity_kpa": E_KPA, "viscosity_n_s_per_mm2": ETA_VALUE},
            "fitted_recovery": {
                "tau_s": 7.63,
                "tau_se_s": 0.1,
                "model": {"viscosity_n_s_per_mm2": ETA_TAU_VALUE},
            },
            "applied_force_n": 16.0,
            "severity": {"paper_estimator": sev, "fitted_model": None},
            "flags": [],
        },
        "validity": {q: {"status": "valid", "flags": [], "reason": None} for q in names},
        "verdict": {"status": "complete", "line": "Complete: every result is valid."},
    }


def _labels_of(text: str, value: str) -> list[str]:
    """The word right before each occurrence of ``value`` (after an optional '=' or '>=')."""
    return re.findall(r"([A-Za-z_ητ]+)\s*(?:=|>=)?\s*(?:>=\s*)?" + re.escape(value), text)


def test_the_live_panel_names_eta_and_eta_tau_apart() -> None:
    console = OperatorConsole(MeasurementConfig(), io.StringIO(), live=False)
    console.params = LiveParameters(
        t_s=40.0,
        elapsed_s=30.0,
        depth_mm=0.58,
        rebound_force_n=7.25,
        recovery_time_s=27.5,
        settled=True,
        elasticity_kpa=E_KPA,
        tau_s=7.63,
        tau_se_s=0.1,
        viscosity_n_s_per_mm2=ETA_VALUE,
        viscosity_from_time_constant_n_s_per_mm2=ETA_TAU_VALUE,
    )
    out = io.StringIO()
    Console(file=out, width=120).print(console._render())
    panel = out.getvalue()
    assert _labels_of(panel, "6.09") == [ETA] and _labels_of(panel, "1.69") == [ETA_TAU]
    # the plain (log) line
    plain = io.StringIO()
    OperatorConsole(MeasurementConfig(), plain, live=False).update(40.0, params=console.params)
    assert _labels_of(plain.getvalue(), "6.09") == [ETA]
    assert _labels_of(plain.getvalue(), "1.69") == [ETA_TAU]
    assert (ETA, ETA_TAU) == ("eta", "eta_tau")


def test_the_console_results_name_eta_and_eta_tau_apart() -> None:
    text = "\n".join(format_results(_summary()))
    assert _labels_of(text, "6.09") == [ETA] and _labels_of(text, "1.69") == [ETA_TAU]


def test_the_report_names_eta_and_eta_tau_apart() -> None:
    rows = {r.symbol: r for r in parameter_table(_summary())}
    assert rows["η"].value == ETA_VALUE and "E·T_r" in rows["η"].name
    assert rows["η_τ"].value == ETA_TAU_VALUE and "E·τ" in rows["η_τ"].name
    assert [s for s in rows if s.startswith("η")] == ["η", "η_τ"]
    assert QUANTITY_NAMES["viscosity_n_s_per_mm2"][0] == "η"
    assert QUANTITY_NAMES["viscosity_fit_n_s_per_mm2"][0] == "η_τ"
    labels = {key: label for key, label, *_ in COMPARE_PARAMETERS}
    assert labels["viscosity_n_s_per_mm2"] == "η = E·T_r"
    assert labels["viscosity_from_time_constant_n_s_per_mm2"] == "η_τ = E·τ"
    # the recovery models' column is the paper's eta with each model's T_r
    assert [c for c in COLUMNS if "η" in c] == ["η = E·T_r [N·s/mm²]"]
    assert INTERVAL_QUANTITIES["viscosity_n_s_per_mm2"][0] == "η (E·T_r)"


def test_exports_and_the_study_name_eta_and_eta_tau_apart() -> None:
    cells = quantity_cells(_summary())
    assert cells["viscosity_n_s_per_mm2"] == ETA_VALUE
    assert cells["viscosity_fit_n_s_per_mm2"] == ETA_TAU_VALUE
    docs = {name: doc for name, _, _, doc in RESULT_TABLE_COLUMNS}
    assert docs["viscosity_n_s_per_mm2"].startswith("viscosity eta = E*T_r (Eq. 8)")
    assert docs["viscosity_fit_n_s_per_mm2"].startswith("viscosity eta_tau = E*tau")
    schema: pa.Schema = arrow_schema("results")
    names = (("viscosity_n_s_per_mm2", "eta = E*T_r"), ("viscosity_fit_n_s_per_mm2", "eta_tau"))
    for name, want in names:
        meta = schema.field(name).metadata
        assert want in meta[b"doc"].decode() and meta[b"unit"] == b"N*s/mm^2"
    # no column's doc calls E*tau plain "eta"
    for name, doc in docs.items():
        assert "eta = E*tau" not in doc, (name, doc)
