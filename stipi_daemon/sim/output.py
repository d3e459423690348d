"""Files of a simulated measurement: video, frame timestamps, force samples, ground truth.

This module owns the on-disk layout written by ``stipi-daemon simulate`` and
:func:`write_outputs`: ``video.mkv``, ``frames.csv`` (index, t_s, true_area_px of every
frame written), ``force.csv`` (index, t_mcu_us, t_true_s, adc_counts, force_n,
true_force_n) and ``ground_truth.json``. The video is a Matroska file written with PyAV the
way a session's video is stored (:func:`stipi_daemon.storage.video.open_video_file`): a
Motion-JPEG scene (:func:`.jpeg.scene_encoding`) stores each frame's JPEG exactly as the
simulated camera encoded it, muxed without re-encoding (codec ``mjpeg``); every other scene
stores the rendered frames losslessly (FFV1, ``gray`` or ``bgr0``), so that reading the
file back gives the simulator's frames bit for bit. Every frame is intra, so a truncated
file decodes up to its cut. Presentation times are the frames' scene times in ms (a frame
an effect dropped leaves a gap); the declared frame rate is the camera's. It is the
simulator's only I/O; the frames and samples come from :mod:`.pipeline`.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Final, Literal

from stipi_daemon.errors import ConfigError, StipiError
from stipi_daemon.sim.pipeline import Pipeline, frame_count
from stipi_daemon.sim.scene import Scene
from stipi_daemon.sim.truth import ground_truth
from stipi_daemon.storage.video import open_video_file, write_video_frame

__all__ = ["VIDEO_FILE", "OutputPaths", "write_outputs"]

#: File name of the video in the output directory (as a session's: ``video.mkv``).
VIDEO_FILE = "video.mkv"


@dataclass(frozen=True)
class OutputPaths:
    """Where :func:`write_outputs` put each file, and how the video is coded.

    ``video_codec`` is ``mjpeg`` (the camera's JPEGs at ``jpeg_quality``) or ``ffv1``
    (lossless; ``jpeg_quality`` None).
    """

    video: Path
    frames_csv: Path
    force_csv: Path
    ground_truth_json: Path
    frames_written: int
    samples_written: int
    video_codec: str = "ffv1"
    jpeg_quality: int | None = None


#: The files a rendering writes into its directory.
OUTPUT_FILES: Final = (VIDEO_FILE, "frames.csv", "force.csv", "ground_truth.json")


def _check_out_dir(out: Path, overwrite: bool) -> None:
    """Refuse an output directory that would lose something (see :func:`write_outputs`)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a directory")
    if (out / "manifest.json").exists():
        raise ConfigError(f"--out {out}: is a session directory; a rendering never goes there")
    present = [name for name in OUTPUT_FILES if (out / name).exists()]
    if present and not overwrite:
        raise ConfigError(
            f"--out {out}: holds an earlier rendering ({', '.join(present)}); "
            "give --overwrite to replace it"
        )


def write_outputs(
    scene: Scene,
    out_dir: str | Path,
    seed: int | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
    overwrite: bool = False,
) -> OutputPaths:
    """Render ``scene`` and write its video, frame times, force samples and ground truth.

    Parameters
    ----------
    scene : Scene
        The scene; its camera and effects decide the video's coding (module docstring).
    out_dir : str or Path
        Directory to write into (created if missing).
    seed : int, optional
        Random seed (default: the scene's).
    progress : callable, optional
        Called as ``progress(frames_done, frames_total)`` after every frame.
    overwrite : bool
        Replace the files of an earlier rendering in ``out_dir``.

    Raises
    ------
    ConfigError
        ``out_dir`` is a file or a session directory, or holds an earlier rendering and
        ``overwrite`` is not set (nothing is written then).
    StipiError
        The directory or a file cannot be written (the message names it).
    """
    out = Path(out_dir)
    _check_out_dir(out, overwrite)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StipiError(f"{out}: cannot create output directory: {exc.strerror}") from exc
    pipe = Pipeline(scene, seed)
    codec: Literal["mjpeg", "ffv1"] = "mjpeg" if pipe.encoding.is_jpeg else "ffv1"
    paths = OutputPaths(
        video=out / VIDEO_FILE,
        frames_csv=out / "frames.csv",
        force_csv=out / "force.csv",
        ground_truth_json=out / "ground_truth.json",
        frames_written=0,
        samples_written=0,
        video_codec=codec,
        jpeg_quality=pipe.encoding.jpeg_quality,
    )
    try:
        written = _write_video(pipe, paths, progress)
    except (OSError, ValueError) as exc:  # av.FFmpegError is an OSError or ValueError
        raise StipiError(f"{paths.video}: cannot write the video: {exc}") from exc
    try:
        n_samples = _write_force(pipe, paths.force_csv)
    except OSError as exc:
        raise StipiError(f"{paths.force_csv}: cannot write: {exc.strerror or exc}") from exc
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
        "video_codec": codec,
        "jpeg_quality": pipe.encoding.jpeg_quality,
        "video_encoding_from": pipe.encoding.source,
        "frames_csv": paths.frames_csv.name,
        "force_csv": paths.force_csv.name,
        "frames_written": written,
        "samples_written": n_samples,
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
        samples_written=n_samples,
        video_codec=codec,
        jpeg_quality=pipe.encoding.jpeg_quality,
    )


def _write_video(
    pipe: Pipeline, paths: OutputPaths, progress: Callable[[int, int], None] | None
) -> int:
    """Write ``video.mkv`` and ``frames.csv`` frame by frame; the number of frames."""
    cam = pipe.scene.camera
    layout = "gray" if pipe.renderer.channels == 1 else "bgr"
    codec: Literal["mjpeg", "ffv1"] = "mjpeg" if paths.video_codec == "mjpeg" else "ffv1"
    container: Any
    container, stream = open_video_file(
        paths.video,
        codec,
        layout,
        (cam.width, cam.height),
        frame_rate=Fraction(repr(float(cam.fps))),
        options={},  # written in one go: no flush per packet
    )
    total = frame_count(pipe.scene)
    written = 0
    last_pts = -1
    try:
        with paths.frames_csv.open("w", newline="", encoding="utf-8") as fcsv:
            w = csv.writer(fcsv)
            w.writerow(["index", "t_s", "true_area_px"])
            for frame in pipe.frames():
                pts = max(last_pts + 1, round(frame.t_s * 1000.0))
                write_video_frame(container, stream, pts, frame.image, frame.packet)
                last_pts = pts
                w.writerow([frame.index, repr(frame.t_s), repr(frame.true_area_px)])
                written += 1
                if progress is not None:
                    progress(written, total)
        if codec == "ffv1":
            for packet in stream.encode(None):  # the encoder's last frames
                container.mux_one(packet)
    finally:
        container.close()
    return written


def _write_force(pipe: Pipeline, path: Path) -> int:
    """Write ``force.csv``; the number of samples."""
    batch = pipe.force_batch()
    with path.open("w", newline="", encoding="utf-8") as f:
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
    return len(batch)
