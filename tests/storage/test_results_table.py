"""The one-row-per-session results table and the MATLAB export on edge cases.

The summaries follow the daemon's validity schema (``summary["validity"][quantity]`` =
status, flags, reason; ``summary["verdict"]``; docs/storage.md); the real daemon's
sessions are covered in tests/commands/test_sessions_metadata.py.
"""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.io

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.export import (
    check_export_target,
    default_export_dir,
    default_table_path,
    export_mat,
    write_results_table,
)
from stipi_daemon.storage.results_table import COLUMN_NAMES
from tests.storage.conftest import Recorded

OPTIONS = StorageOptions(min_free_bytes=0)

SUMMARY: dict[str, Any] = {
    "status": "complete",
    "results": {
        "pitting": {"depth_mm": 3.5, "rebound_force_n": 7.25, "recovery_time_s": 27.5},
        "paper_estimator": {"elasticity_kpa": 356.0, "viscosity_n_s_per_mm2": 9.8},
        "severity": {"paper_estimator": {"severity": "severe", "nearest_grade": "III"}},
        "fitted_recovery": {"tau_s": 12.0},
        "applied_force_n": 16.0,
    },
    "validity": {
        "depth_mm": {"status": "invalid", "flags": ["release_not_observed"], "reason": "gap"},
        "rebound_force_n": {"status": "flagged", "flags": ["a", "b"], "reason": "caveat"},
        "severity": {"status": "invalid", "flags": [], "reason": "depends on D_p"},
    },
    "verdict": {"status": "invalid", "line": "Not valid: D_p (gap)."},
}


