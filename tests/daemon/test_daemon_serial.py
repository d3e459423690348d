"""The daemon end to end over ``probe.transport: serial``, against an emulated Feather.

The emulated Feather (:class:`~stipi_daemon.sim.feather.EmulatedFeather`) is started by
the test, not by the daemon: it sits on its own pty like a plugged-in probe, with a
resonator 200 ppm fast and ``micros()`` 3 s before its 2^32 wrap, and plays the scene
whose frames the simulator camera renders. The test owns the session clock and the
scene origin (the Feather's scene start is the camera's t0), so both streams share one
timeline, as on a real probe the physical event does. The daemon reaches it through the
real serial path (pyserial, ``loop.add_reader``), configures it (GET_INFO, SET_RATE,
SET_LED, STREAM_START), takes its EEPROM calibration, and must measure the scene's ground
truth within the simulator's tolerances (D_p, F_r, E 1 %, fitted tau 2 %).
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.analysis.imaging import sk_kernel
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.clock import ScaledClock
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.feather import EmulatedFeather, FeatherCore, McuClock, SceneAdc
from stipi_daemon.storage.reader import SessionReader
from tests.daemon._support import (
    SHORT_MEASUREMENT,
    TRUTH_TOLERANCES,
    check_against_truth,
    short_scene,
    write_config,
)

#: Session seconds per wall second (the emulated devices pace themselves on the clock).
SPEED = 4.0
#: MCU resonator error [ppm] and micros() at boot [us] (wraps 3 s after boot).
RATE_ERROR_PPM = 200.0
BOOT_OFFSET_US = (1 << 32) - 3_000_000


@dataclass
class Rig:
    scene: Path
    clock: ScaledClock
    origin_s: float
    feather: EmulatedFeather


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    scene_path = short_scene(tmp_path)
    scene = load_scene(scene_path)
    clock = ScaledClock(SPEED)
    # Scene time 0 one wall second from now: the daemon has opened both devices by then.
    origin_s = clock.now() + 1.0 * SPEED
    mcu = McuClock(clock.now(), BOOT_OFFSET_US, RATE_ERROR_PPM)
    adc = SceneAdc(scene, None, start_mcu_us=mcu.mcu_us(origin_s), rate_error_ppm=RATE_ERROR_PPM)
    core = FeatherCore(
        adc,
        boot_us=mcu.mcu_us(clock.now()),
        zero_counts=adc.zero_counts,
        span_un_per_count=adc.span_un_per_count,
    )
    feather = EmulatedFeather(core, clock, mcu, link_path=tmp_path / "ttyFEATHER", seed=1)
    await feather.start()
    try:
        yield Rig(scene_path, clock, origin_s, feather)
    finally:
        await feather.stop()


async def test_serial_transport_measures_the_ground_truth(rig: Rig, tmp_path: Path) -> None:
    config = load_config(
        write_config(
            tmp_path,
            {
                "probe": {
                    "transport": {"kind": "serial", "port": str(rig.feather.path)},
                    "rate_hz": 100,
                    "led_level": 200,
                },
                "camera": {"kind": "simulator", "scene": str(rig.scene)},
                "measurement": SHORT_MEASUREMENT,
                "run": {"speed": SPEED},
            },
        )
    )
    outcome = await run_daemon(config, clock=rig.clock, scene_origin_s=rig.origin_s, quiet=True)

    assert outcome.exit_code == 0, outcome.summary
    summary = json.loads((outcome.session_dir / "summary.json").read_text())
    check_against_truth(summary, rel=TRUTH_TOLERANCES)
    # The probe was configured as asked and its EEPROM calibration used.
    core = rig.feather.core
    assert (core.rate_hz, core.led_level, core.streaming) == (100, 200, False)
    probe = summary["run"]["probe"]
    assert probe["samples_lost"] == 0 and probe["samples_received"] == probe["samples_sent"]
    # A clean link: every sample the probe took while streaming reached the session.
    with SessionReader(outcome.session_dir) as reader:
        firmware = reader.manifest["firmware"]
        assert firmware["calibration_source"] == "probe"
        assert firmware["transport"] == f"serial:{rig.feather.path}"
        assert reader.manifest["software"]["sk_kernel"] == sk_kernel()
        assert reader.integrity_check().ok
        assert str(reader.status) == "complete"
        # No force gap. (A frame gap, a loaded machine's stall of the accelerated simulated
        # camera, is the camera's, counted and flagged by the daemon; not this test's subject.)
        assert not (reader.gaps()["stream"] == "force").any(), reader.gaps()
        force = reader.force_samples()
    index = force["sample_index"]
    assert (index[1:] - index[:-1] == 1).all()
    assert (
        force["t_mcu_raw_us"].min()
        < 1_000_000
        < (1 << 32) - 1_000_000
        < force["t_mcu_raw_us"].max()
    ), "the probe clock wrapped during the run"
    # The clock sync maps each sample's probe time onto the session clock: against the
    # instant the emulated probe took it (known exactly here) the mapped times are off by
    # the link's delay (a few ms on an idle machine, tens of ms on a loaded one), never by
    # a wrong epoch, wrap or drift (which would be seconds over this run).
    mcu = rig.feather.mcu_clock
    true_s = np.array([mcu.session_s(int(t)) for t in force["t_mcu_us"]])
    off_s = force["t_host_s"] - true_s
    assert np.abs(off_s).max() < 0.1, np.percentile(off_s, [0, 50, 100])
