"""Disk full while recording, and the free-space check before a session starts.

The daemon (``stipi-daemon --config``, a subprocess) records onto a file system that
fills up: a 1.5 MB tmpfs the test mounts (when it runs as root; ENOSPC) and, everywhere,
a file-size limit set in the child (``RLIMIT_FSIZE``: writes past it fail with EFBIG, a
real OS failure path; CPython ignores SIGXFSZ). The daemon must stop recording within 1 s
of the last write that reached the disk (measured when its error line appears: by then the
session is closed and the devices released), print one line saying why, exit non-zero,
and leave a session that opens, passes its integrity check and holds every row it
committed. (The interpreter's own teardown after that takes another 0.3-1 s; reported.)

The session records its video (the default ``storage.video: passthrough``: FFV1 of the
scene's raw frames; the JPEGs of an MJPG scene), which fills the disk first; video and rows
must stop together (docs/storage.md, "Disk full"): FFmpeg (PyAV) decodes every frame the
``video_frames`` rows name (but the newest, which the muxer may have held when the write
failed), and the newest frame that plays and the newest stored frame row are within one
commit interval, or the frames the encoders hold, of each other. A run without video
(``video: off``) fills the disk with the database itself.
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
from stipi_daemon.storage.video import ENCODER_QUEUE_FRAMES, ENCODER_WORKERS

from ._video import check_rows_in_video, stored_video
from .conftest import PYTHON, REPO_ROOT, fast_scene, report, write_config

SPEED = 4.0
#: Largest file the daemon may write [B] (RLIMIT_FSIZE), by the session video's codec
#: (None: no video). A video frame of the full-size scene is about 19 kB either way (FFV1
#: of the clean frame, or its JPEG): 4 MB hold about 210 frames (3.5 s of the scene), so
#: the run is well under way when the video reaches the limit; without video the database
#: reaches 1 MB.
FSIZE_LIMIT_B = {"ffv1": 4_000_000, "mjpeg": 4_000_000, None: 1_000_000}
#: The tmpfs the root form mounts (session with FFV1 video).
TMPFS_SIZE = "5000k"
#: The scene's frame rate (``fast_scene(cheap=False)``) [fps].
FPS = 60.0
#: Commit interval of the daemon under test [s of wall time] (the config default).
COMMIT_INTERVAL_S = 0.2
#: How far apart the video and the rows may stop [s of session time]: one commit interval
#: (rows of frames the video holds not yet committed, or the reverse), or the frames whose
#: rows are stored while the FFV1 encoders still hold them (the queue, one per encoder, the
#: newest held by the muxer), with a frame of slack.
STOP_TOGETHER_S = (
    max(COMMIT_INTERVAL_S * SPEED, (ENCODER_QUEUE_FRAMES + ENCODER_WORKERS + 1) / FPS) + 1.0 / FPS
)


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


def _check_video(session: Path, codec: str) -> dict[str, float]:
    """Video and rows stopped together (module docstring); the figures for the report."""
    video = stored_video(session)
    assert video.codec == codec, (video.codec, video.error)
    check_rows_in_video(video, newest_may_be_missing=True)
    apart_s = video.newest_frame_capture_s - video.plays_to_s
    assert abs(apart_s) <= STOP_TOGETHER_S, (apart_s, video.decoded, len(video.row_index))
    assert video.decoded > 100, video.decoded
    return {"video_frames_decoded": video.decoded, "video_rows_minus_plays_s": apart_s}


def _record_until_full(
    tmp_path: Path, root: Path, *, fsize: bool, codec: str | None = "ffv1"
) -> None:
    scene = fast_scene(tmp_path, cheap=False, pixel_format="mjpg" if codec == "mjpeg" else "bgr8")
    storage = {"video": "off"} if codec is None else {}
    cfg = write_config(tmp_path / "c.yaml", scene, root, speed=SPEED, storage=storage)
    limit_b = FSIZE_LIMIT_B[codec]

    def limit() -> None:
        if fsize:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_b, limit_b))

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
    # The rows' or the video's failure, whichever came first (the video fills the disk first).
    assert "recording stopped" in line
    assert "could not be stored" in line or "video could not be written" in line
    assert ("full" in line) or ("too large" in line) or ("disk I/O" in line)
    stopped_after_s = t_line - last[0]
    assert stopped_after_s < 1.0
    (session,) = [d for d in root.iterdir() if d.is_dir()]
    with SessionReader(session) as r:
        assert r.integrity_check().ok, r.integrity_check().problems
        counts = r.counts()
        status = r.status
    assert counts["force_samples"] > 100 and counts["frames"] > 100
    if codec is None:
        assert not (session / "video.mkv").exists()
    assert not list(session.rglob("*.tmp"))  # a failed atomic write leaves no partial file
    figures = {} if codec is None else _check_video(session, codec)
    report(
        "disk_full_" + ("rlimit_fsize" if fsize else "tmpfs") + f"_{codec or 'no_video'}",
        **figures,
        stopped_after_last_write_s=stopped_after_s,
        exited_after_last_write_s=t_exit - last[0],
        rows_kept=counts,
        status=str(status),
        message=line,
    )


def test_file_system_full_tmpfs(tmp_path: Path) -> None:
    with _tmpfs(tmp_path / "fs", TMPFS_SIZE) as mounted:
        if not mounted:
            pytest.skip("mounting a tmpfs needs root; the RLIMIT_FSIZE form covers this")
        _record_until_full(tmp_path, tmp_path / "fs" / "sessions", fsize=False)


@pytest.mark.parametrize("codec", ["ffv1", "mjpeg", None], ids=["ffv1", "mjpeg", "no_video"])
def test_file_size_limit_rlimit_fsize(tmp_path: Path, codec: str | None) -> None:
    _record_until_full(tmp_path, tmp_path / "sessions", fsize=True, codec=codec)


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
