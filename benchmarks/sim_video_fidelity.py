"""What the simulator's ``video.mkv`` keeps of S_k, and its size, per camera pixel format.

Run as ``./dev python benchmarks/sim_video_fidelity.py [SCENE]`` (default
``configs/scenes/grade3.yaml``; about a minute per format). For ``gray8``, ``bgr8`` and
``mjpg`` (quality 95) cameras it writes the scene with
:func:`stipi_daemon.sim.write_outputs`, reads the video back with
:func:`stipi_daemon.storage.video_readback.iter_video_images`, counts S_k (Eqs. 1-2,
:class:`~stipi_daemon.analysis.imaging.FrameProcessor`, the renderer's ROI and the scene's
threshold) and prints, as Markdown rows, on how many frames S_k differs from the rendered
true area round(S), the largest difference, and the file's size per minute of video.
The figures are quoted in docs/simulator.md ("Video").
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from stipi_daemon.analysis.imaging import FrameProcessor  # noqa: E402
from stipi_daemon.sim import Pipeline, load_scene, write_outputs  # noqa: E402
from stipi_daemon.sim.scene import Scene  # noqa: E402
from stipi_daemon.storage.video_readback import iter_video_images  # noqa: E402


def measure(scene: Scene, out: Path) -> str:
    """One Markdown row for ``scene``."""
    t = time.perf_counter()
    paths = write_outputs(scene, out)
    wall = time.perf_counter() - t
    pipe = Pipeline(scene)
    proc: FrameProcessor | None = None
    n = differing = largest = 0
    for frame, image in zip(pipe.frames(), iter_video_images(paths.video), strict=True):
        if proc is None:
            proc = FrameProcessor(image.shape, scene.probe.threshold, pipe.renderer.roi)
        d = abs(proc.count(image) - round(frame.true_area_px))
        n += 1
        differing += d > 0
        largest = max(largest, d)
    size_mb = paths.video.stat().st_size / 1e6
    per_min = size_mb / (n / scene.camera.fps) * 60.0
    q = "" if paths.jpeg_quality is None else f" q{paths.jpeg_quality}"
    return (
        f"| {scene.camera.pixel_format} | {paths.video_codec}{q} | {n} | {differing} | "
        f"{largest} | {size_mb:.1f} | {per_min:.1f} | {wall:.1f} |"
    )


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "configs/scenes/grade3.yaml"
    base = load_scene(path)
    print(f"scene {path.name}, {base.camera.width}x{base.camera.height}, {base.camera.fps:g} fps")
    print(
        "| pixel_format | codec | frames | S_k != round(S) | max [px] | MB | MB/min | "
        "write [s] |\n|---|---|---:|---:|---:|---:|---:|---:|"
    )
    with tempfile.TemporaryDirectory(prefix="stipi_sim_fidelity_") as tmp:
        for fmt in ("gray8", "bgr8", "mjpg"):
            cam = base.camera.model_copy(update={"pixel_format": fmt, "jpeg_quality": None})
            scene = base.model_copy(update={"camera": cam})
            print(measure(scene, Path(tmp) / fmt), flush=True)


if __name__ == "__main__":
    main()
