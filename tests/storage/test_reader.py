from __future__ import annotations

import json
import shutil
import sqlite3
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, SessionState, SessionWriter, list_sessions
from tests.storage.conftest import OPTIONS, Recorded, write_full_session

CHILD = Path(__file__).with_name("writer_child.py")
REPO_ROOT = Path(__file__).resolve().parents[2]


def _one_line_error(directory: Path) -> str:
    """Open ``directory`` and run the integrity check; return the SessionError message."""
    with pytest.raises(SessionError) as info:
        with SessionReader(directory) as reader:
            reader.integrity_check().raise_if_bad()
    message = str(info.value)
    assert "\n" not in message
    return message


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _damage_page(path: Path, offset_from_end: int | None, garbage: bytes) -> None:
    """Overwrite part of the force_samples root page (header if offset is None, else cells)."""
    conn = sqlite3.connect(path)
    page_size = conn.execute("PRAGMA page_size").fetchone()[0]
    root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name='force_samples'").fetchone()
    conn.close()
    start = (root[0] - 1) * page_size
    start += 0 if offset_from_end is None else page_size - offset_from_end
    data = bytearray(path.read_bytes())
    data[start : start + len(garbage)] = garbage
    path.write_bytes(bytes(data))


def _set_user_version(path: Path) -> None:
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA user_version=99")
    conn.commit()
    conn.close()


def _manifest_version(path: Path) -> None:
    manifest = json.loads(path.read_text())
    manifest["format_version"] = 2
    path.write_text(json.dumps(manifest))


def _manifest_field(path: Path) -> None:
    manifest = json.loads(path.read_text())
    del manifest["calibration"]
    path.write_text(json.dumps(manifest))


