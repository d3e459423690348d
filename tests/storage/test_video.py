"""The session video: passthrough and lossless recording, rows, reading back, integrity."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.video import (
    ENCODER_NICE,
    ENCODER_QUEUE_FRAMES,
    ENCODER_WORKERS,
    VideoRecorder,
)
from stipi_daemon.storage.video_readback import (
    iter_video_images,
    probe_video,
    read_video_image,
    set_decode_threads,
)

OPTS = StorageOptions(min_free_bytes=0, background_commit=False)


def _images(n: int, shape: tuple[int, ...], seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (9, 9), 3)
    return [np.roll(base, 3 * k, axis=1) for k in range(n)]


def _writer(tmp_path: Path) -> SessionWriter:
    return SessionWriter.create(tmp_path, {}, {}, session_id="s", video=True, options=OPTS)


def _store(
    w: SessionWriter,
    rec: VideoRecorder,
    seq: int,
    t_s: float,
    image: np.ndarray,
    packet: bytes | None,
    *,
    wait: bool = False,
) -> bool:
    """A frame stored as the daemon stores it: its ``frames`` row, then the video
    (``app.frame_measurer``); the integrity check ties every video row to its frame row."""
    w.add_frames([(seq, t_s, t_s, 0, "")])
    return rec.record(seq, t_s, image, packet, wait=wait)


def test_passthrough_stores_the_jpeg_packets_unchanged(tmp_path: Path) -> None:
    images = _images(12, (48, 64))
    quality = [cv2.IMWRITE_JPEG_QUALITY, 80]
    packets = [cv2.imencode(".jpg", im, quality)[1].tobytes() for im in images]
    with _writer(tmp_path) as w:
        assert w.video_path is not None and w.video_path.name == "video.mkv"
        rec = VideoRecorder(w.video_path, w, "passthrough")
        for k, pk in enumerate(packets):
            gray = cv2.imdecode(np.frombuffer(pk, np.uint8), cv2.IMREAD_GRAYSCALE)
            assert _store(w, rec, 10 + k, 5.0 + k / 30, gray, pk)
        rec.close()
        w.finish("complete")
    import av

    with av.open(str(tmp_path / "s" / "video.mkv")) as c:
        stored = [bytes(p) for p in c.demux(video=0) if p.size]
    assert stored == packets
    info = probe_video(tmp_path / "s" / "video.mkv")
    assert (info.codec, info.frames, info.width, info.height) == ("mjpeg", 12, 64, 48)
    decoded = list(iter_video_images(info.path))
    for pk, img in zip(packets, decoded, strict=True):
        assert np.array_equal(img, cv2.imdecode(np.frombuffer(pk, np.uint8), cv2.IMREAD_GRAYSCALE))
    with SessionReader(tmp_path / "s") as r:
        vf = r.video_frames()
        assert vf["seq"].tolist() == list(range(10, 22))
        assert vf["frame_index"].tolist() == list(range(12))
        assert np.all(np.diff(vf["pts_ms"]) > 0)
        assert r.integrity_check().ok
        assert any(e.kind == "video_started" for e in r.events())


# Widths whose rows FFmpeg pads (50 and 61 px: gray rows of 64, bgr0 rows of 256 bytes),
# decoded with FFmpeg's threads and with one (a study's worker).
@pytest.mark.parametrize("threads", [0, 1])
@pytest.mark.parametrize("shape", [(40, 50), (40, 50, 3), (33, 61), (33, 61, 3)])
def test_lossless_reproduces_every_pixel(
    tmp_path: Path, shape: tuple[int, ...], threads: int
) -> None:
    set_decode_threads(threads)
    try:
        _lossless_round_trip(tmp_path, shape)
    finally:
        set_decode_threads(0)
    with pytest.raises(ValueError, match="decode threads"):
        set_decode_threads(-1)


def _lossless_round_trip(tmp_path: Path, shape: tuple[int, ...]) -> None:
    images = _images(6, shape)
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "passthrough")  # no packets: lossless
        for k, im in enumerate(images):
            assert rec.record(k, k / 60, im, None)
        rec.close()
        w.finish("complete")
    path = tmp_path / "s" / "video.mkv"
    assert probe_video(path).codec == "ffv1"
    back = list(iter_video_images(path))
    assert len(back) == len(images)
    for a, b in zip(images, back, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(read_video_image(path, 4), images[4])
    with pytest.raises(SessionError):
        read_video_image(path, 6)
    import av

    with av.open(str(path)) as c, SessionReader(tmp_path / "s") as r:
        # the file's timestamps are the rows' pts [ms], not rounded to another time base
        assert [f.pts for f in c.decode(video=0)] == r.video_frames()["pts_ms"].tolist()


@pytest.mark.parametrize("mode", ["passthrough", "lossless"])
@pytest.mark.parametrize("fps", [60.0, 29.97])
def test_the_camera_frame_rate_is_declared(tmp_path: Path, mode: str, fps: float) -> None:
    # without it OpenCV reports FFmpeg's default of 24 fps for a 60 fps session video
    images = _images(ENCODER_QUEUE_FRAMES - 2, (48, 64))  # never more than the encoder queue
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, mode, frame_rate_hz=fps)  # type: ignore[arg-type]
        for k, im in enumerate(images):
            pk = cv2.imencode(".jpg", im)[1].tobytes()
            assert rec.record(k, k / fps, im, pk)
        rec.close()
        w.finish("complete")
    cap = cv2.VideoCapture(str(tmp_path / "s" / "video.mkv"), cv2.CAP_FFMPEG)
    try:
        assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(fps, rel=1e-3)
    finally:
        cap.release()


def test_lossless_crop_stores_the_rectangle(tmp_path: Path) -> None:
    images = _images(3, (40, 50))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless", crop=(5, 6, 25, 30))
        for k, im in enumerate(images):
            assert rec.record(k, k / 60, im, b"ignored")
        rec.close()
        w.finish("complete")
    info = probe_video(tmp_path / "s" / "video.mkv")
    assert (info.width, info.height, info.crop) == (20, 24, (5, 6, 25, 30))
    for a, b in zip(images, iter_video_images(info.path), strict=True):
        assert np.array_equal(a[6:30, 5:25], b)


def test_integrity_check_counts_video_frames(tmp_path: Path) -> None:
    images = _images(4, (16, 16))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless")
        for k, im in enumerate(images):
            rec.record(k, k / 60, im, None)
        rec.close()
        w.add_video_frames([(99, 4, 999, 9.0)])  # a row without its frame
        w.finish("complete")
    with SessionReader(tmp_path / "s") as r:
        report = r.integrity_check()
    assert not report.ok
    assert "video" in " ".join(report.problems)


def test_write_failure_stops_rows_too(tmp_path: Path) -> None:
    images = _images(3, (16, 16))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path / "nodir" / "v.mkv", w, "lossless")
        rec.record(0, 0.0, images[0], None)  # accepted; fails in the encoder thread
        rec.close()
        assert rec.failed is not None and rec.frames == 0
        with pytest.raises(SessionError, match="video"):
            w.add_frames([(0, 0.0, 0.0, 1, "")])
        assert not rec.record(1, 0.1, images[1], None)


@pytest.mark.parametrize("mode", ["passthrough", "lossless"])
@pytest.mark.parametrize("other", [(8, 16), (32, 16), (16, 16, 3)])
def test_a_frame_of_another_shape_stops_the_video_naming_both(
    tmp_path: Path, mode: str, other: tuple[int, ...]
) -> None:
    """A stream keeps its frame size, and FFmpeg encodes an FFV1 frame of another size at
    the stream's size without an error (and muxes a JPEG of any size): the recorder
    refuses it, the video stops with one line naming both shapes, the rows with it; the
    frames before stay whole."""
    images = _images(3, (16, 16))
    odd = _images(1, other)[0]
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, mode)  # type: ignore[arg-type]
        for k in range(2):
            pk = cv2.imencode(".jpg", images[k])[1].tobytes()
            assert _store(w, rec, k, k / 60, images[k], pk)
        assert not _store(w, rec, 2, 2 / 60, odd, cv2.imencode(".jpg", odd)[1].tobytes())
        assert rec.failed is not None
        assert f"frame 2 has shape {other}, the video's frames (16, 16)" in rec.failed
        assert "\n" not in rec.failed
        with pytest.raises(SessionError, match="frame 2 has shape"):
            w.commit()
        rec.close()
        assert rec.frames == 2
    info = probe_video(tmp_path / "s" / "video.mkv")
    assert info.frames == 2 and (info.width, info.height) == (16, 16)


_KILLED_WRITER = textwrap.dedent(
    """
    import sys, time
    import cv2, numpy as np
    from stipi_daemon.storage import SessionWriter, StorageOptions
    from stipi_daemon.storage.video import VideoRecorder
    w = SessionWriter.create(sys.argv[1], {}, {}, session_id="k", video=True,
                             options=StorageOptions(min_free_bytes=0))
    rec = VideoRecorder(w.video_path, w, sys.argv[2])
    rng = np.random.default_rng(0)
    shape = (120, 160) if sys.argv[3] == "large" else (24, 32)
    img = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (9, 9), 3)
    pk = cv2.imencode(".jpg", img)[1].tobytes()
    k = 0
    while True:
        accepted = rec.record(k, k / 60, img, pk)
        w.add_frames([(k, k / 60, k / 60, 1, "")])
        w.commit()
        print(k, int(accepted), rec.left_out, flush=True)  # what the recorder reported
        if k == 20:
            print("ready", flush=True)
        k += 1
        time.sleep(0.001)
    """
)


# Large frames (a 120x160 JPEG, 6 kB) and small ones (24x32, under 1 kB): FFmpeg's muxer
# holds a cluster in memory until it ends, by default once it exceeds 4 kB, which kept
# several small frames from the file (MUXER_OPTIONS: a cluster per frame).
@pytest.mark.parametrize("size", ["large", "small"])
@pytest.mark.parametrize("mode", ["passthrough", "lossless"])
def test_kill_9_leaves_a_playable_video_covering_the_rows(
    tmp_path: Path, mode: str, size: str
) -> None:
    """The documented promise, whatever CPU is left: every frame the recorder accepted
    (``record`` True) and whose ``video_frames`` row was committed plays; the accepted
    frames not playable yet lie within one commit interval of the newest accepted one (the
    FFV1 queue and the block the muxer holds); a frame left out (``record`` False, the
    lossless encoder lagging) is counted in ``left_out`` and has no row."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _KILLED_WRITER, str(tmp_path), mode, size],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    with proc.stdout:
        lines = []
        while (line := proc.stdout.readline().strip()) != "ready":
            assert line, "the writer ended before it was ready"
            lines.append(line)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        lines += [ln.strip() for ln in proc.stdout if ln.strip()]
    reported = [tuple(int(v) for v in ln.split()) for ln in lines]
    accepted = [k for k, ok, _ in reported if ok]
    left_out = [k for k, ok, _ in reported if not ok]
    # Every frame left out is counted, and only in lossless mode can one be.
    assert [n for _, _, n in reported] == [
        sum(1 for kk in left_out if kk <= k) for k, _, _ in reported
    ]
    assert mode == "lossless" or not left_out
    with SessionReader(tmp_path / "k") as r:
        frames = r.frames()
        video_rows = r.video_frames()
        assert r.status.value == "interrupted"
        report = r.integrity_check()
    assert frames.size > 20 and report.ok, report.problems
    assert not set(video_rows["seq"].tolist()) & set(left_out)
    assert set(video_rows["seq"].tolist()) <= set(accepted)
    import av

    path = tmp_path / "k" / "video.mkv"
    try:
        info = probe_video(path)
    except SessionError:  # FFmpeg opens a Matroska file once it holds its first cluster,
        info = None  # i.e. once a second frame is muxed: no row may depend on it then
        assert video_rows.size <= 1
        n_decoded, pts_ms = 0, []
    if info is not None:
        n_decoded = sum(1 for _ in iter_video_images(info.path))
        with av.open(str(info.path)) as c:
            pts_ms = [p.pts for p in c.demux(video=0) if p.size]
        assert len(pts_ms) >= n_decoded
        # Every committed row's frame plays (the row is added after the frame is muxed).
        assert n_decoded >= video_rows.size - 1
    # The accepted frames the video does not play yet: the block the muxer holds and one
    # cut off mid-write, plus in lossless mode the encoder queue and the frame in the encoder.
    unplayed = accepted[n_decoded:]
    lag = 2 + (ENCODER_QUEUE_FRAMES + 1 if mode == "lossless" else 0)
    assert len(unplayed) <= lag, (mode, n_decoded, unplayed)
    # At 60 fps that lag is within one commit interval (the documented bound in time).
    assert (lag - 1) / 60 <= OPTS.commit_interval_s
    # The rows that the video lacks are the left-out frames and the unplayed accepted ones.
    rows = set(frames["seq"].tolist())
    assert rows - set(accepted[:n_decoded]) <= set(left_out) | set(unplayed)


