"""A daemon run on the simulated camera records the session video as a real camera's
(docs/simulator.md, "Video"; docs/storage.md).

An MJPG scene's camera hands the daemon each frame's JPEG, so the default
``storage.video: passthrough`` stores those JPEGs as they were encoded (codec ``mjpeg``, at
any clock speed, no frame left out), and the S_k the daemon stored is the count on the
decode of the very packet stored (``analyze --recompute-sk`` reproduces every one). A scene
with raw frames is recorded losslessly (codec ``ffv1``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import av
import pytest

from stipi_daemon.cli import main
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.storage import SessionReader
from tests.daemon._support import short_session


def _run(
    directory: Path,
    pixel_format: str,
    storage: dict[str, Any],
    measurement: dict[str, Any] | None = None,
) -> Path:
    return short_session(
        directory, storage, pixel_format=pixel_format, speed=0.0, measurement=measurement
    )


def _show(session: Path, capsys: pytest.CaptureFixture[str]) -> str:
    capsys.readouterr()
    assert main(["sessions", "show", str(session)]) == 0
    return capsys.readouterr().out


def test_mjpg_scene_is_recorded_passthrough(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _run(tmp_path, "mjpg", {})  # the default: passthrough
    summary = json.loads((session / "summary.json").read_text())
    video = summary["run"]["video"]
    assert (video["mode"], video["codec"], video["left_out"]) == ("passthrough", "mjpeg", 0)
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
        seqs = reader.frames()["seq"].tolist()
        stored = reader.video_frames()
        assert stored["seq"].tolist() == seqs and len(seqs) > 100  # every measured frame
        started = [e.detail for e in reader.events() if e.kind == "video_started"]
    assert summary["run"]["frames"] == len(seqs)
    assert [(d["mode"], d["codec"]) for d in started] == [("passthrough", "mjpeg")]
    # The stored packets are the simulator's JPEGs of those frames, byte for byte.
    scene = load_scene(tmp_path / "grade1_daemon_e2e.yaml")
    encoded = {f.index: f.packet for f in Pipeline(scene).frames()}
    with av.open(str(session / "video.mkv")) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "mjpeg"
        packets = [bytes(p) for p in container.demux(stream) if p.size]
    assert packets == [encoded[s] for s in seqs]
    assert "mjpeg 160x120" in _show(session, capsys)
    # The S_k the daemon stored is the count on the decode of the stored packet.
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--recompute-sk", "--out", str(out)]) == 0
    check = json.loads(out.read_text())["settings"]["imaging"]["s_k_vs_stored"]
    assert (check["frames"], check["differing"], check["frames_without_video"]) == (
        len(seqs),
        0,
        0,
    )


def test_raw_scene_is_recorded_losslessly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _run(tmp_path, "bgr8", {"video": "lossless"})
    video = json.loads((session / "summary.json").read_text())["run"]["video"]
    assert (video["mode"], video["codec"]) == ("lossless", "ffv1") and video["frames"] > 0
    assert "ffv1 160x120" in _show(session, capsys)
    # The simulator waits for the video's encoders: every measured frame is in the video.
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
        seqs = reader.frames()["seq"].tolist()
        assert reader.video_frames()["seq"].tolist() == seqs and len(seqs) > 100
    assert video["left_out"] == 0 and video["frames"] == len(seqs)


def test_the_sessions_frames_end_with_the_recovery_window(tmp_path: Path) -> None:
    """The paper's protocol (the whole recovery window): the session stores the frames up
    to the window's end and none captured after it, whatever the final analysis costs
    while the camera goes on; the run's frame count is the rows'; the report's frames are
    among them."""
    # a window that ends 3 s before the scene does: the camera goes on after it
    window = {"stop_when_settled": False, "recovery_max_s": 15.0}
    session = _run(tmp_path, "mjpg", {}, window)
    summary = json.loads((session / "summary.json").read_text())
    m = summary["measurement"]
    assert m["t_end_s"] == summary["release"]["t_release_s"] + 15.0
    fps = summary["run"]["camera"]["source"]["fps"]
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
        rows = reader.frames()
        assert reader.video_frames()["seq"].tolist() == rows["seq"].tolist()
    t_last_s = float(rows["t_capture_host_s"][-1])
    assert m["t_end_s"] - 1.5 / fps < t_last_s <= m["t_end_s"]
    assert summary["run"]["frames"] == rows.size
    index = json.loads((session / "frames" / "representative.json").read_text())
    assert {e["seq"] for e in index.values()} <= set(rows["seq"].tolist())
    # the stored data alone (no frame after the end) give the live results again
    out = tmp_path / "replay.json"
    assert main(["analyze", str(session), "--out", str(out), "--quiet"]) == 0
    replay = json.loads(out.read_text())
    assert replay["comparison"]["stored_summary"] == {"identical": True, "differences": []}
