"""The one-row-per-session results table and the MATLAB export on edge cases.

The summaries follow the daemon's validity schema (``summary["validity"][quantity]`` =
status, flags, reason; ``summary["verdict"]``; docs/storage.md); the real daemon's
sessions are covered in tests/commands/test_sessions_metadata.py.
"""

from __future__ import annotations

import csv
import math
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
    # Another sessions directory's session (database present) is refused as well.
    elsewhere = tmp_path / "other" / "x"
    elsewhere.mkdir(parents=True)
    (elsewhere / "session.sqlite").touch()
    with pytest.raises(SessionError, match="inside the session directory"):
        check_export_target(elsewhere / "out", [root])
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
