"""The emulated probe plays its scene's force effects, and the daemon stores what they do.

One short run of the real daemon (the tiny grade-I scene, 160x120, video off) on the
simulated clock, its emulated Feather (pty, real serial path) reading a scene with

* ``force_drift`` 0.1 N/s from 0 (F' = F + 0.1 N/s * t, the effect's definition),
* ``force_noise`` sigma 0.2 N (white, Gaussian, per sample, before the ADC),
* a hold force of 52 N, beyond the load cell's range: the 10-bit ADC sits at its rail,
  code 1023, through the hold,
* ``force_dropout`` over 5.0-5.5 s of scene time: the 50 samples taken then (100 Hz) are
  taken and not delivered, one index gap recorded as a force gap of 50 samples.

The expectations are written here from the effects' and the load cell's definitions (FC22
10 lbf: zero at 0.1 of the 5 V supply, full scale 0.8 of it above, divider 0.66 to a 3.3 V
10-bit ADC: zero 102.4 counts, 819.2 counts for 44.48 N), not by calling the effect code;
the true force before the effects is the scene's force model (physics, not an effect).
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.app.devices import DaemonHandles
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.storage.reader import SessionReader
from tests.daemon._support import tiny_config, tiny_scene

RATE_N_PER_S = 0.1
SIGMA_N = 0.2
HOLD_N = 52.0
DROPOUT_S = (5.0, 5.5)
SAMPLE_RATE_HZ = 100.0
#: How far a stored sample's host time may be from its true time [s].
TIMING_S = 0.02

# The FC22 through the divider into the 10-bit ADC (the scene's load_cell section).
COUNTS_PER_V = 0.66 / 3.3 * 1024  # [counts/V]
ZERO_COUNTS = 5.0 * 0.1 * COUNTS_PER_V  # 102.4 [counts]
N_PER_COUNT = 44.48 / (5.0 * 0.8 * COUNTS_PER_V)  # 54.3 mN [N/count]
RAIL_COUNTS = 1023


def _scene(directory: Path) -> Path:
    path = tiny_scene(directory, "force_effects")
    doc = yaml.safe_load(path.read_text())
    doc["force_profile"]["hold_force_n"] = HOLD_N
    doc["probe"]["pitting_phase_occlusion"] = "none"  # S at 52 N would not fit the ROI
    doc["effects"] = [
        {"name": "force_drift", "offset_n": 0.0, "rate_n_per_s": RATE_N_PER_S},
        {"name": "force_noise", "sigma_n": SIGMA_N},
        {"name": "force_dropout", "t_start_s": DROPOUT_S[0], "t_end_s": DROPOUT_S[1]},
    ]
    path.write_text(yaml.safe_dump(doc))
    return path


async def _record(directory: Path) -> tuple[dict[str, Any], Path, float]:
    directory.mkdir()
    scene = _scene(directory)
    cfg = tiny_config(
        directory / "run",
        scene,
        storage={"root": str(directory / "run" / "sessions"), "min_free_mb": 0, "video": "off"},
        # the hold reads the rail (50.0 N): the band around it, so the run pits and releases
        measurement={
            "target_force_n": 49.0,
            "force_tolerance_n": 1.5,
            "pitting_duration_s": 2.5,
            "recovery_max_s": 6.0,
            "settle_hold_s": 3.0,
            "stop_when_settled": False,
        },
    )
    origin: list[float] = []

    async def grab_origin(h: DaemonHandles) -> None:
        cam: Any = h.camera.camera
        while cam.t0_s is None:
            await asyncio.sleep(0.01)
        origin.append(float(cam.t0_s))

    outcome = await run_daemon(load_config(cfg), quiet=True, on_running=grab_origin)
    assert outcome.session_dir is not None and origin
    with SessionReader(outcome.session_dir) as r:
        force, gaps = r.force_samples(), r.gaps()
    rows = {
        "index": np.asarray(force["sample_index"], dtype=np.int64),
        "adc": np.asarray(force["adc_counts"], dtype=np.int64),
        "t_s": np.asarray(force["t_host_s"], dtype=np.float64),
        "gaps": [tuple(g) for g in gaps],
    }
    return rows, scene, origin[0]


@pytest.mark.timeout(600)
async def test_the_emulated_probe_plays_drift_noise_rail_and_dropout(tmp_path: Path) -> None:
    rows, scene_path, origin_s = await _record(tmp_path / "run")
    scene = load_scene(scene_path)
    model = Pipeline(scene).model  # the force before any effect (physics)
    t = rows["t_s"] - origin_s  # scene time of each stored sample [s]
    adc = rows["adc"]
    f_true = model.force_n(t)
    ideal = ZERO_COUNTS + (f_true + RATE_N_PER_S * t) / N_PER_COUNT  # drift, before noise
    # The host times a sample by the clock sync's fit (within a few ms of its true time):
    # samples within TIMING_S of a step of the force (the release) are not judged.
    lo, hi = model.force_n(t - TIMING_S), model.force_n(t + TIMING_S)
    steady = np.abs(hi - lo) < SIGMA_N

    # Rail: where the drifting force is 10 sigma beyond the ADC's top, every code is 1023.
    top_n = (RAIL_COUNTS - ZERO_COUNTS) * N_PER_COUNT
    pinned = (np.minimum(lo, hi) + RATE_N_PER_S * t > top_n + 10 * SIGMA_N) & steady
    assert pinned.sum() > 200  # most of the 3 s hold at 100 Hz
    assert np.all(adc[pinned] == RAIL_COUNTS)

    # Off the rails: the residual to F + rate * t is the noise and the rounding.
    free = (ideal > 10 * SIGMA_N / N_PER_COUNT) & (ideal < RAIL_COUNTS - 10 * SIGMA_N / N_PER_COUNT)
    free &= (t > 0.0) & steady
    r = adc[free] - ideal[free]
    n = int(free.sum())
    assert n > 300  # the recovery window (6 s at 100 Hz), less the steps
    sd_want = math.sqrt((SIGMA_N / N_PER_COUNT) ** 2 + 1.0 / 12.0)  # noise + quantisation
    # SD of a sample SD: sd / sqrt(2 (n - 1)); 5 of them
    assert abs(float(np.std(r, ddof=1)) - sd_want) < 5 * sd_want / math.sqrt(2 * (n - 1))
    assert abs(float(np.mean(r))) < 5 * sd_want / math.sqrt(n)
    # Drift: the slope of the reading minus the force model is the effect's rate.
    x = t[free]
    y = adc[free] - (ZERO_COUNTS + f_true[free] / N_PER_COUNT)
    slope, _ = np.polyfit(x, y, 1)
    se = sd_want / math.sqrt(float(np.sum((x - x.mean()) ** 2)))
    assert abs(slope * N_PER_COUNT - RATE_N_PER_S) < 5 * se * N_PER_COUNT

    # Dropout: exactly the samples taken in [5.0, 5.5) are missing, one link gap of 50.
    index = rows["index"]
    missing = np.setdiff1d(np.arange(index.min(), index.max() + 1), index)
    assert missing.size == round((DROPOUT_S[1] - DROPOUT_S[0]) * SAMPLE_RATE_HZ)
    before, after = index < missing.min(), index > missing.max()
    assert t[before].max() < DROPOUT_S[0] <= t[before].max() + 1.5 / SAMPLE_RATE_HZ
    assert t[after].min() >= DROPOUT_S[1] - 0.5 / SAMPLE_RATE_HZ
    force_gaps = [g for g in rows["gaps"] if g[0] == "force"]  # stream, start, count, t, cause
    assert [(g[2], g[4]) for g in force_gaps] == [(missing.size, "link")], force_gaps
    assert force_gaps[0][1] == missing.min()
