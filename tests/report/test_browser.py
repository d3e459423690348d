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


def _screenshot(
    page: Path, tmp_path: Path, size: tuple[int, int] = (1200, 3000)
) -> tuple[np.ndarray, str]:
    """Chromium's screenshot of ``page`` in a window of ``size`` (width, height) [px]."""
    shot = tmp_path / "shot.png"
    proc = subprocess.run(
        [
            "chromium",
            *CHROMIUM_FLAGS,
            f"--user-data-dir={tmp_path / 'profile'}",
            f"--screenshot={shot}",
            "--hide-scrollbars",
            "--force-device-scale-factor=1",
            f"--window-size={size[0]},{size[1]}",
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


def test_invalid_session_page_reads_in_chromium(demo_session: Path, tmp_path: Path) -> None:
    """A gap over the release: the verdict box is red, the S_k figure is drawn with the gap."""
    from stipi_daemon.report.load import load_report_input
    from stipi_daemon.report.write import render_session_report
    from tests.report.test_validity import release_gap_copy, with_validity

    inp = with_validity(
        release_gap_copy(load_report_input(demo_session)),
        ("invalid", "Not valid: D_p, E, eta, severity (release not observed)."),
        depth_mm=("invalid", ["release_not_observed"], "release not observed"),
        elasticity_kpa=("invalid", [], "D_p is invalid (release not observed)"),
        viscosity_n_s_per_mm2=("invalid", [], "E is invalid"),
        severity=("invalid", [], "eta is invalid"),
    )
    render_session_report(inp, tmp_path / "rep")
    require_tool("chromium")
    img, log = _screenshot(tmp_path / "rep" / REPORT_HTML, tmp_path)
    assert "Uncaught" not in log and "net::ERR_" not in log
    # The verdict badge is red (#c62828) near the top of the page.
    top = img[:400].reshape(-1, 3).astype(int)
    red = (np.abs(top - np.array([0x28, 0x28, 0xC6])) < 25).all(axis=1)
    assert int(red.sum()) > 200, "no red verdict badge at the top of the page"
    cv2.imwrite(str(tmp_path / "invalid_page.png"), img)
