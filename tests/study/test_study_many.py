"""1,000 small synthetic sessions indexed and queried.

The sessions are written by the real storage writer (5 force samples, 3 frames and a
summary each, tests/study/_synthetic.py) across three sites and three probes, a fifth of
them with an invalid viscosity. "Mean eta per grade per site" from ``study query`` is
checked against the same mean computed directly from the sessions' ``summary.json`` and
``manifest.json`` files, read as the storage format documents them (docs/storage.md),
not through the package.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import random
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.study.index import index_sessions
from stipi_daemon.study.query import run_query
from tests.study._synthetic import PROBES, SITES, Synthetic, write_session

N_SESSIONS = 1000


@dataclass(frozen=True)
class Study:
    root: Path
    dataset: Path
    sessions: list[Synthetic]
    first_line: str


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Study:
    base = tmp_path_factory.mktemp("many")
    rng = random.Random(19)
    sessions = [write_session(base / "sessions", i, rng) for i in range(N_SESSIONS)]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(["study", "index", str(base / "sessions"), "--out", str(base / "ds")])
    assert status == 0
    return Study(base / "sessions", base / "ds", sessions, out.getvalue().strip())


def _files(directory: Path) -> dict[str, int]:
    return {str(p.relative_to(directory)): p.stat().st_mtime_ns for p in directory.rglob("*")}


def test_every_session_is_indexed_once(study: Study) -> None:
    assert study.first_line.endswith(
        f"{N_SESSIONS} added, 0 replaced, 0 unchanged, 0 unreadable, 0 passed over"
    )
    for table in ("sessions", "force_samples", "frames", "results"):
        files = list((study.dataset / table).rglob("*.parquet"))
        assert len(files) == N_SESSIONS, table
    counts = run_query(
        study.dataset,
        "SELECT (SELECT count(*) FROM sessions) AS s, (SELECT count(*) FROM force_samples) AS f,"
        " (SELECT count(*) FROM frames) AS fr, (SELECT count(*) FROM results) AS r,"
        " (SELECT count(DISTINCT session_uid) FROM results) AS u",
    ).to_pylist()[0]
    assert counts == {
        "s": N_SESSIONS,
        "f": 5 * N_SESSIONS,
        "fr": 3 * N_SESSIONS,
        "r": N_SESSIONS,
        "u": N_SESSIONS,
    }


def test_partitions_decode_sites_and_probes(study: Study) -> None:
    rows = run_query(
        study.dataset,
        "SELECT site, probe, count(*) AS n FROM sessions WHERE probe = probe_id GROUP BY ALL",
    ).to_pylist()
    got = {(r["site"], r["probe"]): r["n"] for r in rows}
    want: dict[tuple[str, str], int] = defaultdict(int)
    for s in study.sessions:
        want[(s.site, s.probe_id)] += 1
    assert got == dict(want)
    assert set(SITES) == {site for site, _ in got} and set(PROBES) == {p for _, p in got}


def _direct_means(root: Path) -> dict[tuple[str, str], tuple[float, int]]:
    """Mean viscosity [N*s/mm^2] per (site, grade) from the files, invalid ones left out."""
    values: dict[tuple[str, str], list[float]] = defaultdict(list)
    for directory in sorted(root.iterdir()):
        summary = json.loads((directory / "summary.json").read_text())
        manifest = json.loads((directory / "manifest.json").read_text())
        grade = summary["results"]["severity"]["paper_estimator"]["nearest_grade"]
        key = (manifest["metadata"]["site"], grade)
        values.setdefault(key, [])
        if summary["validity"]["viscosity_n_s_per_mm2"]["status"] != "invalid":
            values[key].append(summary["results"]["paper_estimator"]["viscosity_n_s_per_mm2"])
    return {k: (math.fsum(v) / len(v) if v else math.nan, len(v)) for k, v in values.items()}


def test_mean_eta_per_grade_per_site(study: Study, tmp_path: Path) -> None:
    out = tmp_path / "eta.csv"
    sql = (
        "SELECT site, severity_grade AS grade, avg(viscosity_n_s_per_mm2) AS eta, "
        "count(viscosity_n_s_per_mm2) AS n FROM results WHERE analysis = 'recorded' "
        "GROUP BY ALL ORDER BY ALL"
    )
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["study", "query", str(study.dataset), sql, "--out", str(out)]) == 0
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    want = _direct_means(study.root)
    assert {(r["site"], r["grade"]) for r in rows} == set(want)
    for r in rows:
        eta, n = want[(r["site"], r["grade"])]
        assert int(r["n"]) == n
        assert float(r["eta"]) == pytest.approx(eta, rel=1e-12)
    # An invalid viscosity is null in the dataset, with its status and reason beside it.
    invalid = run_query(
        study.dataset,
        "SELECT count(*) AS n, count(viscosity_n_s_per_mm2) AS v, "
        "count(viscosity_n_s_per_mm2_reason) AS r "
        "FROM results WHERE viscosity_n_s_per_mm2_status = 'invalid'",
    ).to_pylist()[0]
    assert invalid == {
        "n": sum(s.status == "invalid" for s in study.sessions),
        "v": 0,
        "r": invalid["n"],
    }
    assert invalid["n"] > 100


def test_reindex_rewrites_nothing(study: Study) -> None:
    before = _files(study.dataset)
    state_before = json.loads((study.dataset / "study.json").read_text())["sessions"]
    report = index_sessions([study.root], study.dataset)
    assert (report.added, report.replaced, report.unchanged) == ([], [], N_SESSIONS)
    after = _files(study.dataset)
    after.pop("study.json"), before.pop("study.json")
    assert after == before
    assert json.loads((study.dataset / "study.json").read_text())["sessions"] == state_before
