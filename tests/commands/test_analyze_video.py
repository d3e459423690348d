"""``analyze SESSION --recompute-sk`` on the video the daemon recorded (docs/storage.md).

The oracle is independent of the project's readback and counting: PyAV demuxes and decodes
the stored video itself (JPEG packets decoded by OpenCV's ``imdecode``, as the camera
decodes them), and numpy counts the pixels at or below the threshold p whose centre lies
in the ROI (Eqs. 1-2), in camera-frame coordinates (a cropped video's pixel (i, j) is
camera pixel (x0 + i, y0 + j)).
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
import numpy.typing as npt
import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.cli import main
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.output import write_outputs
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.storage import SessionReader
from tests._offline import run_with_whole_video
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config


def record(directory: Path, camera: dict[str, Any], storage: dict[str, Any]) -> Path:
    """Record the short grade-I scene at 160x120 with the live daemon; every frame is in
    the video (:func:`tests._offline.run_with_whole_video`)."""
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
        "run": {"speed": 0.0},
    }
    path = write_config(directory, doc)
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"].update(storage)
    path.write_text(yaml.safe_dump(cfg))
    return run_with_whole_video(path)


def digest(directory: Path) -> dict[str, str]:
    """SHA-256 of every file under ``directory`` (``frames/``, ``report/`` too), by path."""
    return {
        str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def assert_untouched(directory: Path, before: dict[str, str]) -> None:
    """Every file ``before`` lists is there with the same bytes; any new file is an
    ``analysis-*.json`` directly in ``directory``."""
    after = digest(directory)
    assert {k: after.get(k) for k in before} == before
    assert all(k.startswith("analysis-") and "/" not in k for k in set(after) - set(before))


def decoded_gray(video: Path) -> tuple[list[npt.NDArray[np.uint8]], tuple[int, int]]:
    """Every frame PyAV decodes from ``video`` (in file order), as gray images, and the
    file's ``STIPI_CROP`` offset ``(x0, y0)`` [px] ((0, 0) without one). A damaged tail
    ends the list, as FFmpeg stops there."""
    images: list[npt.NDArray[np.uint8]] = []
    with av.open(str(video)) as container:
        tags = dict(container.metadata)
        stream = container.streams.video[0]
        jpeg = stream.codec_context.name == "mjpeg"
        flag = cv2.IMREAD_GRAYSCALE if tags.get("STIPI_IMAGE") == "gray" else cv2.IMREAD_COLOR
        try:
            for pkt in container.demux(stream):
                if not pkt.size:
                    continue
                if jpeg:
                    img = cv2.imdecode(np.frombuffer(bytes(pkt), np.uint8), flag)
                    if img is None:
                        break
                    images.append(img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
                    continue
                for frame in stream.codec_context.decode(pkt):
                    if frame.format.name == "gray":
                        images.append(frame.to_ndarray(format="gray"))
                    else:
                        bgr = frame.to_ndarray(format="bgr24")
                        images.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        except (OSError, ValueError):
            pass
    crop = tags.get("STIPI_CROP")
    x0, y0 = (0, 0) if not crop else (int(v) for v in str(crop).split(",")[:2])
    return images, (x0, y0)


def oracle_s_k(video: Path, threshold_p: int, roi: dict[str, Any] | None) -> list[int]:
    """S_k of every frame PyAV decodes from ``video``: the pixels <= ``threshold_p`` whose
    centre lies in ``roi`` (a circle or rect, camera-frame coordinates [px]; None: all)."""
    images, (x0, y0) = decoded_gray(video)
    if not images:
        return []
    h, w = images[0].shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xs + x0, ys + y0
    if roi is None:
        mask = np.ones((h, w), dtype=bool)
    elif roi["kind"] == "circle":
        mask = (x - roi["cx_px"]) ** 2 + (y - roi["cy_px"]) ** 2 <= roi["radius_px"] ** 2
    else:
        mask = (x >= roi["x_px"]) & (x < roi["x_px"] + roi["width_px"])
        mask &= (y >= roi["y_px"]) & (y < roi["y_px"] + roi["height_px"])
    return [int(np.count_nonzero(img[mask] <= threshold_p)) for img in images]


def stored_rows(session: Path) -> tuple[list[int], list[int], dict[int, int]]:
    """``frames`` seq and s_k in storage order, and seq -> ``video_frames`` frame_index,
    read with SQLite."""
    with sqlite3.connect(f"file:{session / 'session.sqlite'}?mode=ro", uri=True) as conn:
        rows = conn.execute("SELECT seq, s_k FROM frames ORDER BY id").fetchall()
        index = dict(conn.execute("SELECT seq, frame_index FROM video_frames").fetchall())
    conn.close()
    return [r[0] for r in rows], [r[1] for r in rows], index


def recorded_counting(session: Path) -> tuple[int, dict[str, Any] | None]:
    """The threshold p and ROI (None: the whole frame) the session counted its S_k with
    (its manifest)."""
    cal = json.loads((session / "manifest.json").read_text())["calibration"]
    return int(cal["threshold_p"]), cal["roi"]


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
    session = record(tmp_path, camera, storage)
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
    seqs, s_k, index = stored_rows(session)
    assert len(seqs) > 100 and sorted(index) == sorted(seqs)  # every stored frame has video
    with av.open(str(session / "video.mkv")) as container:
        assert container.streams.video[0].codec_context.name == codec
        assert bool(container.metadata.get("STIPI_CROP")) == bool(storage.get("video_roi_only"))
    p, roi = recorded_counting(session)
    oracle = oracle_s_k(session / "video.mkv", p, roi)
    assert len(oracle) == len(seqs)  # PyAV decodes exactly one frame per stored frame
    assert [oracle[index[q]] for q in seqs] == s_k  # the stored S_k are the video's
    stored_verdict = json.loads((session / "summary.json").read_text())["verdict"]
    before = digest(session)
    capsys.readouterr()
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--recompute-sk", "--out", str(out)]) == 0
    n = len(seqs)
    assert f"S_k recounted from the video: {n} of {n} stored frames, all equal" in (
        capsys.readouterr().out
    )
    doc = json.loads(out.read_text())
    assert doc["settings"]["imaging"]["s_k_vs_stored"] == {
        "stored_frames": n,
        "frames": n,
        "differing": 0,
        "max_abs_difference_px": 0.0,
        "frames_without_video": 0,
        "undecodable_frames": 0,
        "settings": "recorded",
        "problem": None,
    }
    assert doc["summary"]["verdict"] == stored_verdict
    # Another threshold: re-analysed beside the session, never over it; the differences
    # are expected (reported, not an error) and are those of the oracle.
    at_90 = oracle_s_k(session / "video.mkv", 90, roi)
    differ = sum(at_90[index[q]] != v for q, v in zip(seqs, s_k, strict=True))
    assert differ > 0
    assert main(["analyze", str(session), "--recompute-sk", "--threshold", "90"]) == 0
    text = capsys.readouterr().out
    assert f"S_k recounted from the video: {n} of {n} stored frames (threshold 90" in text
    assert f": {differ} differ (up to " in text
    other = imaging_of_default_output(session)
    assert other["threshold_p"] == 90
    assert other["s_k_vs_stored"]["differing"] == differ
    assert other["s_k_vs_stored"]["problem"] is None
    assert_untouched(session, before)


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
    their stored frames out, says so, and flags the results (exit 3) rather than pairing
    them by guess."""
    session = record(tmp_path, {"kind": "file", "pace": True}, {})
    with SessionReader(session) as reader:
        n_rows = reader.count("video_frames")
    cut = 5
    with sqlite3.connect(session / "session.sqlite") as conn:  # the last batch, never handed
        conn.execute("DELETE FROM video_frames WHERE frame_index >= ?", (n_rows - cut,))
    conn.close()
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--recompute-sk", "--out", str(out)]) == 3
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    check = doc["settings"]["imaging"]["s_k_vs_stored"]
    assert (check["frames_without_video"], check["differing"]) == (cut, 0)
    assert check["problem"] == (
        f"S_k recount from the video: of the {n_rows} stored frames, {cut} not in the video"
    )
    assert (
        f"S_k recounted from the video: {n_rows - cut} of {n_rows} stored frames: 0 differ, "
        f"{cut} not in the video, 0 undecodable: the results are flagged"
    ) in text
    assert doc["summary"]["verdict"]["status"] != "complete"
    assert check["problem"] in doc["summary"]["verdict"]["line"]
    assert any(
        f"the video holds {cut} frame(s) more than its video_frames rows" in note
        for note in doc["notes"]
    ), doc["notes"]
