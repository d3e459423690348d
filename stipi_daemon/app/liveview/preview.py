"""Preview images for the view: a frame made small, the counted pixels tinted, as JPEG.

The page shows the camera frame with the pixels S_k counts tinted: those at or below the
threshold p of Eq. (1) inside the ROI (Eq. (2)). The frame is first reduced to at most
:data:`PREVIEW_MAX_WIDTH_PX` wide by taking every n-th pixel (nearest neighbour: each
shown pixel is a camera pixel, unblended, so its tint is exactly whether S_k counts it),
then tinted and encoded. This runs in a view server's worker thread, only for a frame a
viewer asked for, and never on the daemon's loop or capture thread.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["JPEG_QUALITY", "PREVIEW_MAX_WIDTH_PX", "preview_jpeg"]

#: Widest preview image [px]; larger frames are subsampled by an integer step.
PREVIEW_MAX_WIDTH_PX = 640
#: JPEG quality of preview images (0-100).
JPEG_QUALITY = 80
#: Tint of counted pixels (BGR) and how much of it covers the pixel [-].
_TINT_BGR = np.array([40, 40, 230], dtype=np.float32)
_TINT_ALPHA = 0.55


def _gray(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    if image.ndim == 2:
        return image
    code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(image.shape[2])
    if code is None:  # another layout: its first channel as luminance
        return np.ascontiguousarray(image[..., 0])
    return np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)


def _roi_mask(
    shape: tuple[int, int], step: int, roi: dict[str, Any] | None
) -> npt.NDArray[np.bool_]:
    """Which pixels of the subsampled frame lie in the ROI (camera coordinates / step)."""
    h, w = shape
    if roi is None:
        return np.ones((h, w), dtype=bool)
    ys = (np.arange(h) * step)[:, None]
    xs = (np.arange(w) * step)[None, :]
    if roi.get("kind") == "circle":
        r = float(roi["radius_px"])
        return bool_array(
            (xs - float(roi["cx_px"])) ** 2 + (ys - float(roi["cy_px"])) ** 2 <= r * r
        )
    x0, y0 = int(roi["x_px"]), int(roi["y_px"])
    x1, y1 = x0 + int(roi["width_px"]), y0 + int(roi["height_px"])
    return bool_array((xs >= x0) & (xs < x1) & (ys >= y0) & (ys < y1))


def bool_array(a: Any) -> npt.NDArray[np.bool_]:
    """``a`` as a boolean array."""
    return np.asarray(a, dtype=bool)


def preview_jpeg(
    image: npt.NDArray[np.uint8], threshold_p: int, roi: dict[str, Any] | None
) -> tuple[bytes, int]:
    """The preview JPEG of ``image`` and the subsampling step [px of camera per px shown].

    Pixels inside ``roi`` (camera coordinates; None: the whole frame) at or below
    ``threshold_p`` are tinted red.
    """
    step = max(1, math.ceil(image.shape[1] / PREVIEW_MAX_WIDTH_PX))
    small = image[::step, ::step]
    gray = _gray(small)
    counted = (gray <= threshold_p) & _roi_mask(gray.shape[:2], step, roi)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    if counted.any():
        px = bgr[counted].astype(np.float32)
        bgr[counted] = (px * (1.0 - _TINT_ALPHA) + _TINT_BGR * _TINT_ALPHA).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("the preview frame could not be encoded as JPEG")
    return bytes(buf), step
