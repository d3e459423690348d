"""Occluded-pixel counting of one camera frame: Eqs. (1)-(2) of the STIP-I paper.

This module owns the regions of interest (:class:`RectROI`, :class:`CircleROI`), the
grayscale conversion, the binary-inverted thresholding of Eq. (1), the occluded-pixel sum
S_k of Eq. (2), an optional sub-pixel estimate of the occluded area (soft threshold over
the anti-aliased disc edge), frame-quality checks (saturation, empty ROI) and the automatic
choice of the threshold p (Otsu). Its hot path, :meth:`FrameProcessor.count`, runs once per
frame at the camera rate. It does not decode video, keep time series, or convert S_k into
physical units: pitting parameters are :mod:`~stipi_daemon.analysis.pitting`'s job and the
S-to-mm/N conversion is :mod:`~stipi_daemon.analysis.calibration`'s.

Pixel and ROI conventions
-------------------------
Frames are numpy arrays in OpenCV layout: ``frame[y, x]`` (row y, column x), origin at the
top-left corner, 8-bit (``uint8``) gray ``(H, W)``, ``(H, W, 1)``, YUYV ``(H, W, 2)``, BGR
``(H, W, 3)`` or BGRA ``(H, W, 4)``. YUYV (YUY2, packed 4:2:2, bytes Y0 U0 Y1 V0 ...) is the
layout OpenCV's V4L2 backend delivers with ``CAP_PROP_CONVERT_RGB`` off: channel 0 of each
pixel is its luma Y, which is its gray value (``cv2.COLOR_YUV2GRAY_YUYV``). The gray value
of a BGR(A) pixel is ``cv2.cvtColor``'s (``COLOR_BGR2GRAY``, ``Y = 0.299 R + 0.587 G +
0.114 B`` in the fixed point of the OpenCV build, see :func:`bgr_gray_formula`). Pixel
(x, y) has its centre at integer coordinates (x, y). 16-bit frames are
rejected: the threshold p of Eq. (1) is on the 8-bit scale (0 = black, 255 = white), and
only the caller knows the sensor's bit depth (10, 12 or 16 bit) needed to rescale.

* A :class:`RectROI` covers columns ``x_px .. x_px + width_px - 1`` and rows
  ``y_px .. y_px + height_px - 1``.
* A :class:`CircleROI` covers the pixels whose centre satisfies
  ``(x - cx_px)**2 + (y - cy_px)**2 <= radius_px**2`` (evaluated in float64).

An ROI may extend beyond the frame: it is clipped to the frame and only its pixels inside
the frame are counted (flag :attr:`~stipi_daemon.analysis.flags.Flag.ROI_CLIPPED`). An ROI
with no pixel inside the frame gives S_k = 0 and flag
:attr:`~stipi_daemon.analysis.flags.Flag.EMPTY_ROI`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Annotated, Any, Final, Literal

import cv2
import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.errors import AnalysisError

_skcount: ModuleType | None
try:  # the compiled single-pass kernel (built by `pip install`; see _skcount.c)
    from stipi_daemon.analysis import _skcount as _sk_module

    _skcount = _sk_module
except ImportError:  # pragma: no cover - exercised by forcing the fallback in the tests
    _skcount = None

__all__ = [
    "DEFAULT_EDGE_WIDTH_LEVELS",
    "DEFAULT_MIN_SEPARABILITY",
    "DEFAULT_SATURATION_LIMIT_FRACTION",
    "ROI",
    "SATURATION_LEVEL",
    "BgrGrayFormula",
    "CircleROI",
    "Frame",
    "FrameMeasurement",
    "FrameProcessor",
    "RectROI",
    "bgr_gray_formula",
    "covers_frame",
    "describe_roi",
    "occluded_area_subpixel",
    "occluded_pixel_count",
    "otsu_threshold",
    "roi_from_record",
    "roi_mask",
    "same_roi",
    "sk_kernel",
    "subpixel_membership_lut",
    "threshold_binary_inverted",
    "to_gray",
    "whole_frame_roi",
]

GrayImage = npt.NDArray[np.uint8]
"""2-D ``uint8`` image, values 0 (black) .. 255 (white)."""

Frame = npt.NDArray[Any]
"""A camera frame as accepted by this module's functions (layout checked at run time)."""

SATURATION_LEVEL: Final = 255
"""Gray value [8-bit] at which a pixel counts as saturated (clipped at the sensor maximum)."""

DEFAULT_SATURATION_LIMIT_FRACTION: Final = 0.01
"""Default fraction [1] of ROI pixels at :data:`SATURATION_LEVEL` above which a frame is
flagged :attr:`~Flag.SATURATED_FRAME`. A correctly exposed probe image has essentially no
clipped pixels; 1 % leaves room for specular highlights at the LEDs."""

DEFAULT_MIN_SEPARABILITY: Final = 0.8
"""Default minimum Otsu separability [1] (between-class over total variance) accepted by
:func:`otsu_threshold`. A unimodal Gaussian histogram scores 2/pi = 0.64 and a flat one 0.75;
two well separated intensity levels score close to 1."""

DEFAULT_EDGE_WIDTH_LEVELS: Final = 64.0
"""Default width w [8-bit levels] of the soft threshold of :func:`occluded_area_subpixel`:
the gray-level change across one pixel at the disc edge. 64 levels suits an edge whose
intensity ramps by about 64 levels per pixel (the simulator's 130-level contrast over a 2 px
ramp); for an edge sharper than a pixel, use the dark-to-bright contrast instead."""

_UINT8: Final = np.dtype(np.uint8)

_SUBPIXEL_SCALE: Final = 65535
"""Fixed-point scale of the membership look-up table (uint16; 1/65535 per pixel)."""


def sk_kernel() -> str:
    """Name of the routine that counts S_k in :class:`FrameProcessor` (recorded per session).

    ``"avx2"``, ``"sse2"`` or ``"c"``: the compiled single-pass kernel of
    ``stipi_daemon/analysis/_skcount.c`` (the best one the CPU runs), which reads each pixel
    once, computing the gray value of YUYV and BGR pixels on the fly. ``"opencv"``: the
    extension was not built (no C compiler at install time), and S_k is counted with
    ``cv2.cvtColor`` (colour frames) + ``cv2.threshold`` + ``cv2.countNonZero`` (two or
    three passes, about 2-3x slower on raw frames). All give identical counts.
    """
    return "opencv" if _skcount is None else str(_skcount.kernel())


