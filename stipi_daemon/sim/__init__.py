"""Everything simulated or emulated: scenes, the simulated camera, the emulated probe.

A scene file (``configs/scenes/*.yaml``) describes tissue, indenter, force profile, probe,
camera, load cell and a list of effects. The package turns it into frames, load-cell
samples and a ground truth: :mod:`.scene` (typed scene files), :mod:`.physics` (closed-form
mechanics), :mod:`.render` (frames), :mod:`.loadcell` (ADC), :mod:`.pipeline` (streams and
effects), :mod:`.jpeg` (the camera's JPEG encoding), :mod:`.truth` (ground truth),
:mod:`.output` (files), :mod:`.effects` (one module per effect, imported only when a scene
lists it). As live devices for the daemon:
:mod:`.camera` (the scene as a camera), :mod:`.imaging` (a scene's calibration, threshold,
ROI and truth), :mod:`.feather` (an emulated Feather 32u4 speaking the wire protocol on a
pty), :mod:`.emulated_transport` (that Feather behind the real serial path) and
:mod:`.ble` (the emulated BLE module, peripheral, radio and bleak backend).

Runtime code never imports this package: a config that asks for a simulated device names
it by kind, and :mod:`stipi_daemon.registry` imports the module by name on first use. See
docs/simulator.md and docs/architecture.md.
"""

from __future__ import annotations

from stipi_daemon.sim.loadcell import LoadCellModel
from stipi_daemon.sim.output import OutputPaths, write_outputs
from stipi_daemon.sim.physics import SceneModel, scaled_calibration
from stipi_daemon.sim.pipeline import (
    ForceBatch,
    ForceSample,
    Pipeline,
    SimFrame,
    force_samples,
    frame_count,
    iter_force_samples,
    iter_frames,
)
from stipi_daemon.sim.render import Renderer, render_frame
from stipi_daemon.sim.scene import Scene, load_scene, parse_scene
from stipi_daemon.sim.truth import GroundTruth, ground_truth

__all__ = [
    "ForceBatch",
    "ForceSample",
    "GroundTruth",
    "LoadCellModel",
    "OutputPaths",
    "Pipeline",
    "Renderer",
    "Scene",
    "SceneModel",
    "SimFrame",
    "force_samples",
    "frame_count",
    "ground_truth",
    "iter_force_samples",
    "iter_frames",
    "load_scene",
    "parse_scene",
    "render_frame",
    "scaled_calibration",
    "write_outputs",
]
