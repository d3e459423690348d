"""T_0 comes from what was observed, never from a timer (issue 14, cases 1, 2, 3 and 8).

* Case 1: a release before the 15 s pitting timer ends (inside the grace) puts T_0 at the
  force drop, not at the timer's end; F_a averages the hold before the drop only.
* Case 2: the S_k refinement of T_0 stays within a bound of the force drop (one force
  sample interval + two frame periods) with S_k ~ 0 during pitting and noisy frames, in
  both pitting-phase occlusion modes, over many seeds.
* Case 3 (NaN at T_0): S_0 never comes from interpolating across the release; a lost
  frame at the release takes S_0 from the next valid frame within the bound, otherwise
  S_0 is "not observed" and the pipeline says so (``release.s0_observed``).
* Case 8: every shipped scene measures to a result with the demo's settings (pure
  pipeline on the scene's physics, and the grade scenes through the real daemon).

The synthetic measurements follow the simulator's model (docs/simulator.md): the force
ramps to F_a, is held, drops at the release to the tip force F_0, which relaxes to F_inf
with the recovery time constant; S_k = C1 + C2 F (Eq. 5) after the release and either
C1 + C2 F_a (the tip carries the applied force) or 0 (Fig. 4 (a)) during pitting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.pitting import detect_recovery_start
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.errors import LinkLostError
from stipi_daemon.measurement.outputs import Phase
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.replay import Recording, ReplaySetup, replay
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.scene import load_scene
from tests.conftest import REPO_ROOT

SCENES = REPO_ROOT / "configs" / "scenes"
CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7, alpha2_mm_per_px=2.556e-3, c1_px=1500.0, c2_px_per_n=2500.0
)
FRAME_S = 1.0 / 60.0
FORCE_S = 0.01
#: The stated bound between the force drop and the frame S_0 is read from [s].
BOUND_S = FORCE_S + 2.0 * FRAME_S + 0.005


@dataclass(frozen=True)
class Synth:
    """One synthetic measurement (see the module docstring)."""

    occlusion: str = "applied_force"
    release_before_timer_s: float = 0.9
    tau_s: float = 20.0
    noise_px: float = 0.0
    seed: int = 0
    f0_n: float = 1.5
    f_inf_n: float = 6.0
    nan_frames_rel: tuple[int, ...] = ()
    """Frames made NaN, counted from the first frame after the release (0 = that one)."""
    window_s: float = 20.0

    @property
    def t_pit_start_s(self) -> float:
        return 1.0 + 14.5 / 16.0

    @property
    def t_release_s(self) -> float:
        return self.t_pit_start_s + 15.0 - self.release_before_timer_s

    def force_n(self, t: np.ndarray) -> np.ndarray:
        before = np.clip((t - 1.0) * 16.0, 0.0, 16.0)
        x = np.maximum(t - self.t_release_s, 0.0) / self.tau_s
        after = self.f_inf_n - (self.f_inf_n - self.f0_n) * np.exp(-x)
        return np.where(t < self.t_release_s, before, after)

    def s_px(self, t: np.ndarray) -> np.ndarray:
        f = self.force_n(t)
        after = CAL.c1_px + CAL.c2_px_per_n * f
        if self.occlusion == "applied_force":
            before = np.where(f > 0.0, CAL.c1_px + CAL.c2_px_per_n * f, 0.0)
        else:
            before = np.zeros_like(t)
        return np.where(t < self.t_release_s, before, after)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Frame times, S_k (NaN where asked), force times and forces."""
        rng = np.random.default_rng(self.seed)
        end = self.t_release_s + self.window_s + 1.0
        tf = np.arange(rng.uniform(0.0, FORCE_S), end, FORCE_S)
        tv = np.arange(rng.uniform(0.0, FRAME_S), end, FRAME_S)
        fv = self.force_n(tf)
        sv = self.s_px(tv) + rng.normal(0.0, self.noise_px, tv.size)
        sv = np.maximum(sv, 0.0)
        first_after = int(np.searchsorted(tv, self.t_release_s))
        for k in self.nan_frames_rel:
            sv[first_after + k] = math.nan
        return tv, sv, tf, fv

    def measurement(self) -> MeasurementConfig:
        return MeasurementConfig(recovery_max_s=self.window_s, settle_hold_s=self.window_s / 4)

    def run(self) -> MeasurementPipeline:
        tv, sv, tf, fv = self.arrays()
        end = float(max(tv[-1], tf[-1]))
        mp = MeasurementPipeline(
            measurement=self.measurement(),
            analysis=AnalysisSettings(indenter_radius_mm=7.5, recovery_window_s=self.window_s),
            calibration=CAL,
            reference=load_reference(),
        )
        mp.arm(0.0)
        events = sorted(
            [(float(t), 0, float(f)) for t, f in zip(tf, fv, strict=True)]
            + [(float(t), 1, float(s)) for t, s in zip(tv, sv, strict=True)]
        )
        for t, kind, v in events:
            if kind == 0:
                mp.force(t, v)
            else:
                mp.frame(t, v)
            if mp.finished:
                break
        mp.close(end)
        return mp

    def true_depth_mm(self) -> float:
        s0 = CAL.c1_px + CAL.c2_px_per_n * self.f0_n
        return CAL.indenter_length_mm - float(CAL.depth_change_mm(s0))