BAD_CASES: dict[str, tuple[str, Callable[[Path], object], str]] = {
    "sqlite missing": ("session.sqlite", lambda p: p.unlink(), "session database is missing"),
    "sqlite empty": ("session.sqlite", lambda p: p.write_bytes(b""), "is empty (0 bytes)"),
    "sqlite truncated": ("session.sqlite", _truncate, "truncated or corrupt"),
    "sqlite not a database": (
        "session.sqlite",
        lambda p: p.write_bytes(b"this is not sqlite" * 300),
        "file is not a database",
    ),
    "sqlite page header corrupt": (
        "session.sqlite",
        lambda p: _damage_page(p, None, b"\xff" * 8),
        "not readable (database disk image is malformed)",
    ),
    "sqlite cells corrupt": (
        "session.sqlite",
        lambda p: _damage_page(p, 60, b"\x07" * 60),
        "integrity_check failed",
    ),
    "unknown schema version": (
        "session.sqlite",
        _set_user_version,
        "schema version 99 is not supported (this stipi-daemon reads versions 1, 2)",
    ),
    "manifest missing": ("manifest.json", lambda p: p.unlink(), "manifest is missing"),
    "manifest not json": (
        "manifest.json",
        lambda p: p.write_text('{"format": "stipi-session",'),
        "manifest is not valid JSON",
    ),
    "manifest wrong version": (
        "manifest.json",
        _manifest_version,
        "format_version 2 is not supported (this stipi-daemon reads version 1)",
    ),
    "manifest wrong format": (
        "manifest.json",
        lambda p: p.write_text('{"format": "other"}'),
        "format is 'other', expected 'stipi-session'",
    ),
    "manifest field missing": ("manifest.json", _manifest_field, "field 'calibration' is missing"),
    "summary not json": ("summary.json", lambda p: p.write_text("{"), "summary is not valid JSON"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_directory_gives_one_line_error(recorded: Recorded, case: str) -> None:
    file_name, damage, expected = BAD_CASES[case]
    damage(recorded.directory / file_name)
    message = _one_line_error(recorded.directory)
    assert str(recorded.directory / file_name) in message
    assert expected in message


def test_missing_directory_and_not_a_session_database(tmp_path: Path, recorded: Recorded) -> None:
    message = _one_line_error(tmp_path / "nope")
    assert message == f"{tmp_path / 'nope'}: session directory does not exist"
    db = recorded.directory / "session.sqlite"
    db.unlink()
    conn = sqlite3.connect(db)
    conn.execute("CREATE TABLE other (x)")
    conn.commit()
    conn.close()
    assert "not a stipi session database" in _one_line_error(recorded.directory)


def test_missing_table_and_mismatched_session_id(recorded: Recorded) -> None:
    copy = recorded.root / "copy"
    shutil.copytree(recorded.directory, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["session_id"] = "someone-else"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    assert "differs from the database's 's-full'" in _one_line_error(copy)
    conn = sqlite3.connect(recorded.directory / "session.sqlite")
    conn.execute("DROP TABLE gaps")
    conn.commit()
    conn.close()
    assert "table 'gaps' is missing" in _one_line_error(recorded.directory)


def test_integrity_ok_and_unknown_table(recorded: Recorded) -> None:
    with SessionReader(recorded.directory) as reader:
        assert reader.integrity_check().ok
        with pytest.raises(SessionError, match="no session table 'nope'"):
            reader.array("nope")


def test_reader_in_another_process_sees_committed_rows_only(tmp_path: Path) -> None:
    from stipi_daemon.storage import StorageOptions

    script = textwrap.dedent(
        """
        import sys
        from stipi_daemon.storage import SessionReader
        with SessionReader(sys.argv[1]) as r:
            print(r.status.value, r.count("force_samples"), r.count("events"))
        """
    )

    def read_in_child() -> list[str]:
        out = subprocess.run(
            [sys.executable, "-c", script, str(tmp_path / "s")],
            capture_output=True,
            text=True,
            check=True,
            cwd=REPO_ROOT,
        )
        return out.stdout.split()

    options = StorageOptions(min_free_bytes=0, background_commit=False, commit_interval_s=60)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        writer.add_force_samples([(i, 1, i, i, float(i), None) for i in range(50)])
        writer.commit()
        writer.add_event(1.0, "pending", {})  # buffered, not committed
        assert read_in_child() == ["recording", "50", "0"]
        writer.commit()
        assert read_in_child() == ["recording", "50", "1"]
        writer.finish("complete")
        assert read_in_child() == ["complete", "50", "1"]


def test_reader_follows_a_writer_in_another_process(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, str(CHILD), str(tmp_path), "child", "hold", "0.2"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
    )
    assert proc.stdin is not None and proc.stdout is not None
    try:
        assert proc.stdout.readline().strip() == "committed 100"
        with SessionReader(tmp_path / "child") as reader:
            assert reader.status is SessionState.RECORDING
            owner = reader.writer_owner
            assert owner is not None and owner["pid"] == proc.pid
            assert reader.count("force_samples") == 100
            proc.stdin.write("more 50\n")
            proc.stdin.flush()
            assert proc.stdout.readline().strip() == "committed 150"
            assert reader.count("force_samples") == 150
            assert reader.integrity_check().ok
            proc.stdin.write("finish\n")
            proc.stdin.flush()
            assert proc.stdout.readline().strip() == "done"
            assert proc.wait(timeout=10) == 0
            assert reader.status.value == "complete"
            assert reader.summary == {"n": 150}
    finally:
        if proc.poll() is None:  # pragma: no cover - only if an assertion fired early
            proc.kill()
            proc.wait()
        proc.stdin.close()
        proc.stdout.close()


def test_snapshot_is_consistent_while_writer_commits(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        writer.add_event(1.0, "a", {})
        writer.commit()
        with SessionReader(tmp_path / "s") as reader:
            with reader.snapshot():
                assert reader.count("events") == 1
                writer.add_event(2.0, "b", {})
                writer.commit()
                assert reader.count("events") == 1
            assert reader.count("events") == 2
        writer.finish("complete")


def test_list_sessions(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    write_full_session(root, "a-complete")
    write_full_session(root, "b-interrupted", finish=None)
    live = SessionWriter.create(root, {}, {}, session_id="c-live", options=OPTIONS)
    bad = write_full_session(root, "d-bad").directory
    (bad / "manifest.json").unlink()
    (root / "not-a-session").mkdir()
    try:
        listing = {s.session_id: s for s in list_sessions(root)}
    finally:
        live.close()
    assert list(listing) == ["a-complete", "b-interrupted", "c-live", "d-bad"]
    a = listing["a-complete"]
    assert (a.status, a.n_samples, a.n_frames, a.severity) == ("complete", 6, 3, "severe (3+)")
    assert a.duration_s == pytest.approx(3 / 60 + 0.004)
    assert listing["b-interrupted"].status == "interrupted"
    assert listing["b-interrupted"].severity is None
    assert listing["c-live"].status == "recording"
    assert listing["c-live"].duration_s is None
    assert listing["d-bad"].status == "error"
    assert listing["d-bad"].error is not None and "manifest is missing" in listing["d-bad"].error
    with pytest.raises(SessionError, match="sessions directory does not exist"):
        list_sessions(tmp_path / "nowhere")


@pytest.mark.parametrize(
    ("summary", "shown"),
    [
        (None, None),
        ({}, None),
        ({"severity": "mild"}, "mild"),
        ({"severity": {"severity": "severe", "nearest_grade": "4+"}}, "severe (4+)"),
        ({"severity": {"grade": "2+"}}, "2+"),
        ({"severity": {"other": 1}}, None),
        # Where the daemon writes it: the paper estimator's class under results.
        (
            {
                "results": {
                    "severity": {"paper_estimator": {"severity": "mild", "nearest_grade": 1}}
                }
            },
            "mild (1)",
        ),
        (
            {
                "results": {"severity": {"paper_estimator": {"severity": "mild"}}},
                "validity": {"severity": {"status": "invalid", "flags": [], "reason": "x"}},
            },
            "invalid",
        ),
    ],
)
def test_severity_of(summary: dict[str, object] | None, shown: str | None) -> None:
    from stipi_daemon.storage.reader import severity_of

    assert severity_of(summary) == shown


@pytest.mark.parametrize(
    ("summary", "shown"),
    [
        (None, "unknown"),
        ({"status": "complete"}, "unknown"),
        ({"verdict": {"status": "flagged", "line": "x"}}, "flagged"),
        ({"verdict": {"status": "bogus"}}, "unknown"),
        ({"verdict": "complete"}, "unknown"),
    ],
)
def test_verdict_of_reads_old_sessions_as_unknown(
    summary: dict[str, object] | None, shown: str
) -> None:
    from stipi_daemon.storage.reader import verdict_of

    assert verdict_of(summary) == shown
