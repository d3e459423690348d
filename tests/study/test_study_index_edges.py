"""Indexing edge cases on small sessions written by the real storage writer: an interrupted
session, two sessions under one id, deleted dataset files, a second indexer, bad --out and
roots."""

from __future__ import annotations

import contextlib
import io
import random
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionWriter, StorageOptions
from stipi_daemon.storage.lock import WriterLock
from stipi_daemon.study.dataset import StudyError
from stipi_daemon.study.index import LOCK_NAME, index_sessions
from stipi_daemon.study.query import run_query
from tests.study._synthetic import write_session


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


def test_interrupted_session_is_indexed_with_the_reason_it_has_no_results(
    tmp_path: Path,
) -> None:
    writer = SessionWriter.create(
        tmp_path / "root",
        {},
        {},
        None,
        session_id="cut",
        options=StorageOptions(min_free_bytes=0, background_commit=False),
    )
    writer.add_force_samples([(0, 100, 0, 0, 0.0, 0.0), (1, 101, 10, 10, 0.01, 0.05)])
    writer.close()  # not finished: a killed recorder leaves it so
    report = index_sessions([tmp_path / "root"], tmp_path / "ds")
    assert report.added == ["cut"]
    row = run_query(
        tmp_path / "ds",
        "SELECT s.status, s.site, s.probe, r.verdict, r.depth_mm, r.depth_mm_status, r.error "
        "FROM sessions s JOIN results r USING (session_uid)",
    ).to_pylist()
    assert row == [
        {
            "status": "interrupted",
            "site": "unknown",
            "probe": "unknown",
            "verdict": "unknown",
            "depth_mm": None,
            "depth_mm_status": "unknown",
            "error": "no summary.json (session interrupted)",
        }
    ]


def test_two_sessions_under_one_id_get_two_uids(tmp_path: Path) -> None:
    first = write_session(tmp_path / "a", 7, random.Random(1))
    second = write_session(tmp_path / "b", 7, random.Random(2))  # same id, other data
    report = index_sessions([tmp_path / "a", tmp_path / "b"], tmp_path / "ds")
    assert report.added[0] == first.directory.name
    assert report.added[1].startswith(second.directory.name + "-") and len(report.added) == 2
    paths = run_query(tmp_path / "ds", "SELECT path FROM sessions ORDER BY session_uid")
    assert paths["path"].to_pylist() == [str(first.directory), str(second.directory)]


def test_deleted_dataset_files_are_written_again(tmp_path: Path) -> None:
    write_session(tmp_path / "root", 1, random.Random(1))
    index_sessions([tmp_path / "root"], tmp_path / "ds")
    (frames,) = (tmp_path / "ds" / "frames").rglob("*.parquet")
    frames.unlink()
    report = index_sessions([tmp_path / "root"], tmp_path / "ds")
    assert report.replaced == ["S00001"] and frames.is_file()


def test_a_second_indexer_is_refused(tmp_path: Path) -> None:
    write_session(tmp_path / "root", 1, random.Random(1))
    index_sessions([tmp_path / "root"], tmp_path / "ds")
    lock = WriterLock.acquire(tmp_path / "ds" / LOCK_NAME, started_utc="now")
    try:
        with pytest.raises(StudyError, match="another `study index` is writing"):
            index_sessions([tmp_path / "root"], tmp_path / "ds")
    finally:
        lock.release()


def test_bad_out_and_roots_are_one_line_and_write_nothing(tmp_path: Path) -> None:
    write_session(tmp_path / "root", 1, random.Random(1))
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    status, out, err = _run(["study", "index", str(tmp_path / "root"), "--out", str(other)])
    assert (status, out) == (2, "") and len(err.splitlines()) == 1
    assert err.startswith(f"stipi-daemon: error: {other}: not a study dataset")
    assert [p.name for p in other.iterdir()] == ["thesis.tex"]
    missing = tmp_path / "nope"
    status, out, err = _run(["study", "index", str(missing), "--out", str(tmp_path / "ds")])
    assert (status, out) == (2, "")
    assert err == f"stipi-daemon: error: {missing}: sessions directory does not exist\n"
    assert not (tmp_path / "ds").exists()
