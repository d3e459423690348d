"""The simulator's streams: frames with timestamps and load-cell samples, with effects.

This module owns the schedule of frames (k / fps) and samples (i / rate on the MCU's
clock), the seeding (one ``SeedSequence`` per scene seed, one child per effect and
stream, so that frames and samples are reproducible and independent of each other) and
the application of the scene's effects in registry order, and the camera's encoder: in a
Motion-JPEG scene (:func:`.jpeg.scene_encoding`) each frame is JPEG-encoded once, after
every image effect, and the frame's image is the decode of that JPEG, which the frame
carries (``packet``); other scenes' frames are raw. The decode is made when the image is
first asked for (``SimFrame.image``, ``cv2.imdecode`` as always), so the simulated camera
hands the JPEG over at the frame's capture time and decodes it after, as an MJPG camera's
frame is decoded. A scene without effects builds an empty effect list and runs no effect
code. It does not write files (:mod:`.output`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.sim.effects import EFFECT_MODULES, effect_module
from stipi_daemon.sim.effects.base import (
    EffectContext,
    ForceEffect,
    FrameDropEffect,
    FrameEffect,
    RenderEffect,
    SampleClockEffect,
)
from stipi_daemon.sim.jpeg import Encoding, decode_jpeg, encode_jpeg, scene_encoding
from stipi_daemon.sim.loadcell import LoadCellModel
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.render import Renderer
from stipi_daemon.sim.scene import Scene

__all__ = [
    "ForceBatch",
    "ForceSample",
    "JpegImage",
    "Pipeline",
    "SimFrame",
    "force_samples",
    "frame_count",
    "iter_force_samples",
    "iter_frames",
]


class JpegImage:
    """A frame's JPEG and its decode (:func:`.jpeg.decode_jpeg`), made on first use and kept
    (frames that repeat the picture before them share it: one decode)."""

    __slots__ = ("_channels", "_image", "_read_only", "packet")

    def __init__(self, packet: bytes, channels: int, *, read_only: bool = False) -> None:
        #: The JPEG as the camera delivers it.
        self.packet = packet
        self._channels = channels
        self._read_only = read_only
        self._image: NDArray[np.uint8] | None = None

    def image(self) -> NDArray[np.uint8]:
        """The decode (``cv2.imdecode`` to the pipeline's layout), made now if not yet."""
        if self._image is None:
            image = decode_jpeg(self.packet, self._channels)
            image.flags.writeable = not self._read_only
            self._image = image
        return self._image


@dataclass(frozen=True)
class SimFrame:
    """One frame: its camera index, timestamp [s], picture and the true S at that time [px].

    ``pixels`` is the raw image as rendered (``packet`` None, ``image`` that image), or in a
    Motion-JPEG scene the :class:`JpegImage` the camera delivered: ``packet`` is then its
    JPEG and ``image`` its decode, made when ``image`` is first read.
    """

    index: int
    t_s: float
    pixels: NDArray[np.uint8] | JpegImage
    true_area_px: float

    @property
    def image(self) -> NDArray[np.uint8]:
        """The image the daemon measures (a JPEG frame's decode, made now if not yet)."""
        p = self.pixels
        return p.image() if isinstance(p, JpegImage) else p

    @property
    def packet(self) -> bytes | None:
        """The frame's JPEG in a Motion-JPEG scene, else None."""
        p = self.pixels
        return p.packet if isinstance(p, JpegImage) else None


@dataclass(frozen=True)
class ForceSample:
    """One load-cell sample.

    Attributes
    ----------
    index : int
        Sample counter since boot (gaps: lost samples).
    t_mcu_us : int
        MCU clock when the sample was taken, 64-bit, unwrapped [us].
    t_true_s : float
        True time of the sample on the scene's clock [s].
    adc_counts : int
        Raw ADC code.
    force_n : float
        The host's conversion of ``adc_counts`` (nominal zero and span) [N].
    true_force_n : float
        The model's force at ``t_true_s`` before effects and quantisation [N].
    t_host_s : float
        When the host receives the sample, on the scene's clock [s] (``t_true_s`` without
        a link effect such as ``ble_link``).
    """

    index: int
    t_mcu_us: int
    t_true_s: float
    adc_counts: int
    force_n: float
    true_force_n: float
    t_host_s: float


@dataclass(frozen=True)
class ForceBatch:
    """All delivered samples of a scene as arrays (fields as :class:`ForceSample`).

    ``lost_index`` holds the index of every sample taken but not delivered (sorted), so
    that ``index`` and ``lost_index`` together are exactly ``0 .. n - 1``.
    """

    index: NDArray[np.int64]
    t_mcu_us: NDArray[np.int64]
    t_true_s: NDArray[np.float64]
    adc_counts: NDArray[np.int64]
    force_n: NDArray[np.float64]
    true_force_n: NDArray[np.float64]
    t_host_s: NDArray[np.float64]
    lost_index: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.index.size)

    def samples(self) -> Iterator[ForceSample]:
        """The samples one by one."""
        for i in range(self.index.size):
            yield ForceSample(
                index=int(self.index[i]),
                t_mcu_us=int(self.t_mcu_us[i]),
                t_true_s=float(self.t_true_s[i]),
                adc_counts=int(self.adc_counts[i]),
                force_n=float(self.force_n[i]),
                true_force_n=float(self.true_force_n[i]),
                t_host_s=float(self.t_host_s[i]),
            )


