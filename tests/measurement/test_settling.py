"""Ending a recovery early: the state machine's settling test agrees with the analysis.

Unit tests of the stop criterion (state_machine.py, settling_tracker.py), a property
test over Kelvin-Voigt recoveries (an early stop leaves Eq. (6) within its tolerance of the
paper's full 105 s window), and the simulator's grade scenes replayed offline through the
real measurement pipeline (stop time; D_p, F_r, T_r, tau, E, eta from the truncated record
against the full record and the ground truth).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import event as hyp_event
from hypothesis import strategies as st
from pydantic import ValidationError

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import RecoveryTime, recovery_time
from stipi_daemon.analysis.results import AnalysisSettings, MeasurementResult, analyze_recovery
from stipi_daemon.analysis.settling_rules import truncation_hold_factor
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.app.config import parse_config
from stipi_daemon.errors import ConfigError
from stipi_daemon.measurement.events import Arm, FrameSample, OperatorRelease, Tick
from stipi_daemon.measurement.events import ForceSample as MachineForce
from stipi_daemon.measurement.outputs import Advisory, AdvisoryKind, Output, Phase, StartAnalysis
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.measurement.settling_tracker import LEVELS_PER_BAND, SettlingTracker
from stipi_daemon.measurement.state_machine import MachineState, initial_state, transition
from stipi_daemon.sim import Pipeline, ground_truth, load_scene
from tests.conftest import REPO_ROOT
from tests.sim._analysis import calibration_of, count_frames

CFG = MeasurementConfig()
T0 = 16.5  # release (operator's button) of recovering()
F = CFG.settle_fraction


def recovering(cfg: MeasurementConfig = CFG) -> MachineState:
    """A machine in RECOVERY with T_0 = 16.5 s and no frame yet."""
    s = initial_state(0.0)
    for e in (Arm(1.0), MachineForce(1.1, 16.0), MachineForce(16.2, 16.0), OperatorRelease(T0)):
        s, _ = transition(s, e, cfg)
    assert s.phase is Phase.RECOVERY and s.t_release_s == T0
    return s


@dataclass
class Fed:
    state: MachineState
    start: StartAnalysis | None
    frames: int
    """Frames consumed, the one that ended the recovery included."""
    outputs: list[Output]


def feed(
    times_s: Sequence[float] | np.ndarray,
    s_px: Sequence[float] | np.ndarray,
    cfg: MeasurementConfig = CFG,
) -> Fed:
    """Frames in order until the machine asks for the analysis, else a Tick past the window."""
    state, outputs = recovering(cfg), list[Output]()
    for i, (t, s) in enumerate(zip(times_s, s_px, strict=True)):
        state, out = transition(state, FrameSample(float(t), float(s)), cfg)
        outputs += out
        start = next((o for o in out if isinstance(o, StartAnalysis)), None)
        if start is not None:
            return Fed(state, start, i + 1, outputs)
    state, out = transition(state, Tick(T0 + cfg.recovery_max_s + 1.0), cfg)
    outputs += out
    start = next((o for o in out if isinstance(o, StartAnalysis)), None)
    return Fed(state, start, len(times_s), outputs)


def same_reading(a: RecoveryTime, b: RecoveryTime) -> bool:
    """Eq. (6) read the same on two records (all but the number of frames)."""
    return replace(a, n_frames=0) == replace(b, n_frames=0)


def frame_times(fps: float = 60.0, window_s: float = 105.0, first: int = 0) -> np.ndarray:
    """Frame times T_0 + k / fps for k = first .. window_s * fps [s]."""
    return T0 + np.arange(first, math.floor(window_s * fps + 1e-9) + 1) / fps


def kelvin_voigt(t_s: np.ndarray, tau_s: float, s0_px: float, s_inf_px: float) -> np.ndarray:
    return s_inf_px - (s_inf_px - s0_px) * np.exp(-(t_s - T0) / tau_s)


# --------------------------------------------------------------------------- the criterion


def test_a_plateau_too_short_for_its_rise_time_does_not_stop() -> None:
    # A 20 s linear rise from 5000 to 15000 px, then flat: inside the 2 % band from
    # ~19.7 s on. The old test stopped 10 s later; T_r of Eq. (6) (19.7 s) asks for
    # about 2.1 x that before the 98 % level can no longer move.
    t = frame_times()
    s = np.minimum(5000.0 + 500.0 * (t - T0), 15000.0)
    fed = feed(t, s)
    assert fed.start is not None and fed.start.settled
    tracker = fed.state.settling
    assert tracker is not None
    p = tracker.plateau_start_s
    assert p is not None
    # p is the start of the run at or above 98 % of the peak, to one grid step (0.1 %)
    grid_step_s = 0.98 * 15000.0 * (1.0 - F) / LEVELS_PER_BAND / 500.0
    assert T0 + 19.4 <= p <= T0 + 19.4 + grid_step_s + 1 / 60
    factor = truncation_hold_factor(5000.0 / 15000.0, F, CFG.settle_bias_fraction)
    assert factor is not None and factor == pytest.approx(2.15, abs=0.01)
    t_stop = fed.start.t_end_s
    assert t_stop - p > CFG.settle_hold_s + 10.0  # the old 10 s hold would have stopped
    # not before the truncation bound; a ramp is no recovery model's curve, so the models
    # fitted to it keep the recording going past the bound until they too allow the stop
    assert t_stop - T0 >= factor * (p - T0)
    assert fed.state.settle_check is not None and fed.state.settle_check.startswith("may stop")
    # and the analysis of the truncated record reads T_r as the full one does
    part = recovery_time(t[: fed.frames], s[: fed.frames], T0)
    full = recovery_time(t, s, T0)
    assert part.recovery_time_s == pytest.approx(full.recovery_time_s, rel=1e-9)
    assert not part.flags and not full.flags


def test_a_true_plateau_stops_at_the_end_of_the_hold() -> None:
    # The recovery completes within one frame (the paper's grade I at 60 fps is 2.2 s;
    # this is the simulator's fast_recovery): the hold is the only wait.
    t = frame_times()
    s = np.full(t.size, 15000.0)
    s[0] = 4500.0  # S_0 at T_0
    fed = feed(t, s)
    assert fed.start is not None and fed.start.settled
    # plateau from the second frame; the first frame 10 s later ends the recovery
    assert fed.start.t_settled_s == pytest.approx(T0 + 1 / 60 + CFG.settle_hold_s, abs=1 / 60)
    part = recovery_time(t[: fed.frames], s[: fed.frames], T0)
    full = recovery_time(t, s, T0)
    assert same_reading(part, full)
    assert part.flags == {Flag.SETTLED_WITHIN_ONE_FRAME}


def test_a_single_recovery_frame_times_out_not_settled() -> None:
    fed = feed([T0 + 0.5], [9000.0])
    assert fed.start is not None and not fed.start.settled
    assert fed.start.t_end_s == T0 + CFG.recovery_max_s
    assert Flag.NOT_SETTLED in fed.start.flags


@pytest.mark.parametrize(
    ("name", "shape"),
    [
        # Kelvin-Voigt with T_r (Eq. (6)) = 30 s x ln(37.5) = 109 s: longer than the window
        ("slow_kelvin_voigt", lambda t: kelvin_voigt(t, 30.0, 5000.0, 20000.0)),
        # linear creep of 0.04 %/s: inside the band over any 10 s hold, never level
        ("linear_creep", lambda t: 15000.0 * (1.0 + 4e-4 * (t - T0))),
    ],
)
def test_a_slowly_rising_series_never_stops(name: str, shape: Any) -> None:
    t = frame_times()
    fed = feed(t, shape(t))
    assert fed.start is not None and not fed.start.settled, name
    assert fed.start.t_end_s == T0 + CFG.recovery_max_s
    assert fed.start.t_settled_s is None
    assert Flag.NOT_SETTLED in fed.start.flags


@pytest.mark.parametrize("level_px", [0.0, 12000.0])
def test_s_k_constant_from_t0_stops_after_the_hold(level_px: float) -> None:
    t = frame_times()
    s = np.full(t.size, level_px)
    fed = feed(t, s)
    assert fed.start is not None and fed.start.settled
    assert fed.start.t_settled_s == pytest.approx(T0 + CFG.settle_hold_s, abs=1 / 60)
    part = recovery_time(t[: fed.frames], s[: fed.frames], T0)
    assert same_reading(part, recovery_time(t, s, T0))
    assert part.flags == {Flag.NO_RECOVERY}


def test_noise_at_the_edge_of_the_2_percent_band() -> None:
    t = frame_times()
    every_other = np.arange(t.size) % 2 == 1
    inside = np.where(every_other, 0.981 * 15000.0, 15000.0)  # 1.9 % below: in the band
    fed = feed(t, inside)
    assert fed.start is not None and fed.start.settled
    assert fed.start.t_settled_s == pytest.approx(T0 + CFG.settle_hold_s, abs=1 / 60)
    outside = np.where(every_other, 0.9799 * 15000.0, 15000.0)  # 2.01 % below: out
    fed = feed(t, outside)
    assert fed.start is not None and not fed.start.settled
    assert fed.start.t_end_s == T0 + CFG.recovery_max_s
    # a frame one grid step above the 98 % level always counts, one below it never
    step = (1.0 - F) / LEVELS_PER_BAND
    tracker = SettlingTracker.first(0.0, 5000.0, F).add(0.1, 15000.0)
    for k in range(2, 50):
        tracker = tracker.add(k * 0.1, 15000.0 * F * (1.0 + 1.001 * step) if k % 2 else 15000.0)
    assert tracker.plateau_start_s == 0.1
    tracker = tracker.add(5.0, 15000.0 * F * (1.0 - 1e-9))
    assert tracker.plateau_start_s is None


def test_the_release_transient_and_a_bright_frame() -> None:
    t = frame_times()
    s = kelvin_voigt(t, 2.0, 5000.0, 16000.0)
    clean = feed(t, s)
    assert clean.start is not None and clean.start.settled
    # The S_k of the pressed indenter (41500 px) falling to S_0 over the first 12 frames
    # after T_0: the rise starts again at the lowest frame and the stop hardly moves.
    transient = s.copy()
    transient[:12] = np.linspace(41500.0, 5000.0, 12)
    fed = feed(t, transient)
    assert fed.start is not None and fed.start.settled
    assert fed.state.settling is not None and fed.state.settling.rise_start_px == 5000.0
    assert fed.start.t_end_s == pytest.approx(clean.start.t_end_s, abs=0.5)
    # A bright frame 3 % above the plateau at 12 s (the clean record stops at ~17 s): the
    # machine's S_max is that frame and it does not stop (it records the whole window); the
    # analysis leaves the isolated outlier frame out of S_max, flags it and times the
    # recovery as the clean record's.
    bright = s.copy()
    bright[720] = 1.03 * 16000.0
    fed = feed(t, bright)
    assert fed.start is not None and not fed.start.settled
    analysed = recovery_time(t, bright, T0)
    assert analysed.flags == {Flag.OUTLIER_FRAMES}
    assert analysed.recovery_time_s == pytest.approx(recovery_time(t, s, T0).recovery_time_s)


def test_out_of_order_frames_are_dropped_and_change_nothing() -> None:
    t = frame_times()
    s = kelvin_voigt(t, 3.0, 5000.0, 16000.0)
    clean = feed(t, s)
    assert clean.start is not None
    state, dropped = recovering(), 0
    for i, (ti, si) in enumerate(zip(t, s, strict=True)):
        state, out = transition(state, FrameSample(float(ti), float(si)), CFG)
        if state.phase is not Phase.RECOVERY:
            break
        if i % 100 == 50:
            before = state.settling
            state, out = transition(state, FrameSample(float(ti) - 0.5, 30000.0), CFG)
            assert state.settling is before
            dropped += sum(
                1
                for o in out
                if isinstance(o, Advisory) and o.kind is AdvisoryKind.OUT_OF_ORDER_SAMPLE
            )
    assert state.t_recovery_end_s == clean.start.t_end_s
    assert dropped == sum(1 for i in range(clean.frames - 1) if i % 100 == 50) > 3


@pytest.mark.parametrize(
    "values",
    [
        [0.0, 5e-324, 0.0, 5e-324],  # subnormal: f x peak is 0
        [0.0, 0.0, 1.0, 1.0],
        [1e300, 1e308, 1.7e308, 1.7e308],  # grid levels beyond the float range
        [7.0, 1e-300, 1e4, 9.9e3],
    ],
)
def test_the_tracker_takes_any_finite_s_k(values: list[float]) -> None:
    tracker = SettlingTracker.first(0.0, values[0], F)
    for k, v in enumerate(values[1:], start=1):
        tracker = tracker.add(float(k), v)
        assert tracker.peak_px == max(values[: k + 1]) or tracker.rise_start_s > 0.0
    p = tracker.plateau_start_s
    assert p is None or 0.0 <= p <= len(values) - 1
    tracker.settled(0.0, hold_s=1.0, bias_fraction=0.005, window_end_s=105.0)


def _trailing_run_start(times_s: list[float], s_px: list[float], level_px: float) -> float | None:
    """Brute force: first frame of the trailing run at or above ``level_px``."""
    if s_px[-1] < level_px:
        return None
    i = len(s_px) - 1
    while i > 0 and s_px[i - 1] >= level_px:
        i -= 1
    return times_s[i]


@given(st.lists(st.floats(1000.0, 1100.0), min_size=2, max_size=150))
@settings(max_examples=200, deadline=None, derandomize=True)
def test_the_plateau_start_is_exact_to_one_grid_step(values: list[float]) -> None:
    step = (1.0 - F) / LEVELS_PER_BAND
    tracker = SettlingTracker.first(0.0, values[0], F)
    times, rise = [0.0], [values[0]]
    for k, v in enumerate(values[1:], start=1):
        tracker = tracker.add(float(k), v)
        if tracker.rise_start_s == k:
            times, rise = [float(k)], [v]
        else:
            times.append(float(k))
            rise.append(v)
        assert tracker.peak_px == max(rise)
        p = tracker.plateau_start_s
        exact = _trailing_run_start(times, rise, F * tracker.peak_px)
        one_step_up = _trailing_run_start(
            times, rise, F * tracker.peak_px * (1.0 + step) * 1.000001
        )
        if p is None:
            assert one_step_up is None
            continue
        assert exact is not None and exact <= p  # never early
        assert one_step_up is None or p <= one_step_up  # at most one grid step late
        sums = tracker.plateau_sums
        assert sums is not None and sums.n == len(times) - times.index(p)


def test_stop_when_settled_off_always_watches_the_whole_window() -> None:
    cfg = MeasurementConfig(stop_when_settled=False)
    t = frame_times()
    fed = feed(t, np.full(t.size, 15000.0), cfg)
    assert fed.start is not None and not fed.start.settled
    assert fed.start.t_end_s == T0 + 105.0


def test_config_fields_are_validated_with_their_names() -> None:
    for bad in (0.0, -0.01, 0.2, math.nan, math.inf):
        with pytest.raises(ValidationError, match="settle_bias_fraction"):
            MeasurementConfig(settle_bias_fraction=bad)
    with pytest.raises(ValidationError, match="settle_hold_s"):
        MeasurementConfig(settle_hold_s=0.0)
    with pytest.raises(ValidationError, match="settle_hold_s"):
        MeasurementConfig(settle_hold_s=105.0)
    assert MeasurementConfig(settle_bias_fraction=0.1).settle_bias_fraction == 0.1
    base: dict[str, Any] = {
        "probe": {"transport": {"kind": "emulated", "scene": "x.yaml"}},
        "camera": {"kind": "simulator", "scene": "x.yaml"},
    }
    with pytest.raises(ConfigError, match=r"measurement\.settle_fraction \(0\.95\)"):
        parse_config({**base, "measurement": {"settle_fraction": 0.95}}, "c.yaml")
    with pytest.raises(ConfigError, match=r"field 'measurement\.settle_bias_fraction'"):
        parse_config({**base, "measurement": {"settle_bias_fraction": 1.0}}, "c.yaml")
    both = {"settle_fraction": 0.95}
    assert parse_config({**base, "measurement": both, "analysis": both}, "c.yaml")


# --------------------------------------------------------------------------- property


@given(
    tau_s=st.floats(0.5, 40.0),
    s0_over_s_inf=st.floats(0.0, 0.85),
    s_inf_px=st.floats(5000.0, 40000.0),
    fps=st.sampled_from([30.0, 60.0]),
    noise_fraction=st.sampled_from([0.0, 0.0, 2e-5, 5e-5]),
    seed=st.integers(0, 2**32 - 1),
)
@settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
def test_an_early_stop_leaves_eq6_within_tolerance(
    tau_s: float,
    s0_over_s_inf: float,
    s_inf_px: float,
    fps: float,
    noise_fraction: float,
    seed: int,
) -> None:
    """Kelvin-Voigt recoveries as pixel counts (rounded), optionally with frame noise.

    Whenever the machine ends the recovery early, Eq. (6) on the truncated record agrees
    with Eq. (6) on the paper's 105 s record: T_r within 1 % (within
    ``settle_bias_fraction`` plus one pixel of S_max without noise), S_max (hence F_r)
    within 0.2 %, and the truncated record is not flagged ``not_settled``. The noise is
    kept small (up to 0.005 % of S_k, a pixel or two): S_max is the largest noisy frame,
    so with more noise Eq. (6) itself depends on the record's length (see
    test_a_noisy_grade_stops_early_no_further_from_the_truth). 1500 random cases of this
    domain: worst |1 - T_r(truncated) / T_r(105 s)| 0.92 %, none ``not_settled``.
    """
    t = frame_times(fps)
    s = kelvin_voigt(t, tau_s, s0_over_s_inf * s_inf_px, s_inf_px)
    if noise_fraction > 0.0:
        s = s + np.random.default_rng(seed).normal(0.0, noise_fraction * s_inf_px, t.size)
    s = np.maximum(np.round(s), 0.0)
    fed = feed(t, s)
    assert fed.start is not None
    if not fed.start.settled:
        hyp_event("watched the whole window")
        assert fed.start.t_end_s == T0 + CFG.recovery_max_s
        return
    hyp_event("stopped early")
    part = recovery_time(t[: fed.frames], s[: fed.frames], T0)
    full = recovery_time(t, s, T0)
    assert Flag.NOT_SETTLED not in part.flags
    assert part.s_max_px == pytest.approx(full.s_max_px, rel=0.002)
    assert part.recovery_time_s is not None and full.recovery_time_s is not None
    bias = 1.0 - part.recovery_time_s / full.recovery_time_s
    assert abs(bias) <= 0.01
    if noise_fraction == 0.0:
        # one pixel of S_max moves the 98 % crossing by f / S'(T_s) = tau / (0.02 S_inf)
        pixel = tau_s / (0.02 * s_inf_px) / full.recovery_time_s
        assert -pixel <= bias <= CFG.settle_bias_fraction * 1.05 + pixel


# --------------------------------------------------------------------------- simulator

SCENES = REPO_ROOT / "configs" / "scenes"
REALISTIC = [
    {"name": "sensor_noise", "sigma_levels": 2.0},
    {"name": "led_flicker", "depth": 0.02, "frequency_hz": 3.3, "sigma": 0.005},
]


@dataclass(frozen=True)
class Replay:
    """A scene replayed offline through the measurement pipeline (truncated by the
    machine) and analysed again on the whole 105 s record."""

    stop_s: float
    """Recovery recorded, from the machine's T_0 [s]."""
    settled: bool
    truncated: MeasurementResult
    full: MeasurementResult
    truth: dict[str, float]


