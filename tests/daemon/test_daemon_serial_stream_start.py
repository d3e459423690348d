"""A Feather in another process plays its scene from STREAM_START: the daemon starts it at
the camera's scene origin.

The emulated Feather (:class:`~stipi_daemon.sim.feather.EmulatedFeather` on its own pty,
as a plugged-in probe) is given no scene start: like ``mock-peripheral`` its scene time 0
is its first sample after STREAM_START. The daemon is given no scene origin either, so it
chooses one once the probe link is open and sends STREAM_START one sample period before it
(docs/bench.md, "One scene, two clocks"). The measurement must be valid and meet the
scene's ground truth within the tolerances of the serial end-to-end test, and the probe's
first sample must have been taken at the camera's scene origin (the emulated MCU clock
tells when, exactly).
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.clock import ScaledClock
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.feather import EmulatedFeather, McuClock, scene_core
from stipi_daemon.storage.reader import SessionReader
from tests.daemon._support import SHORT_MEASUREMENT, check_against_truth, short_scene, write_config

SPEED = 4.0


@pytest.fixture
async def feather(tmp_path: Path) -> AsyncIterator[tuple[EmulatedFeather, ScaledClock, Path]]:
    scene_path = short_scene(tmp_path)
    clock = ScaledClock(SPEED)
    mcu = McuClock(clock.now(), 123_456, 150.0)
    core = scene_core(load_scene(scene_path), None, mcu, clock.now())  # scene from 1st sample
    dev = EmulatedFeather(core, clock, mcu, link_path=tmp_path / "ttyFEATHER", seed=1)
    await dev.start()
    try:
        yield dev, clock, scene_path
    finally:
        await dev.stop()


async def test_the_daemon_starts_the_probes_scene_at_the_cameras_origin(
    feather: tuple[EmulatedFeather, ScaledClock, Path], tmp_path: Path
) -> None:
    dev, clock, scene = feather
    config = load_config(
        write_config(
            tmp_path,
            {
                "probe": {"transport": {"kind": "serial", "port": str(dev.path)}},
                "camera": {"kind": "simulator", "scene": str(scene)},
                "measurement": SHORT_MEASUREMENT,
                "run": {"speed": SPEED},
            },
        )
    )
    outcome = await run_daemon(config, clock=clock, quiet=True)

    assert outcome.exit_code == 0, outcome.summary
    summary = json.loads((outcome.session_dir / "summary.json").read_text())
    assert summary["verdict"]["status"] == "complete", summary["verdict"]
    check_against_truth(
        summary,
        rel={
            "depth_mm": 0.01,
            "rebound_force_n": 0.01,
            "time_constant_s": 0.02,
            "elasticity_kpa": 0.01,
        },
    )
    origin_s = summary["run"]["camera"]["source"]["t0_s"]
    with SessionReader(outcome.session_dir) as reader:
        force = reader.force_samples()
        (start,) = [e for e in reader.events() if e.kind == "stream_start"]
    detail = start.detail
    assert detail["scene_origin_s"] == origin_s
    assert detail["scheduled_s"] == pytest.approx(origin_s - 0.01)
    # The probe's scene time 0 is its first sample: taken when, on the session clock?
    first_s = dev.mcu_clock.session_s(int(force["t_mcu_us"][0]))
    assert force["sample_index"][0] == 0
    # STREAM_START's way through the pty and a late timer on a loaded host, no more.
    assert -1e-3 < first_s - origin_s < 0.1, (first_s, origin_s, detail)
    print(f"first sample {(first_s - origin_s) * 1e3:+.2f} ms after the camera's origin")  # -s