@dataclass(frozen=True)
class BgrGrayFormula:
    """The fixed-point BGR -> gray formula of ``cv2.cvtColor(COLOR_BGR2GRAY)`` on 8-bit pixels.

    ``Y = (cb * B + cg * G + cr * R + d) >> s`` (integers; ``cb + cg + cr == 2**s``, so
    white stays 255).

    Attributes
    ----------
    name : str
        Which implementation uses it: ``"opencv"`` (OpenCV's own code, ``cv::RGB2Gray<uchar>``
        in ``imgproc/src/color_rgb.simd.hpp``: weights 1868, 9617, 4899 = 0.114, 0.587,
        0.299 x 2**14, rounding term 2**13) or ``"ipp"`` (builds with the Intel IPP HAL, whose
        ``ippiColorToGray_8u_C3C1R`` computes 3735, 19235, 9798 = 0.114, 0.587, 0.299 x
        2**15 with the blue weight rounded down so that they sum to 2**15, rounding term
        2**14; identified on all 2**24 BGR values against ``cv2.cvtColor``).
    weights : tuple of int
        ``(cb, cg, cr, d, s)`` as the compiled kernel takes them (``bgr_weights``).
    """

    name: str
    weights: tuple[int, int, int, int, int]


_BGR_GRAY_FORMULAS: Final = (
    BgrGrayFormula("ipp", (3735, 19235, 9798, 16384, 15)),
    BgrGrayFormula("opencv", (1868, 9617, 4899, 8192, 14)),
)
_bgr_formula_cache: dict[bool, BgrGrayFormula | None] = {}


def bgr_gray_formula() -> BgrGrayFormula | None:
    """The formula ``cv2.cvtColor(COLOR_BGR2GRAY)`` computes on this OpenCV build, or None.

    S_k of a BGR frame counts pixels by their gray value, so the compiled kernel, which
    computes that value on the fly, must round exactly as ``cv2.cvtColor`` does; which
    fixed point that is depends on how OpenCV was built (its own code, or the Intel IPP HAL
    on x86 builds with IPP; an ARM HAL may differ again). This checks each known formula
    (:class:`BgrGrayFormula`) against ``cv2.cvtColor`` on all 2**24 BGR values (in 256
    blocks of 256 x 256 pixels, about 0.1 s once per process and IPP setting) and on a few
    narrow images, and returns the one that equals it on every value. None when no known
    formula does: :class:`FrameProcessor` then converts BGR frames with ``cv2.cvtColor``
    before counting (slower, never different).
    """
    ipp = getattr(cv2, "ipp", None)  # switching IPP off may change the formula
    key = bool(ipp.useIPP()) if ipp is not None else False
    if key not in _bgr_formula_cache:
        _bgr_formula_cache[key] = _identify_bgr_formula()
    return _bgr_formula_cache[key]


def _identify_bgr_formula() -> BgrGrayFormula | None:
    bg = np.empty((256, 256, 3), dtype=np.uint8)
    bg[:, :, 0] = np.arange(256, dtype=np.uint8)[None, :]
    bg[:, :, 1] = np.arange(256, dtype=np.uint8)[:, None]
    b, g = bg[:, :, 0].astype(np.int32), bg[:, :, 1].astype(np.int32)
    alive = {f.name: f for f in _BGR_GRAY_FORMULAS}
    partial = {f.name: f.weights[0] * b + f.weights[1] * g for f in _BGR_GRAY_FORMULAS}
    for r in range(256):
        bg[:, :, 2] = r
        got = cv2.cvtColor(bg, cv2.COLOR_BGR2GRAY)
        for name, f in list(alive.items()):
            cb, cg, cr, d, s = f.weights
            if not np.array_equal(got, (partial[name] + (cr * r + d)) >> s):
                del alive[name]
        if not alive:
            return None
    # Narrow images and crops (OpenCV may take another code path for them), on the values
    # where the known formulas disagree.
    rng = np.random.default_rng(0)
    probe = rng.integers(0, 256, size=(4096, 3), dtype=np.uint8)
    for f in list(alive.values()):
        for h, w in ((1, 1), (1, 7), (3, 33), (5, 17)):
            img = probe[: h * (w + 2)].reshape(h, w + 2, 3)[:, 1 : w + 1]
            px = img.astype(np.int32)
            cb, cg, cr, d, s = f.weights
            want = (cb * px[:, :, 0] + cg * px[:, :, 1] + cr * px[:, :, 2] + d) >> s
            if not np.array_equal(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), want):
                del alive[f.name]
                break
    return next(iter(alive.values()), None)


# --------------------------------------------------------------------------------------------
# Regions of interest
# --------------------------------------------------------------------------------------------


class RectROI(BaseModel):
    """Axis-aligned rectangular region of interest (the paper's m x n window, Eq. (2)).

    Attributes
    ----------
    kind : "rect"
        Discriminator for :data:`ROI`.
    x_px, y_px : int
        Column and row of the top-left pixel [px]; may be negative (ROI clipped to the frame).
    width_px, height_px : int
        Size [px], > 0.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    kind: Literal["rect"] = "rect"
    x_px: int
    y_px: int
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)


class CircleROI(BaseModel):
    """Circular region of interest around the light-occlusion disc (Fig. 5 (a)).

    Attributes
    ----------
    kind : "circle"
        Discriminator for :data:`ROI`.
    cx_px, cy_px : float
        Centre column and row [px]; integers are pixel centres; may lie outside the frame.
    radius_px : float
        Radius [px], > 0. Pixels whose centre is within ``radius_px`` of the centre belong
        to the ROI.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    kind: Literal["circle"] = "circle"
    cx_px: float
    cy_px: float
    radius_px: float = Field(gt=0)


ROI = Annotated[RectROI | CircleROI, Field(discriminator="kind")]
"""Either ROI shape; the ``kind`` field selects it when loading from a config file."""

_ROI_ADAPTER: Final = TypeAdapter[RectROI | CircleROI](ROI)


def roi_from_record(value: Any) -> RectROI | CircleROI | None:
    """The ROI a file records as the config's ``imaging.roi`` does (``{"kind": "circle",
    "cx_px": ..., ...}``; None: none).

    Raises
    ------
    ValueError
        The value is not a valid ROI (pydantic's first complaint).
    """
    if value is None:
        return None
    try:
        roi: RectROI | CircleROI = _ROI_ADAPTER.validate_python(value)
    except ValidationError as exc:
        raise ValueError(f"not a valid ROI: {exc.errors()[0]['msg']}") from None
    return roi


