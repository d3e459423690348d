"""Damaged session videos: found by the integrity check, named by readback, never skipped.

Real PyAV-written videos (the recorder, MJPG passthrough and FFV1) are damaged on purpose
(bytes flipped inside a frame, the file cut short, a region zeroed, a header only); where the
frames are comes from PyAV's own demuxer (``Packet.pos``, ``Packet.size``), and what they
should decode to from the images written and PyAV's / OpenCV's own decoding.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
import pytest

from stipi_daemon.app.sessions_view import show_text
from stipi_daemon.cli import main
from stipi_daemon.errors import EXIT_DAMAGED
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.video import UNINDEXED_FRAMES_MAX, VideoRecorder
from stipi_daemon.storage.video_readback import (
    VideoDamageError,
    check_video,
    count_video_frames,
    iter_video_frames,
    iter_video_images,
    read_video_image,
    read_video_images,
)

OPTS = StorageOptions(min_free_bytes=0, background_commit=False)


@dataclass
class Recording:
    """A session written by the recorder: its directory and the images the daemon counted."""

    directory: Path
    images: list[np.ndarray]

    @property
    def video(self) -> Path:
        return self.directory / "video.mkv"


def _pictures(n: int, shape: tuple[int, int] = (48, 64)) -> list[np.ndarray]:
    """``n`` different frames (a blurred noise field moved 3 px per frame)."""
    rng = np.random.default_rng(5)
    base = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (9, 9), 3)
    return [np.roll(base, 3 * k, axis=1) for k in range(n)]


def _record(
    root: Path,
    codec: str,
    n: int,
    *,
    finish: str | None = "complete",
    summary: dict[str, Any] | None = None,
    packets: list[bytes] | None = None,
) -> Recording:
    """``n`` frames stored as the daemon stores them (the ``frames`` row, then the video),
    60 fps; ``finish``: the final state (None: left unfinished, read as interrupted)."""
    images = _pictures(n)
    if codec == "mjpeg" and packets is None:
        packets = [cv2.imencode(".jpg", im)[1].tobytes() for im in images]
        images = [cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_GRAYSCALE) for p in packets]
    w = SessionWriter.create(root, {}, {}, session_id="s", video=True, options=OPTS)
    assert w.video_path is not None
    rec = VideoRecorder(w.video_path, w, "passthrough" if codec == "mjpeg" else "lossless")
    for k, image in enumerate(images):
        w.add_frames([(k, k / 60, k / 60, 0, "")])
        assert rec.record(k, k / 60, image, None if packets is None else packets[k], wait=True)
    rec.close()
    if finish is not None:
        w.finish(finish, summary)
    w.close()
    return Recording(root / "s", images)


def _packets(path: Path) -> list[tuple[int, int]]:
    """``(pos, size)`` of every frame, as PyAV's demuxer finds them."""
    with av.open(str(path)) as container:
        return [(int(p.pos), int(p.size)) for p in container.demux(video=0) if p.size]


def _flip(path: Path, offset: int, n: int) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        data = bytes(b ^ 0xFF for b in f.read(n))
        f.seek(offset)
        f.write(data)


def _problems(directory: Path, *, decode: bool = False) -> tuple[str, ...]:
    with SessionReader(directory) as r:
        return r.integrity_check(decode=decode).problems


