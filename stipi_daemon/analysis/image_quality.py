"""Image quality measured from the frames: LED flicker, pixel noise, vignetting, saturation.

Eq. (1) thresholds every ROI pixel at p. A lit pixel whose gray level comes within reach
of p (by the LEDs' flicker, the sensor's noise, or a dark corner of the waveguide) is
counted as occluded and biases S_k up; an occluded pixel lifted above p biases it down; a
pixel at the 8-bit rail (255) says nothing about its brightness. This module estimates
those effects from the frames themselves and says how far they can move S_k, hence D_p,
F_r and T_r (pure, no I/O):

* :class:`LevelMeter` sums a few gray-level statistics of one frame (:class:`FrameLevels`)
  on a strided sample of the ROI's pixels, split at p into lit and dark pixels and into
  :data:`RINGS` equal-area rings from the ROI's centre outwards; plus the temporal
  difference of the lit pixels with the previous frame (the pixel noise). A few numpy
  operations on :data:`SAMPLE_PIXELS` of the ROI's pixels per frame: no per-pixel Python.
* :func:`assess_image_quality` pools the frames of the steady phases (the pitting hold and
  the settled recovery, where the picture should not change) into an
  :class:`ImageQuality`: flicker (the frames' relative brightness modulation), noise (the
  temporal standard deviation of one pixel [gray levels]), vignetting (the outer ring's
  lit level relative to the inner one), the share of saturated frames.
* :meth:`ImageQuality.misclassified_px` is the expected number of ROI pixels on the wrong
  side of p for a brightness factor g: sum over rings of the lit pixels times
  Phi((p + 1/2 - g mu_ring) / sigma) plus the dark pixels times
  Phi((g mu_dark - p - 1/2) / sigma), Phi the standard normal distribution (the noise as
  Gaussian), mu the rings' lit levels and the dark level of the steady frames, sigma the
  noise (at least the 8-bit quantisation, 1/sqrt(12) level). At g = 1 it is the
  systematic bias of S_k; at g = 1 - flicker the worst frame's.
* :func:`image_quality_rules` turns that into each quantity's status: D_p moves by
  |d d_s / d S_0| (Eq. 4) times the bias, F_r by the bias / C2 (Eq. 5), T_r by the change
  of the settling level against the slope of S_k at the crossing (Eq. 6); beyond its
  tolerance (5 % for D_p and F_r, 5 % or 2 frames for T_r) a quantity is invalid, beyond a
  quarter of it flagged. Frames at the sensor's rail (more than
  :data:`~stipi_daemon.analysis.imaging.DEFAULT_SATURATION_LIMIT_FRACTION` of the ROI at
  255) make what they carry invalid: the release frame D_p, the frames around S_max F_r,
  more than :data:`SATURATED_RECOVERY_FRACTION` of the recovery frames T_r and tau.

Domain: 8-bit frames; the ring model assumes the ROI is centred on the waveguide (a
:class:`~stipi_daemon.analysis.imaging.CircleROI` around it, or a rectangle around it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import cv2
import numpy as np
import numpy.typing as npt
from scipy.special import ndtr

from stipi_daemon.analysis.imaging import (
    DEFAULT_SATURATION_LIMIT_FRACTION,
    CircleROI,
    RectROI,
    bgr_gray_formula,
    roi_mask,
)
from stipi_daemon.analysis.pitting import DEFAULT_SETTLE_FRACTION
from stipi_daemon.errors import AnalysisError

__all__ = [
    "DEPTH_TOLERANCE",
    "FORCE_TOLERANCE",
    "RINGS",
    "SAMPLE_PIXELS",
    "SATURATED_RECOVERY_FRACTION",
    "TIME_TOLERANCE",
    "TIME_TOLERANCE_FRAMES",
    "FrameLevels",
    "FramePictures",
    "ImageQuality",
    "LevelMeter",
    "QualityRule",
    "assess_image_quality",
    "image_quality_rules",
    "judge_pictures",
    "steady_phases",
]

#: Equal-area rings the ROI is split into, centre outwards [-].
RINGS: Final = 8
#: A ring at least this dark is filled by the disc (see :meth:`FrameLevels.stray_dark_px`).
FULL_RING: Final = 0.98
#: :class:`LevelMeter` samples every n-th row and column of the ROI, n the largest that
#: leaves at least this many pixels (all of them in a smaller ROI) [px]: about 1/25 of a
#: 640 x 480 frame's waveguide.
SAMPLE_PIXELS: Final = 5000
#: Tolerance of D_p and of F_r (relative) [-].
DEPTH_TOLERANCE: Final = 0.05
FORCE_TOLERANCE: Final = 0.05
#: Tolerance of T_r: the larger of this fraction of T_r [-] and ...
TIME_TOLERANCE: Final = 0.05
#: ... this many frame periods [-].
TIME_TOLERANCE_FRAMES: Final = 2.0
#: A quantity moved by more than this fraction of its tolerance is flagged [-].
FLAG_FRACTION: Final = 0.25
#: T_r and tau are invalid when more than this fraction of the recovery frames is
#: saturated [-].
SATURATED_RECOVERY_FRACTION: Final = 0.1
#: Standard deviation of the 8-bit rounding [gray levels]: the least noise there is.
QUANTISATION_SD: Final = 1.0 / math.sqrt(12.0)
#: Gray level of a saturated pixel.
RAIL_LEVEL: Final = 255

_FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class FrameLevels:
    """Summed gray-level statistics of one frame's sampled ROI pixels.

    Attributes
    ----------
    n_px : int
        Sampled ROI pixels [px].
    level_sum : float
        Sum of their gray levels [levels].
    lit_n, lit_sum : tuple
        Per ring (centre outwards): pixels above p [px] and the sum of their levels.
    dark_n : tuple
        Per ring: pixels at or below p [px] ...
    dark_sum : float
        ... and the sum of all their levels.
    saturated_n : int
        Pixels at 255 [px].
    pair_n : int
        Pixels lit in this frame and the previous one measured (0 for the first) [px];
    pair_sums : tuple
        over them, with x the previous level and y this one: (sum x, sum y, sum x^2,
        sum y^2, sum x y) [levels, levels^2].
    """

    n_px: int
    level_sum: float
    lit_n: tuple[int, ...]
    lit_sum: tuple[float, ...]
    dark_n: tuple[int, ...]
    dark_sum: float
    saturated_n: int
    pair_n: int = 0
    pair_sums: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def to_list(self) -> list[float]:
        """Flat list (the layout of a stored row): n, sum, lit_n..., lit_sum..., dark_n...,
        dark_sum, saturated_n, pair_n, pair_sums..."""
        return [
            self.n_px,
            self.level_sum,
            *self.lit_n,
            *self.lit_sum,
            *self.dark_n,
            self.dark_sum,
            self.saturated_n,
            self.pair_n,
            *self.pair_sums,
        ]

    @classmethod
    def from_list(cls, values: Sequence[float]) -> FrameLevels:
        """Inverse of :meth:`to_list`.

        Raises
        ------
        AnalysisError
            The list does not have the length :meth:`to_list` gives.
        """
        r = RINGS
        if len(values) != 3 * r + 10:
            raise AnalysisError(f"frame levels need {3 * r + 10} values, got {len(values)}")
        v = [float(x) for x in values]
        tail = v[2 + 3 * r :]
        return cls(
            n_px=int(v[0]),
            level_sum=v[1],
            lit_n=tuple(int(x) for x in v[2 : 2 + r]),
            lit_sum=tuple(v[2 + r : 2 + 2 * r]),
            dark_n=tuple(int(x) for x in v[2 + 2 * r : 2 + 3 * r]),
            dark_sum=tail[0],
            saturated_n=int(tail[1]),
            pair_n=int(tail[2]),
            pair_sums=(tail[3], tail[4], tail[5], tail[6], tail[7]),
        )

    def stray_dark_px(self) -> int:
        """Dark pixels away from the central disc [sampled px]: those of the rings beyond
        the one the disc's edge lies in and its neighbour.

        The light-occluded disc is central and compact: it fills the rings from the centre
        out to the first one it does not fill (at least :data:`FULL_RING` dark), its edge
        (and an off-centre disc's) reaching one ring further. Dark pixels further out are
        not the pit: a dark corner of the waveguide (vignetting), the LEDs' low phase,
        noise on dim pixels.
        """
        edge = 0
        while edge < RINGS and self.dark_n[edge] >= FULL_RING * (
            self.dark_n[edge] + self.lit_n[edge]
        ):
            edge += 1
        return int(sum(self.dark_n[edge + 2 :]))


def _ring_of(
    ys: npt.NDArray[np.float64], xs: npt.NDArray[np.float64], roi: RectROI | CircleROI
) -> npt.NDArray[np.intp]:
    """Equal-area ring index (0 = centre) of pixel centres (``ys``, ``xs``) [px]."""
    if isinstance(roi, CircleROI):
        u = ((xs - roi.cx_px) ** 2 + (ys - roi.cy_px) ** 2) / roi.radius_px**2
    else:
        hw, hh = roi.width_px / 2.0, roi.height_px / 2.0
        cx, cy = roi.x_px + hw - 0.5, roi.y_px + hh - 0.5
        u = np.maximum(np.abs(xs - cx) / hw, np.abs(ys - cy) / hh) ** 2
    out: npt.NDArray[np.intp] = np.minimum((u * RINGS).astype(np.intp), RINGS - 1)
    return out


class LevelMeter:
    """Measures :class:`FrameLevels` of frames of one shape, ROI and threshold.

    Parameters
    ----------
    frame_shape : tuple of int
        ``(H, W)``, ``(H, W, 1)``, ``(H, W, 2)`` (YUYV: luma in channel 0), ``(H, W, 3)``
        (BGR) or ``(H, W, 4)`` (BGRA); uint8 frames.
    p : int
        Threshold of Eq. (1) [8-bit level].
    roi : RectROI or CircleROI or None
        The ROI S_k is counted in (None: the whole frame).
    stride : int or None
        Every ``stride``-th row and column is sampled [px]; None: the largest stride that
        leaves :data:`SAMPLE_PIXELS` pixels of the ROI.

    Notes
    -----
    Keeps the previous frame's sample for the temporal difference: one instance per
    stream, frames in capture order.
    """

    def __init__(
        self,
        frame_shape: tuple[int, ...],
        p: int,
        roi: RectROI | CircleROI | None = None,
        *,
        stride: int | None = None,
    ) -> None:
        mask = roi_mask(tuple(int(n) for n in frame_shape), roi)
        if stride is None:
            stride = max(1, math.isqrt(int(np.count_nonzero(mask)) // SAMPLE_PIXELS))
        if not 0 <= int(p) <= 255 or stride < 1:
            raise AnalysisError(f"need 0 <= p <= 255 and stride >= 1, got p={p}, stride={stride}")
        self._shape = tuple(int(n) for n in frame_shape)
        self._p = int(p)
        height, width = self._shape[0], self._shape[1]
        grid = np.zeros_like(mask)
        grid[::stride, ::stride] = True
        ys, xs = np.nonzero(mask & grid)
        self._flat = (ys * width + xs).astype(np.intp)
        box = roi if roi is not None else RectROI(x_px=0, y_px=0, width_px=width, height_px=height)
        ring = _ring_of(ys.astype(np.float64), xs.astype(np.float64), box)
        self._label = (2 * ring).astype(np.intp)
        self._channels = self._shape[2] if len(self._shape) == 3 else 1
        self._previous: npt.NDArray[np.int64] | None = None
        formula = bgr_gray_formula() if self._channels == 3 else None
        self._bgr = None if formula is None else formula.weights

    def _sample(self, frame: npt.NDArray[np.uint8]) -> npt.NDArray[np.int64]:
        if frame.shape != self._shape or frame.dtype != np.uint8:
            raise AnalysisError(f"frame {frame.shape} {frame.dtype}; meter built for {self._shape}")
        c = self._channels
        pixels = frame.reshape(-1, c)[self._flat]
        if c in (1, 2):
            return pixels[:, 0].astype(np.int64)
        if c == 3 and self._bgr is not None:  # cv2.cvtColor's own fixed point, in numpy
            cb, cg, cr, d, shift = self._bgr
            p64 = pixels.astype(np.int64)
            out: npt.NDArray[np.int64] = (
                p64[:, 0] * cb + p64[:, 1] * cg + p64[:, 2] * cr + d
            ) >> shift
            return out
        code = cv2.COLOR_BGR2GRAY if c == 3 else cv2.COLOR_BGRA2GRAY
        gray = np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels.reshape(-1, 1, c)), code))
        return gray.ravel().astype(np.int64)

    def measure(self, frame: npt.NDArray[np.uint8]) -> FrameLevels:
        """The levels of one frame (and its difference with the previous one measured)."""
        g = self._sample(frame)
        lit = g > self._p
        # one label per (ring, lit): counts and level sums of both sides in two passes
        label = self._label + lit
        n = np.bincount(label, minlength=2 * RINGS)
        sums = np.bincount(label, weights=g, minlength=2 * RINGS)
        pair_n, pair = 0, (0.0, 0.0, 0.0, 0.0, 0.0)
        prev = self._previous
        if prev is not None:
            both = lit & (prev > self._p)
            # integer dot products: exact, and no BLAS call (nor its threads) per frame
            x, y = prev[both], g[both]
            pair_n = int(x.size)
            pair = (
                float(x.sum()),
                float(y.sum()),
                float(np.dot(x, x)),
                float(np.dot(y, y)),
                float(np.dot(x, y)),
            )
        self._previous = g
        return FrameLevels(
            n_px=int(g.size),
            level_sum=float(sums.sum()),
            lit_n=tuple(int(v) for v in n[1::2]),
            lit_sum=tuple(float(v) for v in sums[1::2]),
            dark_n=tuple(int(v) for v in n[0::2]),
            dark_sum=float(sums[0::2].sum()),
            saturated_n=int(np.count_nonzero(g >= RAIL_LEVEL)),
            pair_n=pair_n,
            pair_sums=pair,
        )


@dataclass(frozen=True)
class ImageQuality:
    """What the steady frames say about the picture (see the module docstring).

    Attributes
    ----------
    n_frames : int
        Steady frames pooled [-].
    flicker : float
        Relative brightness modulation: the 95th percentile of |mean level / its median
        - 1| over the steady frames (each compared within its own phase) [-].
    noise_levels : float
        Temporal standard deviation of one lit pixel [gray levels].
    ring_levels : tuple of float
        Median lit level of each ring, centre outwards [gray levels] (p for a ring with no
        lit pixel).
    ring_lit_px : tuple of float
        Median lit pixels of each ring, scaled to the whole ROI [px].
    vignetting : float
        1 - outermost lit ring's level / innermost lit ring's [-] (a ring is lit when at
        least half its pixels are, in the median frame).
    stray_px : float
        Median dark pixels away from the disc (:meth:`FrameLevels.stray_dark_px`) over the
        steady frames, scaled to the whole ROI [px]: a bias of S_k seen directly.
    stray_spread_px : float
        95th percentile minus median of the same [px]: how much it changes frame to frame.
    saturated_fraction : float
        Median fraction of the ROI at 255 over the steady frames [-].
    p : int
        The threshold the levels were split at.
    """

    n_frames: int
    flicker: float
    noise_levels: float
    ring_levels: tuple[float, ...]
    ring_lit_px: tuple[float, ...]
    vignetting: float
    stray_px: float
    stray_spread_px: float
    saturated_fraction: float
    p: int

    def misclassified_px(self, gain: float = 1.0) -> float:
        """Expected lit ROI pixels below p at brightness factor ``gain`` [px] (Gaussian
        noise of :attr:`noise_levels` on each ring's lit level)."""
        sigma = max(self.noise_levels, QUANTISATION_SD)
        edge = self.p + 0.5
        return sum(
            n * float(ndtr((edge - gain * mu) / sigma))
            for n, mu in zip(self.ring_lit_px, self.ring_levels, strict=True)
            if n > 0
        )

    def bias_px(self) -> tuple[float, float]:
        """(steady, worst frame) bias of S_k [px]: the larger of the stray dark pixels seen
        and the noise model's at gain 1, and of those plus their frame-to-frame spread and
        the model's at gain 1 - flicker."""
        steady = max(self.stray_px, self.misclassified_px(1.0))
        low = self.misclassified_px(max(0.0, 1.0 - self.flicker))
        return steady, max(self.stray_px + self.stray_spread_px, low, steady)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping (``summary.json``'s ``image_quality``), units in the keys."""
        steady, worst = self.bias_px()
        return {
            "frames": self.n_frames,
            "flicker_fraction": self.flicker,
            "noise_gray_levels": self.noise_levels,
            "ring_lit_levels": list(self.ring_levels),
            "vignetting_fraction": self.vignetting,
            "stray_dark_px": self.stray_px,
            "saturated_fraction": self.saturated_fraction,
            "bias_px": steady,
            "worst_frame_bias_px": worst,
        }


def _pair_noise(levels: Sequence[FrameLevels]) -> float:
    """Median over frames of the temporal noise of one pixel [gray levels].

    For each pair of frames r = y - (mean y / mean x) x removes the common brightness
    change (flicker scales every level) and keeps (1 + c^2) times the noise variance.
    """
    out: list[float] = []
    for lv in levels:
        n = lv.pair_n
        if n < 10:
            continue
        sx, sy, sxx, syy, sxy = lv.pair_sums
        mx, my = sx / n, sy / n
        if mx <= 0.0:
            continue
        c = my / mx
        vx, vy, cxy = sxx / n - mx * mx, syy / n - my * my, sxy / n - mx * my
        var_r = vy - 2.0 * c * cxy + c * c * vx
        out.append(math.sqrt(max(var_r, 0.0) / (1.0 + c * c)))
    return float(np.median(out)) if out else 0.0


def _flicker(mean: _FloatArray, phase: npt.NDArray[np.int64]) -> float:
    """95th percentile of |mean level / its phase's median - 1| [-]."""
    dev = np.zeros_like(mean)
    for ph in np.unique(phase):
        sel = phase == ph
        ref = float(np.median(mean[sel]))
        dev[sel] = np.abs(mean[sel] / ref - 1.0) if ref > 0.0 else 0.0
    return float(np.percentile(dev, 95))


def assess_image_quality(
    levels: Sequence[FrameLevels], phases: Sequence[int], p: int, roi_pixel_count: int
) -> ImageQuality | None:
    """Pool the steady frames' levels into an :class:`ImageQuality`.

    Parameters
    ----------
    levels : sequence of FrameLevels
        One per steady frame, in capture order.
    phases : sequence of int
        The steady phase each frame belongs to (e.g. 0 the hold, 1 the settled recovery):
        brightness is compared within a phase, where the picture should not change.
    p : int
        Threshold of Eq. (1).
    roi_pixel_count : int
        Pixels in the whole ROI [px] (the sample is scaled to it).

    Returns
    -------
    ImageQuality or None
        None when fewer than 3 frames have sampled pixels.
    """
    keep = [(lv, ph) for lv, ph in zip(levels, phases, strict=True) if lv.n_px > 0]
    if len(keep) < 3:
        return None
    lvs = [lv for lv, _ in keep]
    scale = roi_pixel_count / float(np.median([lv.n_px for lv in lvs]))
    mean = np.array([lv.level_sum / lv.n_px for lv in lvs])
    lit_n = np.array([lv.lit_n for lv in lvs], dtype=np.float64)
    lit_sum = np.array([lv.lit_sum for lv in lvs], dtype=np.float64)
    ring_levels = tuple(
        float(np.median(lit_sum[lit_n[:, r] > 0, r] / lit_n[lit_n[:, r] > 0, r]))
        if np.any(lit_n[:, r] > 0)
        else float(p)
        for r in range(RINGS)
    )
    ring_px = tuple(float(np.median(lit_n[:, r])) * scale for r in range(RINGS))
    dark_n = np.array([lv.dark_n for lv in lvs], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.nanmedian(lit_n / (lit_n + dark_n), axis=0)
    lit_rings = [ring_levels[r] for r in range(RINGS) if share[r] >= 0.5]
    stray = np.array([lv.stray_dark_px() for lv in lvs], dtype=np.float64) * scale
    stray_median = float(np.median(stray))
    return ImageQuality(
        n_frames=len(lvs),
        flicker=_flicker(mean, np.array([ph for _, ph in keep], dtype=np.int64)),
        noise_levels=_pair_noise(lvs),
        ring_levels=ring_levels,
        ring_lit_px=ring_px,
        vignetting=1.0 - lit_rings[-1] / lit_rings[0] if lit_rings and lit_rings[0] > 0 else 0.0,
        stray_px=stray_median,
        stray_spread_px=float(np.percentile(stray, 95)) - stray_median,
        saturated_fraction=float(np.median([lv.saturated_n / lv.n_px for lv in lvs])),
        p=int(p),
    )


@dataclass(frozen=True)
class QualityRule:
    """What the picture does to one quantity.

    Attributes
    ----------
    quantity : str
        The quantity (a key of :data:`~stipi_daemon.analysis.validity.QUANTITY_SYMBOLS`).
    invalid : bool
        True beyond its tolerance (or at the sensor's rail), else flagged.
    reason : str
        The rule and the amount, one line.
    """

    quantity: str
    invalid: bool
    reason: str


def _judge(quantity: str, moved: float, tolerance: float, what: str) -> QualityRule | None:
    if not math.isfinite(moved) or moved > tolerance:
        return QualityRule(quantity, True, f"{what}, beyond the tolerance")
    if moved > FLAG_FRACTION * tolerance:
        return QualityRule(quantity, False, what)
    return None


def _saturation_rules(
    saturated: npt.NDArray[np.bool_],
    t: _FloatArray,
    t0_s: float,
    s_max_time_s: float,
    period_s: float,
    release: npt.NDArray[np.intp],
) -> list[QualityRule]:
    """Frames at the rail (``saturated`` per frame with statistics, at times ``t`` [s]) and
    what they carry; ``release`` indexes the release frame among them (empty: it has none),
    ``period_s`` is the frame period [s]."""
    out: list[QualityRule] = []
    rec = t >= t0_s
    if not rec.any():
        return out
    if release.size and saturated[int(release[0])]:
        out.append(QualityRule("depth_mm", True, "the release frame (S_0) is saturated"))
    if np.any(saturated & rec & (np.abs(t - s_max_time_s) <= 2.0 * period_s)):
        out.append(QualityRule("rebound_force_n", True, "the frames that set S_max are saturated"))
    share = float(np.mean(saturated[rec]))
    if share > SATURATED_RECOVERY_FRACTION:
        why = f"{100 * share:.0f} % of the recovery frames are saturated"
        out += [QualityRule(q, True, why) for q in ("recovery_time_s", "tau_s")]
    return out


def image_quality_rules(
    quality: ImageQuality,
    *,
    depth_mm: float,
    depth_slope_mm_per_px: float,
    c2_px_per_n: float,
    rebound_force_n: float,
    recovery_time_s: float | None,
    crossing_slope_px_per_s: float | None,
    frame_period_s: float,
    release_stray_px: float = 0.0,
) -> list[QualityRule]:
    """Each quantity's status from how far the measured picture can move S_k.

    Parameters
    ----------
    quality : ImageQuality
        The steady frames' quality.
    depth_mm, depth_slope_mm_per_px : float
        D_p [mm] and |d d_s / d S_0| at S_0 (Eq. 4) [mm/px].
    c2_px_per_n : float
        C2 of Eq. (5) [px/N].
    rebound_force_n : float
        F_r [N].
    recovery_time_s : float or None
        T_r [s] (None: not judged).
    crossing_slope_px_per_s : float or None
        Slope of S_k at the settling crossing [px/s] (None: T_r not judged; <= 0: T_r
        cannot be timed against any bias).
    frame_period_s : float
        Median frame period [s].
    release_stray_px : float
        Stray dark pixels of the release frame itself, scaled to the ROI [px].

    Returns
    -------
    list of QualityRule
        Empty when the picture cannot move any quantity beyond a quarter of its tolerance.
    """
    out: list[QualityRule] = []
    steady, worst = quality.bias_px()
    said = (
        f"flicker {100 * quality.flicker:.0f} %, noise {quality.noise_levels:.1f} levels, "
        f"vignetting {100 * quality.vignetting:.0f} %: S_k off by up to {worst:.0f} px "
        f"(pixels on the wrong side of p = {quality.p})"
    )
    if depth_mm > 0.0:
        d_rel = depth_slope_mm_per_px * max(worst, release_stray_px) / depth_mm
        rule = _judge("depth_mm", d_rel, DEPTH_TOLERANCE, f"{said}: D_p by {100 * d_rel:.1f} %")
        out += [] if rule is None else [rule]
    if rebound_force_n > 0.0 and c2_px_per_n > 0.0:
        f_rel = worst / c2_px_per_n / rebound_force_n
        rule = _judge(
            "rebound_force_n", f_rel, FORCE_TOLERANCE, f"{said}: F_r by {100 * f_rel:.1f} %"
        )
        out += [] if rule is None else [rule]
    if recovery_time_s is not None and crossing_slope_px_per_s is not None:
        tol = max(TIME_TOLERANCE * recovery_time_s, TIME_TOLERANCE_FRAMES * frame_period_s)
        # a steady bias moves the 98 % level by 2 % of it; its frame-to-frame part (flicker)
        # can cross the level early by all of it
        shift = (1.0 - DEFAULT_SETTLE_FRACTION) * steady + (worst - steady)
        dt = shift / crossing_slope_px_per_s if crossing_slope_px_per_s > 0.0 else math.inf
        dt = 0.0 if shift == 0.0 else dt
        rule = _judge("recovery_time_s", dt, tol, f"{said}: T_r by {dt:.2f} s")
        out += [] if rule is None else [rule]
    return out


@dataclass(frozen=True)
class FramePictures:
    """Per-frame picture statistics of one measurement, what :func:`judge_pictures` needs.

    Any subset of the frames may have them (a live shell may measure one frame in n): the
    estimates pool what there is; a rule about one frame (the release frame's, those
    beside S_max) applies when that frame has them.

    Attributes
    ----------
    times_s : tuple of float
        Times of the frames with statistics [s], increasing, on the S_k series' clock.
    levels : tuple of FrameLevels
        One per time.
    p : int
        Threshold of Eq. (1).
    roi_pixel_count : int
        Pixels in the ROI [px].
    saturation_limit : float
        A frame with more than this fraction of its ROI at 255 is saturated [-].
    hold_s : tuple of float or None
        The pitting hold [s] (a steady phase), when known.
    """

    times_s: tuple[float, ...]
    levels: tuple[FrameLevels, ...]
    p: int
    roi_pixel_count: int
    saturation_limit: float = DEFAULT_SATURATION_LIMIT_FRACTION
    hold_s: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if len(self.times_s) != len(self.levels):
            raise AnalysisError(
                f"{len(self.times_s)} frame times but {len(self.levels)} frame levels"
            )


def _crossing_slope(
    t: _FloatArray, s: _FloatArray, ts_s: float, half_width_s: float
) -> float | None:
    """Least-squares slope of S_k [px/s] over the frames within ``half_width_s`` of T_s."""
    sel = (np.abs(t - ts_s) <= half_width_s) & np.isfinite(s)
    if np.count_nonzero(sel) < 3:
        return None
    tt, ss = t[sel], s[sel]
    var = float(np.var(tt))
    return float(np.mean((tt - tt.mean()) * (ss - ss.mean())) / var) if var > 0.0 else None


def steady_phases(
    times_s: _FloatArray,
    t0_s: float,
    ts_s: float | None,
    window_s: float,
    hold_s: tuple[float, float] | None,
) -> npt.NDArray[np.int64]:
    """Per frame: 0 in the hold, 1 in the settled recovery (from T_s, or the window's last
    10 % without one, to the window's end), -1 elsewhere."""
    out = np.full(times_s.shape, -1, dtype=np.int64)
    if hold_s is not None:
        out[(times_s >= hold_s[0]) & (times_s <= min(hold_s[1], t0_s)) & (times_s < t0_s)] = 0
    start = ts_s if ts_s is not None else t0_s + 0.9 * window_s
    out[(times_s >= start) & (times_s <= t0_s + window_s) & (times_s > t0_s)] = 1
    return out


def judge_pictures(
    pictures: FramePictures,
    times_s: npt.ArrayLike,
    s_k: npt.ArrayLike,
    *,
    t0_s: float,
    ts_s: float | None,
    window_s: float,
    quantities: dict[str, float],
    period_s: float,
) -> tuple[ImageQuality | None, list[QualityRule]]:
    """The image quality of one measurement and what it does to its quantities.

    ``times_s`` [s] and ``s_k`` [px] are the whole series; ``quantities`` holds ``depth_mm``,
    ``depth_slope_mm_per_px`` [mm/px], ``c2_px_per_n`` and ``rebound_force_n`` [N] and,
    when T_r is defined, ``recovery_time_s`` [s]; ``period_s`` is the frame period [s].
    """
    t = np.asarray(times_s, dtype=np.float64)
    s = np.asarray(s_k, dtype=np.float64)
    if s.shape != t.shape:
        raise AnalysisError(f"{t.size} frame times but {s.size} S_k values")
    tp = np.asarray(pictures.times_s, dtype=np.float64)
    phase = steady_phases(tp, t0_s, ts_s, window_s, pictures.hold_s)
    steady = np.flatnonzero(phase >= 0)
    quality = assess_image_quality(
        [pictures.levels[i] for i in steady],
        [int(phase[i]) for i in steady],
        pictures.p,
        pictures.roi_pixel_count,
    )
    saturated = np.array(
        [
            lv.n_px > 0 and lv.saturated_n > pictures.saturation_limit * lv.n_px
            for lv in pictures.levels
        ],
        dtype=np.bool_,
    )
    rec = (t >= t0_s) & (t <= t0_s + window_s) & np.isfinite(s)
    s_max_time = float(t[rec][int(np.argmax(s[rec]))]) if rec.any() else t0_s
    # the release frame: the first frame at or after T_0, when it has statistics
    first = float(t[rec][0]) if rec.any() else math.nan
    release = np.flatnonzero(np.abs(tp - first) <= 1e-9 * max(1.0, abs(first)))
    rules = _saturation_rules(saturated, tp, t0_s, s_max_time, period_s, release)
    if quality is None:
        return None, rules
    t_r = quantities.get("recovery_time_s")
    slope = None
    if t_r is not None and ts_s is not None:
        slope = _crossing_slope(t, s, ts_s, max(2.0 * period_s, TIME_TOLERANCE * t_r))
    release_stray = 0.0
    if release.size:
        lv = pictures.levels[int(release[0])]
        if lv.n_px > 0:
            release_stray = lv.stray_dark_px() * pictures.roi_pixel_count / lv.n_px
    rules += image_quality_rules(
        quality,
        depth_mm=quantities["depth_mm"],
        depth_slope_mm_per_px=quantities["depth_slope_mm_per_px"],
        c2_px_per_n=quantities["c2_px_per_n"],
        rebound_force_n=quantities["rebound_force_n"],
        recovery_time_s=t_r,
        crossing_slope_px_per_s=slope,
        frame_period_s=period_s,
        release_stray_px=release_stray,
    )
    return quality, rules
