"""Where exports and analyses may write, what a failed export leaves, and frame order.

* A stray ``session.sqlite`` or ``writer.lock`` in a parent directory (a 0-byte file)
  makes no directory a session: exports and ``analyze --out`` below it are allowed; a
  real session (manifest beside its database) still is one.
* ``--out ''`` is refused in one line (it was the current directory).
* An export that fails (a file-size limit in a child process, a real EFBIG) leaves no
  partial or temporary file and no directory it created.
* An export's ``frames`` rows are in capture order (``seq``) even where the session
  stored them out of it (the measurer's workers finish in any order).
"""

from __future__ import annotations

import csv
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from stipi_daemon.app.offline_io import read_frame_times_csv
from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions, export_session
from tests.storage.conftest import write_full_session


def test_a_stray_database_or_lock_up_the_tree_is_no_session(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = write_full_session(tmp_path / "sessions")
    place = tmp_path / "elsewhere"
    place.mkdir()
    (place / "session.sqlite").write_bytes(b"")
    (place / "writer.lock").write_bytes(b"")
    out = place / "deeper" / "export"
    assert main(["sessions", "export", str(rec.directory), "--out", str(out)]) == 0
    assert (out / "frames.csv").is_file()
    analysis = place / "deeper" / "analysis.json"
    code = main(["analyze", str(rec.directory), "--out", str(analysis)])
    captured = capsys.readouterr()
    assert "inside the session directory" not in captured.err
    assert code != 2 or "session directory" not in captured.err
    # a real session is one still: its database beside its manifest
    code = main(["sessions", "export", str(rec.directory), "--out", str(rec.directory / "x")])
    assert code == 2 and "inside the session directory" in capsys.readouterr().err


def test_an_empty_out_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = write_full_session(tmp_path / "sessions")
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)  # where '' wrote
    for argv in (
        ["sessions", "export", str(rec.directory), "--out", ""],
        ["sessions", "table", "--root", str(rec.directory.parent), "--out", " "],
    ):
        assert main(argv) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("stipi-daemon: error: --out") and "empty" in line
    assert not any(here.iterdir())


CHILD = """
import sys
from pathlib import Path
from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, export_session
with SessionReader(Path(sys.argv[1])) as reader:
    try:
        export_session(reader, Path(sys.argv[2]), sys.argv[3])
    except SessionError as exc:
        print(exc)
"""


OVERWRITING_CHILD = CHILD.replace("sys.argv[3])", "sys.argv[3], overwrite=True)")


def _limit_file_size() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (1500, 1500))


@pytest.mark.parametrize("fmt", ["csv", "parquet", "mat"])
def test_a_failed_export_leaves_nothing(tmp_path: Path, fmt: str) -> None:
    rec = write_full_session(tmp_path / "sessions")
    out = tmp_path / "exports" / "one"
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(rec.directory), str(out), fmt],
        capture_output=True,
        text=True,
        preexec_fn=_limit_file_size,
        check=True,
    )
    (line,) = proc.stdout.strip().splitlines()
    assert "export failed (nothing written)" in line or "cannot write" in line, line
    assert not (tmp_path / "exports").exists()


def test_a_failed_export_replaces_nothing(tmp_path: Path) -> None:
    rec = write_full_session(tmp_path / "sessions")
    out = tmp_path / "exports"
    out.mkdir()
    (out / "frames.csv").write_text("mine\n")
    proc = subprocess.run(
        [sys.executable, "-c", OVERWRITING_CHILD, str(rec.directory), str(out), "csv"],
        capture_output=True,
        text=True,
        preexec_fn=_limit_file_size,
        check=True,
    )
    assert proc.stdout.strip(), proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["frames.csv"]
    assert (out / "frames.csv").read_text() == "mine\n"


def test_exported_frames_are_in_capture_order(tmp_path: Path) -> None:
    with SessionWriter.create(
        tmp_path / "sessions",
        {},
        {},
        None,
        session_id="shuffled",
        options=StorageOptions(min_free_bytes=0),
    ) as writer:
        writer.add_frames([(seq, seq / 60, seq / 60, 100 + seq, "") for seq in (0, 2, 1, 4, 3)])
        writer.finish("complete", {"status": "complete"})
    session = tmp_path / "sessions" / "shuffled"
    with SessionReader(session) as reader:
        assert [r[0] for r in reader.iter_rows("frames")] == [0, 2, 1, 4, 3]
        export_session(reader, tmp_path / "out", "csv")
    with open(tmp_path / "out" / "frames.csv", newline="") as f:
        assert [int(r["seq"]) for r in csv.DictReader(f)] == [0, 1, 2, 3, 4]
    # what analyze --video reads of an export: frame times that increase
    times, _ = read_frame_times_csv(tmp_path / "out" / "frames.csv")
    assert list(times) == sorted(times)
    shutil.rmtree(tmp_path / "out")
