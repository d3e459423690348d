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

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from tests.daemon._support import session_record, tiny_config, tiny_scene


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
    cfg = tiny_config(tmp_path / name, scene, run={"speed": speed})
    outcome = await run_daemon(load_config(cfg), quiet=True)
    assert outcome.exit_code == 0, outcome.summary["end_reason"]
    assert outcome.summary["run"]["clock"] == "simulated"
    return session_record(outcome.session_dir)


@pytest.mark.timeout(600)
async def test_rows_and_results_are_the_same_at_any_speed_and_load(tmp_path: Path) -> None:
    scene = tiny_scene(tmp_path, "grade1_speed_identity")
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
