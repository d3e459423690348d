"""A processing stall on purpose: the lag handling of real devices, the same every run.

On a simulated run's clock the daemon is never late by itself; the scene effect
``processing_stall`` holds back the frames of one span of scene time until its end, as a
machine busy elsewhere would. The short grade-I scene (:func:`short_scene`, 160x120 at
60 fps, release about 6.5 s into the scene) with a 10 s stall from 8 s:

* with ``run.max_lag_s`` 12, frames more than 6 s late (captured 8-12 s into the scene:
  241 frames, 12 s included) are stored as ``processing_behind`` gaps, the rest measured
  late; the run ends with results, and the recovery's gap flags them;
* with ``run.max_lag_s`` 8, the first late frame (10 s) ends the run: a fault, one line.

Both runs are made twice and must be identical, row for row.

A 40 s stall in the recovery of a grade-III tissue (the same short scene, its recovery
60 s; release about 6.5 s, the stall 10-50 s; T_r about 27 s after the release, in the
stall but after its frames that become gaps):

* with ``run.max_lag_s`` 60 (its largest value), frames more than 30 s late (captured
  10-20 s into the scene: 601 frames, 20 s included) are gaps, the rest measured late:
  the run ends with results, and the verdict says what the gap does to them;
* with ``run.max_lag_s`` 30 (configs/demo.yaml's), the first frame 40 s late ends the run
  with a fault that names the stall (not the machine: on a simulated run's clock there is
  no other lag).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from tests.daemon._support import (
    SHORT_MEASUREMENT,
    TRUTH_TOLERANCES,
    check_against_truth,
    session_record,
    short_scene,
    write_config,
)

#: The ground truth's quantities the 40 s stall leaves exact (not the fitted tau).
PRIMARY = ("depth_mm", "rebound_force_n", "elasticity_kpa")


#: The 40 s stall's scene changes: a grade-III tissue, 60 s of recovery, the stall 10-50 s.
LONG_STALL: dict[str, Any] = {
    "grade": "III",
    "recovery_s": 60.0,
    "stall_s": (10.0, 50.0),
    "window_s": 50.0,
}


def _stalled_scene(directory: Path, long: bool) -> Path:
    path = short_scene(directory, width=160, height=120)
    doc = yaml.safe_load(path.read_text())
    start_s, end_s = LONG_STALL["stall_s"] if long else (8.0, 18.0)
    doc["effects"] = [{"name": "processing_stall", "t_start_s": start_s, "t_end_s": end_s}]
    if long:
        doc["tissue"] = {"grade": LONG_STALL["grade"]}
        doc["force_profile"]["recovery_s"] = LONG_STALL["recovery_s"]
    path.write_text(yaml.safe_dump(doc))
    return path


async def _run(directory: Path, max_lag_s: float, long: bool) -> tuple[dict[str, Any], int]:
    directory.mkdir()
    scene = _stalled_scene(directory, long)
    measurement = {**SHORT_MEASUREMENT, "stop_when_settled": False}
    if long:
        measurement["recovery_max_s"] = LONG_STALL["window_s"]
    cfg = write_config(
        directory,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": measurement,
            "storage": {"root": str(directory / "sessions"), "min_free_mb": 0, "video": "off"},
            "run": {"speed": 0 if long else 50.0, "max_lag_s": max_lag_s},
        },
    )
    outcome = await run_daemon(load_config(cfg), quiet=True)
    return session_record(outcome.session_dir), outcome.exit_code


async def _twice(
    directory: Path, max_lag_s: float, long: bool = False
) -> tuple[dict[str, Any], int]:
    """The run made twice: its record (identical both times) and exit status."""
    first, code = await _run(directory / "a", max_lag_s, long)
    again, _ = await _run(directory / "b", max_lag_s, long)
    assert again == first
    return first, code


@pytest.mark.timeout(600)
async def test_frames_late_beyond_half_the_lag_bound_are_gaps(tmp_path: Path) -> None:
    record, code = await _twice(tmp_path, 12.0)
    summary = record["summary"]
    assert code == 0 and summary["status"] == "complete"
    behind = [g for g in record["tables"]["gaps"] if g[5] == "processing_behind"]
    # frames captured 8-12 s into the scene, 12 s itself included: it is handed over 4 us
    # after 18 s (STALL_HANDOVER_SPACING), more than 6 s after its capture
    assert sum(g[3] for g in behind) == 241
    assert summary["run"]["late_frames"] == 241
    assert summary["run"]["lag_s"]["max"] == pytest.approx(10.0, abs=1 / 60 + 1e-9)
    assert summary["verdict"]["status"] != "complete", summary["verdict"]


@pytest.mark.timeout(600)
async def test_a_lag_beyond_the_bound_ends_the_run_with_a_fault(tmp_path: Path) -> None:
    record, code = await _twice(tmp_path, 8.0)
    summary = record["summary"]
    assert summary["status"] == "fault" and code == 1
    assert summary["end_reason"].startswith("falling behind: a frame was handled 10.0 s after")


@pytest.mark.timeout(900)
async def test_a_40_s_stall_in_the_recovery_leaves_gaps_and_says_what_they_do(
    tmp_path: Path,
) -> None:
    record, code = await _twice(tmp_path, 60.0, long=True)
    summary = record["summary"]
    assert code == 0 and summary["status"] == "complete", summary.get("end_reason")
    behind = [g for g in record["tables"]["gaps"] if g[5] == "processing_behind"]
    # frames captured 10-20 s into the scene, 20 s itself included (handed over 10 us
    # after 50 s, more than 30 s after its capture)
    assert sum(g[3] for g in behind) == 601
    assert summary["run"]["late_frames"] == 601
    assert summary["run"]["lag_s"]["max"] == pytest.approx(40.0, abs=1 / 60 + 1e-9)
    # The frames after the gap were measured late but measured: T_r (about 27 s after the
    # release) lies after the gap and is exact; the fit over the recovery has a 10 s hole
    # and says so.
    statuses = {k: v["status"] for k, v in summary["validity"].items()}
    assert set(statuses.values()) <= {"valid", "flagged", "invalid"}
    assert statuses["tau_s"] == "flagged", statuses
    assert "tau flagged" in summary["verdict"]["line"], summary["verdict"]
    check_against_truth(summary, rel={k: TRUTH_TOLERANCES[k] for k in PRIMARY})


@pytest.mark.timeout(900)
async def test_a_40_s_stall_beyond_the_lag_bound_is_a_fault_that_names_the_stall(
    tmp_path: Path,
) -> None:
    record, code = await _twice(tmp_path, 30.0, long=True)
    summary = record["summary"]
    assert summary["status"] == "fault" and code == 1
    reason = summary["end_reason"]
    assert reason.startswith("falling behind: a frame was handled 40.0 s after"), reason
    assert "processing stall" in reason and "run.speed" not in reason, reason
