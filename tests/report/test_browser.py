"""The report page opens in headless Chromium without errors and renders its content."""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import numpy as np

from stipi_daemon.report.write import REPORT_DIR, REPORT_HTML
from tests.conftest import require_tool

#: Flags that keep Chromium offline and quiet (no first-run, sync or update traffic).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-logging=stderr",
    "--v=0",
)


def _screenshot(page: Path, tmp_path: Path) -> tuple[np.ndarray, str]:
    shot = tmp_path / "shot.png"
    proc = subprocess.run(
        [
            "chromium",
            *CHROMIUM_FLAGS,
            f"--user-data-dir={tmp_path / 'profile'}",
            f"--screenshot={shot}",
            "--window-size=1200,3000",
            page.resolve().as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None, f"no screenshot written; stderr: {proc.stderr[-2000:]}"
    return img, proc.stderr


def test_report_page_renders_in_chromium(demo_session: Path, tmp_path: Path) -> None:
    require_tool("chromium")
    img, log = _screenshot(demo_session / REPORT_DIR / REPORT_HTML, tmp_path)
    assert img.shape[:2] == (3000, 1200)
    for marker in ("Uncaught", "ERROR:CONSOLE", "Not allowed to load", "net::ERR_"):
        assert marker not in log, f"{marker!r} in chromium's log:\n{log[-3000:]}"
    # Not blank: the page draws text and embedded figures (coloured phase shading and
    # curves), not one flat colour.
    assert float(img.std()) > 20.0
    non_white = np.count_nonzero(img.min(axis=2) < 200) / (img.shape[0] * img.shape[1])
    assert non_white > 0.05
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    coloured = np.count_nonzero(hsv[:, :, 1] > 60) / (img.shape[0] * img.shape[1])
    assert coloured > 0.02, "no coloured figure content in the screenshot"