def _quantities(res: MeasurementResult) -> dict[str, float]:
    p, paper, fit = res.pitting, res.paper_model, res.fit_model
    assert paper is not None and fit is not None and p.recovery_time_s is not None
    assert res.fit.tau_s is not None
    return {
        "D_p": p.depth_mm,
        "F_r": p.rebound_force_n,
        "T_r": p.recovery_time_s,
        "tau": res.fit.tau_s,
        "E": paper.elasticity_kpa,
        "eta": paper.viscosity_n_s_per_mm2,
    }


def replay(name: str, effects: list[dict[str, Any]] | None = None, seed: int = 1) -> Replay:
    """Render the scene, count S_k, feed force samples and frames in time order."""
    scene = load_scene(SCENES / f"{name}.yaml")
    if effects is not None:
        scene = scene.with_effects(effects)
    truth = ground_truth(scene, seed)
    pipe = Pipeline(scene, seed)
    t, s, _ = count_frames(pipe.frames(0.0, truth.t0_s + truth.window_s), truth)
    batch = pipe.force_batch()
    # The grade scenes hold 14 s after a 1 s ramp (the paper's timing); the machine's
    # pitting time counts from entering the band, so it must be shorter to see the release.
    fp = scene.force_profile
    pitting_s = min(15.0, fp.hold_s - 0.5)
    settings_ = AnalysisSettings(indenter_radius_mm=truth.indenter_radius_mm)
    cal = calibration_of(truth)
    reference = load_reference()
    mp = MeasurementPipeline(
        measurement=MeasurementConfig(pitting_duration_s=pitting_s),
        analysis=settings_,
        calibration=cal,
        reference=reference,
    )
    mp.arm(0.0)
    events = sorted(
        [(float(a), 0, float(b)) for a, b in zip(batch.t_true_s, batch.force_n, strict=True)]
        + [(float(a), 1, float(b)) for a, b in zip(t, s, strict=True)]
    )
    for time_s, kind, value in events:
        mp.force(time_s, value) if kind == 0 else mp.frame(time_s, value)
        if mp.start is not None:
            break
    if mp.start is None:
        mp.close(truth.t0_s + 200.0)
    start = mp.start
    assert start is not None and mp.result is not None and mp.t0_s is not None
    ft, fv = mp.force_series()
    f_a = float(np.mean(fv[(ft >= start.t_pit_start_s) & (ft <= min(start.t_pit_end_s, mp.t0_s))]))
    full = analyze_recovery(t, s, mp.t0_s, cal, f_a, settings_, reference)
    return Replay(
        stop_s=start.t_end_s - start.t0_s,
        settled=start.settled,
        truncated=mp.result,
        full=full,
        truth=truth.parameters(),
    )


