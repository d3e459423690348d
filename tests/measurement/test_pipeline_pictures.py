"""The pipeline judges the picture when the frames' levels are fed (measurement/pipeline.py).

The simulator's own camera effects (stipi_daemon/sim/effects) on the grade-III scene,
rendered small (160 x 120 at 30 fps) to keep the test short; the frames' levels are
measured here with :class:`~stipi_daemon.analysis.image_quality.LevelMeter` and fed with
each frame, as the live shell would. The rule checked: a result off its truth by more than
its tolerance is never valid, and the clean scene stays valid. (The laws behind the
estimates are checked against frames rendered in tests/analysis/test_image_quality.py.)
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from stipi_daemon.analysis.image_quality import LevelMeter
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import assess_validity
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.pipeline import Pipeline
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.sim.truth import ground_truth
from tests.conftest import REPO_ROOT


def _run(
    tmp_path: Path, effects: list[dict[str, Any]], force_rail_n: float | None = None
) -> tuple[dict[str, Any], Any, Any]:
    """The scene through the pipeline; ``force_rail_n``: the load cell reads at most this
    [N] (pinned at its full scale above it), and the pipeline is told so."""
    spec = yaml.safe_load((REPO_ROOT / "configs" / "scenes" / "grade3.yaml").read_text())
    spec["camera"].update(width=160, height=120, fps=30.0)
    spec["effects"] = effects
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(spec))
    scene = load_scene(path)
    truth = ground_truth(scene)
    cal, _ = scaled_calibration(scene)
    sim = Pipeline(scene)
    roi = CircleROI(kind="circle", **truth.roi)
    p = int(truth.frame["threshold_p"])
    proc: FrameProcessor | None = None
    meter: LevelMeter | None = None
    mp = MeasurementPipeline(
        measurement=MeasurementConfig(),
        analysis=AnalysisSettings(
            indenter_radius_mm=scene.indenter.diameter_mm / 2, bootstrap_replicates=0
        ),
        calibration=cal,
        reference=load_reference(),
    )
    batch = sim.force_batch()
    force = np.asarray(batch.force_n, dtype=np.float64)
    if force_rail_n is not None:
        force = np.minimum(force, force_rail_n)
        mp.force_full_scale_n = (force_rail_n, 0.0543)
    mp.arm(0.0)
    fi = 0
    for fr in sim.frames():
        if proc is None or meter is None:
            proc = FrameProcessor(fr.image.shape, p, roi)
            meter = LevelMeter(fr.image.shape, p, roi)
            mp.picture_setup = (p, proc.roi_pixel_count, 0.01)
        while fi < batch.index.size and batch.t_true_s[fi] <= fr.t_s:
            mp.force(float(batch.t_true_s[fi]), float(force[fi]))
            fi += 1
        mp.picture(fr.t_s, meter.measure(fr.image))
        mp.frame(fr.t_s, float(proc.count(fr.image)))
        if mp.finished:
            break
    assert mp.result is not None, mp.analysis_error
    validity = assess_validity(mp.result, ended_done=True)["validity"]
    return validity, mp.result, truth


def _check(validity: dict[str, Any], result: Any, truth: Any) -> list[str]:
    """The quantities off their truth beyond tolerance; each must be invalid."""
    p = result.pitting
    measured = {
        "depth_mm": (p.depth_mm, truth.depth_mm, 0.05 * truth.depth_mm),
        "rebound_force_n": (p.rebound_force_n, truth.rebound_force_n, 0.05 * truth.rebound_force_n),
        "recovery_time_s": (
            p.recovery_time_s,
            truth.recovery_time_s,
            max(0.05 * truth.recovery_time_s, 2 / 30),
        ),
    }
    off = []
    for q, (value, true, tol) in measured.items():
        if value is None or not math.isfinite(value) or abs(value - true) > tol:
            off.append(q)
            assert validity[q]["status"] == "invalid", (q, value, true, validity[q])
    return off


def test_clean_scene_is_valid_with_its_picture_judged(tmp_path: Path) -> None:
    validity, result, truth = _run(tmp_path, [])
    assert result.image_quality is not None
    assert _check(validity, result, truth) == []
    assert all(
        validity[q]["status"] == "valid" for q in ("depth_mm", "rebound_force_n", "recovery_time_s")
    ), {q: validity[q] for q in ("depth_mm", "rebound_force_n", "recovery_time_s")}


@pytest.mark.parametrize(
    "effect",
    [
        {"name": "led_flicker", "depth": 0.4, "frequency_hz": 0.7, "sigma": 0.0},
        {"name": "sensor_noise", "sigma_levels": 20.0},
        {"name": "vignetting", "strength": 0.9, "radius_fraction": 0.8},
        {"name": "saturation", "gain": 3.0},
    ],
    ids=["flicker", "noise", "vignetting", "saturation"],
)
def test_a_camera_effect_never_leaves_a_wrong_result_valid(
    tmp_path: Path, effect: dict[str, Any]
) -> None:
    validity, result, truth = _run(tmp_path, [effect])
    off = _check(validity, result, truth)
    judged = [q for q, v in validity.items() if "image_quality" in v["flags"]]
    assert off or judged  # the effect is seen: a result is off (and invalid) or flagged
    assert np.isfinite(result.image_quality.noise_levels) if result.image_quality else True


def test_a_load_cell_pinned_at_full_scale_invalidates_fa_and_e(tmp_path: Path) -> None:
    validity, result, _truth = _run(tmp_path, [], force_rail_n=15.0)
    assert result.applied_force_n < 0.95 * 16.0  # the mean of pinned samples is low
    assert validity["applied_force_n"]["status"] == "invalid"
    assert "full scale" in validity["applied_force_n"]["reason"]
    assert validity["elasticity_kpa"]["status"] == "invalid"
    assert validity["depth_mm"]["status"] == "valid"
