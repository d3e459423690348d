"""A simulated scene's imaging: its calibration, threshold p, waveguide ROI and ground truth.

The application chooses which calibration, threshold and ROI apply
(:mod:`stipi_daemon.app.imaging`); when the camera is the scene simulator, the scene is one
of the sources it weighs. The application reaches this module through the lazy registry
(:mod:`stipi_daemon.registry`, name ``"scene:imaging"``), never by an import statement.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.imaging import CircleROI
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.sim.truth import ground_truth

__all__ = ["scene_imaging"]


def scene_imaging(
    scene_path: str | Path, seed: int | None
) -> tuple[Calibration, int, CircleROI, dict[str, Any]]:
    """What a simulated scene says about the imaging.

    Parameters
    ----------
    scene_path : str or Path
        The scene file.
    seed : int or None
        The camera's noise seed (the ground truth's rendering depends on it).

    Returns
    -------
    (Calibration, int, CircleROI, dict)
        The scene's calibration in the rendered resolution's pixel units
        (:func:`~stipi_daemon.sim.physics.scaled_calibration`, made in the waveguide
        disc: its true occluded area is the area within the disc), its threshold p of
        Eq. (1) [8-bit intensity], the waveguide disc as the ROI [px] and the ground truth
        (``ground_truth.json``'s document).
    """
    scene = load_scene(scene_path)
    gt = ground_truth(scene, seed)
    roi = CircleROI(kind="circle", **gt.roi)
    calibration = dataclasses.replace(scaled_calibration(scene)[0], roi=roi)
    return calibration, int(gt.frame["threshold_p"]), roi, gt.to_json_dict()
