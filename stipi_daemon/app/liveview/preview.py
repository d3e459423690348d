"""Preview images for the view: a frame made small, the counted pixels tinted, as JPEG.

The page shows the camera frame with the pixels S_k counts tinted: those at or below the
threshold p of Eq. (1) inside the ROI (Eq. (2)). The frame is first reduced to at most
:data:`PREVIEW_MAX_WIDTH_PX` wide by taking every n-th pixel (nearest neighbour: each
shown pixel is a camera pixel, unblended, so its tint is exactly whether S_k counts it),
then tinted (a few whole-image passes of OpenCV, no lookup tables: about a third of the
encoding's cost) and encoded. This runs in the view server's thread, only for a frame a viewer
asked for, and never on the daemon's loop or capture thread.
"""

from __future__ import annotations

import functools
import json
import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["JPEG_QUALITY", "PREVIEW_MAX_WIDTH_PX", "preview_jpeg"]

#: Widest preview image [px]; larger frames are subsampled by an integer step (a 1280 px
#: wide frame by 4, to 320 px: the encoding's cost goes with the pixels shown).
PREVIEW_MAX_WIDTH_PX = 320
#: JPEG quality of preview images (0-100).
JPEG_QUALITY = 60
#: Tint of counted pixels (its B and G, which are equal, and its R) [8-bit] and how much
#: of it covers the pixel [-].
_TINT_BG_R = (40, 230)
_TINT_ALPHA = 0.55


def _gray(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(image.shape[2])
    if code is None:  # another layout: its first channel as luminance
        return np.ascontiguousarray(image[..., 0])
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), code), dtype=np.uint8)


@functools.lru_cache(maxsize=4)
def _roi_mask(shape: tuple[int, int], step: int, roi_key: str) -> npt.NDArray[np.uint8]:
    """255 where a pixel of the subsampled frame lies in the ROI (``roi_key``: its JSON;
    camera coordinates, pixel ``(i, j)`` shown is camera pixel ``(i * step, j * step)``)."""
    roi = json.loads(roi_key)
    h, w = shape
    if roi is None:
        return np.full((h, w), 255, dtype=np.uint8)
    ys = (np.arange(h) * step)[:, None]
    xs = (np.arange(w) * step)[None, :]
    if roi.get("kind") == "circle":
        r = float(roi["radius_px"])
        inside = (xs - float(roi["cx_px"])) ** 2 + (ys - float(roi["cy_px"])) ** 2 <= r * r
    else:
        x0, y0 = int(roi["x_px"]), int(roi["y_px"])
        x1, y1 = x0 + int(roi["width_px"]), y0 + int(roi["height_px"])
        inside = (xs >= x0) & (xs < x1) & (ys >= y0) & (ys < y1)
    return np.where(inside, 255, 0).astype(np.uint8)


def _roi_key(roi: dict[str, Any] | None) -> str:
    return json.dumps(roi, sort_keys=True)


def preview_jpeg(
    image: npt.NDArray[np.uint8], threshold_p: int, roi: dict[str, Any] | None
) -> tuple[bytes, int]:
    """The preview JPEG of ``image`` and the subsampling step [px of camera per px shown].

    Pixels inside ``roi`` (camera coordinates; None: the whole frame) at or below
    ``threshold_p`` are tinted red.
    """
    step = max(1, math.ceil(image.shape[1] / PREVIEW_MAX_WIDTH_PX))
    gray = _gray(image[::step, ::step])
    h, w = gray.shape[:2]
    # counted: at or below p (Eq. (1), inverted) and inside the ROI (Eq. (2))
    _, below = cv2.threshold(gray, threshold_p, 255, cv2.THRESH_BINARY_INV)
    counted = cv2.bitwise_and(below, _roi_mask((h, w), step, _roi_key(roi)))
    # B and G tint alike: gray * (1 - alpha) + tint * alpha, rounded [8-bit]
    b_g, r = (
        cv2.convertScaleAbs(gray, alpha=1.0 - _TINT_ALPHA, beta=c * _TINT_ALPHA) for c in _TINT_BG_R
    )
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    cv2.copyTo(cv2.merge([b_g, b_g, r]), counted, bgr)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("the preview frame could not be encoded as JPEG")
    return bytes(buf), step
