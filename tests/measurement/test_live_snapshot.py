"""Live parameters from a snapshot: what the daemon computes on its worker thread.

The daemon takes :meth:`MeasurementPipeline.live_inputs` on its event loop and runs
:func:`compute_live` on a worker thread while more samples and frames are fed. The snapshot
must give what :meth:`MeasurementPipeline.live` gave at the instant it was taken, however
much was fed since (the series' buffer grows and is reallocated meanwhile).
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.measurement.pipeline import LiveInputs, MeasurementPipeline, compute_live
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.pipeline import Pipeline
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.sim.truth import ground_truth
from tests.conftest import REPO_ROOT


def test_snapshot_gives_the_live_parameters_of_its_instant() -> None:
    scene = load_scene(REPO_ROOT / "configs" / "scenes" / "grade1.yaml").with_camera(
        width=160, height=120, fps=60.0
    )
    truth = ground_truth(scene)
    cal, _ = scaled_calibration(scene)
    sim = Pipeline(scene)
    frames = list(sim.frames())
    proc = FrameProcessor(
        frames[0].image.shape,
        int(truth.frame["threshold_p"]),
        CircleROI(kind="circle", **truth.roi),
    )
    mp = MeasurementPipeline(
        measurement=MeasurementConfig(),
        analysis=AnalysisSettings(indenter_radius_mm=scene.indenter.diameter_mm / 2),
        calibration=cal,
        reference=load_reference(),
    )
    batch = sim.force_batch()
    mp.arm(0.0)
    taken: list[tuple[LiveInputs, dict[str, object]]] = []
    fi = 0
    for fr in frames:
        while fi < batch.index.size and batch.t_true_s[fi] <= fr.t_s:
            mp.force(float(batch.t_true_s[fi]), float(batch.force_n[fi]))
            fi += 1
        mp.frame(fr.t_s, float(proc.count(fr.image)))
        if mp.finished:
            break
        if fr.index % 60 == 0:
            inputs = mp.live_inputs()
            live = mp.live()
            assert (inputs is None) == (live is None)
            if inputs is not None and live is not None:
                taken.append((inputs, asdict(live)))
    # the recovery was seen, with fits (>= 2 s of it), and the buffer grew meanwhile
    assert len(taken) >= 5
    assert any(d["tau_s"] is not None for _, d in taken)
    assert taken[0][0].t.size < mp.frame_series()[0].size
    for inputs, then in taken:
        later = compute_live(inputs)
        assert later is not None
        assert asdict(later) == then
        assert not inputs.t.flags.writeable and np.all(np.diff(inputs.t) > 0)