def whole_frame_roi(frame_size_px: tuple[int, int]) -> RectROI:
    """The whole ``(width, height)`` [px] frame as an ROI: the rect a calibration records
    for S counted in the whole frame (``calibrate --roi full``)."""
    width, height = frame_size_px
    return RectROI(kind="rect", x_px=0, y_px=0, width_px=int(width), height_px=int(height))


def covers_frame(roi: RectROI | CircleROI | None, frame_size_px: tuple[int, int]) -> bool:
    """Whether ``roi`` [px] (None: the whole frame) holds every pixel of a ``(width,
    height)`` [px] frame, so that S counted in it is S of the whole frame."""
    if roi is None:
        return True
    width, height = frame_size_px
    if isinstance(roi, RectROI):
        return (
            roi.x_px <= 0
            and roi.y_px <= 0
            and roi.x_px + roi.width_px >= width
            and roi.y_px + roi.height_px >= height
        )
    # the farthest pixel centre, by the mask's own test (module docstring)
    far_x = max(abs(roi.cx_px), abs(width - 1 - roi.cx_px))
    far_y = max(abs(roi.cy_px), abs(height - 1 - roi.cy_px))
    return far_x * far_x + far_y * far_y <= roi.radius_px * roi.radius_px


def same_roi(
    a: RectROI | CircleROI | None,
    b: RectROI | CircleROI | None,
    frame_size_px: tuple[int, int] | None,
) -> bool:
    """Whether S counted in ROI ``a`` and in ROI ``b`` [px] (None: the whole frame) count
    the same pixels: the same ROI, or, in frames of ``frame_size_px`` (None: unknown), two
    that both hold the whole frame."""
    if a == b:
        return True
    return frame_size_px is not None and all(covers_frame(x, frame_size_px) for x in (a, b))


def describe_roi(roi: RectROI | CircleROI | None) -> str:
    """The ROI in words for messages: ``circle centre (x, y) r R px``, ``rect at (x, y)
    size WxH px`` or, for None, ``the whole frame``."""
    if roi is None:
        return "the whole frame"
    if isinstance(roi, CircleROI):
        return f"circle centre ({roi.cx_px:g}, {roi.cy_px:g}) r {roi.radius_px:g} px"
    return f"rect at ({roi.x_px}, {roi.y_px}) size {roi.width_px}x{roi.height_px} px"


# --------------------------------------------------------------------------------------------
# Frame validation and grayscale conversion
# --------------------------------------------------------------------------------------------

_SUPPORTED_LAYOUTS = (
    "uint8 gray (H, W) or (H, W, 1), YUYV (H, W, 2), BGR (H, W, 3) or BGRA (H, W, 4)"
)


def _check_frame_layout(shape: tuple[int, ...], dtype: np.dtype[np.generic]) -> int | None:
    """Validate a frame's shape and dtype; return the cvtColor code (None for gray).

    Raises
    ------
    AnalysisError
        For any dtype other than uint8, a dimension other than 2 or 3, a channel count other
        than 1, 2, 3 or 4, or an empty frame.
    """
    if dtype != np.uint8:
        if dtype == np.uint16:
            raise AnalysisError(
                "frame dtype uint16 is not accepted: the threshold p of Eq. (1) is on the "
                "8-bit scale 0..255; rescale with the sensor's bit depth first, e.g. "
                "(frame >> (bits - 8)).astype(np.uint8)"
            )
        raise AnalysisError(f"frame dtype {dtype} is not supported; expected {_SUPPORTED_LAYOUTS}")
    if len(shape) == 2:
        code = None
    elif len(shape) == 3 and shape[2] == 1:
        code = None
    elif len(shape) == 3 and shape[2] == 2:
        code = cv2.COLOR_YUV2GRAY_YUYV
    elif len(shape) == 3 and shape[2] == 3:
        code = cv2.COLOR_BGR2GRAY
    elif len(shape) == 3 and shape[2] == 4:
        code = cv2.COLOR_BGRA2GRAY
    else:
        raise AnalysisError(f"frame shape {shape} is not supported; expected {_SUPPORTED_LAYOUTS}")
    if shape[0] == 0 or shape[1] == 0:
        raise AnalysisError(f"frame shape {shape} is empty (zero rows or columns)")
    return code


def _as_gray(image: npt.NDArray[np.uint8], code: int | None) -> GrayImage:
    if code is None:
        return image if image.ndim == 2 else image[:, :, 0]
    return np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)


def to_gray(frame: Frame) -> GrayImage:
    """Convert a camera frame to an 8-bit grayscale image (Section III.A).

    Parameters
    ----------
    frame : numpy.ndarray
        uint8 gray ``(H, W)`` or ``(H, W, 1)`` (returned as a 2-D view, not copied),
        YUYV ``(H, W, 2)`` (its Y bytes), BGR ``(H, W, 3)`` or BGRA ``(H, W, 4)``
        (converted with OpenCV's ``Y = 0.299 R + 0.587 G + 0.114 B``, alpha ignored).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` uint8 gray image [8-bit intensity].

    Raises
    ------
    AnalysisError
        For any other dtype (uint16 included, see the module docstring) or shape.
    """
    if not isinstance(frame, np.ndarray):
        raise AnalysisError(f"frame must be a numpy array, got {type(frame).__name__}")
    code = _check_frame_layout(frame.shape, frame.dtype)
    return _as_gray(frame.view(np.uint8), code)


def _check_threshold(p: object) -> int:
    if isinstance(p, bool) or not isinstance(p, int | np.integer):
        raise AnalysisError(f"threshold p must be an integer 0..255, got {p!r}")
    if not 0 <= int(p) <= 255:
        raise AnalysisError(f"threshold p must be in 0..255, got {int(p)}")
    return int(p)


def _check_edge_width(edge_width_levels: object) -> float:
    if isinstance(edge_width_levels, bool) or not isinstance(
        edge_width_levels, int | float | np.integer | np.floating
    ):
        raise AnalysisError(
            f"edge_width_levels must be a number in (0, 255], got {edge_width_levels!r}"
        )
    w = float(edge_width_levels)
    if not (math.isfinite(w) and 0.0 < w <= 255.0):
        raise AnalysisError(f"edge_width_levels must be in (0, 255] gray levels, got {w}")
    return w


