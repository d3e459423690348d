"""``stipi-daemon simulate SCENE --out DIR``: render a scene to video, force and truth files.

Thin shell over :func:`stipi_daemon.sim.write_outputs`: parses the options, applies the
``--resolution``/``--fps`` overrides, shows a rich progress bar on a terminal (none when
stdout is not a TTY or with ``--quiet``) and prints where the files went.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stipi_daemon.commands import frame_size_arg, given_path
from stipi_daemon.errors import ConfigError, SessionError
from stipi_daemon.storage.export import check_export_target


def _coding(codec: str, jpeg_quality: int | None) -> str:
    if codec == "mjpeg":
        return f"MJPG, JPEG quality {jpeg_quality}"
    return "lossless FFV1"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="render a simulated measurement (video, force samples, ground truth)",
        description=(
            "Render a scene file (configs/scenes/*.yaml) into DIR: video.mkv (the camera's "
            "JPEGs as encoded when the scene's camera is mjpg or it names jpeg_compression, "
            "else lossless FFV1), frames.csv, force.csv and ground_truth.json."
        ),
    )
    parser.add_argument("scene_file", type=Path, metavar="SCENE", help="scene YAML file")
    parser.add_argument("--out", type=str, required=True, metavar="DIR", help="output directory")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: scene's)")
    parser.add_argument(
        "--resolution", type=frame_size_arg, default=None, metavar="WxH", help="frame size override"
    )
    parser.add_argument("--fps", type=float, default=None, help="frame rate override [1/s]")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no summary")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an earlier rendering in DIR"
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from stipi_daemon.sim import load_scene, write_outputs

    scene = load_scene(args.scene_file)
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    if args.fps is not None and not 0.0 < args.fps <= 1000.0:
        raise ConfigError(f"--fps must be in (0, 1000], got {args.fps}")
    if args.resolution is not None or args.fps is not None:
        w, h = args.resolution if args.resolution is not None else (None, None)
        try:
            scene = scene.with_camera(width=w, height=h, fps=args.fps)
        except ValueError as exc:
            raise ConfigError(f"{args.scene_file.name}: camera override: {exc}") from exc
    out = given_path(args.out)
    try:  # a simulation's files never land in a session (video.mkv, frames.csv...)
        check_export_target(out, [], what="a simulation")
    except SessionError as exc:
        raise ConfigError(str(exc)) from None
    show = not args.quiet and sys.stdout is not None and sys.stdout.isatty()
    if show:
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        with Progress(
            TextColumn(f"[bold]{scene.name}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} frames"),
            TimeRemainingColumn(),
        ) as bar:
            task = bar.add_task("render", total=None)

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            paths = write_outputs(
                scene, out, args.seed, progress=progress, overwrite=args.overwrite
            )
    else:
        paths = write_outputs(scene, out, args.seed, overwrite=args.overwrite)
    if not args.quiet:
        print(
            f"{paths.frames_written} frames ({_coding(paths.video_codec, paths.jpeg_quality)}) "
            f"-> {paths.video}\n"
            f"{paths.samples_written} force samples -> {paths.force_csv}\n"
            f"frame times -> {paths.frames_csv}\nground truth -> {paths.ground_truth_json}"
        )
    return 0
