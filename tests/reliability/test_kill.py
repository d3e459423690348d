"""kill -9 of the whole daemon (``stipi-daemon --config``) at random instants.

Each run starts a real daemon process (emulated Feather on a pty + simulator camera,
accelerated), waits until it has committed its first frame, sleeps a random time and
SIGKILLs it. Every session directory must then open, pass its integrity check, be
``interrupted``, hold no hole that is not a recorded gap, and have lost at most one commit
interval: the newest stored frame is compared with the kill instant on the host's
monotonic clock (the ``session_clock`` event maps session times onto it), both by the time
the daemon handed it to storage (the commit-interval promise, <= 0.25 s) and by the time
the simulator captured it (end to end, including the camera pipeline's latency).
``sessions list`` lists every session and ``analyze`` works on what was kept.

Each session records its video (the default ``storage.video: passthrough``: the scene's
raw frames losslessly, FFV1; an MJPG scene's JPEGs as they came), and the video is checked
on its own (:mod:`._video`: FFmpeg's decoding through PyAV, the rows through SQLite) under
the rule of docs/storage.md: the file opens and plays every frame its ``video_frames``
rows name (but the newest, which the muxer may still hold), up to within one commit
interval of the newest stored ``frames`` row (FFV1: within the frames the encoders may
still hold when that is longer). (Frames beyond the rows are the integrity check's.)
20 kills in the normal suite (and 6 of an MJPG scene), 100 behind ``slow``.
"""

from __future__ import annotations

import os
import random
import signal
import sqlite3
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader, SessionState
from stipi_daemon.storage.video import ENCODER_QUEUE_FRAMES, ENCODER_WORKERS

from ._video import check_rows_in_video, stored_video
from .conftest import FAST_FPS, PYTHON, REPO_ROOT, fast_scene, report, write_config

#: Commit interval of the daemon under test [s] (the config default).
COMMIT_INTERVAL_S = 0.2
#: What a kill may lose on top of the commit interval: event-loop and thread wake-up
#: delays on a loaded 2-CPU machine [s]. The promise is 0.25 s in all.
LOSS_SLACK_S = 0.05
SPEED = 2.0
#: Speeds of the attempts at one kill: a daemon that fell behind its lag bound on a loaded
#: machine (a ``falling_behind`` fault, before or at the kill) did not run what this test
#: kills; it is run again, slower. Beside two busy loops, 3 of 26 daemons at speed 2 did.
SPEEDS = (SPEED, 1.0, 0.5)
#: The daemon's lag bound in this test [s of session time] (``run.max_lag_s``): it handles
#: every frame within this of its capture (later ones are recorded gaps; beyond it the
#: run faults). The end-to-end loss is the storage promise plus this, in wall time: how
#: far the camera pipeline runs behind depends on the CPU the machine has to spare, and
#: the daemon bounds and measures it itself (docs/reliability.md, "Falling behind").
MAX_LAG_S = 1.0
#: The probe sends batches of 10 samples at 100 Hz: the newest sample arrives up to one
#: batch after it was taken [s of session time].
BATCH_S = 0.1
#: Frames whose rows may be stored while the FFV1 encoders still hold them [-]: the queue,
#: one in each encoder, and the newest, which the muxer holds until the next arrives.
VIDEO_PENDING_FRAMES = ENCODER_QUEUE_FRAMES + ENCODER_WORKERS + 1


def video_lag_bound_s(speed: float) -> float:
    """How far the video may lag the newest stored frame row [s of wall time]: one commit
    interval (docs/storage.md), or the frames the encoders may hold when that is longer."""
    return max(COMMIT_INTERVAL_S, VIDEO_PENDING_FRAMES / FAST_FPS / speed) + LOSS_SLACK_S


@dataclass(frozen=True)
class Kill:
    directory: Path
    speed: float
    delay_s: float
    stored_lost_s: float
    frames_lost_s: float
    force_lost_s: float
    video_lag_s: float
    video_frames: int


def _first_frame_committed(root: Path) -> Path | None:
    for d in root.iterdir() if root.exists() else ():
        db = d / "session.sqlite"
        if not db.exists():
            continue
        try:
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.05)
            try:
                n = con.execute("SELECT count(*) FROM frames").fetchone()[0]
            finally:
                con.close()
        except sqlite3.Error:
            continue
        if n > 0:
            return d
    return None


