"""The session video of a killed or stopped daemon, checked on its own terms.

The file is read with PyAV (FFmpeg's demuxer and decoders: its own frame count, its own
presentation times), the rows with SQLite, and the two compared under the rules of
docs/storage.md ("Video": kill -9, disk full); nothing here uses the project's video
reader or integrity check.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from pathlib import Path

import av


@dataclass(frozen=True)
class StoredVideo:
    """What a session's ``video.mkv`` and its rows hold.

    Attributes
    ----------
    codec : str or None
        FFmpeg's codec name; None when FFmpeg cannot open the file.
    pts_ms : list of int
        Presentation times of the frames FFmpeg decodes, in order, up to the first frame it
        cannot decode [ms].
    error : str or None
        Why decoding stopped before the end of the file (None: it reached the end).
    t0_s : float
        Session time of pts 0: the first stored frame's capture time (``video_started``) [s].
    row_pts_ms : list of int
        ``pts_ms`` of the ``video_frames`` rows, by ``frame_index`` [ms].
    row_index : list of int
        Their ``frame_index``, in order.
    newest_frame_capture_s : float
        Capture time of the newest ``frames`` row [s of session time].
    """

    codec: str | None
    pts_ms: list[int]
    error: str | None
    t0_s: float
    row_pts_ms: list[int]
    row_index: list[int]
    newest_frame_capture_s: float

    @property
    def decoded(self) -> int:
        """Frames FFmpeg decodes [-]."""
        return len(self.pts_ms)

    @property
    def plays_to_s(self) -> float:
        """Capture time of the newest frame that plays [s of session time] (the first
        frame's when none plays: a recording cut before its first cluster)."""
        return self.t0_s + (self.pts_ms[-1] / 1000.0 if self.pts_ms else 0.0)


def decode(path: Path) -> tuple[str | None, list[int], str | None]:
    """Codec, the pts [ms] of every frame FFmpeg decodes from ``path`` (until the first it
    cannot) and why it stopped early (None: the end of the file)."""
    try:
        container = av.open(str(path))
    except (OSError, ValueError) as exc:  # av.FFmpegError: not a file FFmpeg opens
        return None, [], f"does not open: {exc}"
    pts: list[int] = []
    with container:
        stream = container.streams.video[0]
        codec = stream.codec_context.name
        try:
            for frame in container.decode(stream):
                assert frame.pts is not None, f"{path}: a frame without pts"
                pts.append(int(frame.pts))
        except (OSError, ValueError) as exc:  # a frame cut by the kill or the full disk
            return codec, pts, str(exc)
    return codec, pts, None


def stored_video(directory: Path) -> StoredVideo:
    """Decode ``directory/video.mkv`` and read its rows (read-only SQLite)."""
    codec, pts, error = decode(directory / "video.mkv")
    con = sqlite3.connect(f"file:{directory / 'session.sqlite'}?mode=ro", uri=True)
    try:
        rows = con.execute(
            "SELECT frame_index, pts_ms FROM video_frames ORDER BY frame_index"
        ).fetchall()
        (newest,) = con.execute("SELECT max(t_capture_host_s) FROM frames").fetchone()
        started = con.execute(
            "SELECT detail_json FROM events WHERE kind = 'video_started' ORDER BY t_host_s"
        ).fetchall()
    finally:
        con.close()
    assert len(started) == 1, f"{directory}: {len(started)} video_started events"
    return StoredVideo(
        codec=codec,
        pts_ms=pts,
        error=error,
        t0_s=float(json.loads(started[0][0])["t0_s"]),
        row_pts_ms=[int(p) for _, p in rows],
        row_index=[int(i) for i, _ in rows],
        newest_frame_capture_s=float(newest),
    )


def check_rows_in_video(video: StoredVideo, *, newest_may_be_missing: bool) -> None:
    """Every ``video_frames`` row names a frame FFmpeg decodes, at the row's pts.

    ``newest_may_be_missing``: a killed recording's newest row may name the one frame the
    muxer still held (docs/storage.md, kill -9).
    """
    n = len(video.row_index)
    assert video.row_index == list(range(n)), "video_frames indices do not run 0, 1, 2, ..."
    playable = min(n, video.decoded)
    assert video.row_pts_ms[:playable] == video.pts_ms[:playable], "rows' pts differ"
    allowed = n - 1 if newest_may_be_missing else n
    assert video.decoded >= allowed, (
        f"video_frames rows name {n} frames, FFmpeg decodes {video.decoded} ({video.error})"
    )
