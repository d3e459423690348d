"""The simulated camera's encoder: whether a scene's frames are JPEGs, and the JPEG itself.

This module owns the rule of docs/simulator.md ("the simulator compresses only when the
scene asks for it"): a scene is Motion-JPEG when its camera's ``pixel_format`` is ``mjpg``
or it names the ``jpeg_compression`` effect, at that effect's quality when it names it,
else at ``camera.jpeg_quality``. Every other scene's frames are raw. It also owns the one
encode and the decode of a frame (OpenCV's libjpeg: ``cv2.imencode`` at the quality,
``cv2.imdecode`` to the image's own layout, as the daemon's cameras decode an MJPG frame).
It imports no effect module (a scene without effects runs no effect code).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from stipi_daemon.sim.scene import DEFAULT_JPEG_QUALITY, Scene

__all__ = ["Encoding", "decode_jpeg", "encode_jpeg", "scene_encoding"]


@dataclass(frozen=True)
class Encoding:
    """How a scene's camera delivers its frames.

    Attributes
    ----------
    jpeg_quality : int or None
        JPEG quality [1..100] of every frame; None: raw frames (no compression).
    source : str
        What asked for it (``camera.pixel_format``, ``effects.jpeg_compression``), or
        ``raw``.
    """

    jpeg_quality: int | None
    source: str

    @property
    def is_jpeg(self) -> bool:
        """True for a Motion-JPEG scene."""
        return self.jpeg_quality is not None


def scene_encoding(scene: Scene) -> Encoding:
    """The scene's frame encoding (see the module docstring)."""
    for effect in scene.effects:
        if effect.name == "jpeg_compression":
            quality = getattr(effect, "quality", None)
            if not isinstance(quality, int):  # pragma: no cover - the effect's Params has one
                raise TypeError(f"jpeg_compression parameters without a quality: {effect!r}")
            return Encoding(quality, "effects.jpeg_compression")
    cam = scene.camera
    if cam.pixel_format == "mjpg":
        q = cam.jpeg_quality if cam.jpeg_quality is not None else DEFAULT_JPEG_QUALITY
        return Encoding(q, "camera.pixel_format")
    return Encoding(None, "raw")


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    """One frame as a baseline JPEG (BGR: YCbCr 4:2:0; gray: one component) [1..100]."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError("OpenCV failed to JPEG-encode a frame")
    return bytes(buf.tobytes())


def decode_jpeg(packet: bytes, channels: int) -> NDArray[np.uint8]:
    """The frame a JPEG decodes to: BGR ``(H, W, 3)`` for ``channels`` 3, gray ``(H, W)``
    for 1 (``cv2.imdecode``, as the daemon's MJPG cameras decode)."""
    flag = cv2.IMREAD_COLOR if channels == 3 else cv2.IMREAD_GRAYSCALE
    img = cv2.imdecode(np.frombuffer(packet, dtype=np.uint8), flag)
    if img is None:  # pragma: no cover - the packet came from encode_jpeg
        raise RuntimeError("OpenCV failed to decode a JPEG it encoded")
    out: NDArray[np.uint8] = np.asarray(img, dtype=np.uint8)
    return out
