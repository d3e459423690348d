"""The acquisition loop's camera side: S_k measured, the image kept there, a result queued."""

from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace
from typing import Any

import numpy as np

from stipi_daemon.app.acquisition import FrameMeasurer, FrameResult
from stipi_daemon.cameras import CameraFrame, CameraStalled
from stipi_daemon.clock import ScaledClock
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase


def _pipeline(phase: Phase) -> Any:
    state = SimpleNamespace(phase=phase, t_pit_start_s=0.0, t_release_s=None)
    return SimpleNamespace(state=state)


def test_frame_result_carries_no_image_and_the_keeper_gets_it() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    measurer = FrameMeasurer(ScaledClock(1.0), 128, None, 0.5, keeper, _pipeline(Phase.PITTING))
    image = np.zeros((4, 5), dtype=np.uint8)
    image[:2] = 255  # 10 pixels above p: S_k counts the 10 at or below it (Eq. 2)
    result = measurer(CameraFrame(7, 1.0, image, 0))
    assert isinstance(result, FrameResult)
    assert (result.seq, result.t_capture_s, result.s_k, result.dropped_before) == (7, 1.0, 10, 0)
    assert not any(isinstance(getattr(result, f.name), np.ndarray) for f in fields(result))
    chosen = keeper.selected()
    assert [f.kind for f in chosen] == ["pitting", "recovery_start"]
    assert chosen[0].image is image


def test_other_camera_events_pass_unchanged() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    measurer = FrameMeasurer(ScaledClock(1.0), 128, None, 0.5, keeper, _pipeline(Phase.ARMED))
    stalled = CameraStalled(3.0, 6, 1.0, "timeout")
    assert measurer(stalled) is stalled
    assert keeper.selected() == ()