def test_schema_version_1_sessions_still_read(tmp_path: Path) -> None:
    import sqlite3

    with _writer(tmp_path) as w:
        w.add_frames([(0, 1.0, 1.0, 5, "")])
        w.finish("complete")
    db = tmp_path / "s" / "session.sqlite"
    with sqlite3.connect(db) as conn:  # as a stipi-daemon before video wrote it
        conn.execute("DROP TABLE video_frames")
        conn.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
        conn.execute("PRAGMA user_version = 1")
    with SessionReader(tmp_path / "s") as r:
        assert r.schema_version == 1
        assert r.count("video_frames") == 0
        assert len(r.video_frames()) == 0
        assert r.counts()["frames"] == 1
        assert r.integrity_check().ok


def test_report_reads_representative_frames_from_the_video(tmp_path: Path) -> None:
    from stipi_daemon.measurement.representative_frames import RepresentativeFrame
    from stipi_daemon.report.frames import read_representative_frames, write_representative_frames

    images = _images(5, (24, 32))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless")
        for k, im in enumerate(images):
            rec.record(100 + k, k / 60, im, None)
        rec.close()
        w.finish("complete")
    session = tmp_path / "s"
    kept = [RepresentativeFrame("pitting", 103, 3 / 60, 7, images[3])]
    write_representative_frames(session, kept)
    png = next((session / "frames").glob("*.png"))
    import cv2 as _cv2

    _cv2.imwrite(str(png), np.zeros_like(images[3]))  # the PNG differs: the video is read
    (frame,) = read_representative_frames(session)
    assert frame.seq == 103 and np.array_equal(frame.image, images[3])
    assert np.array_equal(read_video_image(session / "video.mkv", 3), images[3])