@pytest.mark.parametrize("codec", ["mjpeg", "ffv1"])
def test_a_frame_damaged_mid_file_is_found_and_named(tmp_path: Path, codec: str) -> None:
    """Bytes flipped inside frame 12: PyAV still demuxes every packet and (FFV1) decodes
    every frame without an error, frame 12's picture wrong; the cheap check finds it (its
    cluster's CRC-32), readback names it and never skips it."""
    rec = _record(tmp_path, codec, 30)
    packets = _packets(rec.video)
    pos, size = packets[12]
    _flip(rec.video, pos + size // 2, 8)
    assert len(_packets(rec.video)) == 30  # the count alone cannot see it
    assert count_video_frames(rec.video) == 30
    if codec == "ffv1":
        with av.open(str(rec.video)) as container:  # FFmpeg decodes on, no error raised
            decoded = [f.to_ndarray(format="gray") for f in container.decode(video=0)]
        assert len(decoded) == 30 and not np.array_equal(decoded[12], rec.images[12])
        assert all(np.array_equal(a, b) for a, b in zip(decoded[:12], rec.images, strict=False))
    problems = _problems(rec.directory)
    assert len(problems) == 1
    assert problems[0].startswith(str(rec.video))
    assert f"frame 12 (seq 12, byte {pos})" in problems[0] and "CRC-32" in problems[0]
    with pytest.raises(VideoDamageError) as raised:
        images = []
        for image in iter_video_images(rec.video):
            images.append(image)
    assert (raised.value.frame_index, raised.value.pos_bytes) == (12, pos)
    assert "frame 12" in str(raised.value) and str(pos) in str(raised.value)
    assert all(np.array_equal(a, b) for a, b in zip(images, rec.images[:12], strict=True))
    frames = list(iter_video_frames(rec.video))  # goes on past it: every frame, in order
    assert [f.frame_index for f in frames] == list(range(30))
    assert [f.pos_bytes for f in frames] == [p for p, _ in packets]
    assert [f.frame_index for f in frames if f.damage is not None] == [12]
    assert frames[12].image is None
    for f in frames[:12] + frames[13:]:
        assert f.image is not None and np.array_equal(f.image, rec.images[f.frame_index])
    with pytest.raises(VideoDamageError, match="frame 12"):
        read_video_image(rec.video, 12)
    assert np.array_equal(read_video_image(rec.video, 13), rec.images[13])
    # several at once, in one pass (the decoder reset after each): as read one by one
    got = read_video_images(rec.video, [29, 12, 0, 30, 13, 29])
    kinds = ["ndarray", "VideoDamageError", "ndarray", "SessionError", "ndarray", "ndarray"]
    assert [type(g).__name__ for g in got] == kinds
    for g, k in zip(got, [29, 12, 0, 30, 13, 29], strict=True):
        if isinstance(g, np.ndarray):
            assert np.array_equal(g, rec.images[k]), k
    assert "frame 12" in str(got[1]) and "holds no frame 30" in str(got[3])
    text, status = show_text(rec.directory)
    assert status == EXIT_DAMAGED and "integrity  FAILED: " in text and "frame 12" in text


def test_a_frame_that_only_decoding_finds_is_found_with_decode(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A passthrough packet that is no JPEG (what a camera could hand over) is stored
    whole: its bytes pass the cheap check; decoding every frame (``decode=True``) finds it,
    as OpenCV's own decoder cannot read it."""
    pictures = _pictures(6)
    packets = [cv2.imencode(".jpg", im)[1].tobytes() for im in pictures]
    packets[3] = b"\xff\xd8 not a JPEG \xff\xd9"
    assert cv2.imdecode(np.frombuffer(packets[3], np.uint8), cv2.IMREAD_GRAYSCALE) is None
    rec = _record(tmp_path, "mjpeg", 6, packets=packets)
    assert _problems(rec.directory) == ()
    (problem,) = _problems(rec.directory, decode=True)
    assert "frame 3 (seq 3, byte" in problem and "does not decode" in problem
    with pytest.raises(VideoDamageError, match="frame 3"):
        list(iter_video_images(rec.video))
    checked = check_video(rec.video, decode=True)
    assert checked.decoded and [f.frame_index for f in checked.damaged] == [3]
    # ``sessions show`` runs the cheap check; ``--decode`` decodes every frame and says so.
    assert main(["sessions", "show", str(rec.directory)]) == 0
    (line,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("integrity")]
    assert line.split(None, 1)[1] == "ok"
    assert main(["sessions", "show", str(rec.directory), "--decode"]) == EXIT_DAMAGED
    (line,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("integrity")]
    assert "FAILED: " in line and "frame 3 (seq 3, byte" in line and "does not decode" in line
    assert line.endswith("(every video frame decoded)")
    good = _record(tmp_path / "good", "mjpeg", 6)
    assert main(["sessions", "show", str(good.directory), "--decode"]) == 0
    out = capsys.readouterr().out
    assert "integrity  ok (every video frame decoded)" in out
    good.video.unlink()  # nothing decoded: the line does not claim it
    assert main(["sessions", "show", str(good.directory), "--decode"]) == EXIT_DAMAGED
    (line,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("integrity")]
    assert "FAILED: " in line and "missing" in line and "decoded" not in line


@pytest.mark.parametrize("codec", ["mjpeg", "ffv1"])
def test_a_cut_off_tail_is_allowed_only_where_the_recording_did_not_end_cleanly(
    tmp_path: Path, codec: str
) -> None:
    """The file cut inside its last frame (as a kill mid-write leaves it): PyAV's demuxer
    reads the frames before it; readback gives them, no damage. An unfinished session
    (interrupted) passes; a complete one does not (its file ended whole)."""
    for finish in (None, "complete"):
        rec = _record(tmp_path / str(finish), codec, 20, finish=finish)
        pos, size = _packets(rec.video)[-1]
        with open(rec.video, "r+b") as f:
            f.truncate(pos + size // 2)
        assert len(_packets(rec.video)) == 19 == count_video_frames(rec.video)
        frames = list(iter_video_frames(rec.video))
        assert len(frames) == 19 and all(f.damage is None for f in frames)
        assert len(list(iter_video_images(rec.video))) == 19
        problems = _problems(rec.directory)
        if finish is None:
            assert problems == ()
        else:
            assert len(problems) == 2
            assert "ends inside an element" in problems[0]
            assert "video holds 19 frames, video_frames has 20 rows" in problems[1]


def test_a_broken_structure_ends_readback_with_an_error(tmp_path: Path) -> None:
    """4 kB zeroed from inside frame 8 on: the Matroska structure breaks off there; the
    frames before it are read, then readback raises naming the byte (never ends quietly)."""
    rec = _record(tmp_path, "mjpeg", 30)
    packets = _packets(rec.video)
    pos, size = packets[8]
    with open(rec.video, "r+b") as f:
        f.seek(pos + size - 16)
        f.write(bytes(4096))
    frames: list[Any] = []
    with pytest.raises(VideoDamageError, match="breaks off at byte") as raised:
        for frame in iter_video_frames(rec.video):
            frames.append(frame)
    assert raised.value.pos_bytes is not None and raised.value.pos_bytes > pos
    assert [f.frame_index for f in frames if f.damage is None] == list(range(8))
    assert frames[8].damage is not None  # its cluster's CRC-32 fails
    assert count_video_frames(rec.video) == check_video(rec.video).frames == 9
    problems = _problems(rec.directory)
    assert any("breaks off at byte" in p for p in problems)
    assert all(p.startswith(str(rec.video)) for p in problems)


_KILLED_AFTER_ONE_FRAME = textwrap.dedent(
    """
    import os, signal, sys, time
    import cv2, numpy as np
    from stipi_daemon.storage import SessionWriter, StorageOptions
    from stipi_daemon.storage.video import VideoRecorder
    w = SessionWriter.create(sys.argv[1], {}, {}, session_id="k", video=True,
                             options=StorageOptions(min_free_bytes=0))
    rec = VideoRecorder(w.video_path, w, "passthrough")
    img = np.random.default_rng(0).integers(0, 256, (120, 160), dtype=np.uint8)
    pk = cv2.imencode(".jpg", img)[1].tobytes()
    w.add_frames([(0, 0.0, 0.0, 1, "")])
    assert rec.record(0, 0.0, img, pk)
    w.commit()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_a_recording_killed_after_its_first_frame_leaves_a_sound_session(
    tmp_path: Path,
) -> None:
    """Killed once the first frame is muxed, before the second: the file holds Matroska's
    header only (the muxer keeps the frame until the next), FFmpeg cannot open it, and there
    is no video row: within the kill rule, so the check passes and ``sessions show`` works.
    The same file with rows spanning more than a commit interval is one problem line."""
    proc = subprocess.run([sys.executable, "-c", _KILLED_AFTER_ONE_FRAME, str(tmp_path)])
    assert proc.returncode == -signal.SIGKILL
    session = tmp_path / "k"
    video = session / "video.mkv"
    assert 0 < video.stat().st_size < 1024
    with pytest.raises(av.FFmpegError):
        av.open(str(video)).close()
    with SessionReader(session) as r:
        assert r.status.value == "interrupted" and r.video_frames().size == 0
        assert r.integrity_check().ok, r.integrity_check().problems
    text, status = show_text(session)
    assert status == 0 and "integrity  ok" in text and "holds no frame" in text
    assert (
        check_video(video).frames == 0 == count_video_frames(video)
        and list(iter_video_frames(video)) == []
    )
    with sqlite3.connect(session / "session.sqlite") as conn:  # rows whose frames are lost
        conn.executemany(
            "INSERT INTO frames (seq, t_capture_host_s, t_host_s, s_k, flags) VALUES (?,?,?,0,'')",
            [(k, k / 60, k / 60) for k in range(1, 20)],
        )
        conn.executemany(
            "INSERT INTO video_frames (seq, frame_index, pts_ms, t_capture_host_s) "
            "VALUES (?,?,?,?)",
            [(k, k, round(k * 1000 / 60), k / 60) for k in range(20)],
        )
    (problem,) = _problems(session)
    assert problem.startswith(f"{video}: video holds 0 frames, video_frames has 20 rows")


N_ROWS_TEST = UNINDEXED_FRAMES_MAX + 4


@pytest.mark.parametrize(
    ("finish", "summary", "dropped", "ok"),
    [
        ("complete", None, 2, False),
        ("aborted", None, 2, False),
        ("fault", {"status": "fault", "end_reason": "fell behind"}, 2, False),
        ("fault", {"status": "fault", "storage_error": "disk full"}, 2, True),
        ("fault", {"run": {"video": {"error": "video.mkv: ExternalError"}}}, 2, True),
        (None, None, 2, True),
        (None, None, UNINDEXED_FRAMES_MAX, True),
        (None, None, UNINDEXED_FRAMES_MAX + 1, False),
    ],
)
def test_frames_without_rows_by_how_the_recording_ended(
    tmp_path: Path, finish: str | None, summary: dict[str, Any] | None, dropped: int, ok: bool
) -> None:
    """A recording that ended cleanly (complete, aborted, fault without a storage or video
    failure: the recorder hands over every row) holds one frame per row; one that did not
    (killed, or stopped by a failure) may hold up to UNINDEXED_FRAMES_MAX frames more."""
    rec = _record(tmp_path, "mjpeg", N_ROWS_TEST, finish=finish, summary=summary)
    assert len(_packets(rec.video)) == N_ROWS_TEST
    with sqlite3.connect(rec.directory / "session.sqlite") as conn:
        conn.execute("DELETE FROM video_frames WHERE frame_index >= ?", (N_ROWS_TEST - dropped,))
    problems = _problems(rec.directory)
    if ok:
        assert problems == ()
    else:
        (problem,) = problems
        expected = (
            f"video holds {N_ROWS_TEST} frames, video_frames has {N_ROWS_TEST - dropped} rows"
        )
        assert problem.startswith(f"{rec.video}: {expected}")


def test_a_recording_that_finishes_while_it_is_checked_is_judged_as_not_ended(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``sessions show`` of a live session: its rows are read while it records, its state
    may be read after it finished. The rows then lag the video by the rows not yet handed
    over, which a recording that has not ended may do; judged by the later state, the
    check said FAILED "(the recording ended cleanly)" of a sound session."""
    rec = _record(tmp_path, "ffv1", N_ROWS_TEST, finish=None)
    db = rec.directory / "session.sqlite"
    with sqlite3.connect(db) as conn:  # the last rows not yet handed over
        conn.execute("DELETE FROM video_frames WHERE frame_index >= ?", (N_ROWS_TEST - 2,))
    iter_rows = SessionReader.iter_rows

    def finishing_meanwhile(self: SessionReader, table: Any, *args: Any, **kwargs: Any) -> Any:
        rows = list(iter_rows(self, table, *args, **kwargs))
        with sqlite3.connect(db) as conn:  # the writer finishes as the rows were read
            conn.execute("UPDATE meta SET value = 'complete' WHERE key = 'state'")
        return iter(rows)

    monkeypatch.setattr(SessionReader, "iter_rows", finishing_meanwhile)
    assert _problems(rec.directory) == ()


@pytest.mark.parametrize(
    ("sql", "message"),
    [
        ("UPDATE video_frames SET seq = 99 WHERE frame_index = 3", "seq 99 has no frames row"),
        ("UPDATE video_frames SET seq = 2 WHERE frame_index = 3", "seq 2 appears 2 times"),
        (
            "INSERT INTO frames (seq, t_capture_host_s, t_host_s, s_k, flags) "
            "SELECT seq, t_capture_host_s, t_host_s, s_k, flags FROM frames WHERE seq = 4",
            "seq 4 has 2 frames rows",
        ),
        (
            "UPDATE video_frames SET t_capture_host_s = t_capture_host_s + 0.5 WHERE seq = 5",
            "seq 5 has another capture time than its frames row (+0.5 s)",
        ),
        (
            "UPDATE video_frames SET pts_ms = pts_ms + 3 WHERE frame_index = 6",
            "frame 6 (seq 6): ",
        ),
    ],
)
def test_video_rows_agree_with_the_frames_rows_and_the_file(
    tmp_path: Path, sql: str, message: str
) -> None:
    rec = _record(tmp_path, "ffv1", 10)
    assert _problems(rec.directory) == ()
    with sqlite3.connect(rec.directory / "session.sqlite") as conn:
        conn.execute(sql)
    problems = _problems(rec.directory)
    assert any(message in p for p in problems), problems


def test_an_unreadable_video_is_named_not_the_database(tmp_path: Path) -> None:
    rec = _record(tmp_path, "mjpeg", 5)
    rec.video.write_bytes(b"this is no Matroska file " * 40)
    with pytest.raises(av.FFmpegError):
        av.open(str(rec.video)).close()
    problems = _problems(rec.directory)
    assert problems and all(p.startswith(f"{rec.video}: ") for p in problems), problems
    assert not any("session.sqlite" in p for p in problems)
    with pytest.raises(VideoDamageError, match="byte 0"):
        list(iter_video_images(rec.video))


@pytest.mark.parametrize("clusters", ["one frame each", "4 kB"])
def test_a_killed_recording_passes_its_check_at_every_cut(
    tmp_path: Path, clusters: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever byte the file is cut at (every 97th across the last three frames), the
    check passes an unfinished session and readback gives the frames PyAV's demuxer reads,
    all sound: in the recorder's files (a cluster per frame) and in files written with
    FFmpeg's default clusters (up to 4 kB, several small frames each; before
    ``cluster_size_limit``), whose cut-off cluster still holds whole frames."""
    from stipi_daemon.storage import video

    if clusters == "4 kB":
        monkeypatch.setattr(video, "MUXER_OPTIONS", {"flush_packets": "1"})
    rec = _record(tmp_path, "mjpeg", 12, finish=None)
    whole = rec.video.read_bytes()
    n_clusters = whole.count(bytes.fromhex("1f43b675"))  # Matroska's Cluster ID
    assert n_clusters == 12 if clusters == "one frame each" else 1 < n_clusters < 6
    packets = _packets(rec.video)
    start, end = packets[-3][0] - 24, packets[-1][0] + packets[-1][1]
    for cut in range(start, end, 97):
        rec.video.write_bytes(whole[:cut])
        n = len(_packets(rec.video))
        checked = check_video(rec.video)
        assert checked.ok and checked.frames == n == count_video_frames(rec.video), (cut, checked)
        assert sum(1 for f in iter_video_frames(rec.video, decode=False) if f.damage is None) == n
        assert _problems(rec.directory) == (), cut


def test_sessions_show_names_a_damaged_video_once(tmp_path: Path) -> None:
    rec = _record(tmp_path, "ffv1", 12)
    pos, size = _packets(rec.video)[5]
    _flip(rec.video, pos + size // 3, 4)
    text, status = show_text(rec.directory)
    assert status == EXIT_DAMAGED
    (line,) = [ln for ln in text.splitlines() if ln.startswith("integrity")]
    assert f"frame 5 (seq 5, byte {pos})" in line and "session.sqlite" not in line
    assert os.path.basename(rec.video) in line
