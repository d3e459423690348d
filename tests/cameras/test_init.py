"""open_camera imports only the configured source's module."""

from __future__ import annotations

import ast
import subprocess
import sys

from tests.conftest import REPO_ROOT

_PROBE = """
import sys
from stipi_daemon.cameras import VideoFileCameraConfig, open_camera
from stipi_daemon.clock import ScaledClock
open_camera(VideoFileCameraConfig(path="x.avi"), ScaledClock())
print(sorted(m for m in sys.modules if m.startswith(("stipi_daemon.sim", "stipi_daemon.cameras."))))
"""


def test_open_camera_imports_only_the_chosen_source() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    ).stdout
    loaded = ast.literal_eval(out)  # a printed list of module names
    assert "stipi_daemon.cameras.video_file" in loaded
    assert "stipi_daemon.cameras.v4l2" not in loaded
    assert "stipi_daemon.sim.camera" not in loaded
    assert not any(m.startswith("stipi_daemon.sim") for m in loaded)
