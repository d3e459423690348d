from __future__ import annotations

import os
from pathlib import Path

import pytest

from stipi_daemon.errors import SessionError
from stipi_daemon.storage.lock import WriterLock, read_owner, writer_alive


def test_lock_is_seen_in_the_same_process_and_released(tmp_path: Path) -> None:
    path = tmp_path / "writer.lock"
    assert not writer_alive(path)
    lock = WriterLock.acquire(path, started_utc="2025-01-01T00:00:00Z")
    try:
        assert writer_alive(path)
        owner = read_owner(path)
        assert owner is not None and owner["pid"] == os.getpid()
        with pytest.raises(SessionError, match="another writer is recording"):
            WriterLock.acquire(path, started_utc="x")
    finally:
        lock.release()
    lock.release()  # idempotent
    assert not lock.held
    assert not path.exists()
    assert not writer_alive(path)


def test_stale_lock_file_is_not_alive(tmp_path: Path) -> None:
    path = tmp_path / "writer.lock"
    path.write_text('{"pid": 999999999, "host": "gone"}\n')
    assert not writer_alive(path)
    assert read_owner(path) == {"pid": 999999999, "host": "gone"}
    path.write_text("garbage")
    assert read_owner(path) is None