def _check(mp: MeasurementPipeline, sy: Synth, *, rel: float = 0.01) -> None:
    assert mp.phase is Phase.DONE, mp.state.end_reason
    assert mp.result is not None, mp.analysis_error
    assert mp.t0_s is not None
    assert sy.t_release_s <= mp.t0_s <= sy.t_release_s + BOUND_S
    assert mp.release is not None and mp.release.s0_observed
    assert mp.result.pitting.depth_mm == pytest.approx(sy.true_depth_mm(), rel=rel)
    assert mp.result.applied_force_n == pytest.approx(16.0, rel=1e-3)


# ----------------------------------------------------------------------- case 1


@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
@pytest.mark.parametrize("early_s", [0.0, 0.3, 0.9])
def test_release_before_the_timer_is_placed_at_the_force_drop(
    occlusion: str, early_s: float
) -> None:
    sy = Synth(occlusion=occlusion, release_before_timer_s=early_s, seed=3)
    mp = sy.run()
    _check(mp, sy)
    # the machine's own T_0 (before the image) is the interpolated force crossing
    assert mp.state.t_release_s == pytest.approx(sy.t_release_s, abs=FORCE_S)


# ----------------------------------------------------------------------- case 2


# Twelve whole synthetic measurements: about 50 s each with the suite beside it, several
# times that beside two busy loops (a hang guard, not a time limit).
@pytest.mark.timeout(900)
@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
def test_refinement_stays_near_the_force_drop_with_noise(occlusion: str) -> None:
    for seed in range(12):
        sy = Synth(occlusion=occlusion, tau_s=44.0, noise_px=20.0, seed=seed)
        mp = sy.run()
        _check(mp, sy, rel=0.02)
        assert not any("disagree" in f for f in mp.release.flags)  # type: ignore[union-attr]


def test_image_that_disagrees_with_the_force_keeps_the_force_and_flags() -> None:
    # the image jumps 0.3 s after the force dropped (e.g. a camera clock offset)
    sy = Synth(occlusion="none", seed=1)
    base = sy.s_px

    @dataclass(frozen=True)
    class Late(Synth):
        def s_px(self, t: np.ndarray) -> np.ndarray:
            return base(t - 0.3)

    late = Late(occlusion="none", seed=1)
    mp = late.run()
    assert mp.release is not None and mp.t0_s is not None
    assert "t0_image_force_disagree" in mp.release.flags
    assert abs(mp.t0_s - late.t_release_s) <= BOUND_S


# ----------------------------------------------------------------------- case 3 (NaN at T_0)


