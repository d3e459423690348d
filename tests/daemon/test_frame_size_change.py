"""A camera whose frames change size mid-measurement ends the run with one clear line.

S_k counts pixels: the ROI, the threshold and the calibration (Eqs. 3-5) are those of the
session's frame size, so a frame of another size is not the session's quantity, and the
session video's stream cannot take it either (FFmpeg would encode an FFV1 frame of another
size at the stream's size without an error). The real daemon replays, as its camera, an
H.264 recording whose frames change from 160x120 to 320x240 during the hold: two MPEG-TS
files written by libx264 and joined byte for byte, as a lab joins two recordings, and
decoded by FFmpeg, which hands over frames of the new size after the second stream's
sequence parameter set. And a Motion-JPEG recording whose JPEGs change size at the same
frame (a camera switched to another resolution under a recorder that copies its packets,
as ``ffmpeg -c copy`` does): Matroska muxed by FFmpeg, each frame a JPEG of OpenCV's
encoder; the camera decodes every JPEG itself. The emulated Feather plays the same scene on
a pty.
"""

from __future__ import annotations

import asyncio
import io
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.cli import main
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.storage import SessionReader
from stipi_daemon.storage.schema import GAPS
from stipi_daemon.storage.video_readback import iter_video_images, probe_video
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config

FPS = 20
#: The first frame of the larger size: 4 s into the file, during the 5.5 s hold.
CHANGE_AT = 4 * FPS


def _h264_ts(path: Path, images: list[np.ndarray], first_pts: int) -> None:
    """``images`` (gray) as one lossless H.264 stream in an MPEG-TS file (libx264)."""
    import av

    h, w = images[0].shape
    with av.open(str(path), "w", format="mpegts") as out:
        stream = out.add_stream("libx264", rate=FPS)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        stream.options = {"qp": "0", "preset": "ultrafast"}
        for k, image in enumerate(images):
            frame = av.VideoFrame.from_ndarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), "bgr24")
            frame.pts = first_pts + k
            out.mux(stream.encode(frame))
        out.mux(stream.encode(None))


def _mjpg_mkv(path: Path, images: list[np.ndarray]) -> None:
    """``images`` (gray, of any sizes) as OpenCV's JPEGs muxed into one Matroska stream
    (FFmpeg), declared at the first image's size, each packet copied as it is."""
    import av

    h, w = images[0].shape
    with av.open(str(path), "w", format="matroska") as out:
        stream = out.add_stream("mjpeg", rate=FPS)
        stream.width, stream.height, stream.pix_fmt = w, h, "yuvj420p"
        stream.time_base = Fraction(1, FPS)
        for k, image in enumerate(images):
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            pkt = av.Packet(jpeg.tobytes())
            pkt.stream, pkt.time_base = stream, Fraction(1, FPS)
            pkt.pts, pkt.dts, pkt.is_keyframe = k, k, True
            out.mux(pkt)


def _rendered(tmp_path: Path, scene: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The scene rendered at 160x120 (the simulator), gray: the frames before CHANGE_AT and,
    scaled to 320x240, those from CHANGE_AT to 8 s."""
    rendered = tmp_path / "render"
    assert main(["simulate", str(scene), "--out", str(rendered), "--fps", str(FPS), "--quiet"]) == 0
    video = next(p for p in rendered.iterdir() if p.name.startswith("video."))
    images = [
        img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        for img in iter_video_images(video)
    ]
    first, rest = images[:CHANGE_AT], images[CHANGE_AT : 8 * FPS]
    return first, [cv2.resize(img, (320, 240), interpolation=cv2.INTER_NEAREST) for img in rest]


def _joined_recording(tmp_path: Path, scene: Path, codec: str) -> Path:
    """The rendered scene as a recording whose frames grow to 320x240 at CHANGE_AT:
    ``h264``, two H.264 TS files joined byte for byte; ``mjpeg``, one MJPG Matroska file."""
    first, larger = _rendered(tmp_path, scene)
    if codec == "mjpeg":
        _mjpg_mkv(tmp_path / "joined.mkv", first + larger)
        return tmp_path / "joined.mkv"
    _h264_ts(tmp_path / "a.ts", first, 0)
    _h264_ts(tmp_path / "b.ts", larger, CHANGE_AT)
    joined = tmp_path / "joined.ts"
    joined.write_bytes((tmp_path / "a.ts").read_bytes() + (tmp_path / "b.ts").read_bytes())
    return joined


@pytest.mark.parametrize("codec", ["h264", "mjpeg"])
def test_frames_that_change_size_end_the_run_with_one_line_and_keep_what_came_before(
    tmp_path: Path, codec: str
) -> None:
    scene = short_scene(tmp_path, width=160, height=120)
    joined = _joined_recording(tmp_path, scene, codec)
    sc = load_scene(scene).with_camera(width=160, height=120, fps=FPS)
    cal = save_calibration(tmp_path / "cal.json", scaled_calibration(sc)[0])
    cfg = write_config(
        tmp_path,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "file", "path": str(joined), "pace": True},
            "calibration": str(cal),
            "measurement": SHORT_MEASUREMENT,
            "run": {"speed": 0.0},
        },
    )
    out = io.StringIO()
    outcome = asyncio.run(run_daemon(load_config(cfg), out=out, live=False))
    summary = outcome.summary
    line = (
        f"camera: frame {CHANGE_AT} is 320x240 gray, the session's frames are 160x120 gray "
        "(S_k, the ROI and the calibration are for that size); the measurement stopped there"
    )
    assert summary["status"] == "fault" and summary["end_reason"] == line
    assert summary["verdict"]["status"] == "incomplete", summary["verdict"]
    assert f"FAULT {line}" in out.getvalue()
    with SessionReader(outcome.session_dir) as reader:
        assert reader.status == "fault" and outcome.exit_code != 0
        seqs = reader.frames()["seq"].tolist()
        assert seqs == list(range(CHANGE_AT))  # every frame before the change, none after
        gaps = reader.array(GAPS)
        resized = gaps[gaps["cause"] == "frame_size_changed"]
        assert resized["start_index"].tolist() == [CHANGE_AT]
        (fault,) = [e for e in reader.events() if e.kind == "fault:frame_size_changed"]
        assert fault.detail == {
            "seq": CHANGE_AT,
            "shape": [240, 320],
            "session_shape": [120, 160],
            "reported": False,
        }
        assert reader.video_frames()["seq"].tolist() == seqs
        assert reader.integrity_check().ok, reader.integrity_check().problems
        info = probe_video(outcome.session_dir / "video.mkv")
        assert (info.width, info.height, info.frames) == (160, 120, CHANGE_AT)
        assert info.codec == ("mjpeg" if codec == "mjpeg" else "ffv1")