@pytest.fixture
def root(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    with SessionWriter.create(
        root, {}, {}, session_id="a", options=OPTIONS, metadata={"subject": "S1"}
    ) as w:
        w.finish("complete", SUMMARY)
    with SessionWriter.create(root, {}, {}, session_id="b", options=OPTIONS) as w:
        w.finish("aborted")
    bad = root / "c"
    bad.mkdir()
    (bad / "session.sqlite").write_bytes(b"garbage" * 100)
    return root


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_rows_never_show_an_invalid_number(root: Path, tmp_path: Path, suffix: str) -> None:
    out, n = write_results_table(root, tmp_path / f"r.{suffix}")
    assert n == 3
    if suffix == "csv":
        with open(out, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        assert tuple(rows[0]) == COLUMN_NAMES
        a, b, c = rows
        assert a["depth_mm"] == "" and a["severity"] == "" and a["severity_grade"] == ""
        assert float(a["rebound_force_n"]) == 7.25
        assert float(a["elasticity_kpa"]) == 356.0
    else:
        a, b, c = pq.read_table(out).to_pylist()
        assert a["depth_mm"] is None and a["severity"] is None
        assert a["rebound_force_n"] == 7.25
    assert a["depth_mm_status"] == "invalid" and a["depth_mm_reason"] == "gap"
    assert a["depth_mm_flags"] == "release_not_observed"
    assert a["rebound_force_n_status"] == "flagged" and a["rebound_force_n_flags"] == "a;b"
    assert a["recovery_time_s_status"] == "unknown"  # no validity recorded for it
    assert (a["subject"], a["verdict"]) == ("S1", "invalid")
    assert (b["status"], b["verdict"]) == ("aborted", "unknown")  # no summary
    # An unreadable session is a row saying why, never left out.
    assert c["session_id"] == "c" and c["status"] == "error"
    assert c["error"].endswith("c/manifest.json: manifest is missing")


def test_selection_and_bad_targets(root: Path, tmp_path: Path) -> None:
    out, n = write_results_table(root, tmp_path / "s.csv", {"subject": "S1"})
    assert n == 2
    with open(out, newline="", encoding="utf-8") as f:
        assert [r["session_id"] for r in csv.DictReader(f)] == ["a", "c"]  # c: unreadable
    with pytest.raises(SessionError, match=r"give a file name ending in \.csv or \.parquet"):
        write_results_table(root, tmp_path / "r.xlsx")
    with pytest.raises(SessionError, match="exists already"):
        write_results_table(root, out)
    with pytest.raises(SessionError, match="inside the session directory"):
        write_results_table(root, root / "a" / "r.csv")
    assert not (root / "a" / "r.csv").exists()
    with pytest.raises(SessionError, match="sessions directory does not exist"):
        write_results_table(tmp_path / "none", tmp_path / "x.csv")


def test_default_places_are_next_to_the_root() -> None:
    assert default_export_dir(Path("sessions/S1")) == Path("exports/S1")
    assert default_table_path(Path("/data/sessions")) == Path("/data/exports/results.csv")


def test_target_checks(root: Path, tmp_path: Path) -> None:
    # Another sessions directory's session (its manifest beside its database) is refused
    # as well; a stray database file alone makes no directory a session.
    elsewhere = tmp_path / "other" / "x"
    shutil.copytree(root / "a", elsewhere)
    with pytest.raises(SessionError, match="inside the session directory"):
        check_export_target(elsewhere / "out", [root])
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "session.sqlite").touch()
    check_export_target(stray / "out", [root])
    check_export_target(root / "exports" / "a", [root])  # deeper in the root: allowed
    check_export_target(tmp_path / "exports" / "a", [root])


def test_mat_of_nulls_and_edges(recorded: Recorded, tmp_path: Path) -> None:
    path = tmp_path / "s.mat"
    with SessionReader(recorded.directory) as reader:
        export_mat(reader, path)
        force = reader.force_samples()
    mat = scipy.io.loadmat(path, simplify_cells=True)
    got = mat["force_samples"]["force_n"]
    assert math.isnan(got[2])  # NULL force -> NaN
    np.testing.assert_array_equal(got, force["force_n"])
    # 64-bit probe times beyond 2^32 stay exact as doubles.
    np.testing.assert_array_equal(mat["force_samples"]["t_mcu_us"], force["t_mcu_us"])
    assert mat["metadata"]["subject"].size == 0  # not set: MATLAB []
    assert mat["results"]["verdict"]["status"] == "unknown"  # an old summary


# ---------------------------------------------------------------- recovery models


def _comparison_summary(elasticity_status: str) -> dict[str, Any]:
    """A summary whose recovery models are the analysis' own comparison of a recovery
    with two time constants (docs/analysis.md, "Recovery models, model selection and
    intervals"), as the daemon writes it (``RecoveryModelComparison.to_dict``)."""
    from stipi_daemon.analysis.recovery_models import fit_recovery_models

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 60.0, 1 / 30)
    s = 9000.0 - 6000.0 * (0.4 * np.exp(-t / 1.0) + 0.6 * np.exp(-t / 9.0))
    s = s + rng.normal(0.0, 5.0, t.size)
    comparison = fit_recovery_models(
        t,
        s,
        0.0,
        60.0,
        replicates=40,
        rebound_force=lambda v: (v - 1500.0) / 2500.0,
        elasticity_kpa=220.0,
    )
    summary = {**SUMMARY, "results": {**SUMMARY["results"]}}
    summary["results"]["recovery_models"] = comparison.to_dict("px")
    summary["validity"] = {
        **SUMMARY["validity"],
        "elasticity_kpa": {"status": elasticity_status, "flags": [], "reason": None},
    }
    return summary


