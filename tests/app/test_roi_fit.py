"""The ROI must lie within the camera's frame (issue 14 case 6): a config error otherwise."""

from __future__ import annotations

import pytest

from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.devices import frame_size
from stipi_daemon.app.imaging import check_roi_fits, roi_fit_problem
from stipi_daemon.errors import ConfigError


@pytest.mark.parametrize(
    ("roi", "placement"),
    [
        (None, None),
        (CircleROI(cx_px=319.5, cy_px=239.5, radius_px=209.68), None),  # the scenes' disc
        (CircleROI(cx_px=319.5, cy_px=239.5, radius_px=239.5), None),  # touches top and bottom
        (CircleROI(cx_px=319.5, cy_px=239.5, radius_px=240.6), "partly outside"),
        (CircleROI(cx_px=900.0, cy_px=100.0, radius_px=200.0), "outside"),
        (CircleROI(cx_px=-5.0, cy_px=-5.0, radius_px=8.0), "partly outside"),
        (CircleROI(cx_px=319.5, cy_px=239.5, radius_px=1e7), "partly outside"),
        (CircleROI(cx_px=1e7, cy_px=0.0, radius_px=1e6), "outside"),
        (RectROI(x_px=0, y_px=0, width_px=640, height_px=480), None),
        (RectROI(x_px=1, y_px=0, width_px=640, height_px=480), "partly outside"),
        (RectROI(x_px=-40, y_px=0, width_px=40, height_px=480), "outside"),
    ],
)
def test_roi_placement(roi: CircleROI | RectROI | None, placement: str | None) -> None:
    problem = roi_fit_problem(roi, 640, 480, "field 'imaging.roi'")
    if placement is None:
        assert problem is None
        check_roi_fits(roi, 640, 480, "x")
        return
    assert problem is not None
    assert problem.startswith("field 'imaging.roi': ")
    assert f"lies {placement} the 640x480 frame" in problem
    with pytest.raises(ConfigError, match="the ROI must lie within the frame"):
        check_roi_fits(roi, 640, 480, "field 'imaging.roi'")


def test_frame_size_from_camera_metadata() -> None:
    assert frame_size({"size": [640, 480]}) == (640, 480)
    assert frame_size({"width": 320, "height": 240}) == (320, 240)
    assert frame_size({"size": None}) is None
    assert frame_size({}) is None