@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
def test_nan_frame_at_the_release_is_never_interpolated_across(occlusion: str) -> None:
    # the frame that shows the release is unmeasurable: T_0 stays at the force drop and
    # S_0 comes from the frames after it (extrapolated back, flagged), not from the jump
    sy = Synth(occlusion=occlusion, nan_frames_rel=(0,), seed=5)
    mp = sy.run()
    assert mp.phase is Phase.DONE and mp.result is not None
    assert mp.release is not None and mp.release.s0_observed
    assert mp.t0_s is not None and abs(mp.t0_s - sy.t_release_s) <= FORCE_S
    assert "s0_extrapolated" in {str(f) for f in mp.result.flags}
    assert mp.result.pitting.depth_mm == pytest.approx(sy.true_depth_mm(), rel=0.01)


@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
def test_a_lost_frame_at_a_fast_release_keeps_t0_at_the_release(occlusion: str) -> None:
    # tau 0.3 s: S_k rises ~5 % of its rise per frame; the next frame is no S_0: T_0 stays
    # at the force drop and the analysis extrapolates S_0 there (flagged), never a
    # confident D_p from the late frame
    sy = Synth(occlusion=occlusion, tau_s=0.3, nan_frames_rel=(0,), seed=5)
    mp = sy.run()
    assert mp.release is not None and mp.release.s0_observed
    assert mp.t0_s == mp.release.t_release_s == mp.state.t_release_s
    assert mp.result is not None
    assert "s0_extrapolated" in {str(f) for f in mp.result.flags}
    assert mp.result.pitting.depth_mm == pytest.approx(sy.true_depth_mm(), rel=0.05)


def test_replay_of_a_recording_with_a_nan_frame_at_the_release() -> None:
    sy = Synth(occlusion="none", nan_frames_rel=(0,), seed=2)
    tv, sv, tf, fv = sy.arrays()
    setup = ReplaySetup(
        measurement=sy.measurement(),
        analysis=AnalysisSettings(indenter_radius_mm=7.5, recovery_window_s=sy.window_s),
        calibration=CAL,
        reference=load_reference(),
    )
    out = replay(Recording(tv, sv, tf, fv, t_arm_s=0.0), setup)
    assert out.phase is Phase.DONE and out.result is not None
    assert out.t0_s is not None and abs(out.t0_s - sy.t_release_s) <= BOUND_S
    assert out.result.pitting.depth_mm == pytest.approx(sy.true_depth_mm(), rel=0.01)
    summary = out.summary()
    assert summary["release"]["s0_observed"] is True
    assert any("without a finite S_k" in n for n in out.notes)


@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
def test_release_not_observed_makes_s0_not_observed(occlusion: str) -> None:
    sy = Synth(occlusion=occlusion, nan_frames_rel=tuple(range(-3, 8)), seed=5)
    mp = sy.run()
    rel = mp.release
    assert rel is not None
    assert not rel.s0_observed
    assert "s0_not_observed" in rel.flags
    assert rel.s0_gap_s is not None and rel.s0_gap_s > BOUND_S
    assert "depth_mm" in rel.invalid_reasons()
    assert "S_0 not observed" in (rel.reason or "")


# ----------------------------------------------------------------------- case 8


