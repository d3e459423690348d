"""The session video by default (issue 16; docs/storage.md, "Video").

``storage.video`` is ``passthrough`` by default: the simulator's clean (raw) frames are
recorded losslessly at any clock speed, as a raw camera's are (the simulator waits for
the encoders); ``video_roi_only`` cannot crop the JPEGs a passthrough stores, and says so:
a ``video_roi_only_ignored`` event and one warning line at start. The video is read back
with PyAV (FFmpeg's own decoding), not with the project's reader.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import av
import pytest

from stipi_daemon.app.config import load_config
from stipi_daemon.storage import SessionReader
from tests.daemon._support import short_session

SPEED = 0.0  # as fast as the daemon goes: every device is simulated


def _run(directory: Path, pixel_format: str, storage: dict[str, Any]) -> Path:
    """One short measurement of a 160x120 scene at :data:`SPEED`, ``storage`` added."""
    return short_session(directory, storage, pixel_format=pixel_format, speed=SPEED)


def _decoded(path: Path) -> tuple[str, int, list[int]]:
    """Codec, frames PyAV decodes and their pts [ms]."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        pts = [int(f.pts) for f in container.decode(stream)]
        return stream.codec_context.name, len(pts), pts


def test_default_records_a_clean_simulation_losslessly_at_speed(tmp_path: Path) -> None:
    session = _run(tmp_path, "bgr8", {})  # storage.video: the default
    assert load_config(tmp_path / "daemon.yaml").storage.video == "passthrough"
    summary = json.loads((session / "summary.json").read_text())
    video = summary["run"]["video"]
    assert (video["mode"], video["codec"], video["left_out"]) == ("passthrough", "ffv1", 0)
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok, reader.integrity_check().problems
        seqs = reader.frames()["seq"].tolist()
        rows = reader.video_frames()
        kinds = [e.kind for e in reader.events()]
    assert "video_not_recorded" not in kinds and kinds.count("video_started") == 1
    codec, n, pts = _decoded(session / "video.mkv")
    # Every measured frame is in the video, decodable, at its row's pts.
    assert codec == "ffv1" and len(seqs) > 100
    assert rows["seq"].tolist() == seqs and n == len(seqs)
    assert pts == rows["pts_ms"].tolist()


def test_roi_only_on_a_jpeg_passthrough_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    capsys.readouterr()
    session = _run(tmp_path, "mjpg", {"video_roi_only": True})
    err = capsys.readouterr().err.splitlines()
    said = [line for line in err if "video_roi_only" in line]
    assert len(said) == 1 and said[0].startswith("stipi-daemon: warning: "), err
    assert "passthrough" in said[0] and "lossless" in said[0]
    with SessionReader(session) as reader:
        events = {e.kind: e.detail for e in reader.events()}
        n_rows = len(reader.video_frames())
    assert "video_roi_only_ignored" in events
    assert "cannot be cropped" in events["video_roi_only_ignored"]["reason"]
    started = events["video_started"]
    assert (started["codec"], started["crop"], started["size"]) == ("mjpeg", None, [160, 120])
    assert "whole" in started["crop_ignored"]  # the recorder says why its crop is null
    codec, n, _ = _decoded(session / "video.mkv")
    with av.open(str(session / "video.mkv")) as container:  # whole frames stored
        stream = container.streams.video[0]
        assert (stream.codec_context.width, stream.codec_context.height) == (160, 120)
    assert codec == "mjpeg" and n == n_rows > 100
