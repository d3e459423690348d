"""The simulator compresses only when the scene asks for it (docs/simulator.md, "Video").

A scene whose camera delivers raw frames (``gray8``, ``bgr8``) is written losslessly: the
file, read back with PyAV and with OpenCV (FFmpeg's decoders, nobody here wrote them), gives
the simulator's in-memory frames bit for bit, so S_k counted on it equals S_k of the
rendered frames on every frame. A Motion-JPEG scene (``camera.pixel_format: mjpg`` or the
``jpeg_compression`` effect) stores each frame's JPEG exactly as the simulator encoded it
(codec ``mjpeg``, no re-encoding), encoded once at the quality the scene names: checked
against the quantisation table the JPEG standard (ITU-T T.81 Annex K, Table K.1) and the
IJG quality scaling give for that quality.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
import pytest
import yaml

from stipi_daemon.analysis.imaging import FrameProcessor
from stipi_daemon.cli import main
from stipi_daemon.errors import ConfigError
from stipi_daemon.sim import Pipeline, write_outputs
from stipi_daemon.sim.render import Renderer
from stipi_daemon.sim.scene import Scene, parse_scene
from tests.conftest import REPO_ROOT

SCENE_DOC: dict[str, Any] = yaml.safe_load(
    (REPO_ROOT / "configs" / "scenes" / "grade1.yaml").read_text()
)

#: ITU-T T.81 Annex K, Table K.1: luminance quantisation table, natural (row-major) order.
LUMA_K1 = np.array(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ]
).ravel()
#: T.81 Figure A.6: natural-order index of the k-th coefficient in zig-zag order.
ZIGZAG = [
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5,
    12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21, 28,
    35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51,
    58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
]  # fmt: skip


def _ijg_luma_table(quality: int) -> list[int]:
    """The luminance table an IJG-style encoder (libjpeg's jpeg_set_quality, baseline)
    writes for ``quality``, in zig-zag order as it appears in the DQT segment."""
    scale = 5000 // quality if quality < 50 else 200 - 2 * quality
    natural = np.clip((LUMA_K1 * scale + 50) // 100, 1, 255)
    return [int(natural[i]) for i in ZIGZAG]


def _dqt_luma_table(jpeg: bytes) -> list[int]:
    """Table 0 of the JPEG's DQT segments (T.81 B.2.4.1), zig-zag order, 8-bit tables."""
    assert jpeg[:2] == b"\xff\xd8", "not a JPEG (no SOI)"
    pos = 2
    while pos + 4 <= len(jpeg):
        assert jpeg[pos] == 0xFF
        marker, length = jpeg[pos + 1], int.from_bytes(jpeg[pos + 2 : pos + 4], "big")
        body = jpeg[pos + 4 : pos + 2 + length]
        if marker == 0xDB:
            i = 0
            while i < len(body):
                pq, tq = body[i] >> 4, body[i] & 0x0F
                size = 64 * (2 if pq else 1)
                if tq == 0 and pq == 0:
                    return list(body[i + 1 : i + 1 + size])
                i += 1 + size
        if marker == 0xDA:  # start of scan: no table 0 before it
            break
        pos += 2 + length
    raise AssertionError("no 8-bit luminance quantisation table")


def _scene(
    pixel_format: str = "bgr8",
    jpeg_quality: int | None = None,
    effects: list[dict[str, Any]] | None = None,
) -> Scene:
    """grade1 at 160x120, 20 fps, 0.5 s approach + 1 s hold + 2 s recovery (71 frames)."""
    doc = copy.deepcopy(SCENE_DOC)
    doc["force_profile"].update({"approach_s": 0.5, "hold_s": 1.0, "recovery_s": 2.0})
    doc["camera"].update({"width": 160, "height": 120, "fps": 20.0})
    doc["camera"]["pixel_format"] = pixel_format
    if jpeg_quality is not None:
        doc["camera"]["jpeg_quality"] = jpeg_quality
    doc["effects"] = effects or []
    return parse_scene(doc, "test-scene.yaml")


def _write_scene_file(scene: Scene, path: Path) -> Path:
    path.write_text(yaml.safe_dump(scene.model_dump(mode="json")))
    return path


def _pyav_frames(path: Path, fmt: str) -> tuple[str, list[np.ndarray]]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format=fmt) for f in container.decode(stream)]
        return str(stream.codec_context.name), frames


