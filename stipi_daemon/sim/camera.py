"""The scene simulator as a live camera, paced on the session clock.

This module owns turning :meth:`stipi_daemon.sim.pipeline.Pipeline.frames` into a camera:
each frame is rendered in the capture thread as soon as the previous one is delivered,
stamped ``t0 + t_frame`` on the session clock (``t0`` = session time of scene time 0, by
default the first open) and delivered no earlier than that time, so a clock running at speed 4
replays a 120 s scene in 30 s of wall time. Frames the scene's effects drop (for example
``dropped_frames``) are missing from the stream and show as ``seq`` gaps. A Motion-JPEG
scene (``camera.pixel_format: mjpg`` or the ``jpeg_compression`` effect) delivers each frame
as an MJPG camera does: the JPEG (``CameraFrame.packet``, which the session video stores as
it is, passthrough), encoded ahead and handed over at its capture time, with its decode
straight to gray (the V4L2 camera's default ``gray: true``), made only then, as the image
the daemon measures (a frame repeating the picture before it, the same JPEG, reuses that
decode); other scenes deliver raw frames as rendered (stored losslessly). It behaves as a
live camera across a stall: a reopen resumes at the current scene time, frames missed
meanwhile are lost. It does not model the probe (that is the simulated transport's job) and
adds no effects of its own; :meth:`~.threaded.ThreadedCamera.stall` injects freezes.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from stipi_daemon.cameras.base import SimulatorCameraConfig
from stipi_daemon.cameras.threaded import RawFrame, ThreadedCamera
from stipi_daemon.clock import SessionClock
from stipi_daemon.sim.effects.processing_stall import Params as ProcessingStall
from stipi_daemon.sim.jpeg import scene_encoding
from stipi_daemon.sim.pipeline import Pipeline, SimFrame
from stipi_daemon.sim.scene import Scene, load_scene

__all__ = ["SimulatorCamera"]

#: Frames the hand-off holds for a lagging consumer [-].
PREFETCH_FRAMES = 8
#: Session seconds between the hand-overs of held-back frames per second of capture time
#: between them (``processing_stall``) [-].
STALL_HANDOVER_SPACING = 1e-6


class SimulatorCamera(ThreadedCamera[Iterator[SimFrame]]):
    """Frames of a simulated scene, delivered in real (session) time.

    Parameters
    ----------
    scene : Scene
        The scene.
    clock : SessionClock
        Session clock.
    seed : int, optional
        Random seed (default: the scene's).
    t0_s : float, optional
        Session time [s] of scene time 0; default: the session time of the first open.
        Pass the simulated probe's origin so frames and force samples share one timeline.
    """

    def __init__(
        self,
        scene: Scene,
        clock: SessionClock,
        *,
        seed: int | None = None,
        t0_s: float | None = None,
    ) -> None:
        super().__init__(clock, capacity=PREFETCH_FRAMES, drop_oldest=False, paced=True)
        self.scene = scene
        self.seed = scene.seed if seed is None else seed
        self._t0_s = t0_s
        self._pipeline: Pipeline | None = None
        self._encoding = scene_encoding(scene)

    @classmethod
    def from_config(
        cls, config: SimulatorCameraConfig, clock: SessionClock, *, t0_s: float | None = None
    ) -> SimulatorCamera:
        """Build from a :class:`~.base.SimulatorCameraConfig` (loads the scene file).

        Raises
        ------
        ConfigError
            The scene file is missing or invalid (the message names file and field).
        """
        return cls(load_scene(Path(config.scene)), clock, seed=config.seed, t0_s=t0_s)

    @property
    def name(self) -> str:
        return f"simulated camera (scene {self.scene.name})"

    @property
    def nominal_fps(self) -> float:
        return float(self.scene.camera.fps)

    @property
    def t0_s(self) -> float | None:
        """Session time of scene time 0 [s] (None until the first open)."""
        return self._t0_s

    def _first_capture_s(self) -> float | None:
        return self._t0_s  # frame 0 is captured at scene time 0

    def _metadata(self) -> dict[str, Any]:
        cam = self.scene.camera
        return {
            "kind": "simulator",
            "scene": self.scene.name,
            "seed": self.seed,
            "fps": cam.fps,
            "size": [cam.width, cam.height],
            "pixel_format": cam.pixel_format,
            "jpeg_quality": self._encoding.jpeg_quality,
            "decoder": "imdecode to gray (JPEG packets)" if self._encoding.is_jpeg else None,
            "t0_s": self._t0_s,
        }

    def _open_source(self) -> Iterator[SimFrame]:
        if self._pipeline is None:
            self._pipeline = Pipeline(self.scene, self.seed, gray_decode=True)
        if self._t0_s is None:
            self._t0_s = self._clock.now()
        # A live camera: resume at the current scene time (a frame due less than half a
        # period ago is still delivered, late), never before the next undelivered frame.
        now_scene_s = self._clock.now() - self._t0_s - 0.5 / self.nominal_fps
        next_s = 0.0 if self._last_seq is None else (self._last_seq + 1) / self.nominal_fps
        start_s = max(0.0, now_scene_s, next_s)
        return self._pipeline.frames(start_s=start_s)

    def _consumer_busy_until_s(self, t_capture_s: float) -> float | None:
        """The scene's ``processing_stall`` spans: a frame captured in one is handed over
        at its end, plus :data:`STALL_HANDOVER_SPACING` of how far into the stall it was
        captured [s of session time]. The spacing puts the held-back frames one after
        another (40 us for a 40 s stall): on a clock that waits for the daemon each is
        handed over once the daemon has dealt with the one before, so what follows (a
        fault at one of them, the end of the run) is the same on every run."""
        t0 = self._t0_s if self._t0_s is not None else 0.0
        t_s = t_capture_s - t0
        until = [
            s.t_end_s + STALL_HANDOVER_SPACING * (t_s - s.t_start_s)
            for s in self.scene.effects
            if isinstance(s, ProcessingStall) and s.t_start_s <= t_s < s.t_end_s
        ]
        return t0 + max(until) if until else None

    def _read(self, handle: Iterator[SimFrame]) -> RawFrame | None:
        f = next(handle, None)  # rendered and, in a Motion-JPEG scene, encoded
        if f is None:
            return None
        t0 = self._t0_s if self._t0_s is not None else 0.0
        t_capture_s = t0 + f.t_s
        if f.packet is not None and not self._wait_until(t_capture_s):
            return None  # closed while waiting for the capture time
        # a JPEG is decoded now, at or after its capture time (a raw frame is as rendered)
        return RawFrame(f.index, t_capture_s, f.image, f.packet)

    def _close_source(self, handle: Iterator[SimFrame]) -> None:
        close = getattr(handle, "close", None)
        if close is not None:
            close()
