"""The live pipeline on simulated measurements: phases, T_0, live values and final results."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.measurement.outputs import Phase, PhaseChanged
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.pipeline import Pipeline
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.sim.truth import ground_truth
from tests.conftest import REPO_ROOT

SCENES = REPO_ROOT / "configs" / "scenes"


def _run(
    scene_name: str,
    measurement: MeasurementConfig | None = None,
    ends: list[tuple[float, bool]] | None = None,
) -> tuple[MeasurementPipeline, object, list[PhaseChanged]]:
    """The scene's force and frames fed in time order until the pipeline finishes; ``ends``
    receives each end time the pipeline tells [s], and whether the analysis had yet to run."""
    scene = load_scene(SCENES / f"{scene_name}.yaml")
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
        measurement=measurement or MeasurementConfig(),
        analysis=AnalysisSettings(indenter_radius_mm=scene.indenter.diameter_mm / 2),
        calibration=cal,
        reference=load_reference(),
    )
    if ends is not None:
        mp.on_end_known = lambda t_s: ends.append((t_s, mp.start is None))
    batch = sim.force_batch()
    changes: list[PhaseChanged] = []
    changes += [o for o in mp.arm(0.0) if isinstance(o, PhaseChanged)]
    fi = 0
    lives = []
    for fr in frames:
        while fi < batch.index.size and batch.t_true_s[fi] <= fr.t_s:
            out = mp.force(float(batch.t_true_s[fi]), float(batch.force_n[fi]))
            changes += [o for o in out if isinstance(o, PhaseChanged)]
            fi += 1
        out = mp.frame(fr.t_s, float(proc.count(fr.image)))
        changes += [o for o in out if isinstance(o, PhaseChanged)]
        if fr.index % 300 == 0:
            lives.append(mp.live())
        if mp.finished:
            break
    return mp, truth, changes


@pytest.fixture(scope="module")
def grade3() -> tuple[MeasurementPipeline, object, list[PhaseChanged]]:
    return _run("grade3")


def test_grade3_runs_through_every_phase_and_matches_truth(
    grade3: tuple[MeasurementPipeline, object, list[PhaseChanged]],
) -> None:
    mp, truth, changes = grade3
    assert [c.new for c in changes] == [
        Phase.ARMED,
        Phase.PITTING,
        Phase.RELEASE,
        Phase.RECOVERY,
        Phase.ANALYSIS,
        Phase.DONE,
    ]
    assert mp.analysis_error is None
    res = mp.result
    assert res is not None
    gt = truth  # GroundTruth
    assert mp.t0_s == pytest.approx(gt.t0_s, abs=1 / 60)  # type: ignore[attr-defined]
    assert res.pitting.depth_mm == pytest.approx(gt.depth_mm, rel=0.01)  # type: ignore[attr-defined]
    assert res.pitting.rebound_force_n == pytest.approx(gt.rebound_force_n, rel=0.01)  # type: ignore[attr-defined]
    assert res.fit.tau_s == pytest.approx(gt.time_constant_s, rel=0.02)  # type: ignore[attr-defined]
    assert res.paper_model is not None
    assert res.paper_model.elasticity_kpa == pytest.approx(gt.elasticity_kpa, rel=0.01)  # type: ignore[attr-defined]
    assert res.severity_paper is not None and res.severity_paper.severity == "severe"
    assert res.severity_paper.nearest_grade == "III"


def test_live_parameters_converge_to_final(
    grade3: tuple[MeasurementPipeline, object, list[PhaseChanged]],
) -> None:
    mp, _, _ = grade3
    live = mp.live()
    assert live is not None and mp.result is not None
    assert live.depth_mm == pytest.approx(mp.result.pitting.depth_mm, rel=1e-9)
    assert live.tau_s == pytest.approx(mp.result.fit.tau_s, rel=1e-3)
    assert live.to_dict()["settled"] in (0.0, 1.0)


def test_no_live_parameters_before_release() -> None:
    cal = Calibration(
        alpha1_mm_per_px2=1e-7, alpha2_mm_per_px=2.5e-3, c1_px=1500.0, c2_px_per_n=2500.0
    )
    mp = MeasurementPipeline(
        measurement=MeasurementConfig(),
        analysis=AnalysisSettings(),
        calibration=cal,
        reference=load_reference(),
    )
    mp.arm(0.0)
    for t in np.arange(0.0, 5.0, 0.01):
        mp.force(float(t), 16.0 * min(1.0, float(t)))
        mp.frame(float(t), 1000.0)
    assert mp.phase == Phase.PITTING
    assert mp.live() is None
    mp.close(5.0)
    assert mp.finished and mp.phase == Phase.ABORTED
    assert mp.result is None


@pytest.mark.parametrize("stop_when_settled", [False, True])
def test_the_end_is_told_at_the_release_and_again_before_the_analysis_runs(
    stop_when_settled: bool,
) -> None:
    """The daemon stores no frame captured after the measurement's end: the pipeline tells
    the latest end once the release is known (the recovery window's end), then the end
    the analysis starts at, before it runs (the window's end, or, settled, earlier)."""
    config = MeasurementConfig(stop_when_settled=stop_when_settled)
    ends: list[tuple[float, bool]] = []
    mp, _, _ = _run("grade3", config, ends)
    assert mp.start is not None and mp.result is not None
    t_rel = mp.state.t_release_s
    assert t_rel is not None and mp.start.t0_s == t_rel
    assert ends == [(t_rel + config.recovery_max_s, True), (mp.start.t_end_s, True)]
    if stop_when_settled:
        assert mp.start.settled and mp.start.t_end_s < t_rel + config.recovery_max_s
    else:
        assert mp.start.t_end_s == t_rel + config.recovery_max_s


def _released_at_a_rounding_time(window_s: float) -> tuple[MeasurementPipeline, float]:
    """A pipeline fed a hold at 16 N and the force's drop, released (RECOVERY) at a time
    t_rel whose (t_rel + window_s) - t_rel < window_s in floating point; the drop time."""
    cal = Calibration(
        alpha1_mm_per_px2=1e-7, alpha2_mm_per_px=2.5e-3, c1_px=1500.0, c2_px_per_n=2500.0
    )
    config = MeasurementConfig(
        pitting_duration_s=22.0, recovery_max_s=window_s, stop_when_settled=False
    )
    for t_drop in np.arange(23.5, 24.5, 1e-3).tolist():
        mp = MeasurementPipeline(
            measurement=config,
            analysis=AnalysisSettings(),
            calibration=cal,
            reference=load_reference(),
        )
        mp.arm(0.0)
        for t in [*np.arange(0.0, t_drop, 0.01).tolist(), *(t_drop + np.arange(0.0, 0.3, 0.01))]:
            held = t < t_drop
            mp.force(float(t), 16.0 * min(1.0, float(t)) if held else 0.0)
            mp.frame(float(t), 1000.0)
        t_rel = mp.state.t_release_s
        assert t_rel is not None and mp.phase == Phase.RECOVERY
        if (t_rel + window_s) - t_rel < window_s:
            return mp, float(t_drop)
    raise AssertionError("no release time that rounds")


def test_a_recording_that_ends_within_the_slack_completes_the_window_whatever_the_rounding() -> (
    None
):
    """A recording that ends just before the recovery window's end (within
    ``recovery_end_slack_s``) completes the window, as its note says, also for a release
    time whose window end minus the release rounds below ``recovery_max_s`` in floating
    point (about 1 release time in 12 for a 105 s window): the daemon closed such sessions
    ABORTED, "session closed in recovery", next to "window taken as complete"."""
    window_s = 105.0
    mp, t_drop = _released_at_a_rounding_time(window_s)
    t_rel = mp.state.t_release_s
    assert t_rel is not None
    # the recovery recorded up to 4 ms before the window's end
    for t in (t_drop + np.arange(0.3, window_s - 0.004, 0.01)).tolist():
        mp.force(t, 0.0)
        mp.frame(t, 1000.0 + 2000.0 * (1.0 - math.exp(-(t - t_drop) / 8.0)))
    assert mp.phase == Phase.RECOVERY
    mp.close(mp.state.now_s)
    assert any("window taken as complete" in n for n in mp.notes), mp.notes
    assert mp.phase == Phase.DONE, mp.state.end_reason
    assert mp.start is not None and mp.start.t_end_s == t_rel + window_s
