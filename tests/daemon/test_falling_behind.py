"""Issue 14 case 7: a run.speed the machine cannot sustain never gives a silent wrong result.

The real daemon with simulated devices at speed 60 (far above what a machine sustains
with a 60 fps camera): either the measurement ends with every frame of its window fed
(never ended while frames were still on their way), or the run ends with one clear
line; Python's memory stays bounded (images never queue up: the queue is bounded and
carries no images).
"""

from __future__ import annotations

import asyncio
import io
import tracemalloc
from pathlib import Path

import numpy as np

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.errors import StipiError
from stipi_daemon.storage import SessionReader
from stipi_daemon.storage.schema import FRAMES, GAPS
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config

#: Peak of Python allocations allowed during the run [bytes] (the queue once reached 3 GB).
PEAK_BOUND_B = 400e6


def test_a_speed_the_machine_cannot_sustain_ends_clearly_with_bounded_memory(
    tmp_path: Path,
) -> None:
    scene = short_scene(tmp_path, width=640, height=480)
    emulated = {"kind": "emulated", "scene": str(scene)}
    cfg = write_config(
        tmp_path,
        {
            "probe": {"transport": emulated},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": SHORT_MEASUREMENT,
            "run": {"speed": 60.0, "max_lag_s": 3.0},
        },
    )
    out = io.StringIO()
    tracemalloc.start()
    try:
        outcome = asyncio.run(run_daemon(load_config(cfg), out=out))
    except StipiError as exc:  # e.g. the probe's heartbeat missed at this speed
        assert "\n" not in str(exc)
        return
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak < PEAK_BOUND_B, peak
    summary = outcome.summary
    run = summary["run"]
    assert run["max_lag_s"] == 3.0 and set(run["lag_s"]) == {"median", "p99", "max"}
    with SessionReader(outcome.session_dir) as reader:
        frames = reader.array(FRAMES)
        gaps = reader.array(GAPS)
    late = gaps[gaps["cause"] == "processing_behind"] if gaps.size else gaps
    assert run["late_frames"] == (int(late["count"].sum()) if late.size else 0)
    text = out.getvalue()
    if "FAULT falling behind: " in text:  # a late frame, or an overdue first frame
        assert outcome.exit_code != 0 and summary["status"] == "fault"
        assert summary["verdict"]["status"] == "incomplete"
        assert "falling behind" in summary["verdict"]["line"]
        return
    if outcome.exit_code != 0:  # ended otherwise (e.g. the probe link): said so, no result
        assert "FAULT" in text and summary["verdict"]["status"] != "complete", text
        return
    # Completed: every frame of the window was fed before the session ended.
    end = summary["measurement"]["t_end_s"]
    assert float(np.max(frames["t_capture_host_s"])) >= end - 0.1