def frame_count(scene: Scene) -> int:
    """Number of frames: every k / fps in [0, duration] [-]."""
    return math.floor(scene.force_profile.duration_s * scene.camera.fps + 1e-9) + 1


class Pipeline:
    """A scene's renderer, physics and instantiated effects, seeded.

    Parameters
    ----------
    scene : Scene
        The scene.
    seed : int, optional
        Random seed (default: the scene's ``seed``).
    renderer : Renderer, optional
        Reuse an existing renderer of the same scene.
    gray_decode : bool
        Decode a Motion-JPEG scene's frames straight to gray (``cv2.IMREAD_GRAYSCALE``, the
        JPEG's luma), as the daemon's MJPG cameras do with ``gray: true``; default: to the
        rendered layout. Raw frames are not affected.
    """

    def __init__(
        self,
        scene: Scene,
        seed: int | None = None,
        renderer: Renderer | None = None,
        *,
        gray_decode: bool = False,
    ):
        self.scene = scene
        self.seed = scene.seed if seed is None else seed
        self.renderer = renderer if renderer is not None else Renderer(scene)
        self.model: SceneModel = self.renderer.model
        self.load_cell = LoadCellModel(scene.load_cell)
        ctx = EffectContext(
            width_px=scene.camera.width,
            height_px=scene.camera.height,
            fps=scene.camera.fps,
            exposure_s=scene.camera.exposure_s,
            threshold=scene.probe.threshold,
            sample_rate_hz=scene.load_cell.sample_rate_hz,
            range_n=scene.load_cell.range_n,
            px_per_mm=self.renderer.px_per_mm,
        )
        order = list(EFFECT_MODULES)
        params = sorted(scene.effects, key=lambda p: order.index(p.name))
        #: Instantiated effects, in order of application (empty for a clean scene).
        self.effects: list[object] = [effect_module(p.name).Effect(p, ctx) for p in params]
        #: The camera's encoding: JPEG quality or raw (``jpeg_compression`` is applied as it).
        self.encoding: Encoding = scene_encoding(scene)
        self._channels = 1 if gray_decode else self.renderer.channels
        children = np.random.SeedSequence(self.seed).spawn(len(self.effects))
        self._seeds = [c.spawn(2) for c in children]

    def _of(self, kind: type[Any], stream: int) -> list[tuple[Any, np.random.SeedSequence]]:
        return [
            (e, s[stream])
            for e, s in zip(self.effects, self._seeds, strict=True)
            if isinstance(e, kind)
        ]

    def frames(self, start_s: float = 0.0, end_s: float | None = None) -> Iterator[SimFrame]:
        """Frames with k / fps in [start_s, end_s] (default: the whole scene).

        A frame's image does not depend on the window: random effects draw per frame from
        generators seeded by (seed, effect, frame index).
        """
        fps = self.scene.camera.fps
        n = frame_count(self.scene)
        k0 = max(0, math.ceil(start_s * fps - 1e-9))
        k1 = n - 1 if end_s is None else min(n - 1, math.floor(end_s * fps + 1e-9))
        render_fx: list[tuple[RenderEffect, np.random.SeedSequence]] = self._of(RenderEffect, 0)
        frame_fx: list[tuple[FrameEffect, np.random.SeedSequence]] = [
            (e, ss)
            for e, ss in self._of(FrameEffect, 0)
            if getattr(getattr(e, "params", None), "name", None) != "jpeg_compression"
        ]
        drop_fx: list[tuple[FrameDropEffect, np.random.SeedSequence]] = self._of(FrameDropEffect, 0)
        model = self.model
        if not (render_fx or frame_fx or drop_fx):
            yield from self._clean_frames(k0, k1)
            return
        for k in range(k0, k1 + 1):
            t = k / fps
            rngs: dict[int, np.random.Generator] = {}
            for group in (render_fx, frame_fx, drop_fx):
                for e, ss in group:
                    rngs[id(e)] = _frame_rng(ss, k)
            if any(not e.keep(k, t, rngs[id(e)]) for e, _ in drop_fx):
                continue
            s = float(model.occluded_area_px(np.asarray([t]))[0])
            image = self._render(k, t, render_fx, rngs)
            for e, _ in frame_fx:
                image = e.apply_frame(image, t, rngs[id(e)])
            yield self._encoded(k, t, image, s)

    def _clean_frames(self, k0: int, k1: int) -> Iterator[SimFrame]:
        """Frames ``k0..k1`` of a scene without effects. A frame's picture depends only on
        its pixel count round(S) (:meth:`Renderer.render_area`), so a frame with the count of
        the one before it is that frame's picture again (and JPEG), not drawn anew: the same
        pixels, read-only, as the frames are (in a recovery S creeps by less than a pixel per
        frame: 72 % of the demo's frames)."""
        fps = self.scene.camera.fps
        times = np.arange(k0, k1 + 1, dtype=np.float64) / fps
        areas = self.model.occluded_area_px(times)
        last: tuple[int, SimFrame] | None = None
        for j, k in enumerate(range(k0, k1 + 1)):
            s, t = float(areas[j]), float(times[j])
            if last is not None and last[0] == round(s):
                yield SimFrame(k, t, last[1].pixels, s)
                continue
            f = self._encoded(k, t, self.renderer.render_area(s), s, read_only=True)
            last = (round(s), f)
            yield f

    def _encoded(
        self, k: int, t: float, image: NDArray[np.uint8], s: float, *, read_only: bool = False
    ) -> SimFrame:
        """The frame as the camera delivers it: raw, or its JPEG (encoded once, decoded when
        its image is first read; ``read_only``: that decode is not writeable)."""
        q = self.encoding.jpeg_quality
        if q is None:
            if read_only:
                image.flags.writeable = False
            return SimFrame(k, t, image, s)
        packet = encode_jpeg(image, q)
        return SimFrame(k, t, JpegImage(packet, self._channels, read_only=read_only), s)

    def _render(
        self,
        k: int,
        t: float,
        render_fx: list[tuple[RenderEffect, np.random.SeedSequence]],
        rngs: dict[int, np.random.Generator],
    ) -> NDArray[np.uint8]:
        if not render_fx:
            return self.renderer.render(t)
        sub_times: tuple[float, ...] = (t,)
        for e, _ in render_fx:
            st = e.sub_times_s(t)
            if len(st) > 1:
                sub_times = st
        acc: NDArray[np.uint16] | None = None
        for j, ts in enumerate(sub_times):
            dx, dy = 0.0, 0.0
            for e, ss in render_fx:
                # Every sub-frame of an exposure restarts the effect's per-frame generator:
                # a random draw (e.g. a tremor phase) is per frame, smooth within it.
                g = rngs[id(e)] if j == 0 else _frame_rng(ss, k)
                ox, oy = e.offset_px(ts, g)
                dx, dy = dx + ox, dy + oy
            img = self.renderer.render(ts, (dx, dy))
            if len(sub_times) == 1:
                return img
            if acc is None:
                acc = img.astype(np.uint16)
            else:
                np.add(acc, img, out=acc)
        assert acc is not None
        # Mean of the sub-frames, rounded half up (uint16: up to 257 sub-frames of 255).
        n = len(sub_times)
        acc += n // 2
        out: NDArray[np.uint8] = (acc // n).astype(np.uint8)
        return out

    def force_counts(self, t_true_s: NDArray[np.float64]) -> NDArray[np.int64]:
        """ADC codes of samples taken at true times ``t_true_s`` [s], every force effect of
        the scene applied, as :meth:`force_batch` applies them.

        The model's force at each time goes through each :class:`ForceEffect` in registry
        order (its ``apply_force``, then the load cell's quantisation and clipping to the
        ADC's range, then its ``apply_counts``). Each effect draws from its own generator,
        seeded by (seed, effect) as in :meth:`force_batch` and started afresh at every
        call, over the array in order: element j of a call gets the draws sample j of the
        scene's own schedule gets, whatever the times (the emulated probe's sample times,
        :class:`stipi_daemon.sim.feather.SceneAdc`).
        """
        force = self.model.force_n(t_true_s)
        force_fx: list[tuple[ForceEffect, np.random.Generator]] = [
            (fe, np.random.default_rng(ss)) for fe, ss in self._of(ForceEffect, 1)
        ]
        for fe, fg in force_fx:
            force = fe.apply_force(t_true_s, force, fg)
        counts = self.load_cell.counts(force)
        for fe, fg in force_fx:
            counts = fe.apply_counts(counts, fg)
        return counts

    def link_lost(self, t_true_s: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which samples taken at true times ``t_true_s`` [s] the scene's ``force_dropout``
        effects lose on the link (each effect's own ``delivered``); all False without one.

        Only ``force_dropout`` is a loss defined by the time a sample is taken; the other
        losses (``ble_link``'s random batches) belong to a link model of their own.
        """
        lost = np.zeros(t_true_s.shape, dtype=np.bool_)
        index = np.arange(t_true_s.size, dtype=np.int64)
        for ce, ss in self._of(SampleClockEffect, 1):
            if getattr(getattr(ce, "params", None), "name", None) != "force_dropout":
                continue
            g = np.random.default_rng(ss)
            ce.true_time_s(t_true_s, g)  # the effect keeps the times delivered() judges
            lost |= ~ce.delivered(index, g)
        return lost

    def force_batch(self) -> ForceBatch:
        """All load-cell samples the host receives, as arrays."""
        spec = self.scene.load_cell
        n = math.floor(self.scene.force_profile.duration_s * spec.sample_rate_hz + 1e-9) + 1
        index = np.arange(n, dtype=np.int64)
        t_nominal = index / spec.sample_rate_hz
        t_true = t_nominal
        mcu_us = t_nominal * 1e6
        delivered = np.ones(n, dtype=np.bool_)
        clock_fx: list[tuple[SampleClockEffect, np.random.SeedSequence]] = self._of(
            SampleClockEffect, 1
        )
        gens = [(ce, np.random.default_rng(ss)) for ce, ss in clock_fx]
        for ce, g in gens:
            t_true = ce.true_time_s(t_true, g)
        for ce, g in gens:
            mcu_us = ce.mcu_time_us(t_true, mcu_us, g)
        for ce, g in gens:
            delivered &= ce.delivered(index, g)
        t_host = t_true
        for ce, g in gens:
            t_host = ce.host_time_s(index, t_host, delivered, g)
        true_force = self.model.force_n(t_true)
        counts = self.force_counts(t_true)
        t_mcu = spec.mcu_boot_offset_us + np.rint(mcu_us).astype(np.int64)
        return ForceBatch(
            index=index[delivered],
            t_mcu_us=t_mcu[delivered],
            t_true_s=t_true[delivered],
            adc_counts=counts[delivered],
            force_n=self.load_cell.force_n(counts[delivered]),
            true_force_n=true_force[delivered],
            t_host_s=t_host[delivered],
            lost_index=index[~delivered],
        )


def _frame_rng(ss: np.random.SeedSequence, k: int) -> np.random.Generator:
    # A per-frame generator derived from the effect's seed and the frame index, so a
    # frame's noise does not depend on which frames were rendered before it.
    return np.random.default_rng(np.random.SeedSequence(ss.entropy, spawn_key=(*ss.spawn_key, k)))


def iter_frames(
    scene: Scene, seed: int | None = None, *, start_s: float = 0.0, end_s: float | None = None
) -> Iterator[SimFrame]:
    """Frames of ``scene`` with timestamps, effects applied, deterministic for ``seed``."""
    return Pipeline(scene, seed).frames(start_s, end_s)


def force_samples(scene: Scene, seed: int | None = None) -> ForceBatch:
    """All delivered load-cell samples of ``scene`` as arrays."""
    return Pipeline(scene, seed).force_batch()


def iter_force_samples(scene: Scene, seed: int | None = None) -> Iterator[ForceSample]:
    """Load-cell samples of ``scene`` one by one."""
    return force_samples(scene, seed).samples()