def _fell_behind(root: Path) -> bool:
    """Whether a session under ``root`` ended for falling behind its lag bound."""
    for d in root.iterdir() if root.exists() else ():
        db = d / "session.sqlite"
        if db.exists():
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            try:
                n = con.execute(
                    "SELECT count(*) FROM events WHERE kind = 'fault:falling_behind'"
                ).fetchone()[0]
            finally:
                con.close()
            if n:
                return True
    return False


def _kill_one(workdir: Path, scene: Path, seed: int, codec: str) -> Kill:
    """Kill one daemon (module docstring), run again slower while a loaded machine made it
    fall behind (:data:`SPEEDS`)."""
    behind: list[float] = []
    for attempt, speed in enumerate(SPEEDS):
        directory = workdir / f"attempt{attempt}"
        directory.mkdir()
        kill = _kill_at(directory, scene, seed, codec, speed)
        if kill is not None:
            return kill
        behind.append(speed)
    raise AssertionError(f"fell behind at every speed {behind} (host overloaded)")


def _kill_at(workdir: Path, scene: Path, seed: int, codec: str, speed: float) -> Kill | None:
    """One daemon at ``speed``, killed; None when it fell behind before or at the kill."""
    rng = random.Random(seed)
    root = workdir / "sessions"
    # on wall time: what a kill loses is measured against the wall instant of the kill
    cfg = write_config(
        workdir / "config.yaml",
        scene,
        root,
        speed=speed,
        run={"max_lag_s": MAX_LAG_S, "clock": "wall"},
    )
    proc = subprocess.Popen(
        [PYTHON, "-m", "stipi_daemon", "--config", str(cfg), "--quiet"],
        cwd=REPO_ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60.0
        directory = None
        while directory is None:
            if proc.poll() is not None and _fell_behind(root):
                return None
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < deadline, "the daemon never committed a frame"
            time.sleep(0.02)
            directory = _first_frame_committed(root)
        delay_s = rng.uniform(0.0, 2.5)
        time.sleep(delay_s)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)
        if proc.stderr:
            proc.stderr.close()
    if _fell_behind(root):
        return None
    assert proc.returncode == -signal.SIGKILL, "the daemon ended before it was killed"
    return _check_session(directory, delay_s, t_kill, codec, speed)


def _contiguous(index: np.ndarray, gaps: np.ndarray) -> None:
    """Stored indices and recorded gaps tile one range exactly (no hole, no overlap)."""
    covered = np.zeros(int(index.max()) + 1, dtype=np.int64)
    np.add.at(covered, index.astype(np.int64), 1)
    for start, count in zip(gaps["start_index"], gaps["count"], strict=True):
        covered[int(start) : int(start) + int(count)] += 1
    first = min([int(index.min()), *(int(g) for g in gaps["start_index"])])
    assert np.all(covered[first:] == 1), np.flatnonzero(covered[first:] != 1)[:10] + first


def _check_video(directory: Path, codec: str, speed: float) -> tuple[float, int]:
    """The killed session's video against its rows (module docstring); returns how far it
    lags the newest stored frame row [s of wall time] and the frames FFmpeg decodes."""
    video = stored_video(directory)
    assert video.codec == codec, (video.codec, video.error)
    check_rows_in_video(video, newest_may_be_missing=True)
    lag_s = (video.newest_frame_capture_s - video.plays_to_s) / speed
    bound_s = video_lag_bound_s(speed)
    assert lag_s <= bound_s, (lag_s, video.decoded, len(video.row_index), video.error)
    return lag_s, video.decoded


