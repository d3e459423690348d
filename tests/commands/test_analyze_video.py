"""``analyze SESSION --recompute-sk`` on the video the daemon recorded (docs/storage.md)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from stipi_daemon.cli import main
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.output import write_outputs
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.storage import SessionReader
from stipi_daemon.storage.video import probe_video
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config


def _record(directory: Path, camera: dict[str, Any], storage: dict[str, Any]) -> Path:
    scene = short_scene(directory, width=160, height=120)
    cam = {"kind": "simulator", "scene": str(scene)} | camera
    extra: dict[str, Any] = {}
    if cam["kind"] == "file":  # the simulator's MJPG rendering of the same scene
        cam.pop("scene")
        plain = load_scene(scene)
        mjpg = plain.model_copy(
            update={"camera": plain.camera.model_copy(update={"pixel_format": "mjpg"})}
        )
        cam["path"] = str(write_outputs(mjpg, directory / "sim").video)
        cal, _ = scaled_calibration(load_scene(scene))
        extra["calibration"] = str(save_calibration(directory / "cal.json", cal))
    doc = extra | {
        "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
        "camera": cam,
        "measurement": SHORT_MEASUREMENT,
        "run": {"speed": 2.0},
    }
    path = write_config(directory, doc)
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"].update(storage)
    path.write_text(yaml.safe_dump(cfg))
    return run_measurement(load_config(path), quiet=True).session_dir


def _digest(directory: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.iterdir())
        if p.is_file()
    }


@pytest.mark.parametrize(
    ("camera", "storage", "codec"),
    [
        ({}, {"video": "lossless"}, "ffv1"),  # simulator: raw frames, lossless
        ({}, {"video": "lossless", "video_roi_only": True}, "ffv1"),  # the ROI's gray box
        ({"kind": "file", "pace": True}, {}, "mjpeg"),  # MJPG file: JPEGs passed through
    ],
    ids=["simulator-lossless", "roi-box", "mjpg-passthrough"],
)
def test_recompute_sk_reproduces_every_stored_s_k(
    tmp_path: Path,
    camera: dict[str, Any],
    storage: dict[str, Any],
    codec: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    session = _record(tmp_path, camera, storage)
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
        rows = set(reader.frames()["seq"].tolist())
        stored = set(reader.video_frames()["seq"].tolist())
    # On a loaded machine the lossless encoder may leave frames out (never the measurement).
    n_paired = len(rows & stored)
    assert n_paired > 0 and len(rows) > 100  # how many depends on the spare CPU
    info = probe_video(session / "video.mkv")
    assert info.codec == codec and info.frames == len(stored)
    if storage.get("video_roi_only"):
        assert info.crop is not None and info.image == "gray"
    before = _digest(session)
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--recompute-sk", "--out", str(out)]) == 0
    imaging = json.loads(out.read_text())["settings"]["imaging"]
    assert imaging["s_k_vs_stored"] == {
        "frames": n_paired,
        "differing": 0,
        "max_abs_difference_px": 0.0,
        "frames_without_video": len(rows - stored),  # reported, never silently dropped
    }
    # Another threshold: re-analysed beside the session, never over it.
    assert main(["analyze", str(session), "--recompute-sk", "--threshold", "90"]) == 0
    other = imaging_of_default_output(session)
    assert other["threshold_p"] == 90 and other["s_k_vs_stored"]["differing"] > 0
    for name, digest in before.items():
        assert _digest(session)[name] == digest, name
    capsys.readouterr()


def imaging_of_default_output(session: Path) -> dict[str, Any]:
    outputs = sorted(session.glob("analysis-*.json"))
    assert outputs, list(session.iterdir())
    doc = json.loads(outputs[-1].read_text())
    imaging: dict[str, Any] = doc["settings"]["imaging"]
    return imaging


def test_recompute_sk_names_video_frames_without_their_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A killed recording's video may hold frames whose ``video_frames`` rows were not
    committed yet (the recorder hands them over in batches): the recount leaves them and
    their stored frames out, and says so, rather than pairing them by guess."""
    import sqlite3

    session = _record(tmp_path, {"kind": "file", "pace": True}, {})
    with SessionReader(session) as reader:
        n_rows = reader.count("video_frames")
    cut = 5
    with sqlite3.connect(session / "session.sqlite") as conn:  # the last batch, never handed
        conn.execute("DELETE FROM video_frames WHERE frame_index >= ?", (n_rows - cut,))
    conn.close()
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--recompute-sk", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["frames_without_video"] == cut
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["differing"] == 0
    assert any(
        f"the video holds {cut} frame(s) more than its video_frames rows" in note
        for note in doc["notes"]
    ), doc["notes"]
    capsys.readouterr()