def _opencv_frames(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    out: list[np.ndarray] = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                return out
            out.append(frame)
    finally:
        cap.release()


def _pyav_packets(path: Path) -> tuple[str, list[bytes], list[int]]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        pkts = [p for p in container.demux(stream) if p.size]
        return (
            str(stream.codec_context.name),
            [bytes(p) for p in pkts],
            [int(p.pts) for p in pkts if p.pts is not None],
        )


def _s_k(scene: Scene, images: list[np.ndarray]) -> list[int]:
    proc = FrameProcessor(images[0].shape, scene.probe.threshold, Renderer(scene).roi)
    return [proc.count(img) for img in images]


@pytest.mark.parametrize("pixel_format", ["bgr8", "gray8"])
def test_a_scene_without_effects_is_written_losslessly(tmp_path: Path, pixel_format: str) -> None:
    scene = _scene(pixel_format)
    out = tmp_path / "out"
    argv = ["simulate", str(_write_scene_file(scene, tmp_path / "s.yaml")), "--out", str(out)]
    assert main([*argv, "--quiet"]) == 0
    video = out / "video.mkv"
    truth = json.loads((out / "ground_truth.json").read_text())["outputs"]
    assert (truth["video"], truth["video_codec"], truth["jpeg_quality"]) == (
        "video.mkv",
        "ffv1",
        None,
    )
    ref = list(Pipeline(scene).frames())
    assert all(f.packet is None for f in ref)
    gray = pixel_format == "gray8"
    codec, decoded = _pyav_frames(video, "gray" if gray else "bgr24")
    assert codec == "ffv1" and len(decoded) == len(ref) == 71
    for f, img in zip(ref, decoded, strict=True):
        np.testing.assert_array_equal(img, f.image)
    by_opencv = _opencv_frames(video)  # OpenCV delivers BGR; gray frames as equal channels
    assert len(by_opencv) == len(ref)
    for f, img in zip(ref, by_opencv, strict=True):
        np.testing.assert_array_equal(
            cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if gray else img, f.image
        )
    # S_k on the stored video equals S_k on the rendered frames on every frame (Eq. 2) ...
    rendered = _s_k(scene, [f.image for f in ref])
    stored = _s_k(scene, decoded)
    assert sum(a != b for a, b in zip(rendered, stored, strict=True)) == 0
    assert rendered == [round(f.true_area_px) for f in ref]  # and the renderer's true area
    assert max(rendered) > 100  # the disc is there to be counted
    # ... which a JPEG of the same frames does not achieve: the check can tell.
    jpeg = write_outputs(_scene("mjpg"), tmp_path / "jpeg")
    assert jpeg.video_codec == "mjpeg"
    _, lossy = _pyav_frames(jpeg.video, "bgr24")
    assert sum(a != b for a, b in zip(rendered, _s_k(scene, lossy), strict=True)) > 0


@pytest.mark.parametrize(
    ("pixel_format", "camera_quality", "effects", "quality"),
    [
        ("mjpg", None, [], 95),  # the camera's default
        ("mjpg", 70, [], 70),
        ("bgr8", None, [{"name": "jpeg_compression", "quality": 40}], 40),
        ("mjpg", None, [{"name": "jpeg_compression", "quality": 30}], 30),
    ],
    ids=["mjpg-default", "mjpg-q70", "effect-q40", "mjpg-and-effect-q30"],
)
def test_an_mjpg_scene_stores_the_simulators_jpegs_as_encoded(
    tmp_path: Path,
    pixel_format: str,
    camera_quality: int | None,
    effects: list[dict[str, Any]],
    quality: int,
) -> None:
    scene = _scene(pixel_format, camera_quality, effects)
    paths = write_outputs(scene, tmp_path / "out")
    assert (paths.video.name, paths.video_codec, paths.jpeg_quality) == (
        "video.mkv",
        "mjpeg",
        quality,
    )
    ref = list(Pipeline(scene).frames())
    codec, packets, pts = _pyav_packets(paths.video)
    assert codec == "mjpeg"
    # The file holds the very bytes the simulator encoded: muxed, not re-encoded.
    assert packets == [f.packet for f in ref]
    assert pts == [round(f.t_s * 1000) for f in ref]
    # Encoded once, at the scene's quality: one JPEG of the rendered frame, whose
    # quantisation table is the standard's for that quality.
    renderer = Renderer(scene)
    for f in ref[::10]:
        raw = renderer.render(f.t_s)
        assert f.packet is not None
        assert (
            f.packet == cv2.imencode(".jpg", raw, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
        )
        assert _dqt_luma_table(f.packet) == _ijg_luma_table(quality)
        # The frame the analysis sees is the decode of that packet.
        decoded = cv2.imdecode(np.frombuffer(f.packet, np.uint8), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(f.image, decoded)
    truth = json.loads(paths.ground_truth_json.read_text())["outputs"]
    assert (truth["video_codec"], truth["jpeg_quality"]) == ("mjpeg", quality)


def test_the_standard_table_oracle_matches_a_reference_value() -> None:
    # Quality 50 is Table K.1 itself (scale 100); quality 100 is all ones.
    assert _ijg_luma_table(50)[:4] == [16, 11, 12, 14]
    assert set(_ijg_luma_table(100)) == {1}


@pytest.mark.parametrize(
    ("camera", "effects", "message"),
    [
        (
            {"pixel_format": "bgr8", "jpeg_quality": 80},
            [],
            "test-scene.yaml: camera: jpeg_quality applies to pixel_format mjpg only",
        ),
        (
            {"pixel_format": "yuyv"},
            [],
            "test-scene.yaml: camera.pixel_format: Input should be 'gray8', 'bgr8' or 'mjpg'",
        ),
        (
            {"pixel_format": "mjpg", "jpeg_quality": 101},
            [],
            "test-scene.yaml: camera.jpeg_quality: Input should be less than or equal to 100",
        ),
        (
            {"pixel_format": "mjpg", "jpeg_quality": 80},
            [{"name": "jpeg_compression", "quality": 60}],
            "camera.jpeg_quality and the jpeg_compression effect's quality both set",
        ),
    ],
)
def test_bad_camera_coding_is_refused_naming_the_field(
    camera: dict[str, Any], effects: list[dict[str, Any]], message: str
) -> None:
    doc = copy.deepcopy(SCENE_DOC)
    doc["camera"].update(camera)
    doc["effects"] = effects
    with pytest.raises(ConfigError) as err:
        parse_scene(doc, "test-scene.yaml")
    assert message in str(err.value)
    assert "\n" not in str(err.value)