def test_video_frames_rows_reach_the_writer_in_batches_and_all_at_close(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``video_frames`` row waits until the oldest waiting one is ROW_BATCH_FRACTION of
    the commit interval old (not one more table in every frame's commit); close hands over
    the rest, so a finished session has one row per stored frame."""
    from stipi_daemon.storage import video as video_module

    now = [100.0]
    monkeypatch.setattr(video_module, "_monotonic", lambda: now[0])
    images = _images(9, (48, 64))
    packets = [cv2.imencode(".jpg", im)[1].tobytes() for im in images]
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "passthrough")
        batch_s = video_module.ROW_BATCH_FRACTION * OPTS.commit_interval_s

        def rows_after(k: int, dt_s: float) -> int:
            now[0] += dt_s
            assert _store(w, rec, k, k / 60, images[k], packets[k])
            w.commit()
            return w.stats.rows["video_frames"]

        assert [rows_after(k, 0.25 * batch_s) for k in range(4)] == [0, 0, 0, 0]
        assert rows_after(4, 0.25 * batch_s) == 5  # the oldest is batch_s old: all 5 go
        assert rows_after(5, 0.0) == 5
        assert rows_after(6, 0.99 * batch_s) == 5
        assert rows_after(7, 0.01 * batch_s) == 8
        assert rows_after(8, 0.0) == 8
        rec.close()
        w.commit()
        assert w.stats.rows["video_frames"] == 9
        w.finish("complete")
    with SessionReader(tmp_path / "s") as r:
        assert r.video_frames()["seq"].tolist() == list(range(9))
        assert r.integrity_check().ok


def _noise(n: int, shape: tuple[int, ...]) -> list[np.ndarray]:
    """Frames of pure noise: FFV1 takes milliseconds for each (far slower than a caller)."""
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(n)]


def test_a_caller_that_can_wait_loses_no_frame_to_a_slow_encoder(tmp_path: Path) -> None:
    """A source that waits for its consumer (a file, the simulator) waits for the encoder
    (``wait=True``): every frame is stored; one that cannot (a live camera) leaves the frames
    the encoder cannot take out of the video, counted, and never waits."""
    images = _noise(4 * ENCODER_QUEUE_FRAMES, (240, 320))
    for wait in (False, True):
        root = tmp_path / f"wait{wait}"
        with SessionWriter.create(root, {}, {}, session_id="s", video=True, options=OPTS) as w:
            assert w.video_path is not None
            rec = VideoRecorder(w.video_path, w, "lossless")
            stored = [_store(w, rec, k, k / 60, im, None, wait=wait) for k, im in enumerate(images)]
            rec.close()
            w.finish("complete")
        with SessionReader(root / "s") as r:
            seqs = r.video_frames()["seq"].tolist()
            assert r.integrity_check().ok
        assert seqs == [k for k, ok in enumerate(stored) if ok]
        if wait:
            assert all(stored) and rec.left_out == 0 and rec.frames == len(images)
        else:  # a burst far faster than the encoder: most frames are left out
            assert rec.left_out == stored.count(False) >= len(images) // 2


def _threads() -> set[int]:
    return {int(t) for t in os.listdir("/proc/self/task")}


@pytest.mark.skipif(
    not Path("/proc/self/task").is_dir() or (os.cpu_count() or 1) < 2,
    reason="counts threads in /proc on a machine where FFmpeg would start some",
)
def test_ffv1_encodes_in_the_recorders_threads_only(tmp_path: Path) -> None:
    """FFmpeg's own slice threads would cost CPU (3.5 against 1.9 ms per 420x420 frame) and
    run at the daemon's priority rather than the encoder threads': none is started, only the
    recorder's encoder threads (whole frames in parallel), each at the lower priority."""
    images = _noise(6, (420, 420))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless")
        before = _threads()
        for k, im in enumerate(images):
            assert rec.record(k, k / 60, im, None, wait=True)
        started = _threads() - before
        nice = {os.getpriority(os.PRIO_PROCESS, tid) for tid in started}
        rec.close()
        w.finish("complete")
    assert len(started) == ENCODER_WORKERS == 2  # the recorder's encoders, nothing of FFmpeg's
    assert nice == {min(19, os.getpriority(os.PRIO_PROCESS, 0) + ENCODER_NICE)}
    assert probe_video(tmp_path / "s" / "video.mkv").frames == len(images)


def test_a_repeated_read_only_frame_is_stored_with_the_bytes_encoding_would_give(
    tmp_path: Path,
) -> None:
    """A clean simulated scene hands the same read-only picture while S_k stays on one
    pixel count: it is encoded once, and each repeat stores that payload again. Encoding it
    again gives the same bytes (shown here by a writable frame, which is always encoded), so
    the file is what encoding every frame would have written."""
    a, b, c = _images(3, (40, 52))
    a.flags.writeable = False
    b.flags.writeable = False
    sequence = [a, a, a, b, b, c, c.copy()]  # c: writable, encoded each time
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless")
        for k, im in enumerate(sequence):
            assert _store(w, rec, k, k / 60, im, None, wait=True)
        rec.close()
        w.finish("complete")
    path = tmp_path / "s" / "video.mkv"
    back = list(iter_video_images(path))
    assert len(back) == len(sequence)
    assert all(np.array_equal(x, y) for x, y in zip(back, sequence, strict=True))
    import av

    with av.open(str(path)) as container:
        payloads = [bytes(p) for p in container.demux(video=0) if p.size]
    assert payloads[0] == payloads[1] == payloads[2] and payloads[3] == payloads[4]
    assert payloads[5] == payloads[6]  # encoded twice: the same bytes
    assert len(set(payloads)) == 3
    with SessionReader(tmp_path / "s") as r:
        assert r.video_frames()["seq"].tolist() == list(range(7))
        assert r.integrity_check().ok


def test_waiting_for_the_encoders_is_bounded_below_a_camera_stall(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Encoders that take no frame for longer than ENCODER_WAIT_MAX_S (starved of CPU) make
    a waiting caller leave the frame out, counted, rather than hold its camera long enough
    to read as stalled."""
    from stipi_daemon.cameras.stream import STALL_MIN_WALL_S
    from stipi_daemon.storage import video as video_module

    assert video_module.ENCODER_WAIT_MAX_S < STALL_MIN_WALL_S
    encode = video_module.encode_video_frame
    release = threading.Event()

    def starved(ctx: object, pts: int, image: np.ndarray) -> list[object]:
        release.wait(10.0)
        return encode(ctx, pts, image)

    monkeypatch.setattr(video_module, "encode_video_frame", starved)
    images = _images(3 * ENCODER_QUEUE_FRAMES, (24, 32))
    with _writer(tmp_path) as w:
        assert w.video_path is not None
        rec = VideoRecorder(w.video_path, w, "lossless")
        waits = []
        for k, im in enumerate(images):
            t0 = time.monotonic()
            rec.record(k, k / 60, im, None, wait=True)
            waits.append(time.monotonic() - t0)
        release.set()
        rec.close()
        w.finish("complete")
    assert rec.left_out > 0 and rec.frames + rec.left_out == len(images)
    # about ENCODER_WAIT_MAX_S each (a loaded machine adds its scheduling), never the 10 s
    assert 0.9 * video_module.ENCODER_WAIT_MAX_S < sorted(waits)[-rec.left_out] < 1.0
