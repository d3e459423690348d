"""Video-file camera throughput: 1280x720 MJPG decoded to gray vs colour.

Run as ``./dev python benchmarks/bench_camera_decode.py``. Renders 600 frames (10 s at
60 fps) of the grade-III scene at 1280x720 (a realistic probe image, BGR), writes them as an
MJPG AVI (quality 95, the simulator's MJPG quality), then measures frames per second of wall time,
best of five passes, with the file in the page cache, for:

* ``VideoFileCamera`` unpaced (the whole path: capture thread, hand-off, asyncio), gray and
  colour;
* the decode alone in one thread: raw packet + ``imdecode(IMREAD_GRAYSCALE)``, raw packet +
  ``imdecode(IMREAD_COLOR)``, FFmpeg's own decoder (``cap.read()``) and FFmpeg + cvtColor.

Writes the table with the machine to docs/bench_camera_decode.md.
"""

from __future__ import annotations

import asyncio
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _machine import cpu_model  # noqa: E402

from stipi_daemon.cameras.video_file import VideoFileCamera  # noqa: E402
from stipi_daemon.clock import ScaledClock  # noqa: E402
from stipi_daemon.sim import Pipeline, load_scene  # noqa: E402

N_FRAMES = 600
WIDTH, HEIGHT, FPS = 1280, 720, 60.0


def write_video(path: Path, noisy: bool) -> None:
    scene = load_scene(ROOT / "configs" / "scenes" / "grade3.yaml")
    scene = scene.with_camera(width=WIDTH, height=HEIGHT, fps=FPS)
    if noisy:
        scene = scene.with_effects([{"name": "sensor_noise", "sigma_levels": 4.0}])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95.0)
    for k, frame in enumerate(Pipeline(scene).frames()):
        if k >= N_FRAMES:
            break
        writer.write(frame.image)
    writer.release()


def best_fps(run: Callable[[], int], passes: int = 5) -> float:
    best = 0.0
    for _ in range(passes):
        t = time.perf_counter()
        n = run()
        best = max(best, n / (time.perf_counter() - t))
    return best


def camera_run(path: Path, gray: bool) -> Callable[[], int]:
    async def go() -> int:
        cam = VideoFileCamera(path, ScaledClock(), pace=False, gray=gray)
        await cam.open()
        n = 0
        async for _ in cam.frames():
            n += 1
        await cam.close()
        return n

    return lambda: asyncio.run(go())


def raw_run(path: Path, flag: int) -> Callable[[], int]:
    def go() -> int:
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        cap.set(cv2.CAP_PROP_FORMAT, -1)
        n = 0
        while True:
            ok, pk = cap.read()
            if not ok:
                break
            cv2.imdecode(pk.reshape(-1), flag)
            n += 1
        cap.release()
        return n

    return go


def ffmpeg_run(path: Path, to_gray: bool) -> Callable[[], int]:
    def go() -> int:
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        n = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if to_gray:
                cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            n += 1
        cap.release()
        return n

    return go


def table(noisy: bool) -> list[str]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.avi"
        write_video(path, noisy)
        size_mb = path.stat().st_size / 1e6
        rows = [
            ("VideoFileCamera, gray (raw MJPG + imdecode gray)", camera_run(path, True)),
            ("VideoFileCamera, colour (raw MJPG + imdecode BGR)", camera_run(path, False)),
            ("decode only: imdecode(IMREAD_GRAYSCALE)", raw_run(path, cv2.IMREAD_GRAYSCALE)),
            ("decode only: imdecode(IMREAD_COLOR)", raw_run(path, cv2.IMREAD_COLOR)),
            ("decode only: FFmpeg cap.read() (BGR)", ffmpeg_run(path, False)),
            ("decode only: FFmpeg cap.read() + cvtColor gray", ffmpeg_run(path, True)),
        ]
        results = [(label, best_fps(run)) for label, run in rows]
    what = "with sensor noise (sigma 4 levels)" if noisy else "clean (no effects)"
    lines = [
        f"## Grade-III scene, {what}: {size_mb * 1e3 / N_FRAMES:.0f} kB/frame",
        "",
        "| path | frames/s | ms/frame |",
        "|---|---:|---:|",
    ]
    lines += [f"| {label} | {fps:.0f} | {1e3 / fps:.2f} |" for label, fps in results]
    return [*lines, ""]


def main() -> None:
    lines = [
        "# Video-file camera decode throughput (1280x720 MJPG)",
        "",
        f"Command: `./dev python benchmarks/bench_camera_decode.py`. Machine: {cpu_model()}, "
        f"{os.cpu_count()} CPUs, Python {platform.python_version()}, OpenCV {cv2.__version__}.",
        f"Video: {N_FRAMES} frames rendered at {WIDTH}x{HEIGHT}, MJPG quality 95 (as the "
        "simulator writes); page cache warm; frames/s of wall time, best of 5 passes. The "
        "VideoFileCamera rows decode in the capture thread while the asyncio consumer runs. "
        "On a busy shared machine the rows vary by up to 2x between runs; compare on an idle "
        "one.",
        "",
        *table(noisy=False),
        *table(noisy=True),
    ]
    text = "\n".join(lines)
    (ROOT / "docs" / "bench_camera_decode.md").write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
