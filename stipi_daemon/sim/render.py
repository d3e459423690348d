"""Rendering of the lit waveguide and its occluded disc, frame by frame.

This module owns the picture the camera sees: a static background (the PDMS waveguide as
a bright disc lit by LEDs at its edge, with a smooth falloff and a dark surround),
computed once, and per frame a copy of it with the occluded disc drawn over it. The disc
is drawn with an anti-aliased edge, an intensity ramp that crosses the threshold p of
Eq. (1) exactly at a sub-pixel radius, and that radius is chosen among the sorted
pixel-centre distances so that the thresholded pixel count equals round(S(t)) at any
resolution. It does not own S(t) (:mod:`.physics`), effects or video files.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.analysis.imaging import CircleROI
from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.scene import Scene

__all__ = ["DISC_CENTRE_OFFSET_PX", "Renderer", "render_frame"]

#: Offset of the occluded disc's centre from the waveguide centre [px]. A generic sub-pixel
#: offset makes all pixel-centre distances distinct, so every integer count is reachable.
DISC_CENTRE_OFFSET_PX = (0.2137, 0.1318)

ImageU8 = NDArray[np.uint8]


def _smoothstep(x: NDArray[np.float64]) -> NDArray[np.float64]:
    x = np.clip(x, 0.0, 1.0)
    result: NDArray[np.float64] = x * x * (3.0 - 2.0 * x)
    return result


class Renderer:
    """Draws the frames of one scene (no effects: those are the pipeline's).

    Parameters
    ----------
    scene : Scene
        The scene; camera size and probe appearance are used.
    model : SceneModel, optional
        Its physics (built from ``scene`` when omitted).

    Raises
    ------
    ConfigError
        The waveguide does not fit the frame, or the largest occluded area does not fit
        the analysis ROI.
    """

    def __init__(self, scene: Scene, model: SceneModel | None = None) -> None:
        self.scene = scene
        self.model = model if model is not None else SceneModel(scene)
        cam, probe = scene.camera, scene.probe
        self.width, self.height = cam.width, cam.height
        #: Channels of a rendered frame: gray8 1, bgr8 and mjpg (a colour camera) 3.
        self.channels = 1 if cam.pixel_format == "gray8" else 3
        self.threshold = probe.threshold
        self.occluded_level = probe.occluded_level
        #: Waveguide radius [px] and centre (pixel centres are integers).
        self.waveguide_radius_px = probe.waveguide_diameter_fraction * cam.height / 2.0
        if 2.0 * self.waveguide_radius_px > cam.width:
            raise ConfigError(
                f"{scene.name}: probe.waveguide_diameter_fraction: the waveguide "
                f"({2 * self.waveguide_radius_px:.0f} px) is wider than the frame ({cam.width} px)"
            )
        self.cx_px = (cam.width - 1) / 2.0
        self.cy_px = (cam.height - 1) / 2.0
        self.px_per_mm = 2.0 * self.waveguide_radius_px / probe.waveguide_diameter_mm
        self._rim_px = max(2.0, 0.02 * self.waveguide_radius_px)
        #: Region of interest for the analysis: the waveguide inside its rim falloff.
        self.roi = CircleROI(
            cx_px=self.cx_px,
            cy_px=self.cy_px,
            radius_px=float(self.waveguide_radius_px - self._rim_px - 2.0),
        )
        self.gray_background = self._background()
        self.background: ImageU8 = (
            np.repeat(self.gray_background[:, :, None], 3, axis=2)
            if self.channels == 3
            else self.gray_background
        )
        # Ramp slope of the disc edge [gray levels / px].
        self._slope = (probe.background_level - probe.occluded_level) / probe.edge_width_px
        self._ramp_out_px = (probe.background_level - probe.threshold) / self._slope + 1.0
        # Static disc centre and the sorted distances of the pixel centres around it.
        self.disc_cx_px = self.cx_px + DISC_CENTRE_OFFSET_PX[0]
        self.disc_cy_px = self.cy_px + DISC_CENTRE_OFFSET_PX[1]
        max_area = self.model.max_occluded_area_px
        roi_area = math.pi * self.roi.radius_px**2
        if max_area >= roi_area:
            raise ConfigError(
                f"{scene.name}: probe.calibration: the largest occluded area {max_area:.0f} px "
                f"does not fit the ROI ({roi_area:.0f} px)"
            )
        half = math.ceil(self.roi.radius_px) + 2
        self._half = half
        self._bx0 = math.floor(self.disc_cx_px) - half
        self._by0 = math.floor(self.disc_cy_px) - half
        xs = np.arange(self._bx0, self._bx0 + 2 * half + 1, dtype=np.float64) - self.disc_cx_px
        ys = np.arange(self._by0, self._by0 + 2 * half + 1, dtype=np.float64) - self.disc_cy_px
        self._dist = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2)
        self._sorted = np.sort(self._dist, axis=None)
        if self._bx0 < 0 or self._by0 < 0:
            raise ConfigError(f"{scene.name}: the occluded disc's box leaves the frame")
        #: Pixels inside the ROI at or below the threshold with no occlusion (dim lighting).
        self.dark_pixels_in_roi = self._dark_pixels()

    def _background(self) -> ImageU8:
        probe = self.scene.probe
        h, w = self.height, self.width
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        dx, dy = xx - self.cx_px, yy - self.cy_px
        rw = self.waveguide_radius_px
        rho = np.sqrt(dx * dx + dy * dy) / rw
        leds = probe.leds
        intens = np.asarray(leds.intensities, dtype=np.float64)
        angles = np.deg2rad(leds.first_angle_deg + 360.0 / leds.count * np.arange(leds.count))
        weight_sum = np.zeros((h, w))
        lit = np.zeros((h, w))
        highlight = np.zeros((h, w))
        sigma_h = leds.highlight_width_fraction * rw
        for a, i_led in zip(angles, intens, strict=True):
            d2 = (xx - (self.cx_px + rw * math.cos(a))) ** 2 + (
                yy - (self.cy_px + rw * math.sin(a))
            ) ** 2
            wgt = np.exp(-d2 / (2.0 * (0.6 * rw) ** 2)) + 0.05
            weight_sum += wgt
            lit += i_led * wgt
            highlight += i_led * np.exp(-d2 / (2.0 * sigma_h**2))
        base = probe.background_level - probe.edge_falloff_level * rho**2
        inside = base * (lit / weight_sum) + leds.highlight_level * highlight
        t = _smoothstep((rw - rho * rw) / self._rim_px)
        img = probe.outside_level + (inside - probe.outside_level) * t
        out: ImageU8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return out

    def _dark_pixels(self) -> int:
        yy, xx = np.ogrid[0 : self.height, 0 : self.width]
        inside = (xx - self.roi.cx_px) ** 2 + (yy - self.roi.cy_px) ** 2 <= self.roi.radius_px**2
        return int(np.count_nonzero(inside & (self.gray_background <= self.threshold)))

    def _edge_radius(self, count: int, dist_sorted: NDArray[np.float64]) -> float:
        if count >= dist_sorted.size:
            raise ConfigError(
                f"{self.scene.name}: occluded area {count} px exceeds the drawable box "
                f"({dist_sorted.size} px)"
            )
        return 0.5 * (float(dist_sorted[count - 1]) + float(dist_sorted[count]))

    def _draw(
        self,
        frame: ImageU8,
        dist: NDArray[np.float64],
        x0: int,
        y0: int,
        r_edge: float,
    ) -> None:
        bg = self.gray_background[y0 : y0 + dist.shape[0], x0 : x0 + dist.shape[1]]
        ramp = self.threshold + np.ceil(self._slope * (dist - r_edge))
        np.clip(ramp, self.occluded_level, 255.0, out=ramp)
        vals = np.minimum(ramp, bg).astype(np.uint8)
        if frame.ndim == 3:
            frame[y0 : y0 + dist.shape[0], x0 : x0 + dist.shape[1], :] = vals[:, :, None]
        else:
            frame[y0 : y0 + dist.shape[0], x0 : x0 + dist.shape[1]] = vals

    def render_area(self, s_px: float, offset_px: tuple[float, float] = (0.0, 0.0)) -> ImageU8:
        """A frame whose thresholded occluded area is round(``s_px``) pixels.

        Parameters
        ----------
        s_px : float
            Occluded area S [px], >= 0.
        offset_px : (float, float)
            Shift (dx, dy) of the disc's centre [px] (hand tremor); (0, 0) uses the
            precomputed distances.

        Returns
        -------
        numpy.ndarray
            uint8 frame, (H, W) or (H, W, 3) neutral BGR.
        """
        frame = self.background.copy()
        count = round(s_px)
        if count <= 0:
            return frame
        dx, dy = offset_px
        if dx == 0.0 and dy == 0.0:
            r_edge = self._edge_radius(count, self._sorted)
            half = min(math.ceil(r_edge + self._ramp_out_px) + 1, self._half)
            c = self._half
            dist = self._dist[c - half : c + half + 1, c - half : c + half + 1]
            self._draw(frame, dist, self._bx0 + c - half, self._by0 + c - half, r_edge)
            return frame
        cx, cy = self.disc_cx_px + dx, self.disc_cy_px + dy
        r_guess = math.sqrt(count / math.pi)
        half = math.ceil(r_guess + self._ramp_out_px) + 3
        x0 = max(math.floor(cx) - half, 0)
        y0 = max(math.floor(cy) - half, 0)
        x1 = min(math.floor(cx) + half + 1, self.width)
        y1 = min(math.floor(cy) + half + 1, self.height)
        xs = np.arange(x0, x1, dtype=np.float64) - cx
        ys = np.arange(y0, y1, dtype=np.float64) - cy
        dist = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2)
        flat = dist.ravel()
        part = np.partition(flat, (count - 1, count))
        r_edge = 0.5 * (float(part[count - 1]) + float(part[count]))
        self._draw(frame, dist, x0, y0, r_edge)
        return frame

    def render(self, t_s: float, offset_px: tuple[float, float] = (0.0, 0.0)) -> ImageU8:
        """The frame at time ``t_s`` [s] (S from the scene's physics)."""
        s = float(self.model.occluded_area_px(np.asarray([t_s]))[0])
        return self.render_area(s, offset_px)


def render_frame(scene: Scene, t_s: float) -> ImageU8:
    """One effect-free frame of ``scene`` at ``t_s`` [s] (builds a Renderer: use the class
    for many frames)."""
    return Renderer(scene).render(t_s)