def relative_errors(r: Replay) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """(truncated vs full, truncated vs truth, full vs truth), relative."""
    a, b = _quantities(r.truncated), _quantities(r.full)
    return (
        {q: a[q] / b[q] - 1.0 for q in a},
        {q: a[q] / r.truth[q] - 1.0 for q in a},
        {q: b[q] / r.truth[q] - 1.0 for q in a},
    )


#: Recovery recorded before the machine ends it [s] (clean scenes, 60 fps, 640 x 480).
EXPECTED_STOP_S = {
    "grade1": (12.0, 13.0),  # tau 0.64 s: the 10 s hold decides
    "grade2": (18.0, 22.0),  # tau 2.5 s
    "grade3": (55.0, 63.0),  # tau 7.6 s
    "grade4": (88.0, 100.0),  # tau 12.2 s: just inside the 105 s window
    "demo_grade3": (55.0, 63.0),
}


@pytest.mark.parametrize("name", list(EXPECTED_STOP_S))
def test_simulated_grades_stop_early_without_changing_the_results(name: str) -> None:
    r = replay(name)
    assert r.settled
    lo, hi = EXPECTED_STOP_S[name]
    assert lo <= r.stop_s <= hi
    vs_full, vs_truth, full_vs_truth = relative_errors(r)
    assert Flag.NOT_SETTLED not in r.truncated.pitting.flags
    for q in ("D_p", "F_r"):
        assert abs(vs_full[q]) <= 0.002, (q, vs_full)
    for q in ("T_r", "tau", "E", "eta"):
        assert abs(vs_full[q]) <= CFG.settle_bias_fraction, (q, vs_full)
    for q, e in vs_truth.items():
        assert abs(e) <= 0.006, (q, vs_truth, full_vs_truth)


# Renders 105 s of a 640x480 scene with per-pixel sensor noise: 64 s on an idle 2-CPU
# machine, over the default 120 s with a busy loop on every CPU beside the suite.
@pytest.mark.timeout(600)
def test_a_noisy_grade_stops_early_no_further_from_the_truth() -> None:
    # Sensor noise and LED flicker (0.08 % of S_k per frame): S_max of Eq. (5)-(6) is the
    # largest noisy frame, which grows with the record, so T_r of the paper's 105 s record
    # is itself 1-2 % long against the truth and an early stop moves it by up to ~1 %,
    # towards the truth (docs/settling.md).
    r = replay("grade3", REALISTIC)
    assert r.settled and 55.0 <= r.stop_s <= 65.0
    vs_full, vs_truth, full_vs_truth = relative_errors(r)
    assert Flag.NOT_SETTLED not in r.truncated.pitting.flags
    for q in ("D_p", "F_r"):
        assert abs(vs_full[q]) <= 0.002, (q, vs_full)
    for q in ("tau", "E"):
        assert abs(vs_full[q]) <= 0.01, (q, vs_full)
    for q, e in vs_truth.items():
        assert abs(e) <= abs(full_vs_truth[q]) + 0.002, (q, vs_truth, full_vs_truth)
