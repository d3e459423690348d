"""A simulated run records the same rows and results at any pace and any load.

Every device of the run is simulated in the daemon's process (the emulated Feather on a
pty, read through pyserial; the simulator camera), so its session clock is a
:class:`~stipi_daemon.clock.VirtualClock`: session time advances only when the daemon
has handled everything due so far. The same short scene (grade I, 0.5 s approach, 3 s
hold, 7 s recovery, 160x120 at 60 fps) is measured at ``run.speed`` 1, at 50 and at 50
beside two busy processes (one per CPU of a 2-CPU machine): every row of every table
(force samples, frames, events, transitions, gaps, clock probes, live parameters, video
frames) and ``summary.json`` must be identical, bit for bit. Nothing here measures time.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from tests.daemon._support import SCENES, session_record, write_config


def _scene(directory: Path) -> Path:
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["name"] = "grade1_speed_identity"
    doc["force_profile"].update({"approach_s": 0.5, "hold_s": 3.0, "recovery_s": 7.0})
    doc["camera"].update({"width": 160, "height": 120})
    path = directory / "grade1_speed_identity.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@contextlib.contextmanager
def _busy_processes(n: int) -> Iterator[None]:
    """``n`` processes that keep a CPU busy each, for the duration of the block."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


async def _measure(tmp_path: Path, scene: Path, name: str, speed: float) -> dict[str, Any]:
    """Every stored row and the summary of a run at ``speed``."""
    (tmp_path / name).mkdir()
    cfg = write_config(
        tmp_path / name,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": {
                "pitting_duration_s": 2.5,
                "recovery_max_s": 6.0,
                "settle_hold_s": 3.0,
                "stop_when_settled": False,
            },
            "run": {"speed": speed},
            "storage": {"root": str(tmp_path / name / "sessions"), "min_free_mb": 0},
        },
    )
    outcome = await run_daemon(load_config(cfg), quiet=True)
    assert outcome.exit_code == 0, outcome.summary["end_reason"]
    assert outcome.summary["run"]["clock"] == "simulated"
    return session_record(outcome.session_dir)


@pytest.mark.timeout(600)
async def test_rows_and_results_are_the_same_at_any_speed_and_load(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    real_time = await _measure(tmp_path, scene, "speed1", 1.0)
    fast = await _measure(tmp_path, scene, "speed50", 50.0)
    with _busy_processes(2):
        loaded = await _measure(tmp_path, scene, "speed50_loaded", 50.0)
    assert real_time["summary"]["verdict"]["status"] == "complete"
    assert real_time["tables"]["frames"] and real_time["tables"]["force_samples"]
    for other in (fast, loaded):
        for table, rows in real_time["tables"].items():
            assert other["tables"][table] == rows, table
        assert other["summary"] == real_time["summary"]