def subpixel_membership_lut(
    p: int, edge_width_levels: float = DEFAULT_EDGE_WIDTH_LEVELS
) -> npt.NDArray[np.float64]:
    """Soft occlusion membership of each gray level, for :func:`occluded_area_subpixel`.

    ``m(I) = clip((p + 0.5 - I) / w + 0.5, 0, 1)``: 1 for pixels well below the threshold
    (fully occluded), 0 well above it (lit), linear across a band of ``w`` levels centred on
    ``p + 0.5``, the midpoint between the last occluded (``<= p``) and the first lit level of
    Eq. (1). Where the disc edge crosses a pixel, its intensity lies between the occluded and
    the lit level in proportion to the area it covers, so ``m`` reads that coverage back.
    For ``w <= 1`` the membership is Eq. (1)'s binary 0/1.

    Parameters
    ----------
    p : int
        Threshold of Eq. (1) [8-bit intensity], 0..255.
    edge_width_levels : float
        Width w of the linear band [8-bit levels], in (0, 255]: the gray-level change across
        one pixel at the edge (the edge gradient [levels/px] for an edge ramp wider than a
        pixel, the dark-to-bright contrast for an edge sharper than a pixel).

    Returns
    -------
    numpy.ndarray
        float64 array of 256 memberships in [0, 1] [1], indexed by gray level.

    Raises
    ------
    AnalysisError
        ``p`` not an integer in 0..255, or ``edge_width_levels`` outside (0, 255] or NaN.
    """
    p_int = _check_threshold(p)
    w = _check_edge_width(edge_width_levels)
    levels = np.arange(256, dtype=np.float64)
    lut: npt.NDArray[np.float64] = np.clip((p_int + 0.5 - levels) / w + 0.5, 0.0, 1.0)
    return lut


def threshold_binary_inverted(gray: Frame, p: int) -> GrayImage:
    """Binary-inverted thresholding, Eq. (1).

    ``I_seg = 0`` where ``I_g > p`` and ``I_seg = 1`` otherwise, i.e. pixels at or below the
    threshold (dark, light-occluded) are 1.

    Parameters
    ----------
    gray : numpy.ndarray
        2-D uint8 grayscale image I_g [8-bit intensity].
    p : int
        Threshold [8-bit intensity], 0..255. p = 255 marks every pixel; p = 0 marks only
        pixels of value 0.

    Returns
    -------
    numpy.ndarray
        uint8 image of the same shape holding 0 or 1.

    Raises
    ------
    AnalysisError
        If ``gray`` is not a non-empty 2-D uint8 array or ``p`` is not an integer in 0..255.
    """
    p_int = _check_threshold(p)
    if not isinstance(gray, np.ndarray) or gray.ndim != 2:
        shape = getattr(gray, "shape", None)
        raise AnalysisError(f"gray image must be a 2-D uint8 array, got shape {shape}")
    _check_frame_layout(gray.shape, gray.dtype)
    _, binary = cv2.threshold(gray.view(np.uint8), p_int, 1, cv2.THRESH_BINARY_INV)
    return np.asarray(binary, dtype=np.uint8)


# --------------------------------------------------------------------------------------------
# ROI geometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _RoiGeometry:
    """An ROI clipped to a frame: bounding box (half-open) and optional mask inside it."""

    y0: int
    y1: int
    x0: int
    x1: int
    mask: npt.NDArray[np.uint8] | None  # 0/1 over the bounding box; None = whole box
    pixel_count: int
    clipped: bool

    @property
    def empty(self) -> bool:
        return self.pixel_count == 0


def _roi_geometry(height: int, width: int, roi: RectROI | CircleROI | None) -> _RoiGeometry:
    if roi is None:
        return _RoiGeometry(0, height, 0, width, None, height * width, False)
    if isinstance(roi, RectROI):
        x0, y0 = max(roi.x_px, 0), max(roi.y_px, 0)
        x1, y1 = min(roi.x_px + roi.width_px, width), min(roi.y_px + roi.height_px, height)
        if x0 >= x1 or y0 >= y1:
            return _RoiGeometry(0, 0, 0, 0, None, 0, True)
        clipped = (x1 - x0, y1 - y0) != (roi.width_px, roi.height_px)
        return _RoiGeometry(y0, y1, x0, x1, None, (x1 - x0) * (y1 - y0), clipped)
    if isinstance(roi, CircleROI):
        return _circle_geometry(height, width, roi)
    raise AnalysisError(f"roi must be a RectROI, a CircleROI or None, got {type(roi).__name__}")


def _circle_membership(
    ys: npt.NDArray[np.float64], xs: npt.NDArray[np.float64], roi: CircleROI
) -> npt.NDArray[np.bool_]:
    """The definition of circle membership (module docstring), on pixel-centre grids."""
    dy = ys[:, None] - roi.cy_px
    dx = xs[None, :] - roi.cx_px
    inside: npt.NDArray[np.bool_] = dx * dx + dy * dy <= roi.radius_px * roi.radius_px
    return inside


