"""Rendering: the thresholded occluded area equals S at any resolution; the image looks right."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.imaging import occluded_pixel_count
from stipi_daemon.sim.render import Renderer
from stipi_daemon.sim.scene import load_scene

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"
_SCENE = load_scene(SCENES / "grade3.yaml")
_R640 = Renderer(_SCENE)
_R720 = Renderer(_SCENE.with_camera(width=1280, height=720))
_GRAY = Renderer(
    _SCENE.model_copy(
        update={
            "camera": _SCENE.camera.model_copy(
                update={"pixel_format": "gray8", "width": 320, "height": 240}
            )
        }
    )
)


@pytest.mark.parametrize("renderer", [_R640, _R720, _GRAY], ids=["640", "1280", "gray320"])
def test_count_equals_area_over_many_radii(renderer: Renderer) -> None:
    top = renderer.model.max_occluded_area_px
    for s in np.linspace(1.0, top, 97):
        frame = renderer.render_area(float(s))
        got = occluded_pixel_count(frame, renderer.threshold, renderer.roi)
        assert abs(got - s) <= 0.5 + 1e-9, s


@settings(max_examples=40, deadline=None)
@given(
    s=st.floats(1.0, 20000.0),
    dx=st.floats(-20.0, 20.0),
    dy=st.floats(-20.0, 20.0),
)
def test_count_with_offset_centre(s: float, dx: float, dy: float) -> None:
    frame = _R640.render_area(s, (dx, dy))
    assert abs(occluded_pixel_count(frame, _R640.threshold, _R640.roi) - s) <= 0.5 + 1e-9


def test_frame_appearance() -> None:
    r = _R640
    frame = r.render_area(10000.0)
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    assert np.array_equal(frame[..., 0], frame[..., 2])  # neutral: gray conversion is exact
    cy, cx = round(r.disc_cy_px), round(r.disc_cx_px)
    assert frame[cy, cx, 0] == r.occluded_level  # gray, not black
    assert frame[0, 0, 0] < r.threshold  # dark outside the waveguide
    assert r.dark_pixels_in_roi == 0  # the lit waveguide is above p everywhere in the ROI
    # Anti-aliased edge: intermediate levels exist between the disc and the background.
    row = frame[cy, :, 0].astype(int)
    assert len(set(row[cx : cx + 80].tolist())) > 4
    assert occluded_pixel_count(r.render_area(0.0), r.threshold, r.roi) == 0
