"""Files of a simulated measurement: video, frame timestamps, force samples, ground truth.

This module owns the on-disk layout written by ``stipi-daemon simulate`` and
:func:`write_outputs`: ``video.avi`` (Motion-JPEG, whose independent frames survive a
truncated file), ``frames.csv`` (index, t_s of every frame written), ``force.csv``
(index, t_mcu_us, t_true_s, adc_counts, force_n, true_force_n) and ``ground_truth.json``.
It is the simulator's only I/O; the frames and samples come from :mod:`.pipeline`.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2

from stipi_daemon.errors import StipiError
from stipi_daemon.sim.pipeline import Pipeline, frame_count
from stipi_daemon.sim.scene import Scene
from stipi_daemon.sim.truth import ground_truth

__all__ = ["VIDEO_FOURCC", "OutputPaths", "write_outputs"]

#: FourCC of the video: Motion-JPEG, every frame an independent JPEG.
VIDEO_FOURCC = "MJPG"


@dataclass(frozen=True)
class OutputPaths:
    """Where :func:`write_outputs` put each file."""

    video: Path
    frames_csv: Path
    force_csv: Path
    ground_truth_json: Path
    frames_written: int
    samples_written: int


def write_outputs(
    scene: Scene,
    out_dir: str | Path,
    seed: int | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
    jpeg_quality: int = 95,
) -> OutputPaths:
    """Render ``scene`` and write its video, frame times, force samples and ground truth.

    Parameters
    ----------
    scene : Scene
        The scene.
    out_dir : str or Path
        Directory to write into (created if missing).
    seed : int, optional
        Random seed (default: the scene's).
    progress : callable, optional
        Called as ``progress(frames_done, frames_total)`` after every frame.
    jpeg_quality : int
        MJPG quality, 1..100.

    Raises
    ------
    StipiError
        The directory or the video cannot be written.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StipiError(f"{out}: cannot create output directory: {exc.strerror}") from exc
    pipe = Pipeline(scene, seed)
    cam = scene.camera
    paths = OutputPaths(
        video=out / "video.avi",
        frames_csv=out / "frames.csv",
        force_csv=out / "force.csv",
        ground_truth_json=out / "ground_truth.json",
        frames_written=0,
        samples_written=0,
    )
    writer = cv2.VideoWriter(
        str(paths.video),
        cv2.VideoWriter.fourcc(*VIDEO_FOURCC),
        float(cam.fps),
        (cam.width, cam.height),
        cam.pixel_format == "bgr8",
    )
    if not writer.isOpened():
        raise StipiError(f"{paths.video}: OpenCV cannot open an {VIDEO_FOURCC} video writer")
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, float(jpeg_quality))
    total = frame_count(scene)
    written = 0
    try:
        with paths.frames_csv.open("w", newline="", encoding="utf-8") as fcsv:
            w = csv.writer(fcsv)
            w.writerow(["index", "t_s", "true_area_px"])
            for n, frame in enumerate(pipe.frames(), start=1):
                writer.write(frame.image)
                w.writerow([frame.index, repr(frame.t_s), repr(frame.true_area_px)])
                written += 1
                if progress is not None:
                    progress(n, total)
    finally:
        writer.release()
    batch = pipe.force_batch()
    with paths.force_csv.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["index", "t_mcu_us", "t_true_s", "adc_counts", "force_n", "true_force_n"])
        for s in batch.samples():
            w.writerow(
                [
                    s.index,
                    s.t_mcu_us,
                    repr(s.t_true_s),
                    s.adc_counts,
                    repr(s.force_n),
                    repr(s.true_force_n),
                ]
            )
    r = pipe.renderer.roi
    truth = ground_truth(
        scene,
        pipe.seed,
        model=pipe.model,
        roi={"cx_px": r.cx_px, "cy_px": r.cy_px, "radius_px": r.radius_px},
    )
    doc = truth.to_json_dict()
    doc["outputs"] = {
        "video": paths.video.name,
        "video_fourcc": VIDEO_FOURCC,
        "frames_csv": paths.frames_csv.name,
        "force_csv": paths.force_csv.name,
        "frames_written": written,
        "samples_written": len(batch),
    }
    paths.ground_truth_json.write_text(
        json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8"
    )
    return OutputPaths(
        video=paths.video,
        frames_csv=paths.frames_csv,
        force_csv=paths.force_csv,
        ground_truth_json=paths.ground_truth_json,
        frames_written=written,
        samples_written=len(batch),
    )