def test_recovery_model_columns_name_their_unit_and_follow_the_registry() -> None:
    from stipi_daemon.analysis.recovery_models import CI_QUANTITIES, known_models
    from stipi_daemon.storage.results_table import COLUMNS, RECOVERY_MODELS

    assert RECOVERY_MODELS == known_models()
    units = {name: unit for name, _, unit, _ in COLUMNS}
    for m in RECOVERY_MODELS:
        assert f"{m}_aicc" in units and f"{m}_aicc_weight" in units and f"{m}_flags" in units
        for q, unit in (
            ("tau_s", "s"),
            ("recovery_time_s", "s"),
            ("rebound_force_n", "N"),
            ("viscosity_n_s_per_mm2", "N*s/mm^2"),
        ):
            assert q in CI_QUANTITIES  # the analysis gives an interval for it
            for name in (f"{m}_{q}", f"{m}_{q}_ci95_low", f"{m}_{q}_ci95_high"):
                assert units[name] == unit, name
    assert {"recovery_models_best", "kelvin_voigt_rejected"} <= set(COLUMN_NAMES)
    assert len(set(COLUMN_NAMES)) == len(COLUMN_NAMES)


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_recovery_models_round_trip(tmp_path: Path, suffix: str) -> None:
    summary = _comparison_summary("valid")
    rm = summary["results"]["recovery_models"]
    root = tmp_path / "sessions"
    with SessionWriter.create(root, {}, {}, session_id="m", options=OPTIONS) as w:
        w.finish("complete", summary)
    out, _ = write_results_table(root, tmp_path / f"r.{suffix}")
    if suffix == "csv":
        with open(out, newline="", encoding="utf-8") as f:
            (raw,) = list(csv.DictReader(f))
        from stipi_daemon.storage.results_table import COLUMNS

        real = {name for name, kind, _, _ in COLUMNS if kind == "real"}
        row: dict[str, Any] = {
            k: None if v == "" else float(v) if k in real else v for k, v in raw.items()
        }
        assert raw["kelvin_voigt_rejected"] == str(rm["kelvin_voigt_rejected"])
    else:
        (row,) = pq.read_table(out).to_pylist()
        assert row["kelvin_voigt_rejected"] is rm["kelvin_voigt_rejected"]
    # Two time constants: the data reject Kelvin-Voigt and pick the two-exponential model.
    assert rm["kelvin_voigt_rejected"] is True
    assert row["recovery_models_best"] == rm["best_model"] == "two_exponential"
    assert row["recovery_models_flags"] == ";".join(rm["flags"])
    for m, fit in rm["models"].items():
        assert row[f"{m}_aicc"] == fit["aicc"] and row[f"{m}_aicc_weight"] == fit["akaike_weight"]
        assert row[f"{m}_flags"] == (";".join(fit["flags"]) or None)
        for q in ("tau_s", "recovery_time_s", "rebound_force_n", "viscosity_n_s_per_mm2"):
            assert row[f"{m}_{q}"] == fit[q]
            lo, hi = fit["ci95"][q] or (None, None)
            assert (row[f"{m}_{q}_ci95_low"], row[f"{m}_{q}_ci95_high"]) == (lo, hi)
    two = rm["models"]["two_exponential"]
    assert two["ci95"]["tau_s"][0] <= two["tau_s"] <= two["ci95"]["tau_s"][1]


def test_recovery_model_eta_is_empty_when_e_is_invalid(tmp_path: Path) -> None:
    from stipi_daemon.storage.results_table import model_cells

    valid = model_cells(_comparison_summary("valid"))
    invalid = model_cells(_comparison_summary("invalid"))
    for m in ("kelvin_voigt", "two_exponential", "power_law"):
        assert valid[f"{m}_viscosity_n_s_per_mm2"] is not None
        for name in ("", "_ci95_low", "_ci95_high"):
            assert invalid[f"{m}_viscosity_n_s_per_mm2{name}"] is None
        # The rest does not depend on E.
        assert invalid[f"{m}_tau_s"] == valid[f"{m}_tau_s"] is not None
        assert invalid[f"{m}_rebound_force_n_ci95_low"] == valid[f"{m}_rebound_force_n_ci95_low"]


def test_recovery_model_cells_of_old_odd_and_absent_comparisons() -> None:
    from stipi_daemon.storage.results_table import model_cells

    assert set(model_cells(SUMMARY).values()) == {None}  # recorded before the models
    assert set(model_cells(None).values()) == {None}
    odd = {
        "results": {
            "recovery_models": {
                "best_model": None,
                "kelvin_voigt_rejected": "yes",  # not a bool: not shown as one
                "kelvin_voigt_delta_qaicc": float("nan"),
                "flags": ["constant_series", "model_selection_unavailable"],
                "models": {
                    "kelvin_voigt": {
                        "aicc": None,
                        "akaike_weight": True,
                        "tau_s": float("inf"),
                        "ci95": {"tau_s": [1.0]},
                        "flags": ["constant_series"],
                    },
                    "power_law": "not a fit",
                },
            }
        }
    }
    row = model_cells(odd)
    assert row["recovery_models_best"] is None and row["kelvin_voigt_rejected"] is None
    assert row["kelvin_voigt_delta_qaicc"] is None
    assert row["recovery_models_flags"] == "constant_series;model_selection_unavailable"
    assert row["kelvin_voigt_flags"] == "constant_series"
    assert row["kelvin_voigt_aicc_weight"] is None and row["kelvin_voigt_tau_s"] is None
    assert row["kelvin_voigt_tau_s_ci95_low"] is None and row["power_law_aicc"] is None
