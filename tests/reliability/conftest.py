"""Shared helpers of the reliability tests (issue 8): configs, daemon runs, figures.

Long forms are marked ``slow`` and are deselected unless the marker expression asks for
them (``./dev pytest tests/reliability -m slow``, or ``STIPI_RELIABILITY_LONG=1``); the
normal suite runs the short forms.
Figures (losses, latencies, error percentiles) are appended as JSON lines to the file
named by ``STIPI_RELIABILITY_REPORT`` when it is set (docs/reliability.md quotes them).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests._offline import SCENES

REPO_ROOT = Path(__file__).resolve().parents[2]
PYTHON = sys.executable

__all__ = [
    "FAST_FPS",
    "PYTHON",
    "REPO_ROOT",
    "SCENES",
    "fast_scene",
    "report",
    "write_config",
]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Deselect (not skip) the long forms here unless asked for; their short forms run."""
    markexpr = str(config.getoption("markexpr", "") or "")
    wants_slow = "slow" in markexpr and "not slow" not in markexpr
    if wants_slow or os.environ.get("STIPI_RELIABILITY_LONG") == "1":
        return
    here = Path(__file__).parent
    keep, drop = [], []
    for item in items:
        long_form = item.get_closest_marker("slow") and here in Path(str(item.fspath)).parents
        (drop if long_form else keep).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


#: Frame size [px] and rate [fps] of the reliability scenes: 160x120 at 20 fps instead of
#: the camera's 640x480 at 60. These tests check storage, gaps and fault handling on an
#: accelerated session clock, not imaging accuracy; a cheap session second lets the daemon
#: keep up on a machine loaded with a CPU hog on every core (several daemons at a time),
#: so the tests measure what they claim rather than the CPU's spare capacity.
FAST_FRAME_PX = (160, 120)
FAST_FPS = 20.0


def fast_scene(
    directory: Path, recovery_s: float = 14.0, *, cheap: bool = True, pixel_format: str = "bgr8"
) -> Path:
    """Grade I scene that follows the daemon's prompts (16.5 s hold) with a short recovery,
    rendered at :data:`FAST_FRAME_PX` and :data:`FAST_FPS` (``cheap=False``: the camera's
    own 640x480 at 60 fps, for tests that need the full data rate, e.g. to fill a disk),
    its camera delivering ``pixel_format`` (``bgr8``: raw frames, recorded losslessly by
    default; ``mjpg``: JPEGs, stored as they came).

    The operator lets go about 1.5 s after the release prompt (the 15 s pitting is counted
    from reaching the band), so a link that starts the scene a little late (BLE) still
    releases after the prompt.

    Grade I settles within ~3 s, so with the default 10 s settling hold the measurement
    reaches DONE about 13 s after the release: a whole measurement is ~31 s of session time.
    """
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["force_profile"]["hold_s"] = 16.5
    doc["force_profile"]["recovery_s"] = recovery_s
    if cheap:
        doc["camera"].update(
            {"width": FAST_FRAME_PX[0], "height": FAST_FRAME_PX[1], "fps": FAST_FPS}
        )
    doc["camera"]["pixel_format"] = pixel_format
    doc["name"] = "grade1_fast" if pixel_format == "bgr8" else f"grade1_fast_{pixel_format}"
    path = directory / f"{doc['name']}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def write_config(
    path: Path,
    scene: Path,
    root: Path,
    *,
    speed: float,
    transport: dict[str, Any] | None = None,
    **sections: Any,
) -> Path:
    """A daemon config: emulated probe (or ``transport``) + simulator camera on ``scene``."""
    doc: dict[str, Any] = {
        "format": "stipi-daemon-config",
        "version": 1,
        "probe": {"transport": transport or {"kind": "emulated", "scene": str(scene)}},
        "camera": {"kind": "simulator", "scene": str(scene)},
        "storage": {"root": str(root), "min_free_mb": 0},
        "run": {"speed": speed},
    }
    for key, value in sections.items():
        doc[key] = {**doc.get(key, {}), **value}
    path.write_text(yaml.safe_dump(doc))
    return path


def report(name: str, **figures: Any) -> None:
    """Record a test's figures (JSON line) when ``STIPI_RELIABILITY_REPORT`` is set."""
    target = os.environ.get("STIPI_RELIABILITY_REPORT")
    if target:
        with open(target, "a", encoding="utf-8") as f:
            f.write(json.dumps({"test": name, **figures}, default=float) + "\n")
