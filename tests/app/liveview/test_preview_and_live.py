"""Preview JPEGs tint exactly the pixels S_k counts; when the daemon serves the view.

The tint test decodes the preview and compares it with the frame: inside the ROI the
pixels at or below p are red, every other pixel is gray. The view is served for an
interactive console or ``view.enabled``, never for a quiet or piped run by default;
another interface than loopback is warned about; a port in use is a warning, not a
failure of the measurement.
"""

from __future__ import annotations

import io
import socket

import cv2
import numpy as np

from stipi_daemon.app.config import ViewSettings
from stipi_daemon.app.console import OperatorConsole
from stipi_daemon.app.liveview.live import live_statuses, serving_live_view, view_wanted
from stipi_daemon.app.liveview.preview import PREVIEW_MAX_WIDTH_PX, preview_jpeg
from stipi_daemon.measurement.state_machine import MeasurementConfig
from tests.app.liveview._view import flagged_params, get, view_info


def test_the_counted_pixels_are_tinted_and_nothing_else() -> None:
    rng = np.random.default_rng(7)
    blocks = rng.integers(0, 256, size=(15, 20), dtype=np.uint8)  # 8x8 px patches
    image = np.kron(blocks, np.ones((8, 8), dtype=np.uint8))
    roi = {"kind": "rect", "x_px": 20, "y_px": 10, "width_px": 100, "height_px": 80}
    jpeg, step = preview_jpeg(image, 100, roi)
    assert step == 1
    shown = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)
    redness = shown[..., 2] - shown[..., 0]
    inside = np.zeros(image.shape, dtype=bool)
    inside[10:90, 20:120] = True
    counted = inside & (image <= 100)
    # JPEG blurs colour at edges: judge pixels whose 3x3 neighbourhood agrees
    calm = cv2.erode(counted.astype(np.uint8), np.ones((3, 3))) > 0
    lit = cv2.dilate(counted.astype(np.uint8), np.ones((3, 3))) == 0
    assert calm.any() and lit.any()
    assert (redness[calm] > 40).mean() > 0.95
    assert (np.abs(redness[lit]) < 25).mean() > 0.95


def test_large_frames_are_subsampled_to_the_preview_width() -> None:
    image = np.full((720, 1280, 3), 200, dtype=np.uint8)
    jpeg, step = preview_jpeg(
        image, 100, {"kind": "circle", "cx_px": 640, "cy_px": 360, "radius_px": 300}
    )
    shown = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert step == 4 and shown.shape[1] == 320 <= PREVIEW_MAX_WIDTH_PX


def _console(tty: bool, quiet: bool = False) -> OperatorConsole:
    class Out(io.StringIO):
        def isatty(self) -> bool:
            return tty

    return OperatorConsole(MeasurementConfig(), Out(), live=False, quiet=quiet)


def test_served_for_interactive_runs_or_when_enabled() -> None:
    auto = ViewSettings()
    assert view_wanted(auto, _console(tty=True))
    assert not view_wanted(auto, _console(tty=False))
    assert not view_wanted(auto, _console(tty=True, quiet=True))
    assert view_wanted(ViewSettings(enabled=True), _console(tty=False, quiet=True))
    assert not view_wanted(ViewSettings(enabled=False), _console(tty=True))


def test_the_address_is_printed_and_another_interface_warned_about() -> None:
    console = _console(tty=False)
    with serving_live_view(ViewSettings(enabled=True), view_info(), console) as served:
        assert served is not None
        state, server = served
        text = console.out.getvalue()
        assert f"live view: {server.url}" in text and "warning" not in text
        assert get(server, f"/?token={server.token}")[0] == 200
    assert state.finished
    console = _console(tty=False)
    with serving_live_view(ViewSettings(enabled=True, host="0.0.0.0"), view_info(), console):
        assert "warning: the live view listens on 0.0.0.0" in console.out.getvalue()


def test_a_port_in_use_is_a_warning_not_a_failure() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        console = _console(tty=False)
        with serving_live_view(ViewSettings(enabled=True, port=port), view_info(), console) as s:
            assert s is None
        assert "measuring without the live view" in console.out.getvalue()


def test_live_statuses() -> None:
    st = live_statuses(flagged_params())
    # eta_tau = E*tau follows tau's flag; eta = E*T_r does not use tau: provisional while
    # T_r is a lower bound (not settled)
    assert st["tau_s"] == "flagged" and st["viscosity_from_time_constant_n_s_per_mm2"] == "flagged"
    assert st["viscosity_n_s_per_mm2"] == "provisional"
    assert st["recovery_time_s"] == "provisional" and st["depth_mm"] == "ok"
