"""``study diff``: verdict and severity class changes, distributions of the changes.

Two analysis versions of synthetic sessions (``_synthetic``): ``recorded`` (each
session's summary, written by ``study index``) and ``v2``, written with the dataset's own
row builder from the same summaries changed in known ways. The statistics are checked
against Python's :func:`statistics.median` and :func:`statistics.quantiles` (inclusive
method: numpy's linear interpolation), not against numpy.
"""

from __future__ import annotations

import copy
import csv
import random
import statistics
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader
from stipi_daemon.study.dataset import StudyError, results_row, to_table, write_parquet_atomic
from stipi_daemon.study.diff import diff_versions
from stipi_daemon.study.index import index_sessions
from tests.study._synthetic import write_session

N = 12


def _v2_summary(summary: dict[str, Any], i: int) -> dict[str, Any]:
    """Viscosity + 0.1 * i; session 3's verdict and viscosity status become invalid;
    session 5 changes severity class."""
    s = copy.deepcopy(summary)
    paper = s["results"]["paper_estimator"]
    paper["viscosity_n_s_per_mm2"] += 0.1 * i
    if i == 3:
        s["validity"]["viscosity_n_s_per_mm2"] = {
            "status": "invalid",
            "flags": ["x"],
            "reason": "test",
        }
        s["verdict"] = {"status": "invalid", "line": "Invalid."}
    if i == 5:
        sev = s["results"]["severity"]["paper_estimator"]
        sev["severity"] = "severe" if sev["severity"] == "mild" else "mild"
    return s


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    rng = random.Random(3)
    out = tmp_path / "study"
    for i in range(N):
        write_session(tmp_path / "sessions", i, rng)
    index_sessions([tmp_path / "sessions"], out)
    for path in sorted((out / "results" / "analysis=recorded").rglob("*.parquet")):
        row = pq.read_table(path).to_pylist()[0]
        i = int(row["session_uid"][1:])
        if i == N - 1:
            continue  # only in 'recorded'
        with SessionReader(tmp_path / "sessions" / row["session_uid"]) as reader:
            summary = reader.summary
        assert summary is not None
        new = results_row(
            session_uid=row["session_uid"],
            analysis_version="v2",
            data_hash=row["data_hash"],
            settings_hash="sha256:test",
            package_version="test",
            analysed_utc=None,
            summary=_v2_summary(summary, i),
            error=None,
        )
        rel = path.relative_to(out / "results" / "analysis=recorded")
        write_parquet_atomic(
            out / "results" / "analysis=v2" / rel,
            to_table("results", {k: [v] for k, v in new.items()}),
        )
    return out


def test_changes_and_their_distribution(dataset: Path) -> None:
    diff = diff_versions(dataset, "recorded", "v2")
    rows = {r["session_uid"]: r for r in diff.sessions}
    assert len(rows) == N and not rows[f"S{N - 1:05d}"]["in_v2"]
    changed = {r["session_uid"]: r for r in diff.changed()}
    assert "S00003" in changed and changed["S00003"]["verdict_v2"] == "invalid"
    assert changed["S00005"]["severity_changed"]
    assert changed["S00005"]["severity_class_v1"] != changed["S00005"]["severity_class_v2"]
    # Viscosity: changes 0.1 * i over the sessions valued in both versions.
    viscosity = next(q for q in diff.quantities if q.quantity == "viscosity_n_s_per_mm2")
    both = [
        r
        for r in diff.sessions
        if r["viscosity_n_s_per_mm2_v1"] is not None and r["viscosity_n_s_per_mm2_v2"] is not None
    ]
    expected = [0.1 * int(r["session_uid"][1:]) for r in both]
    assert viscosity.unit == "N*s/mm^2" and viscosity.n == len(expected) >= 5
    cuts = statistics.quantiles(expected, n=20, method="inclusive")
    assert viscosity.median == pytest.approx(statistics.median(expected), abs=1e-12)
    assert viscosity.p5 == pytest.approx(cuts[0], abs=1e-12)
    assert viscosity.p95 == pytest.approx(cuts[-1], abs=1e-12)
    assert viscosity.max_abs == pytest.approx(max(expected), abs=1e-12)
    assert viscosity.status_changed >= 1  # session 3
    depth = next(q for q in diff.quantities if q.quantity == "depth_mm")
    assert depth.unit == "mm" and depth.max_abs == 0.0 and depth.status_changed == 0
    text = "\n".join(diff.lines())
    assert f"{N - 1} sessions in both, 1 only in recorded, 0 only in v2" in text
    assert "viscosity_n_s_per_mm2" in text and "N*s/mm^2" in text


def test_command_prints_and_writes_csv(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "diff.csv"
    assert main(["study", "diff", str(dataset), "recorded", "v2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "S00003" in printed and f"{out}: {N} rows" in printed
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == N
    s1 = next(r for r in rows if r["session_uid"] == "S00001")
    if s1["viscosity_n_s_per_mm2_change"]:
        assert float(s1["viscosity_n_s_per_mm2_change"]) == pytest.approx(0.1)


def test_unknown_version_is_one_line(dataset: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(StudyError, match=r"no analysis version 'v3' \(there are: recorded, v2\)"):
        diff_versions(dataset, "recorded", "v3")
    assert main(["study", "diff", str(dataset), "v3", "v2", "--out", "x.txt"]) == 2
    assert "no analysis version 'v3'" in capsys.readouterr().err
