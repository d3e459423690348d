"""Camera sources for the daemon: one module per source behind one small protocol.

:mod:`.base` holds the shared types (:class:`CameraFrame`, events, :class:`CameraStats`,
the :class:`Camera` protocol and the config models), :mod:`.threaded` the capture-thread
machinery, :mod:`.stream` stall detection and reopening (:class:`CameraStream`), and one
module per source: :mod:`.v4l2` (a real camera), :mod:`.video_file` (a recorded video),
:mod:`stipi_daemon.sim.camera` (the scene simulator). :func:`open_camera` builds a source from
its config and imports only that source's module, by name through :mod:`stipi_daemon.registry`
(``camera:<kind>``), so the daemon never loads the simulator (or OpenCV's V4L2 code path)
unless the config asks for it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from stipi_daemon.cameras.base import (
    Camera,
    CameraEvent,
    CameraFrame,
    CameraRecovered,
    CameraStalled,
    CameraStats,
    SimulatorCameraConfig,
    V4L2CameraConfig,
    VideoFileCameraConfig,
)
from stipi_daemon.cameras.stream import CameraStream
from stipi_daemon.clock import SessionClock
from stipi_daemon.registry import load

__all__ = [
    "Camera",
    "CameraConfig",
    "CameraEvent",
    "CameraFrame",
    "CameraRecovered",
    "CameraStalled",
    "CameraStats",
    "CameraStream",
    "SimulatorCameraConfig",
    "V4L2CameraConfig",
    "VideoFileCameraConfig",
    "open_camera",
]

CameraConfig = Annotated[
    V4L2CameraConfig | VideoFileCameraConfig | SimulatorCameraConfig,
    Field(discriminator="kind"),
]
"""Any camera source's config; ``kind`` selects it (``v4l2``, ``file``, ``simulator``)."""


def open_camera(
    config: V4L2CameraConfig | VideoFileCameraConfig | SimulatorCameraConfig,
    clock: SessionClock,
    *,
    t0_s: float | None = None,
) -> Camera:
    """Build the camera a config describes (not yet opened: ``await camera.open()``).

    Parameters
    ----------
    config : CameraConfig
        The source's config.
    clock : SessionClock
        Session clock the camera stamps (and, for replayed sources, paces) frames with.
    t0_s : float, optional
        For replayed and simulated sources: session time of their time 0 [s] (default:
        the first open). Ignored by live cameras.

    Raises
    ------
    ConfigError
        A simulator scene file is missing or invalid.
    """
    cls = load(f"camera:{config.kind}")
    if config.kind == "v4l2":
        camera: Camera = cls.from_config(config, clock)
    else:
        camera = cls.from_config(config, clock, t0_s=t0_s)
    return camera
