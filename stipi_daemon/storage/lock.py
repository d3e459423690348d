"""The writer lock of a session directory: who is recording, and is it still alive.

A :class:`WriterLock` is the file ``writer.lock`` in a session directory, holding the
writer's pid, host and start time as JSON, with an exclusive ``flock`` held on it for as
long as the writer is open. The kernel drops the lock when the process dies, however it
dies, so :func:`writer_alive` tells a live writer from a killed one without trusting pids.
``flock`` locks belong to an open file description, so the probe works within one process
as well as across processes. This module does not decide a session's status (that is
:mod:`.reader`, combining the lock with the stored state).

Limitation: ``flock`` is local to one machine; on network file systems (NFS, SMB) a writer
on another host is not seen. Record and read sessions on a local disk.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
from pathlib import Path
from typing import Any

from stipi_daemon.errors import SessionError


class WriterLock:
    """Exclusive lock proving a live writer; released by :meth:`release` or process death."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd: int | None = fd

    @classmethod
    def acquire(cls, path: Path, *, started_utc: str) -> WriterLock:
        """Create ``path``, lock it exclusively and write the owner's identity into it.

        Raises
        ------
        SessionError
            The file cannot be created, or another live writer holds the lock.
        """
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise SessionError(f"{path}: cannot create writer lock: {exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise SessionError(f"{path}: another writer is recording this session") from None
            raise SessionError(f"{path}: cannot lock: {exc}") from exc
        owner = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": started_utc}
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(owner) + "\n").encode())
        os.fsync(fd)
        return cls(path, fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Remove the lock file and drop the lock (idempotent)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


def writer_alive(path: Path) -> bool:
    """Whether a live process holds the writer lock at ``path`` (False if there is no file)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise SessionError(f"{path}: cannot open writer lock: {exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            return True
        raise SessionError(f"{path}: cannot probe writer lock: {exc}") from exc
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def read_owner(path: Path) -> dict[str, Any] | None:
    """The owner recorded in a lock file (pid, host, started_utc), or None if unreadable."""
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None
