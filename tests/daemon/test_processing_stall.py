"""A processing stall on purpose: the lag handling of real devices, the same every run.

On a simulated run's clock the daemon is never late by itself; the scene effect
``processing_stall`` holds back the frames of one span of scene time until its end, as a
machine busy elsewhere would. The short grade-I scene (:func:`short_scene`, 160x120 at
60 fps, release about 6.5 s into the scene) with a 10 s stall from 8 s:

* with ``run.max_lag_s`` 12, frames more than 6 s late (captured 8-12 s into the scene:
  240 frames) are stored as ``processing_behind`` gaps, the rest measured late; the run
  ends with results, and the recovery's gap flags them;
* with ``run.max_lag_s`` 8, the first late frame (10 s) ends the run: a fault, one line.

Both runs are made twice and must be identical, row for row.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from tests.daemon._support import SHORT_MEASUREMENT, session_record, short_scene, write_config


def _stalled_scene(directory: Path) -> Path:
    path = short_scene(directory, width=160, height=120)
    doc = yaml.safe_load(path.read_text())
    doc["effects"] = [{"name": "processing_stall", "t_start_s": 8.0, "t_end_s": 18.0}]
    path.write_text(yaml.safe_dump(doc))
    return path


async def _run(directory: Path, max_lag_s: float) -> tuple[dict[str, Any], int]:
    directory.mkdir()
    scene = _stalled_scene(directory)
    cfg = write_config(
        directory,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": {**SHORT_MEASUREMENT, "stop_when_settled": False},
            "run": {"speed": 50.0, "max_lag_s": max_lag_s},
        },
    )
    outcome = await run_daemon(load_config(cfg), quiet=True)
    return session_record(outcome.session_dir), outcome.exit_code


async def _twice(directory: Path, max_lag_s: float) -> tuple[dict[str, Any], int]:
    """The run made twice: its record (identical both times) and exit status."""
    first, code = await _run(directory / "a", max_lag_s)
    again, _ = await _run(directory / "b", max_lag_s)
    assert again == first
    return first, code


@pytest.mark.timeout(600)
async def test_frames_late_beyond_half_the_lag_bound_are_gaps(tmp_path: Path) -> None:
    record, code = await _twice(tmp_path, 12.0)
    summary = record["summary"]
    assert code == 0 and summary["status"] == "complete"
    behind = [g for g in record["tables"]["gaps"] if g[5] == "processing_behind"]
    assert sum(g[3] for g in behind) == 240  # frames captured 8-12 s into the scene
    assert summary["run"]["late_frames"] == 240
    assert summary["run"]["lag_s"]["max"] == pytest.approx(10.0, abs=1 / 60 + 1e-9)
    assert summary["verdict"]["status"] != "complete", summary["verdict"]


@pytest.mark.timeout(600)
async def test_a_lag_beyond_the_bound_ends_the_run_with_a_fault(tmp_path: Path) -> None:
    record, code = await _twice(tmp_path, 8.0)
    summary = record["summary"]
    assert summary["status"] == "fault" and code == 1
    assert summary["end_reason"].startswith("falling behind: a frame was handled 10.0 s after")
