"""Which calibration, threshold p and ROI apply to a measurement.

One implementation for the acquisition daemon and for the offline ``analyze`` command.
"""

from __future__ import annotations

from typing import Any

from stipi_daemon.analysis.calibration import Calibration, load_calibration
from stipi_daemon.analysis.imaging import CircleROI
from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.errors import ConfigError


def resolve_imaging(
    config: DaemonConfig,
) -> tuple[Calibration, int, CircleROI | Any | None, dict[str, Any] | None]:
    """Calibration, threshold p, ROI and (for simulated devices) the scene's ground truth."""
    scene_path = getattr(config.camera, "scene", None)
    truth: dict[str, Any] | None = None
    sim_cal: Calibration | None = None
    sim_roi: CircleROI | None = None
    sim_p: int | None = None
    if scene_path is not None:
        from stipi_daemon.sim.physics import scaled_calibration
        from stipi_daemon.sim.scene import load_scene
        from stipi_daemon.sim.truth import ground_truth

        scene = load_scene(scene_path)
        seed = getattr(config.camera, "seed", None)
        gt = ground_truth(scene, seed)
        truth = gt.to_json_dict()
        sim_cal, _ = scaled_calibration(scene)
        sim_roi = CircleROI(kind="circle", **gt.roi)
        sim_p = int(gt.frame["threshold_p"])
    if config.calibration is not None:
        calibration = load_calibration(config.calibration)
    elif sim_cal is not None:
        calibration = sim_cal
    else:
        raise ConfigError(
            "field 'calibration': a calibration file is required with a real camera "
            "(run `stipi-daemon calibrate`)"
        )
    p = config.imaging.threshold_p
    if p is None:
        p = calibration.threshold_p if calibration.threshold_p is not None else sim_p
    if p is None:
        raise ConfigError(
            "field 'imaging.threshold_p': no threshold given and the calibration has none"
        )
    roi = config.imaging.roi if config.imaging.roi is not None else sim_roi
    return calibration, int(p), roi, truth
