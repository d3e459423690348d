from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.errors import EXIT_BAD_INPUT, EXIT_DAMAGED
from stipi_daemon.storage import TABLES, SessionReader, SessionWriter, StorageOptions
from tests.storage.conftest import write_full_session
from tests.storage.test_export import assert_equal_to_reader, read_csv_table, read_parquet_table

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def root(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    write_full_session(root, "a-complete")
    write_full_session(root, "b-interrupted", finish=None)
    bad = write_full_session(root, "c-bad").directory
    (bad / "session.sqlite").write_bytes(b"garbage" * 1000)
    return root


def test_list(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sessions", "list", "--root", str(root)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == [
        "ID",
        "CREATED",
        "(UTC)",
        "STATUS",
        "SUBJECT",
        "SITE",
        "OPERATOR",
        "LABEL",
        "VALIDITY",
        "DURATION",
        "FRAMES",
        "SAMPLES",
        "SEVERITY",
    ]
    a = lines[1].split()
    # An old summary (no validity recorded) reads as "unknown", never as a verdict; a
    # session without metadata shows "-".
    assert a[0] == "a-complete"
    assert a[2:] == [
        "complete",
        "-",
        "-",
        "-",
        "-",
        "unknown",
        "0.1",
        "s",
        "3",
        "6",
        "severe",
        "(3+)",
    ]
    assert lines[2].split()[2] == "interrupted"
    assert lines[3].split()[:3] == ["c-bad", "-", "error"]
    assert lines[4].startswith("c-bad: ") and "file is not a database" in lines[4]


def test_list_shows_the_verdict_and_the_daemons_severity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The daemon writes the class under results.severity.paper_estimator (not at the top)."""
    summary = {
        "status": "complete",
        "results": {"severity": {"paper_estimator": {"severity": "mild", "nearest_grade": "1+"}}},
        "verdict": {"status": "flagged", "line": "Complete with caveats on T_r."},
    }
    root = tmp_path / "sessions"
    write_full_session(root, "a", summary=summary)
    assert main(["sessions", "list", "--root", str(root)]) == 0
    row = capsys.readouterr().out.splitlines()[1].split()
    assert row[2:8] == ["complete", "-", "-", "-", "-", "flagged"]
    assert row[-2:] == ["mild", "(1+)"]


def test_list_empty_and_missing_root(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sessions", "list", "--root", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == f"no sessions in {tmp_path}"
    assert main(["sessions", "list", "--root", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err == f"stipi-daemon: error: {tmp_path / 'none'}: sessions directory does not exist\n"


def test_show(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sessions", "show", "a-complete", "--root", str(root)]) == 0
    out = capsys.readouterr().out
    assert "status     complete" in out
    assert "integrity  ok" in out
    assert "video      video.mkv (" in out
    assert "ffv1 8x8 gray, 3 frames)" in out
    assert re.search(r"^  force_samples +6$", out, re.MULTILINE)
    assert re.search(r"^  frames +3$", out, re.MULTILINE)
    assert '"alpha1": 1.2e-09' in out  # manifest calibration
    assert '"nearest_grade": "3+"' in out  # summary
    assert main(["sessions", "show", str(root / "b-interrupted")]) == 0
    out = capsys.readouterr().out
    assert "status     interrupted" in out and "summary: none" in out


def test_show_errors(root: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sessions", "show", "c-bad", "--root", str(root)]) == EXIT_DAMAGED
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "c-bad/session.sqlite: not a readable SQLite database" in err
    assert main(["sessions", "show", "zzz", "--root", str(root)]) == EXIT_BAD_INPUT
    assert "no such session" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export(root: Path, tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    args = ["sessions", "export", "a-complete", "--root", str(root), "--format", fmt]
    assert main([*args, "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    # tables, validity, the session's results row, manifest, summary, video
    assert len(printed) == len(TABLES) + 5
    assert printed[-1].endswith("video.mkv")
    read = read_csv_table if fmt == "csv" else read_parquet_table
    with SessionReader(root / "a-complete") as reader:
        for table in TABLES:
            assert_equal_to_reader(reader, table, read(out / f"{table.name}.{fmt}", table))
    assert main([*args, "--out", str(out)]) == 2
    assert "exists already (use --overwrite" in capsys.readouterr().err
    assert main([*args, "--out", str(out), "--force"]) == 0


def test_sessions_help_via_entry_point() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "stipi_daemon", "sessions", "--help"],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 0
    assert "list" in proc.stdout and "export" in proc.stdout


def test_export_of_a_session_still_recording_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An export of a live session is what was stored so far, which goes stale as it records
    on, without results: a warning says so (the export itself goes on)."""
    root = tmp_path / "sessions"
    writer = SessionWriter.create(
        root, {}, {}, session_id="live", options=StorageOptions(min_free_bytes=0)
    )
    try:
        writer.add_frames([(i, i / 30, i / 30, 1000, "") for i in range(10)])
        writer.commit()
        args = ["sessions", "export", "live", "--root", str(root), "--out", str(tmp_path / "x")]
        assert main(args) == 0
        err = capsys.readouterr().err
        assert err == (
            f"stipi-daemon: warning: {root / 'live'}: the session is still recording: exported "
            "what was stored so far, without its results\n"
        )
    finally:
        writer.close()