def _check_session(
    directory: Path, delay_s: float, t_kill: float, codec: str, speed: float
) -> Kill:
    with SessionReader(directory) as r:
        assert r.integrity_check().ok, r.integrity_check().problems
        assert r.status is SessionState.INTERRUPTED
        clock = next(e.detail for e in r.events() if e.kind == "session_clock")
        t_kill_s = (t_kill - clock["monotonic_origin_s"]) * clock["speed"]
        frames, force, gaps = r.frames(), r.force_samples(), r.gaps()
    # No hole that is not a recorded gap: frame seq and sample indices are contiguous.
    _contiguous(frames["seq"], gaps[gaps["stream"] == "frames"])
    if len(force):
        _contiguous(force["sample_index"], gaps[gaps["stream"] == "force"])
        force_lost_s = (t_kill_s - float(force["t_host_s"].max())) / speed
    else:
        force_lost_s = 0.0
    # What the daemon had handed to storage: at most one commit interval is missing.
    stored_lost_s = (t_kill_s - float(frames["t_host_s"].max())) / speed
    assert stored_lost_s <= COMMIT_INTERVAL_S + LOSS_SLACK_S, stored_lost_s
    # The daemon handled every stored frame within its lag bound of the capture ...
    lag_s = np.asarray(frames["t_host_s"]) - np.asarray(frames["t_capture_host_s"])
    assert float(lag_s.max()) <= MAX_LAG_S, float(lag_s.max())
    # ... so what the simulated devices had produced is the same plus that bound.
    # (capture-to-storage latency on top of the storage promise [s of wall time])
    frames_lost_s = (t_kill_s - float(frames["t_capture_host_s"].max())) / speed
    bound_s = COMMIT_INTERVAL_S + LOSS_SLACK_S + MAX_LAG_S / speed
    assert frames_lost_s <= bound_s, frames_lost_s
    assert force_lost_s <= bound_s + BATCH_S / speed, force_lost_s
    video_lag_s, video_frames = _check_video(directory, codec, speed)
    return Kill(
        directory,
        speed,
        delay_s,
        stored_lost_s,
        frames_lost_s,
        force_lost_s,
        video_lag_s,
        video_frames,
    )


def _run_kills(tmp_path: Path, n: int, workers: int, name: str, pixel_format: str = "bgr8") -> None:
    scene = fast_scene(tmp_path, pixel_format=pixel_format)
    codec = "mjpeg" if pixel_format == "mjpg" else "ffv1"
    dirs = [tmp_path / f"run{i:03d}" for i in range(n)]
    for d in dirs:
        d.mkdir()
    t0 = time.monotonic()
    with ThreadPoolExecutor(workers) as pool:
        kills = list(pool.map(lambda i: _kill_one(dirs[i], scene, 1000 + i, codec), range(n)))
    wall_s = time.monotonic() - t0
    assert len({k.directory for k in kills}) == n

    # `sessions list` shows every killed session as interrupted.
    for k in kills[:: max(1, n // 5)]:
        out = subprocess.run(
            [PYTHON, "-m", "stipi_daemon", "sessions", "list", "--root", str(k.directory.parent)],
            capture_output=True,
            text=True,
            check=True,
            cwd=REPO_ROOT,
        ).stdout
        (line,) = [x for x in out.splitlines() if k.directory.name in x]
        assert "interrupted" in line
    # `analyze` works on what was kept: results, or one line saying why there are none.
    for k in kills:
        out_json = k.directory.parent.parent / "analysis.json"  # in the attempt's directory
        code = main(["analyze", str(k.directory), "--out", str(out_json), "--quiet"])
        assert code in (0, 1)
        assert out_json.exists()

    stored_lost = np.array([k.stored_lost_s for k in kills])
    frames_lost = np.array([k.frames_lost_s for k in kills])
    force_lost = np.array([k.force_lost_s for k in kills])
    video_lag = np.array([k.video_lag_s for k in kills])
    report(
        name,
        kills=n,
        commit_interval_s=COMMIT_INTERVAL_S,
        stored_lost_max_s=stored_lost.max(),
        stored_lost_mean_s=stored_lost.mean(),
        frames_lost_max_s=frames_lost.max(),
        frames_lost_mean_s=frames_lost.mean(),
        force_lost_max_s=force_lost.max(),
        force_lost_mean_s=force_lost.mean(),
        video_codec=codec,
        video_lag_max_s=video_lag.max(),
        video_lag_mean_s=video_lag.mean(),
        video_frames_min=min(k.video_frames for k in kills),
        kill_delay_range_s=[min(k.delay_s for k in kills), max(k.delay_s for k in kills)],
        speeds=sorted({k.speed for k in kills}, reverse=True),
        wall_s=wall_s,
        load_avg=os.getloadavg()[0],
    )


@pytest.mark.timeout(900)  # a loaded machine makes some run again, slower
def test_kill_9_twenty_times(tmp_path: Path) -> None:
    _run_kills(tmp_path, 20, workers=3, name="kill_9_x20")


@pytest.mark.timeout(900)
def test_kill_9_mjpg_passthrough(tmp_path: Path) -> None:
    """An MJPG scene: the JPEGs stored as they came (muxed before the frame's row)."""
    _run_kills(tmp_path, 6, workers=3, name="kill_9_mjpg_x6", pixel_format="mjpg")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_kill_9_hundred_times(tmp_path: Path) -> None:
    _run_kills(tmp_path, 100, workers=3, name="kill_9_x100")
