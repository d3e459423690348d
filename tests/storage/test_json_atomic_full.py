"""A JSON file written atomically onto a full disk leaves nothing behind.

A child process writes ``summary.json`` with a file-size limit (``RLIMIT_FSIZE``: the
write fails with EFBIG, a real OS failure path; CPython ignores SIGXFSZ) smaller than the
document: one :class:`~stipi_daemon.errors.SessionError` line, the old file as it was, and
no ``summary.json.tmp`` left in the directory.
"""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

CHILD = """
import sys
from pathlib import Path
from stipi_daemon.errors import SessionError
from stipi_daemon.storage.layout import write_json_atomic
try:
    write_json_atomic(Path(sys.argv[1]), {"x": "y" * 100_000}, what="summary")
except SessionError as exc:
    print(exc)
"""


def _limit_file_size() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))


def test_a_failed_write_leaves_no_temporary_file(tmp_path: Path) -> None:
    target = tmp_path / "summary.json"
    target.write_text('{"old": true}\n')
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(target)],
        capture_output=True,
        text=True,
        preexec_fn=_limit_file_size,
        check=True,
    )
    (line,) = proc.stdout.strip().splitlines()
    assert line.startswith(f"{target}: cannot write summary"), line
    assert target.read_text() == '{"old": true}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
