"""Disk full while recording, and the free-space check before a session starts.

The daemon (``stipi-daemon --config``, a subprocess) records onto a file system that
fills up: a 1.5 MB tmpfs the test mounts (when it runs as root; ENOSPC) and, everywhere,
a file-size limit set in the child (``RLIMIT_FSIZE``: writes past it fail with EFBIG, a
real OS failure path; CPython ignores SIGXFSZ). The daemon must stop recording within 1 s
of the last write that reached the disk (measured when its error line appears: by then the
session is closed and the devices released), print one line saying why, exit non-zero,
and leave a session that opens, passes its integrity check and holds every row it
committed. (The interpreter's own teardown after that takes another 0.3-1 s; reported.)
"""

from __future__ import annotations

import contextlib
import os
import resource
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader

from .conftest import PYTHON, REPO_ROOT, fast_scene, report, write_config

FSIZE_LIMIT_B = 1_000_000


@contextlib.contextmanager
def _tmpfs(path: Path, size: str) -> Iterator[bool]:
    path.mkdir()
    if os.geteuid() != 0:
        yield False
        return
    ok = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)]
    ).returncode
    try:
        yield ok == 0
    finally:
        if ok == 0:
            subprocess.run(["umount", "-l", str(path)], check=False)


def _watch_growth(root: Path, stop: threading.Event, last: list[float]) -> None:
    """Record the last time any file under ``root`` grew (what reached the disk)."""
    sizes: dict[Path, int] = {}
    while not stop.is_set():
        for f in root.rglob("*"):
            with contextlib.suppress(OSError):
                n = f.stat().st_size
                if n > sizes.get(f, -1):
                    sizes[f] = n
                    last[0] = time.monotonic()
        time.sleep(0.005)


def _record_until_full(tmp_path: Path, root: Path, *, fsize: bool) -> None:
    cfg = write_config(tmp_path / "c.yaml", fast_scene(tmp_path, cheap=False), root, speed=4.0)

    def limit() -> None:
        if fsize:
            resource.setrlimit(resource.RLIMIT_FSIZE, (FSIZE_LIMIT_B, FSIZE_LIMIT_B))

    stop, last = threading.Event(), [time.monotonic()]
    watcher = threading.Thread(target=_watch_growth, args=(root, stop, last))
    watcher.start()
    stderr: list[tuple[float, str]] = []
    try:
        proc = subprocess.Popen(
            [PYTHON, "-m", "stipi_daemon", "--config", str(cfg), "--quiet"],
            cwd=REPO_ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=limit,
        )
        assert proc.stderr is not None
        for line in proc.stderr:
            stderr.append((time.monotonic(), line.rstrip("\n")))
        proc.wait(120)
        t_exit = time.monotonic()
        proc.stderr.close()
    finally:
        stop.set()
        watcher.join()
    assert proc.returncode != 0
    text = "\n".join(line for _, line in stderr)
    assert "Traceback" not in text, text
    # One line from the daemon (a C library may add its own, e.g. libpng's "Write Error").
    ours = [(t, line) for t, line in stderr if line.startswith("stipi-daemon: error:")]
    assert len(ours) == 1, text
    t_line, line = ours[0]
    assert "recording stopped" in line and "could not be stored" in line
    assert ("full" in line) or ("too large" in line) or ("disk I/O" in line)
    stopped_after_s = t_line - last[0]
    assert stopped_after_s < 1.0
    (session,) = [d for d in root.iterdir() if d.is_dir()]
    with SessionReader(session) as r:
        assert r.integrity_check().ok, r.integrity_check().problems
        counts = r.counts()
        status = r.status
    assert counts["force_samples"] > 100 and counts["frames"] > 100
    report(
        "disk_full_" + ("rlimit_fsize" if fsize else "tmpfs"),
        stopped_after_last_write_s=stopped_after_s,
        exited_after_last_write_s=t_exit - last[0],
        rows_kept=counts,
        status=str(status),
        message=line,
    )


def test_file_system_full_tmpfs(tmp_path: Path) -> None:
    with _tmpfs(tmp_path / "fs", "1500k") as mounted:
        if not mounted:
            pytest.skip("mounting a tmpfs needs root; the RLIMIT_FSIZE form covers this")
        _record_until_full(tmp_path, tmp_path / "fs" / "sessions", fsize=False)


def test_file_size_limit_rlimit_fsize(tmp_path: Path) -> None:
    _record_until_full(tmp_path, tmp_path / "sessions", fsize=True)


def test_free_space_is_checked_before_a_session_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = write_config(
        tmp_path / "c.yaml",
        fast_scene(tmp_path),
        tmp_path / "sessions",
        speed=4.0,
        storage={"min_free_mb": 1e12},
    )
    assert main(["--config", str(cfg), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not enough free disk space" in err[0], err
    assert not any((tmp_path / "sessions").iterdir())