def _scene_through_pipeline(path: Path) -> MeasurementPipeline:
    """The scene's physics (force and S(t), no rendering) through a pipeline with the
    demo's measurement settings; the recording ends where the scene ends."""
    scene = load_scene(path)
    model = SceneModel(scene)
    end = scene.force_profile.duration_s
    tf = np.arange(0.0, end + 1e-9, 1.0 / scene.load_cell.sample_rate_hz)
    tv = np.arange(0.0, end + 1e-9, 1.0 / scene.camera.fps)
    demo = yaml.safe_load((REPO_ROOT / "configs" / "demo.yaml").read_text())
    mp = MeasurementPipeline(
        measurement=MeasurementConfig(**demo["measurement"]),
        analysis=AnalysisSettings(**demo["analysis"]),
        calibration=model.calibration,
        reference=load_reference(),
    )
    mp.arm(0.0)
    events = sorted(
        [(float(t), 0, float(f)) for t, f in zip(tf, model.force_n(tf), strict=True)]
        + [(float(t), 1, float(s)) for t, s in zip(tv, model.occluded_area_px(tv), strict=True)]
    )
    for t, kind, v in events:
        (mp.force if kind == 0 else mp.frame)(t, v)
        if mp.finished:
            break
    mp.close(float(max(tf[-1], tv[-1])))
    return mp


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_shipped_scene_measures_with_the_demo_settings(path: Path) -> None:
    mp = _scene_through_pipeline(path)
    assert mp.phase is Phase.DONE, mp.state.end_reason
    assert mp.result is not None, mp.analysis_error
    model = SceneModel(load_scene(path))
    assert mp.t0_s is not None and abs(mp.t0_s - model.t0_s) <= BOUND_S
    assert mp.result.applied_force_n == pytest.approx(model.applied_force_n, rel=0.01)


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("grade", ["grade1", "grade2", "grade4"])
async def test_grade_scene_through_the_daemon_reaches_done(grade: str, tmp_path: Path) -> None:
    """configs/demo.yaml with only the scene changed. The run is accelerated as the demo
    is; when this machine cannot keep up, the run is repeated at half the speed: the test
    measures the measurement, not spare CPU. Not keeping up is the daemon's fault "falling
    behind", or the probe link lost at an accelerated speed: the link's timeouts are in
    session time, floored at 1 s of wall time (``probe.link.LINK_MIN_WALL_S``; before that
    floor, CI saw "no frame from the probe for 2.5 s", 0.25 s of wall time at speed 10,
    during STREAM_START), which a badly loaded host's hiccup can still exceed."""
    cfg = yaml.safe_load((REPO_ROOT / "configs" / "demo.yaml").read_text())
    scene = str(SCENES / f"{grade}.yaml")
    cfg["probe"]["transport"]["scene"] = scene
    cfg["camera"]["scene"] = scene
    speed = float(cfg["run"]["speed"])
    while True:
        cfg["storage"]["root"] = str(tmp_path / f"x{speed:g}" / "sessions")
        cfg["run"]["speed"] = speed
        path = tmp_path / f"config-x{speed:g}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        try:
            outcome = await run_daemon(load_config(path), quiet=True)
        except LinkLostError:
            if speed <= 1.0:
                raise
            speed /= 2.0
            continue
        reason = str(outcome.summary.get("end_reason"))
        if outcome.phase is Phase.DONE or "falling behind" not in reason or speed <= 1.0:
            break
        speed /= 2.0
    assert outcome.phase is Phase.DONE, reason
    summary = outcome.summary
    res, gt = summary["results"], summary["ground_truth"]
    assert res is not None
    assert res["pitting"]["depth_mm"] == pytest.approx(gt["depth_mm"], rel=0.02)
    assert res["paper_estimator"]["elasticity_kpa"] == pytest.approx(gt["elasticity_kpa"], rel=0.02)


# ----------------------------------------------------------------------- T_0 without a release


@pytest.mark.parametrize("occlusion", ["applied_force", "none"])
def test_detect_recovery_start_in_both_occlusion_modes_with_noise(occlusion: str) -> None:
    for seed in range(12):
        sy = Synth(occlusion=occlusion, tau_s=44.0, noise_px=20.0, seed=seed)
        tv, sv, _, _ = sy.arrays()
        t0 = detect_recovery_start(tv, sv)
        assert sy.t_release_s <= t0 <= sy.t_release_s + 2.0 * FRAME_S


def test_detect_recovery_start_ignores_one_outlier_frame_in_the_recovery() -> None:
    sy = Synth(occlusion="none", tau_s=5.0, noise_px=5.0, seed=4)
    tv, sv, _, _ = sy.arrays()
    sv[np.searchsorted(tv, sy.t_release_s + 8.0)] = 0.0  # one dark frame
    t0 = detect_recovery_start(tv, sv)
    assert sy.t_release_s <= t0 <= sy.t_release_s + 2.0 * FRAME_S


def test_detect_recovery_start_follows_a_release_transient_to_its_bottom() -> None:
    sy = Synth(occlusion="applied_force", seed=6)
    tv, sv, _, _ = sy.arrays()
    first = int(np.searchsorted(tv, sy.t_release_s))
    bottom = float(sv[first])
    sv[first : first + 6] = np.linspace(41500.0, bottom, 6)
    assert detect_recovery_start(tv, sv) == float(tv[first + 5])