def _circle_geometry(height: int, width: int, roi: CircleROI) -> _RoiGeometry:
    r = roi.radius_px
    # Unclipped bounding box, widened by one pixel against rounding of cy +- r; the exact
    # membership test below decides, then the box is trimmed to the member pixels.
    full_y0, full_y1 = math.floor(roi.cy_px - r) - 1, math.ceil(roi.cy_px + r) + 2
    full_x0, full_x1 = math.floor(roi.cx_px - r) - 1, math.ceil(roi.cx_px + r) + 2
    y0, y1 = max(full_y0, 0), min(full_y1, height)
    x0, x1 = max(full_x0, 0), min(full_x1, width)
    if y0 >= y1 or x0 >= x1:
        return _RoiGeometry(0, 0, 0, 0, None, 0, True)
    inside = _circle_membership(
        np.arange(y0, y1, dtype=np.float64), np.arange(x0, x1, dtype=np.float64), roi
    )
    rows = np.flatnonzero(inside.any(axis=1))
    cols = np.flatnonzero(inside.any(axis=0))
    if rows.size == 0:
        return _RoiGeometry(0, 0, 0, 0, None, 0, True)
    inside = inside[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    by0, by1 = y0 + int(rows[0]), y0 + int(rows[-1]) + 1
    bx0, bx1 = x0 + int(cols[0]), x0 + int(cols[-1]) + 1
    # Clipped if any member pixel centre of the whole (unclipped) disc lies outside the frame.
    clipped = False
    if full_y0 < 0 or full_x0 < 0 or full_y1 > height or full_x1 > width:
        whole = _circle_membership(
            np.arange(full_y0, full_y1, dtype=np.float64),
            np.arange(full_x0, full_x1, dtype=np.float64),
            roi,
        )
        clipped = int(np.count_nonzero(whole)) != int(np.count_nonzero(inside))
    mask = np.ascontiguousarray(inside, dtype=np.uint8)
    return _RoiGeometry(by0, by1, bx0, bx1, mask, int(np.count_nonzero(mask)), clipped)


def roi_mask(
    frame_shape: tuple[int, ...], roi: RectROI | CircleROI | None
) -> npt.NDArray[np.bool_]:
    """Boolean ``(H, W)`` mask of the frame pixels that belong to ``roi`` (clipped).

    Parameters
    ----------
    frame_shape : tuple of int
        Frame shape ``(H, W)`` or ``(H, W, C)``; see :func:`to_gray` for accepted layouts.
    roi : RectROI or CircleROI or None
        Region of interest; None selects the whole frame.

    Returns
    -------
    numpy.ndarray
        bool array, True inside the ROI. Meant for overlays and checks, not the hot path.
    """
    _check_frame_layout(tuple(frame_shape), np.dtype(np.uint8))
    height, width = int(frame_shape[0]), int(frame_shape[1])
    geo = _roi_geometry(height, width, roi)
    out = np.zeros((height, width), dtype=np.bool_)
    if geo.empty:
        return out
    out[geo.y0 : geo.y1, geo.x0 : geo.x1] = True if geo.mask is None else geo.mask.astype(bool)
    return out


# --------------------------------------------------------------------------------------------
# Frame processor (hot path)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameMeasurement:
    """S_k of one frame with its quality information.

    Attributes
    ----------
    s_k_px : int
        Occluded pixel count S_k, Eq. (2) [px].
    saturated_fraction : float
        Fraction of ROI pixels at gray level :data:`SATURATION_LEVEL` [1]; 0 for an empty ROI.
    flags : frozenset of Flag
        :attr:`~Flag.SATURATED_FRAME`, :attr:`~Flag.EMPTY_ROI` and/or
        :attr:`~Flag.ROI_CLIPPED`.
    """

    s_k_px: int
    saturated_fraction: float
    flags: frozenset[Flag]


class FrameProcessor:
    """Computes S_k (Eq. (2)) of frames of one fixed shape, ROI and threshold.

    Everything that does not depend on the pixel values (ROI clipping, bounding box, the
    circle's per-row column spans, scratch buffers) is computed once here, so :meth:`count`
    only crops (a view) and counts the pixels ``<= p`` of each ROI row in one read-only pass
    (the compiled kernel named by :func:`sk_kernel`); :meth:`measure` counts the saturated
    pixels in the same pass. The kernel computes the gray value of YUYV and BGR pixels on the
    fly in that pass (BGR with :func:`bgr_gray_formula`, bit for bit ``cv2.cvtColor``'s);
    BGRA frames, and BGR frames on an OpenCV build whose formula is not known, are first
    converted with ``cv2.cvtColor`` into a preallocated buffer (:attr:`counts_on_the_fly`
    tells which). Where the kernel is not built, the processor converts colour crops with
    ``cv2.cvtColor``, thresholds with ``cv2.threshold(THRESH_BINARY_INV, maxval=1)`` into a
    preallocated buffer, masks a circular ROI (``cv2.bitwise_and``) and counts with
    ``cv2.countNonZero``; the saturation check then first reads the crop's maximum
    (``cv2.minMaxLoc``). All routes give identical results.

    Parameters
    ----------
    frame_shape : tuple of int
        Shape of every frame to be processed: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 2)``
        (YUYV), ``(H, W, 3)`` (BGR) or ``(H, W, 4)`` (BGRA); frames must be uint8.
    p : int
        Threshold of Eq. (1) [8-bit intensity], 0..255.
    roi : RectROI or CircleROI or None
        Region of interest; None counts the whole frame. Clipped to the frame.
    saturation_limit_fraction : float
        Fraction [1] of ROI pixels at :data:`SATURATION_LEVEL` above which :meth:`measure`
        flags :attr:`~Flag.SATURATED_FRAME`; in [0, 1].
    edge_width_levels : float
        Width of the soft threshold of :meth:`occluded_area_subpixel` [8-bit levels], in
        (0, 255]; see :func:`subpixel_membership_lut`. Not used by :meth:`count`.

    Raises
    ------
    AnalysisError
        For an unsupported frame layout, a threshold outside 0..255 or a bad limit.

    Notes
    -----
    The processor keeps scratch buffers, so one instance must not be used from several
    threads at once. Create one per thread.
    """

    def __init__(
        self,
        frame_shape: tuple[int, ...],
        p: int,
        roi: RectROI | CircleROI | None = None,
        *,
        saturation_limit_fraction: float = DEFAULT_SATURATION_LIMIT_FRACTION,
        edge_width_levels: float = DEFAULT_EDGE_WIDTH_LEVELS,
    ) -> None:
        shape = tuple(int(n) for n in frame_shape)
        self._code = _check_frame_layout(shape, np.dtype(np.uint8))
        self._p = _check_threshold(p)
        limit = float(saturation_limit_fraction)
        if not 0.0 <= limit <= 1.0:
            raise AnalysisError(
                f"saturation_limit_fraction must be in [0, 1], got {saturation_limit_fraction!r}"
            )
        self._saturation_limit = limit
        self._edge_width = _check_edge_width(edge_width_levels)
        # Buffers of the sub-pixel area, allocated on first use (most users never call it).
        self._soft_lut: npt.NDArray[np.uint16] | None = None
        self._soft_mask: npt.NDArray[np.uint16] | None = None
        self._soft_buf: npt.NDArray[np.uint16] | None = None
        self._shape = shape
        self._roi = roi
        self._geo = _roi_geometry(shape[0], shape[1], roi)
        box = (self._geo.y1 - self._geo.y0, self._geo.x1 - self._geo.x0)
        self._gray_buf = np.empty(box, dtype=np.uint8)
        self._bin_buf = np.empty(box, dtype=np.uint8)
        self._mask = self._geo.mask
        self._sk: ModuleType | None = _skcount
        self._spans = None if self._mask is None else _row_spans(self._mask)
        # The kernel counts gray and YUYV crops as they are, BGR with the gray formula of
        # this OpenCV build; everything else is converted to gray first (self._code).
        self._bgr_weights: tuple[int, int, int, int, int] | None = None
        channels = shape[2] if len(shape) == 3 else 1
        g = self._geo
        self._crop_index: tuple[slice | int, ...] = (slice(g.y0, g.y1), slice(g.x0, g.x1))
        if len(shape) == 3 and channels == 1:
            self._crop_index += (0,)
        self._on_the_fly = self._sk is not None and channels in (1, 2)
        if self._sk is not None and channels == 3:
            formula = bgr_gray_formula()
            if formula is not None:
                self._bgr_weights = formula.weights
                self._on_the_fly = True
        # An empty ROI is reported as EMPTY_ROI alone; ROI_CLIPPED means "partly outside".
        if self._geo.empty:
            self._static_flags = frozenset({Flag.EMPTY_ROI})
        elif self._geo.clipped:
            self._static_flags = frozenset({Flag.ROI_CLIPPED})
        else:
            self._static_flags = frozenset()

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Shape every processed frame must have."""
        return self._shape

    @property
    def p(self) -> int:
        """Threshold of Eq. (1) [8-bit intensity]."""
        return self._p

    @property
    def row_spans(self) -> npt.NDArray[np.int32] | None:
        """Column span ``[x0, x1)`` of each row of the bounding box that the ROI covers
        (int32, shape ``(rows, 2)``, relative to the box; a copy), or None when the ROI is
        the whole box. The bytes of these pixels are all that :meth:`count` reads."""
        return None if self._spans is None else self._spans.copy()

    @property
    def counts_on_the_fly(self) -> bool:
        """True when :meth:`count` and :meth:`measure` read the frame's pixels once, gray
        values computed in the counting pass; False when the crop is first converted to gray
        (``cv2.cvtColor``: BGRA, BGR without a known formula, or no compiled kernel)."""
        return self._on_the_fly

    @property
    def roi(self) -> RectROI | CircleROI | None:
        """The ROI as configured (before clipping)."""
        return self._roi

    @property
    def roi_pixel_count(self) -> int:
        """Number of frame pixels inside the clipped ROI [px]; the largest possible S_k."""
        return self._geo.pixel_count

    @property
    def roi_is_empty(self) -> bool:
        """True when no frame pixel lies in the ROI (every S_k is 0, flag EMPTY_ROI)."""
        return self._geo.empty

    @property
    def roi_is_clipped(self) -> bool:
        """True when part of the ROI lies outside the frame (also True for an empty ROI)."""
        return self._geo.clipped

    @property
    def bounding_box(self) -> tuple[int, int, int, int]:
        """Clipped ROI bounding box ``(y0, y1, x0, x1)``, half-open [px]."""
        g = self._geo
        return g.y0, g.y1, g.x0, g.x1

    def _count_crop(self, frame: Frame) -> npt.NDArray[np.uint8]:
        """The ROI crop as the counting routine takes it: the frame's own pixels (a view)
        when the kernel counts this layout on the fly, else the crop converted to gray."""
        if self._on_the_fly:  # the hot path: checks and a view, nothing else
            if not (
                isinstance(frame, np.ndarray)
                and frame.shape == self._shape
                and frame.dtype == _UINT8
            ):
                self._check_frame(frame)
            if self._geo.empty:
                return self._gray_buf
            crop: npt.NDArray[np.uint8] = frame[self._crop_index]
            return crop if frame.flags.c_contiguous else _row_contiguous(crop)
        return _row_contiguous(self._gray_crop(frame))

    def _check_frame(self, frame: Frame) -> None:
        if not isinstance(frame, np.ndarray):
            raise AnalysisError(f"frame must be a numpy array, got {type(frame).__name__}")
        if frame.shape != self._shape or frame.dtype != np.uint8:
            raise AnalysisError(
                f"frame has shape {frame.shape} and dtype {frame.dtype}; this processor was "
                f"built for shape {self._shape} and dtype uint8"
            )

    def _gray_crop(self, frame: Frame) -> GrayImage:
        self._check_frame(frame)
        g = self._geo
        if g.empty:
            return self._gray_buf
        crop = frame[g.y0 : g.y1, g.x0 : g.x1]
        if self._code is None:
            return crop if crop.ndim == 2 else crop[:, :, 0]
        cv2.cvtColor(crop, self._code, dst=self._gray_buf)
        return self._gray_buf

    def _count_le(self, crop: npt.NDArray[np.uint8]) -> int:
        """Pixels of the ROI crop (see :meth:`_count_crop`) with gray value <= p,
        Eqs. (1)-(2) [px]."""
        if self._sk is not None:
            return int(self._sk.count_le(crop, self._p, self._spans, self._bgr_weights))
        return self._count_where(crop, self._p, cv2.THRESH_BINARY_INV)

    def _count_le_and_saturated(self, crop: npt.NDArray[np.uint8]) -> tuple[int, int]:
        """(gray <= p, gray == 255) pixels of the ROI crop [px], in one pass."""
        if self._sk is not None:
            s_k, n_sat = self._sk.count_le_and_saturated(
                crop, self._p, self._spans, self._bgr_weights
            )
            return int(s_k), int(n_sat)
        return self._count_where(crop, self._p, cv2.THRESH_BINARY_INV), self._saturated_count(crop)

    def _count_where(self, gray: GrayImage, thresh: int, kind: int) -> int:
        cv2.threshold(gray, thresh, 1, kind, dst=self._bin_buf)
        if self._mask is not None:
            cv2.bitwise_and(self._bin_buf, self._mask, dst=self._bin_buf)
        return int(cv2.countNonZero(self._bin_buf))

    def _saturated_count(self, crop: npt.NDArray[np.uint8]) -> int:
        if self._sk is not None:
            return self._count_le_and_saturated(crop)[1]
        gray = crop
        # OpenCV route, read-only early exit: with no 255 anywhere in the ROI's bounding box
        # (the usual, correctly exposed frame) no ROI pixel is saturated; this skips a
        # threshold pass that writes a buffer and a count that re-reads it.
        if cv2.minMaxLoc(gray)[1] < SATURATION_LEVEL:
            return 0
        return self._count_where(gray, SATURATION_LEVEL - 1, cv2.THRESH_BINARY)

    def count(self, frame: Frame) -> int:
        """Occluded pixel count S_k of one frame, Eqs. (1)-(2) [px].

        Parameters
        ----------
        frame : numpy.ndarray
            uint8 frame of :attr:`frame_shape`.

        Returns
        -------
        int
            Number of ROI pixels with gray value <= p; 0 for an empty ROI.

        Raises
        ------
        AnalysisError
            If the frame's shape or dtype differs from the processor's.
        """
        crop = self._count_crop(frame)
        if self._geo.empty:
            return 0
        return self._count_le(crop)

    def occluded_area_subpixel(self, frame: Frame) -> float:
        """Occluded area with sub-pixel edges [px]: the sum of soft memberships over the ROI.

        Each ROI pixel contributes ``m(I)`` of :func:`subpixel_membership_lut` (threshold
        :attr:`p`, the processor's ``edge_width_levels``) instead of Eq. (1)'s 0 or 1, so a
        pixel the disc edge half covers counts about one half. Pixels darker than
        ``p + 0.5 - w/2`` count 1 and brighter than ``p + 0.5 + w/2`` count 0: on a frame
        with no level inside that band the result equals :meth:`count` exactly. On an
        anti-aliased (or downsampled) edge it follows the covered area continuously where
        the binary count steps with the pixel lattice. Memberships are applied in 16-bit
        fixed point (resolution 1/65535 per pixel); ``cv2.LUT`` + ``cv2.sumElems``.

        Parameters
        ----------
        frame : numpy.ndarray
            uint8 frame of :attr:`frame_shape`.

        Returns
        -------
        float
            Area [px], in [0, :attr:`roi_pixel_count`]; 0.0 for an empty ROI.

        Raises
        ------
        AnalysisError
            If the frame's shape or dtype differs from the processor's.
        """
        gray = self._gray_crop(frame)
        if self._geo.empty:
            return 0.0
        if self._soft_lut is None:
            lut = subpixel_membership_lut(self._p, self._edge_width)
            self._soft_lut = np.rint(lut * _SUBPIXEL_SCALE).astype(np.uint16).reshape(1, 256)
            self._soft_buf = np.empty(self._bin_buf.shape, dtype=np.uint16)
            if self._mask is not None:
                self._soft_mask = self._mask.astype(np.uint16) * np.uint16(_SUBPIXEL_SCALE)
        buf = self._soft_buf
        assert buf is not None
        cv2.LUT(gray, self._soft_lut, dst=buf)
        if self._soft_mask is not None:
            cv2.bitwise_and(buf, self._soft_mask, dst=buf)
        return float(cv2.sumElems(buf)[0]) / _SUBPIXEL_SCALE

    def saturated_pixel_count(self, frame: Frame) -> int:
        """Number of ROI pixels whose gray value is :data:`SATURATION_LEVEL` (255) [px]."""
        crop = self._count_crop(frame)
        if self._geo.empty:
            return 0
        return self._saturated_count(crop)

    def saturation_fraction(self, frame: Frame) -> float:
        """Fraction of ROI pixels at gray value 255 [1]; 0.0 for an empty ROI.

        A pixel is saturated when its gray value (after BGR -> gray conversion) equals 255,
        the 8-bit ceiling: its true brightness is unknown, and an over-exposed frame shrinks
        the dark, light-occluded area, so S_k may be biased low.
        """
        if self._geo.empty:
            self._check_frame(frame)
            return 0.0
        return self.saturated_pixel_count(frame) / self._geo.pixel_count

    def measure(self, frame: Frame) -> FrameMeasurement:
        """S_k of one frame with its saturation fraction and quality flags.

        Flags: :attr:`~Flag.SATURATED_FRAME` when the saturated fraction exceeds the
        processor's ``saturation_limit_fraction``; :attr:`~Flag.EMPTY_ROI` and
        :attr:`~Flag.ROI_CLIPPED` from the ROI geometry.
        """
        crop = self._count_crop(frame)
        if self._geo.empty:
            return FrameMeasurement(0, 0.0, self._static_flags)
        s_k, n_sat = self._count_le_and_saturated(crop)
        fraction = n_sat / self._geo.pixel_count
        flags = self._static_flags
        if fraction > self._saturation_limit:
            flags = flags | {Flag.SATURATED_FRAME}
        return FrameMeasurement(s_k, fraction, flags)


def _row_spans(mask: npt.NDArray[np.uint8]) -> npt.NDArray[np.int32]:
    """Column span ``[x0, x1)`` of the member pixels of each row of a 0/1 ROI mask.

    A circle meets each row in one run of pixels (it is convex), so a span per row describes
    the mask exactly; rows without a member pixel get the empty span ``[0, 0)``.
    """
    member = mask.astype(bool)
    n_row = member.sum(axis=1)
    x0 = np.where(n_row > 0, member.argmax(axis=1), 0)
    spans = np.stack([x0, x0 + n_row], axis=1).astype(np.int32)
    cols = np.arange(mask.shape[1])[None, :]
    if not np.array_equal((cols >= spans[:, :1]) & (cols < spans[:, 1:]), member):
        raise AnalysisError("ROI mask rows are not single runs of pixels")
    return spans


def _row_contiguous(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """``image`` (2-D gray or 3-D ``(H, W, C)``) itself when its pixels and rows are
    contiguous in memory (what the compiled kernel takes), else a contiguous copy."""
    pixel = image.shape[2] if image.ndim == 3 else 1
    if image.ndim == 3 and pixel > 1 and image.strides[2] != 1:
        return np.ascontiguousarray(image)
    rows, cols = image.strides[0], image.strides[1]
    if (cols == pixel or image.shape[1] == 1) and (
        image.shape[0] == 1 or rows >= image.shape[1] * pixel
    ):
        return image
    return np.ascontiguousarray(image)


def occluded_pixel_count(frame: Frame, p: int, roi: RectROI | CircleROI | None = None) -> int:
    """Occluded pixel count S_k of a single frame, Eqs. (1)-(2) [px].

    Convenience form of :meth:`FrameProcessor.count`; for a video, build one
    :class:`FrameProcessor` and reuse it, and use :meth:`FrameProcessor.measure` to get the
    quality flags (an ROI outside the frame gives 0 here without a flag).

    Parameters
    ----------
    frame : numpy.ndarray
        uint8 gray, YUYV, BGR or BGRA frame (see :func:`to_gray`).
    p : int
        Threshold of Eq. (1) [8-bit intensity], 0..255.
    roi : RectROI or CircleROI or None
        Region of interest (clipped to the frame); None counts the whole frame.

    Returns
    -------
    int
        Number of ROI pixels with gray value <= p.
    """
    if not isinstance(frame, np.ndarray):
        raise AnalysisError(f"frame must be a numpy array, got {type(frame).__name__}")
    _check_frame_layout(frame.shape, frame.dtype)
    return FrameProcessor(frame.shape, p, roi).count(frame)


def occluded_area_subpixel(
    frame: Frame,
    p: int,
    roi: RectROI | CircleROI | None = None,
    *,
    edge_width_levels: float = DEFAULT_EDGE_WIDTH_LEVELS,
) -> float:
    """Occluded area of one frame with sub-pixel edges [px] (an alternative to Eq. (2)).

    ``A = sum over ROI pixels of clip((p + 0.5 - I) / w + 0.5, 0, 1)`` (see
    :func:`subpixel_membership_lut`): Eq. (2)'s binary count with the pixels on the disc
    edge weighted by the fraction of them the disc covers, read from their intensity. It
    equals :func:`occluded_pixel_count` on a frame without levels in the band
    ``p + 0.5 +- w/2`` (a hard-edged disc), and follows the true area more closely on an
    anti-aliased edge, notably on frames decoded or binned at reduced resolution. The
    calibration of Eqs. (4)-(5) is defined on S_k of Eq. (2); use the same estimator for
    calibration and measurement. For a video, build one :class:`FrameProcessor` and call
    :meth:`FrameProcessor.occluded_area_subpixel`.

    Parameters
    ----------
    frame : numpy.ndarray
        uint8 gray, YUYV, BGR or BGRA frame (see :func:`to_gray`).
    p : int
        Threshold of Eq. (1) [8-bit intensity], 0..255.
    roi : RectROI or CircleROI or None
        Region of interest (clipped to the frame); None uses the whole frame.
    edge_width_levels : float
        Width w of the soft threshold [8-bit levels], in (0, 255].

    Returns
    -------
    float
        Occluded area [px].

    Raises
    ------
    AnalysisError
        Unsupported frame layout, ``p`` outside 0..255 or ``edge_width_levels`` outside
        (0, 255].
    """
    if not isinstance(frame, np.ndarray):
        raise AnalysisError(f"frame must be a numpy array, got {type(frame).__name__}")
    _check_frame_layout(frame.shape, frame.dtype)
    proc = FrameProcessor(frame.shape, p, roi, edge_width_levels=edge_width_levels)
    return proc.occluded_area_subpixel(frame)


# --------------------------------------------------------------------------------------------
# Automatic threshold
# --------------------------------------------------------------------------------------------


def otsu_threshold(
    reference_frame: Frame,
    roi: RectROI | CircleROI | None = None,
    *,
    min_separability: float = DEFAULT_MIN_SEPARABILITY,
) -> int:
    """Threshold p for Eq. (1) chosen by Otsu's method on a reference frame's ROI pixels.

    The paper picks p empirically. Use this instead when setting up a probe or a session:
    record a reference frame in which the light-occluded pit pattern is clearly visible
    (e.g. the indenter pressed into a phantom) so the ROI histogram has a dark (occluded)
    and a bright (lit waveguide) mode, then fix the returned p for the whole measurement
    (stored e.g. in the calibration). Do not re-run it per frame: a frame with no pit (the
    "empty white circle" of the pitting state) has no dark mode, and a per-frame threshold
    would make S_k of different frames incomparable.

    Parameters
    ----------
    reference_frame : numpy.ndarray
        uint8 gray, YUYV, BGR or BGRA frame (see :func:`to_gray`).
    roi : RectROI or CircleROI or None
        Region whose pixels form the histogram (clipped to the frame); None = whole frame.
    min_separability : float
        Smallest accepted Otsu separability [1], in [0, 1]: between-class variance over total
        variance at the chosen threshold. Below it the histogram is not bimodal enough for a
        threshold to mean anything (see :data:`DEFAULT_MIN_SEPARABILITY`).

    Returns
    -------
    int
        p [8-bit intensity] such that Eq. (1) marks the dark mode: both classes
        ``<= p`` and ``> p`` are non-empty.

    Raises
    ------
    AnalysisError
        If the ROI has no pixel in the frame; if all ROI pixels have one intensity (a uniform
        frame: no bimodality); or if the separability is below ``min_separability``.
    """
    gray = to_gray(reference_frame)
    if not 0.0 <= min_separability <= 1.0:
        raise AnalysisError(f"min_separability must be in [0, 1], got {min_separability!r}")
    geo = _roi_geometry(gray.shape[0], gray.shape[1], roi)
    if geo.empty:
        raise AnalysisError(f"Otsu threshold: the ROI {roi!r} has no pixel inside the frame")
    crop = gray[geo.y0 : geo.y1, geo.x0 : geo.x1]
    pixels = crop.reshape(-1) if geo.mask is None else crop[geo.mask.astype(bool)]
    hist = np.bincount(pixels, minlength=256).astype(np.float64)
    levels = np.flatnonzero(hist)
    if levels.size < 2:
        raise AnalysisError(
            f"Otsu threshold: no bimodality, all {pixels.size} ROI pixels have intensity "
            f"{int(levels[0])}; record a reference frame with the pit pattern visible"
        )
    column = np.ascontiguousarray(pixels).reshape(-1, 1)
    t_float, _ = cv2.threshold(column, 0, 1, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    t = int(t_float)
    # Separability eta = sigma_between^2 / sigma_total^2 at threshold t.
    values = np.arange(256, dtype=np.float64)
    prob = hist / hist.sum()
    w0 = float(prob[: t + 1].sum())
    w1 = 1.0 - w0
    mean_total = float(prob @ values)
    var_total = float(prob @ (values - mean_total) ** 2)
    if w0 <= 0.0 or w1 <= 0.0:  # cannot happen with >= 2 levels; kept as a guard
        raise AnalysisError(f"Otsu threshold {t} leaves one class empty")
    mean0 = float(prob[: t + 1] @ values[: t + 1]) / w0
    mean1 = float(prob[t + 1 :] @ values[t + 1 :]) / w1
    eta = w0 * w1 * (mean1 - mean0) ** 2 / var_total
    if eta < min_separability:
        raise AnalysisError(
            f"Otsu threshold: no clear bimodality in the ROI histogram (separability "
            f"{eta:.3f} < {min_separability:.3f} at p = {t}); record a reference frame "
            "with the pit pattern visible or set p by hand"
        )
    return t
