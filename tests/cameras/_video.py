"""Test videos written with OpenCV's real MJPG writer."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt


def frame_image(k: int, width: int, height: int, color: bool) -> npt.NDArray[np.uint8]:
    """A smooth test image that differs from frame to frame (a moving dark disc)."""
    yy, xx = np.mgrid[0:height, 0:width]
    base = (120 + 60 * np.sin(xx / 17.0) * np.cos(yy / 23.0)).astype(np.float64)
    cx, cy = (10 + 7 * k) % width, height // 2
    disc = (xx - cx) ** 2 + (yy - cy) ** 2 <= (height // 4) ** 2
    base[disc] = 30.0
    gray = np.clip(base, 0, 255).astype(np.uint8)
    if not color:
        return gray
    bgr = np.stack([gray, np.roll(gray, 5, axis=1), 255 - gray], axis=2)
    return np.ascontiguousarray(bgr)


def write_avi(
    path: Path,
    n_frames: int,
    *,
    width: int = 160,
    height: int = 120,
    fps: float = 30.0,
    color: bool = True,
) -> list[npt.NDArray[np.uint8]]:
    """Write an MJPG AVI; return the images as written (before JPEG compression)."""
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (width, height), color
    )
    assert writer.isOpened()
    images = [frame_image(k, width, height, color) for k in range(n_frames)]
    for img in images:
        writer.write(img)
    writer.release()
    return images


def decode_all(path: Path) -> list[npt.NDArray[np.uint8]]:
    """Every frame as OpenCV's FFmpeg backend decodes it to BGR (the reference)."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        out.append(img)
    cap.release()
    return out


def raw_packets(path: Path) -> list[npt.NDArray[np.uint8]]:
    """Every packet as OpenCV's FFmpeg backend demuxes it, undecoded (``CAP_PROP_FORMAT``
    -1): an MJPG file's JPEGs as they are stored, one flat byte array each."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    assert cap.set(cv2.CAP_PROP_FORMAT, -1)
    out = []
    while True:
        ok, pk = cap.read()
        if not ok:
            break
        out.append(pk.reshape(-1).copy())
    cap.release()
    return out
