"""The fault effects of the fault-injection matrix (tests/faults): each loses or replaces
exactly the frames or samples its parameters name, and nothing else."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.errors import ConfigError
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.sim.scene import Scene

SCENES = Path(__file__).resolve().parents[3] / "configs" / "scenes"
FPS = 30.0


def _scene(effects: list[dict[str, Any]]) -> Scene:
    s = load_scene(SCENES / "grade1.yaml").with_camera(width=160, height=120, fps=FPS)
    fp = s.force_profile.model_copy(update={"hold_s": 2.0, "recovery_s": 3.0})
    return s.model_copy(update={"force_profile": fp}).with_effects(effects)


def _indices(effects: list[dict[str, Any]]) -> list[int]:
    return [f.index for f in Pipeline(_scene(effects)).frames()]


def test_frame_gap_loses_exactly_the_span() -> None:
    all_k = _indices([])
    kept = _indices([{"name": "frame_gap", "t_start_s": 1.0, "t_end_s": 2.5}])
    lost = sorted(set(all_k) - set(kept))
    assert lost == list(range(30, 75))  # k / 30 in [1.0, 2.5)
    assert _indices([{"name": "frame_gap"}]) == all_k  # default: an empty span


def test_frame_gap_rejects_a_reversed_span() -> None:
    with pytest.raises(ConfigError, match="t_end_s"):
        _scene([{"name": "frame_gap", "t_start_s": 2.0, "t_end_s": 1.0}])


def test_corrupt_frames_lose_the_nearest_frames_only() -> None:
    all_k = _indices([])
    kept = _indices([{"name": "corrupt_frames", "times_s": [1.0, 2.49, 3.0]}])
    assert sorted(set(all_k) - set(kept)) == [30, 75, 90]
    with pytest.raises(ConfigError, match="times"):
        _scene([{"name": "corrupt_frames", "times_s": [-1.0]}])


def test_outlier_frames_are_uniform_and_measured_as_such() -> None:
    clean = {f.index: f.image for f in Pipeline(_scene([])).frames()}
    effects = [{"name": "outlier_frames", "dark_times_s": [1.0], "bright_times_s": [2.0]}]
    frames = {f.index: f.image for f in Pipeline(_scene(effects)).frames()}
    assert frames.keys() == clean.keys()
    changed = [k for k in clean if not np.array_equal(clean[k], frames[k])]
    assert changed == [30, 60]
    assert np.all(frames[30] == 4) and np.all(frames[60] == 255)
    h, w = frames[30].shape[:2]
    roi = CircleROI(cx_px=w / 2, cy_px=h / 2, radius_px=0.4 * h)
    proc = FrameProcessor(frames[30].shape, 128, roi)
    dark, bright = proc.measure(frames[30]), proc.measure(frames[60])
    assert dark.s_k_px == proc.measure(np.zeros_like(frames[30])).s_k_px > 0  # whole ROI
    assert bright.s_k_px == 0 and Flag.SATURATED_FRAME in bright.flags


def test_outlier_levels_are_ordered() -> None:
    with pytest.raises(ConfigError, match="dark_level"):
        _scene([{"name": "outlier_frames", "dark_level": 200, "bright_level": 100}])


def test_force_dropout_loses_exactly_the_span() -> None:
    clean = Pipeline(_scene([])).force_batch()
    batch = Pipeline(
        _scene([{"name": "force_dropout", "t_start_s": 1.5, "t_end_s": 2.0}])
    ).force_batch()
    assert list(batch.lost_index) == list(range(150, 200))  # 100 Hz, [1.5, 2.0)
    assert np.array_equal(np.sort(np.concatenate([batch.index, batch.lost_index])), clean.index)
    kept = np.isin(clean.index, batch.index)
    assert np.array_equal(batch.adc_counts, clean.adc_counts[kept])
    assert np.array_equal(batch.t_true_s, clean.t_true_s[kept])


def test_force_dropout_adds_to_link_losses() -> None:
    link = {"name": "ble_link", "loss_probability": 0.2}
    lossy = Pipeline(_scene([link])).force_batch()
    both = Pipeline(
        _scene([link, {"name": "force_dropout", "t_start_s": 1.5, "t_end_s": 2.0}])
    ).force_batch()
    expect = set(lossy.lost_index.tolist()) | set(range(150, 200))
    assert set(both.lost_index.tolist()) == expect
