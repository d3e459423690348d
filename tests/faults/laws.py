"""Recoveries from laws of the literature, rendered into frames by this test (issue 37).

The fault matrix's other cases render the project's own tissue models (``stipi_daemon.sim.tissue``
through the scene simulator), so a rule that only holds for those models passes them by
construction. The cases here take S(t) after the release from laws written below from the
literature, never from the project's tissue classes, and draw the frames with a renderer of
this module (a lit waveguide with a dark disc of round(S) pixels, plus the camera effects the
issue names: LED flicker, Gaussian pixel noise, radial falloff, clipping):

* :func:`findley_recovered`: power-law creep recovery (Findley, Lai & Onaran 1976);
* :func:`terzaghi_recovered`: poroelastic recovery, Terzaghi's consolidation series;
* :func:`kww_recovered`: stretched exponential (Kohlrausch 1854; Williams & Watts 1970);
* :func:`sls_recovered`: standard linear solid (Zener 1948) whose instantaneous part springs
  back at the release, inside the frame period that follows it;
* :func:`kv_recovered`: Kelvin-Voigt (single exponential), the control of the camera cases.

Each law gives the recovered fraction R(t) of the pit, 0 at the release, towards 1; the
occluded area is S(t) = S_0 + (S_inf - S_0) R(t) (S rises as the pit fills, Eq. 5 of the
paper for the tip force). The force the load cell sees follows the same law through Eq. (5)
inverted, so image and force agree as on a real probe.

Truth (:func:`law_truth`) is the paper's definitions on the law itself, written here: S_max
the law's level at the end of the window, T_s its first 98 % crossing (Eq. 6), D_p from S_0
of the hold through Eqs. (3)-(4), F_r Eq. (5), E Eq. (7), eta = E T_r Eq. (8). Only the
calibration's coefficients (the scene's, as the matrix uses them) and the paper's severity
table (``classify_decay_rate``, Section IV.C, which the matrix's truth calls too) come from
the project.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
ImageU8 = NDArray[np.uint8]

#: The paper's settling fraction: T_s is when S_k reaches 98.0 % of S_max (Eq. 6) [-].
SETTLE_FRACTION = 0.98

# ------------------------------------------------------------------------------ laws


def kv_recovered(t_s: FloatArray, tau_s: float) -> FloatArray:
    """Kelvin-Voigt creep recovery, R(t) = 1 - exp(-t / tau) (Findley, Lai & Onaran,
    "Creep and Relaxation of Nonlinear Viscoelastic Materials", 1976, the Kelvin model) [-];
    ``t_s`` since the release [s], >= 0."""
    out: FloatArray = 1.0 - np.exp(-np.maximum(t_s, 0.0) / tau_s)
    return out


def findley_recovered(t_s: FloatArray, hold_s: float, n: float) -> FloatArray:
    """Power-law (Findley) creep recovery after a hold of ``hold_s`` [s].

    Findley's creep law eps(t) = eps_0 + m t^n (Findley, Lai & Onaran 1976) with Boltzmann
    superposition for the unloading at t_1 (their chapter on recovery) gives
    eps_r(t') = m [(t_1 + t')^n - t'^n]: the delayed part of the pit left at t' after the
    release, m t_1^n at t' = 0. R(t') = 1 - [(t_1 + t')^n - t'^n] / t_1^n. Domain: 0 < n < 1,
    t' >= 0; R(t') ~ 1 - n (t_1/t')^(1-n) for t' >> t_1: a tail that never flattens.
    """
    t = np.maximum(t_s, 0.0)
    left = ((hold_s + t) ** n - t**n) / hold_s**n
    out: FloatArray = 1.0 - left
    return out


def terzaghi_recovered(t_s: FloatArray, tau_p_s: float, terms: int = 200) -> FloatArray:
    """Poroelastic recovery: Terzaghi's degree of consolidation (Terzaghi, "Theoretical Soil
    Mechanics", 1943, Ch. XIII; the series used for indentation of poroelastic gels and
    tissue by Hu et al., Appl. Phys. Lett. 96, 121904, 2010):

    U(t) = 1 - sum_n 8 / ((2n+1)^2 pi^2) exp(-(2n+1)^2 pi^2 t / (4 tau_p)),  n = 0, 1, ...

    with the poroelastic time tau_p = h^2 / D [s]. U(0) = 0 (the coefficients sum to 1),
    U ~ sqrt(t) early; ``terms`` terms make the truncation below 8 / (pi^2 (2 terms + 1))
    at t = 0 and negligible after the first frame."""
    t = np.maximum(np.asarray(t_s, dtype=np.float64), 0.0)
    m = 2.0 * np.arange(terms, dtype=np.float64) + 1.0
    coef = 8.0 / (m**2 * math.pi**2)
    rates = m**2 * math.pi**2 / (4.0 * tau_p_s)
    left = np.exp(-np.multiply.outer(t, rates)) @ coef
    out: FloatArray = np.where(t > 0.0, 1.0 - left, 0.0)
    return out


def kww_recovered(t_s: FloatArray, tau_s: float, beta: float) -> FloatArray:
    """Stretched-exponential recovery R(t) = 1 - exp(-(t / tau)^beta) (Kohlrausch, Ann.
    Phys. 167, 179, 1854; Williams & Watts, Trans. Faraday Soc. 66, 80, 1970) [-];
    0 < beta <= 1 (beta = 1: Kelvin-Voigt)."""
    out: FloatArray = 1.0 - np.exp(-((np.maximum(t_s, 0.0) / tau_s) ** beta))
    return out


def sls_recovered(t_s: FloatArray, tau_s: float, instant: float) -> FloatArray:
    """Standard linear solid (Zener, "Elasticity and Anelasticity of Metals", 1948): on
    unloading its spring in series recovers at once, the Kelvin element with the retardation
    time tau: R(t) = a + (1 - a)(1 - exp(-t / tau)) for t > 0, R(0) = 0, with a = ``instant``
    the instantaneous fraction in [0, 1). The jump happens at the release, so the first
    frame after it (at most one frame period later) already shows the sprung-back pit."""
    t = np.asarray(t_s, dtype=np.float64)
    out: FloatArray = np.where(
        t > 0.0, instant + (1.0 - instant) * (1.0 - np.exp(-np.maximum(t, 0.0) / tau_s)), 0.0
    )
    return out


@dataclass(frozen=True)
class Tissue:
    """One law with its parameters and the pit it recovers from.

    Attributes
    ----------
    law : "kv", "findley", "terzaghi", "kww" or "sls"
        The recovery law.
    tau_s : float
        Its time constant [s] (KV, KWW, SLS: tau; Terzaghi: tau_p; Findley: unused).
    shape : float
        Findley's n, KWW's beta, the SLS's instantaneous fraction a [-]; unused otherwise.
    hold_s : float
        Findley's loading time t_1 [s].
    s0_px, s_inf_px : float
        Occluded area at the release (the hold's pit) and after full recovery [px].
    """

    law: str
    tau_s: float = 10.0
    shape: float = 1.0
    hold_s: float = 15.0
    s0_px: float = 1215.0
    s_inf_px: float = 4462.5

    def recovered(self, t_s: FloatArray) -> FloatArray:
        """R(t) of the law, ``t_s`` since the release [s]."""
        if self.law == "kv":
            return kv_recovered(t_s, self.tau_s)
        if self.law == "findley":
            return findley_recovered(t_s, self.hold_s, self.shape)
        if self.law == "terzaghi":
            return terzaghi_recovered(t_s, self.tau_s)
        if self.law == "kww":
            return kww_recovered(t_s, self.tau_s, self.shape)
        if self.law == "sls":
            return sls_recovered(t_s, self.tau_s, self.shape)
        raise ValueError(f"unknown law {self.law!r}")

    def area_px(self, t_rel_s: FloatArray) -> FloatArray:
        """S after the release, ``t_rel_s`` since it [s] -> [px]."""
        out: FloatArray = self.s0_px + (self.s_inf_px - self.s0_px) * self.recovered(t_rel_s)
        return out


def crossing_s(f: Callable[[FloatArray], FloatArray], level: float, end_s: float) -> float:
    """First t in (0, end_s] with f(t) >= level for a non-decreasing f, by bisection to
    1 us after a 10 ms scan [s]."""
    grid = np.arange(1, math.ceil(end_s * 100.0) + 1, dtype=np.float64) / 100.0
    values = f(grid)
    k = int(np.argmax(values >= level))
    if values[k] < level:
        raise ValueError(f"level {level} not reached within {end_s} s")
    lo, hi = (0.0 if k == 0 else float(grid[k - 1])), float(grid[k])
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        if float(f(np.asarray([mid]))[0]) >= level:
            hi = mid
        else:
            lo = mid
    return hi


# ------------------------------------------------------------------------------ rendering


@dataclass(frozen=True)
class Optics:
    """The picture: geometry and gray levels of the test's own renderer, and the camera
    effects applied to it.

    Attributes
    ----------
    width, height : int
        Frame size [px].
    waveguide_fraction : float
        Waveguide diameter over the frame height [-] (the scene's ROI lies inside it).
    lit_level, dark_level, outside_level : float
        Gray levels of the lit waveguide at its centre, the occluded disc, the frame
        outside [0-255].
    falloff : float
        The edge-lit waveguide's own radial falloff: lit level - falloff (r / r_w)^2, r_w
        its radius [gray levels] (175 at the rim: 47 levels above the threshold 128).
    flicker_depth, flicker_hz : float
        LED flicker: the light is multiplied by 1 - depth (1 + sin(2 pi f t)) / 2, i.e.
        dips by ``flicker_depth`` at its trough [-], [Hz].
    noise_sigma : float
        Gaussian pixel noise, standard deviation [gray levels], drawn per frame.
    vignetting : float
        Radial falloff: the light is multiplied by 1 - v (r / r_w)^2, r_w the waveguide's
        radius [-].
    gain : float
        Exposure gain before the 8-bit clip (>1 saturates) [-].
    seed : int
        Seed of the noise (per frame: (seed, frame index)).
    """

    width: int = 320
    height: int = 240
    waveguide_fraction: float = 0.9
    lit_level: float = 200.0
    dark_level: float = 70.0
    outside_level: float = 12.0
    falloff: float = 25.0
    flicker_depth: float = 0.0
    flicker_hz: float = 13.0
    noise_sigma: float = 0.0
    vignetting: float = 0.0
    gain: float = 1.0
    seed: int = 0


class FrameRenderer:
    """Frames whose dark disc is exactly round(S) pixels (before the effects).

    The disc is the round(S) pixel centres nearest a point a generic sub-pixel distance
    off the frame's centre (so that every count is a disc), at a flat level; the waveguide
    a lit circle falling off towards its rim. The effects act on the light (flicker,
    vignetting, gain) and the sensor (noise, 8-bit clip).
    """

    def __init__(self, optics: Optics) -> None:
        self.optics = o = optics
        cy, cx = (o.height - 1) / 2.0, (o.width - 1) / 2.0
        yy, xx = np.mgrid[0 : o.height, 0 : o.width].astype(np.float64)
        r_w = o.waveguide_fraction * o.height / 2.0
        rho = np.hypot(xx - cx, yy - cy) / r_w
        base = np.where(rho <= 1.0, o.lit_level - o.falloff * rho**2, o.outside_level)
        self._light = (1.0 - o.vignetting * np.minimum(rho, 1.0) ** 2) * o.gain
        self._base = base
        d = np.hypot(xx - (cx + 0.3183), yy - (cy + 0.1732)).ravel()
        self._order = np.argsort(d, kind="stable")
        self._clean = o.flicker_depth == 0.0 and o.noise_sigma == 0.0
        self._clean = self._clean and o.vignetting == 0.0 and o.gain == 1.0

    def scene_radiance(self, s_px: float) -> FloatArray:
        """The picture before the camera's effects, as float gray levels."""
        img = self._base.copy().ravel()
        n = max(0, round(s_px))
        img[self._order[:n]] = self.optics.dark_level
        out: FloatArray = img.reshape(self._base.shape)
        return out

    def frame(self, k: int, t_s: float, s_px: float) -> ImageU8:
        """Frame ``k`` taken at ``t_s`` [s] showing S = ``s_px`` [px]: uint8 (H, W)."""
        o = self.optics
        img = self.scene_radiance(s_px)
        if self._clean:
            return img.astype(np.uint8)
        light = self._light
        if o.flicker_depth:
            light = light * (
                1.0 - o.flicker_depth * 0.5 * (1.0 + math.sin(2.0 * math.pi * o.flicker_hz * t_s))
            )
        img = img * light
        if o.noise_sigma:
            rng = np.random.default_rng([o.seed, k])
            img = img + rng.normal(0.0, o.noise_sigma, img.shape)
        out: ImageU8 = np.clip(np.rint(img), 0.0, 255.0).astype(np.uint8)
        return out


def frame_times(
    fps: float, end_s: float, gaps: tuple[tuple[float, float], ...] = ()
) -> Iterator[tuple[int, float]]:
    """(index, time) of the frames k / fps in [0, end_s], less those in a gap [a, b) [s]."""
    n = math.floor(end_s * fps + 1e-9) + 1
    for k in range(n):
        t = k / fps
        if not any(a <= t < b for a, b in gaps):
            yield k, t
