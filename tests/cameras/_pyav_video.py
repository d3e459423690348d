"""Test videos written with PyAV's (FFmpeg's) real encoders: FFV1 and MPEG-4 with B-frames."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
import numpy.typing as npt

from tests.cameras._video import frame_image


def write_pyav(
    path: Path,
    n_frames: int,
    *,
    codec: str = "ffv1",
    fps: int = 10,
    width: int = 160,
    height: int = 120,
    color: bool = True,
) -> list[npt.NDArray[np.uint8]]:
    """Write ``n_frames`` test images with ``codec`` (``ffv1``: lossless, every frame a
    keyframe, BGR as ``bgr0`` or gray; ``mpeg4``: I/P/B frames, two B-frames between
    anchors, a keyframe every 6); return the images as written."""
    images = [frame_image(k, width, height, color) for k in range(n_frames)]
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=fps)
        stream.width, stream.height = width, height
        if codec == "ffv1":
            stream.pix_fmt = "bgr0" if color else "gray"
            stream.codec_context.gop_size = 1
        else:
            stream.pix_fmt = "yuv420p"
            stream.codec_context.gop_size = 6
            stream.codec_context.max_b_frames = 2
            stream.options = {"bf": "2", "qscale": "3"}
        layout = "bgr24" if color else "gray"
        for img in images:
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format=layout)):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return images


def pyav_frames(path: Path, layout: str = "bgr24") -> list[npt.NDArray[np.uint8]]:
    """Every frame as PyAV's own decoder gives it (the reference), as ``layout``."""
    with av.open(str(path)) as container:
        return [
            np.asarray(f.to_ndarray(format=layout), dtype=np.uint8)
            for f in container.decode(video=0)
        ]


def has_b_frames(path: Path) -> bool:
    """Whether the file's packets come in another order than their frames (B-frames)."""
    with av.open(str(path)) as container:
        pts = [p.pts for p in container.demux(video=0) if p.size]
    return pts != sorted(pts)
