"""Effect ``sensor_noise``: Gaussian read noise of the camera sensor, per pixel and channel.

Owns only the noise model: zero-mean Gaussian, ``sigma_levels`` gray levels, rounded to
whole levels and added with clipping to 0..255; one draw per pixel, shared by the three
channels of a BGR frame so that the gray conversion sees the full sigma. Pixels near the
edge of the occluded disc cross the threshold p, so S_k scatters by about the edge pixels
within sigma of p.

Generation (for speed, ~4x faster than drawing normals): each pixel draws a 16-bit
uniform u from the frame's generator and looks up n = rint(sigma * Phi^-1((u + 1/2) /
65536)) in a 65536-entry table (inverse-CDF sampling). The rounded noise has the rounded
Gaussian's distribution with every probability quantised to 2^-16, and the tails are cut
at |z| <= 4.32 (-Phi^-1(0.5 / 65536)): a value beyond 4.32 sigma occurs with probability
1.5e-5 in the exact model and never here. The table is split into positive and negative
parts (uint8) and applied with OpenCV's saturating add and subtract, which equals
clip(image + n, 0, 255) exactly.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.special import ndtri

from stipi_daemon.sim.effects.base import EffectContext, EffectParams, FrameEffect

#: Number of entries of the inverse-CDF table (16-bit uniforms).
TABLE_SIZE = 65536


def noise_table(sigma_levels: float) -> NDArray[np.int16]:
    """Rounded noise [gray levels] for each 16-bit uniform draw, clipped to +-255."""
    q = (np.arange(TABLE_SIZE, dtype=np.float64) + 0.5) / TABLE_SIZE
    out: NDArray[np.int16] = np.clip(np.rint(sigma_levels * ndtri(q)), -255, 255).astype(np.int16)
    return out


class Params(EffectParams):
    """``sigma_levels``: standard deviation of the read noise [gray levels]."""

    name: Literal["sensor_noise"] = "sensor_noise"
    sigma_levels: float = Field(default=2.0, ge=0.0, le=128.0)


class Effect(FrameEffect):
    def __init__(self, params: Params, context: EffectContext) -> None:
        self.params = params
        table = noise_table(params.sigma_levels)
        # One uint16 entry per draw: low byte max(n, 0), high byte max(-n, 0).
        pos = np.maximum(table, 0).astype(np.uint16)
        neg = np.maximum(-table, 0).astype(np.uint16)
        self._packed: NDArray[np.uint16] = np.asarray(pos | (neg << 8), dtype=np.uint16)

    def noise(self, shape: tuple[int, int], rng: np.random.Generator) -> NDArray[np.int16]:
        """One frame's rounded noise [gray levels] (the draws :meth:`apply_frame` makes)."""
        pos, neg = self._draw(shape, rng)
        out: NDArray[np.int16] = pos.astype(np.int16) - neg.astype(np.int16)
        return out

    def _draw(
        self, shape: tuple[int, int], rng: np.random.Generator
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        h, w = shape
        u = np.frombuffer(rng.bytes(2 * h * w), dtype=np.uint16).reshape(h, w)
        packed = np.take(self._packed, u).view(np.uint8).reshape(h, w, 2)
        # Little-endian view: channel 0 the low byte (positive part), 1 the high byte.
        if np.little_endian:
            pos, neg = cv2.split(packed)
        else:  # pragma: no cover - big-endian hosts
            neg, pos = cv2.split(packed)
        return np.asarray(pos, dtype=np.uint8), np.asarray(neg, dtype=np.uint8)

    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        pos, neg = self._draw((image.shape[0], image.shape[1]), rng)
        if image.ndim == 3:
            pos = np.asarray(cv2.merge([pos] * image.shape[2]), dtype=np.uint8)
            neg = np.asarray(cv2.merge([neg] * image.shape[2]), dtype=np.uint8)
        out: NDArray[np.uint8] = np.asarray(cv2.subtract(cv2.add(image, pos), neg), dtype=np.uint8)
        return out
