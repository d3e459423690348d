"""``study query`` changes nothing and reads nothing but the dataset.

A dataset of three synthetic sessions (the real writer and indexer) and a file of the
user's beside it; every statement that would write a file (``COPY``, its ``EXPLAIN
ANALYZE`` forms, ``EXPORT``, ``ATTACH``...), change the connection's settings or read a
file outside the dataset (``read_csv('/etc/passwd')``, ``read_text``...) is run through
the command line with real DuckDB, and must be refused in one line, exit status 2, with
every file under the work directory byte-identical afterwards and none created.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import random
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.study.index import index_sessions

from ._synthetic import write_session


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    } | {str(p.relative_to(root)) + "/": "" for p in root.rglob("*") if p.is_dir()}


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    w = tmp_path_factory.mktemp("query_ro")
    rng = random.Random(40)
    for i in range(3):
        write_session(w / "sessions", i, rng)
    index_sessions([w / "sessions"], w / "ds")
    (w / "mine.csv").write_text("a,b\n1,2\n")
    return w


#: Statements that would write or read outside the dataset; {w} is the work directory,
#: {pq} one of the dataset's own Parquet files.
HOSTILE = (
    "COPY sessions TO '{w}/out.csv'",
    "COPY sessions TO '{w}/mine.csv'",
    "EXPLAIN ANALYZE COPY sessions TO '{w}/mine.csv'",
    "EXPLAIN ANALYZE COPY (SELECT 1 AS a) TO '{w}/ds/study.json' (FORMAT csv)",
    "EXPLAIN ANALYZE COPY (SELECT 1 AS a) TO '{pq}' (FORMAT parquet, USE_TMP_FILE false)",
    "COPY (SELECT 1 AS a) TO '{pq}' (FORMAT parquet, USE_TMP_FILE false)",
    "EXPLAIN COPY sessions TO '{w}/out.csv'",
    "explain analyse copy sessions to '{w}/out.csv'",
    "/* a */ EXPLAIN /* b */ ANALYZE COPY sessions TO '{w}/out.csv'",
    "EXPLAIN (ANALYZE) COPY sessions TO '{w}/out.csv'",
    "EXPLAIN ANALYZE CREATE TABLE t AS SELECT 1",
    "EXPLAIN ANALYZE INSERT INTO sessions SELECT * FROM sessions",
    "EXPORT DATABASE '{w}/export'",
    "ATTACH '{w}/new.duckdb'",
    "ATTACH '{w}/new.duckdb' AS x; CREATE TABLE x.t AS SELECT 1",
    "CREATE TABLE t AS SELECT 1",
    "CREATE OR REPLACE VIEW sessions AS SELECT 1",
    "DROP VIEW sessions",
    "INSTALL httpfs",
    "LOAD httpfs",
    "SET enable_external_access = true",
    "SET lock_configuration = false",
    "PRAGMA enable_profiling",
    "CALL pragma_version()",
    "SELECT * FROM read_csv('/etc/passwd')",
    "SELECT * FROM read_csv_auto('{w}/mine.csv')",
    "SELECT * FROM '{w}/mine.csv'",
    "SELECT * FROM read_text('/etc/passwd')",
    "SELECT * FROM read_blob('/etc/passwd')",
    "SELECT * FROM glob('/etc/*')",
    "SELECT * FROM sniff_csv('/etc/passwd')",
    "SELECT * FROM read_json('{w}/mine.csv')",
    "SELECT * FROM read_parquet('{w}/ds/**/*.json')",
    "WITH x AS (SELECT 1) SELECT * FROM read_text('/etc/passwd')",
    "EXPLAIN ANALYZE SELECT * FROM read_text('/etc/passwd')",
    "SELECT * FROM read_csv('https://example.invalid/x.csv')",
)


@pytest.mark.parametrize("template", HOSTILE)
def test_a_query_that_writes_or_reads_outside_is_refused(work: Path, template: str) -> None:
    pq = next((work / "ds" / "sessions").rglob("*.parquet"))
    sql = template.format(w=work, pq=pq)
    before = _snapshot(work)
    status, out, err = _run(["study", "query", str(work / "ds"), sql])
    assert status == 2 and out == "", (sql, out, err)
    (line,) = err.strip().splitlines()
    assert line.startswith("stipi-daemon: error: SQL: "), line
    assert "Traceback" not in err
    assert _snapshot(work) == before, sql


@pytest.mark.parametrize(
    "sql",
    [
        "SELECT count(*) AS n FROM sessions",
        "EXPLAIN SELECT * FROM results",
        "EXPLAIN ANALYZE SELECT count(*) FROM force_samples",
        "/* a comment */ WITH x AS (SELECT site FROM sessions) SELECT count(*) FROM x",
        "SELECT count(*) FROM sessions s JOIN results r USING (session_uid)",
    ],
)
def test_queries_still_run(work: Path, sql: str) -> None:
    before = _snapshot(work)
    status, _out, err = _run(["study", "query", str(work / "ds"), sql])
    assert status == 0 and err == "", err
    assert _snapshot(work) == before


def test_a_truncated_dataset_file_is_one_line_and_index_writes_it_again(tmp_path: Path) -> None:
    rng = random.Random(41)
    write_session(tmp_path / "sessions", 0, rng)
    dataset = tmp_path / "ds"
    index_sessions([tmp_path / "sessions"], dataset)
    victim = next((dataset / "frames").rglob("*.parquet"))
    victim.write_bytes(victim.read_bytes()[:100])
    status, out, err = _run(["study", "query", str(dataset), "SELECT count(*) FROM sessions"])
    assert status == 2 and out == ""
    (line,) = err.strip().splitlines()
    assert "a dataset file is unreadable" in line and "study index" in line
    report = index_sessions([tmp_path / "sessions"], dataset)
    assert report.unchanged == 0 and len(report.replaced) == 1
    status, out, err = _run(["study", "query", str(dataset), "SELECT count(*) AS n FROM frames"])
    assert status == 0, err
