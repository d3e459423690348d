"""Tests of the pit/release state machine: the table, every transition, synthetic runs, fuzzing."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import event as hyp_event
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule
from pydantic import ValidationError

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.measurement.events import (
    EVENT_TYPES,
    AnalysisDone,
    Arm,
    CameraRecovered,
    CameraStalled,
    Event,
    ForceSample,
    FrameSample,
    LinkLost,
    LinkRestored,
    OperatorAbort,
    OperatorRelease,
    SessionClosed,
    Tick,
)
from stipi_daemon.measurement.outputs import (
    FAULT_PHASES,
    TERMINAL_PHASES,
    Advisory,
    AdvisoryKind,
    Fault,
    MeasurementFlag,
    OperatorPrompt,
    Output,
    Phase,
    PhaseChanged,
    StartAnalysis,
)
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.measurement.state_machine import (
    CAMERA_POLICY,
    CAMERA_WATCHDOG,
    LINK_POLICY,
    LINK_WATCHDOG,
    TABLE,
    TIMER_RULES,
    MachineState,
    Policy,
    _absorb,
    _unexpected,
    close,
    initial_state,
    transition,
)

CFG = MeasurementConfig()
NON_TERMINAL = [p for p in Phase if p not in TERMINAL_PHASES]


def run(
    events: Iterable[Event],
    cfg: MeasurementConfig = CFG,
    state: MachineState | None = None,
) -> tuple[MachineState, list[Output]]:
    """Feed events in order; return the final state and every output."""
    s = state if state is not None else initial_state(0.0)
    out: list[Output] = []
    for e in events:
        s, o = transition(s, e, cfg)
        out += o
    return s, out


def phases(outputs: list[Output]) -> list[Phase]:
    return [o.new for o in outputs if isinstance(o, PhaseChanged)]


def advisories(outputs: list[Output], kind: AdvisoryKind | None = None) -> list[Advisory]:
    return [o for o in outputs if isinstance(o, Advisory) and (kind is None or o.kind is kind)]


# Events that bring a fresh state to each phase (times [s]); pitting starts at 1.1 s.
PIT_START_S = 1.1
TO_PHASE: dict[Phase, list[Event]] = {
    Phase.IDLE: [],
    Phase.ARMED: [Arm(1.0)],
    Phase.PITTING: [Arm(1.0), ForceSample(PIT_START_S, 16.0)],
    Phase.RELEASE: [Arm(1.0), ForceSample(PIT_START_S, 16.0), ForceSample(16.2, 16.0)],
    Phase.RECOVERY: [
        Arm(1.0),
        ForceSample(PIT_START_S, 16.0),
        ForceSample(16.2, 16.0),
        OperatorRelease(16.5),
    ],
    Phase.ANALYSIS: [
        Arm(1.0),
        ForceSample(PIT_START_S, 16.0),
        ForceSample(16.2, 16.0),
        OperatorRelease(16.5),
        Tick(16.5 + 105.0),
    ],
}
TO_PHASE[Phase.DONE] = [*TO_PHASE[Phase.ANALYSIS], AnalysisDone(122.0)]
TO_PHASE[Phase.ABORTED] = [Arm(1.0), OperatorAbort(2.0)]
TO_PHASE[Phase.LINK_LOST] = [Arm(1.0), LinkLost(2.0), Tick(4.5)]
TO_PHASE[Phase.CAMERA_STALLED] = [Arm(1.0), CameraStalled(2.0), Tick(3.5)]
TO_PHASE[Phase.FORCE_OUT_OF_BAND] = [*TO_PHASE[Phase.PITTING], ForceSample(2.0, 20.0), Tick(3.5)]


def state_in(phase: Phase) -> MachineState:
    s, _ = run(TO_PHASE[phase])
    assert s.phase is phase
    return s


def event_of(kind: type[Event], t_s: float) -> Event:
    if kind is ForceSample:
        return ForceSample(t_s, 16.0)
    if kind is FrameSample:
        return FrameSample(t_s, 100.0)
    return kind(t_s)


# Where each (phase, event) goes from the states above, with the events of event_of().
EXPECTED_NEXT: dict[tuple[Phase, type[Event]], Phase] = {
    (Phase.IDLE, Arm): Phase.ARMED,
    (Phase.ARMED, ForceSample): Phase.PITTING,
    (Phase.RELEASE, OperatorRelease): Phase.RECOVERY,
    (Phase.ANALYSIS, AnalysisDone): Phase.DONE,
    **{(p, OperatorAbort): Phase.ABORTED for p in NON_TERMINAL},
    **{(p, SessionClosed): Phase.ABORTED for p in NON_TERMINAL},
}


# --------------------------------------------------------------------------- the table


def test_table_covers_every_phase_event_pair_exactly() -> None:
    expected = {(p, e) for p in Phase for e in EVENT_TYPES}
    assert set(TABLE) == expected
    assert len(TABLE) == len(Phase) * len(EVENT_TYPES) == 132


def test_terminal_phases_absorb_and_others_do_not() -> None:
    for (phase, _), handler in TABLE.items():
        assert (handler is _absorb) == (phase in TERMINAL_PHASES)
    assert TERMINAL_PHASES == FAULT_PHASES | {Phase.DONE}
    assert set(LINK_POLICY) == set(CAMERA_POLICY) == set(NON_TERMINAL)


def test_timer_rules_cover_the_non_terminal_phases_watchdogs_first() -> None:
    assert set(TIMER_RULES) == set(NON_TERMINAL)
    for rules in TIMER_RULES.values():
        assert rules[:2] == (LINK_WATCHDOG, CAMERA_WATCHDOG)
    assert {p for p, rules in TIMER_RULES.items() if len(rules) > 2} == {
        Phase.PITTING,
        Phase.RELEASE,
        Phase.RECOVERY,
    }
    for watchdog in (LINK_WATCHDOG, CAMERA_WATCHDOG):
        assert set(watchdog.flags) == {p for p, v in watchdog.policy.items() if v is Policy.FLAG}
        assert watchdog.fault in FAULT_PHASES


@pytest.mark.parametrize(
    ("phase", "kind"),
    [(p, e) for p in Phase for e in EVENT_TYPES],
    ids=lambda v: v.value if isinstance(v, Phase) else v.__name__,
)
def test_every_transition(phase: Phase, kind: type[Event]) -> None:
    s0 = state_in(phase)
    event = event_of(kind, s0.now_s + 0.01)
    s1, out = transition(s0, event, CFG)
    if phase in TERMINAL_PHASES:
        assert s1 is s0 and out == []
        return
    want = EXPECTED_NEXT.get((phase, kind), phase)
    assert s1.phase is want
    assert s1.now_s == pytest.approx(s0.now_s + 0.01)
    changes = [o for o in out if isinstance(o, PhaseChanged)]
    if want is phase:
        assert changes == []
    else:
        assert [(c.old, c.new) for c in changes] == [(phase, want)]
    unexpected = advisories(out, AdvisoryKind.UNEXPECTED_EVENT)
    assert bool(unexpected) == (TABLE[(phase, kind)] is _unexpected)
    if want in FAULT_PHASES:
        assert [o.kind for o in out if isinstance(o, Fault)] == [want]


# --------------------------------------------------------------------------- synthetic runs


def synthetic_run(
    cfg: MeasurementConfig = CFG,
    *,
    seed: int = 1,
    release: str = "force",
    tau_s: float = 4.0,
    excursions: Iterable[tuple[float, float, float]] = (),
) -> list[Event]:
    """Arm, approach ramp, 15.5 s hold with noise in the band, release, recovery frames.

    ``excursions``: (start after pitting start [s], duration [s], force [N]) overrides.
    """
    rng = np.random.default_rng(seed)
    events: list[Event] = [Arm(10.0)]
    t = 10.5
    dt = 0.01
    # approach ramp 0 -> 16 N over 2 s (reaches 14.5 N at about 12.3 s)
    while t < 12.5:
        events.append(ForceSample(t, 16.0 * (t - 10.5) / 2.0))
        t += dt
    pit_start = next(e.t_s for e in events if isinstance(e, ForceSample) and e.force_n >= 14.5)
    exc = list(excursions)
    t_release = pit_start + 15.6
    while t < t_release:
        f = 16.0 + float(np.clip(rng.normal(0.0, 0.4), -1.2, 1.2))
        for start, dur, force in exc:
            if pit_start + start <= t < pit_start + start + dur:
                f = force
        events.append(ForceSample(t, f))
        t += dt
    if release == "operator":
        events.append(OperatorRelease(t_release))
    # release ramp 16 -> 1 N over 0.2 s, then the rebound force
    t_r0 = t
    s_0, s_max = 200.0, 5000.0
    frame_t = t_r0
    while t < t_r0 + 120.0:
        f = max(1.0, 16.0 - 75.0 * (t - t_r0)) + float(rng.normal(0.0, 0.05))
        events.append(ForceSample(t, f))
        while frame_t <= t:
            s_k = s_0 + (s_max - s_0) * (1.0 - math.exp(-(frame_t - t_r0) / tau_s))
            events.append(FrameSample(frame_t, s_k + float(rng.normal(0.0, 10.0))))
            frame_t += 1.0 / 30.0
        t += dt
    return events


def test_happy_path_idle_to_done_with_a_synthetic_force_trace() -> None:
    events = synthetic_run()
    s, out = run(events)
    assert s.phase is Phase.ANALYSIS
    assert phases(out) == [
        Phase.ARMED,
        Phase.PITTING,
        Phase.RELEASE,
        Phase.RECOVERY,
        Phase.ANALYSIS,
    ]
    assert not [o for o in out if isinstance(o, Fault)]
    assert advisories(out, AdvisoryKind.FORCE_OUT_OF_BAND) == []
    starts = [o for o in out if isinstance(o, StartAnalysis)]
    assert len(starts) == 1
    start = starts[0]
    assert start.settled and Flag.NOT_SETTLED not in start.flags
    assert start.t_pit_end_s - start.t_pit_start_s == pytest.approx(15.0)
    assert start.t_pit_start_s == pytest.approx(12.32, abs=0.011)
    # the force crosses 8 N 0.107 s after the release ramp starts (16 - 75 t = 8)
    assert start.t0_s == pytest.approx(start.t_pit_start_s + 15.6 + 0.107, abs=0.015)
    assert s.release_by == "force"
    # tau = 4 s, S_0 / S_max = 0.04: S_k is inside the 2 % band from ~16-18 s on (T_r of
    # Eq. (6) is 15.5 s); the recovery must then last about twice that (7.8 tau) for
    # T_r to be off by at most settle_bias_fraction (0.5 %), well past the 10 s hold
    assert start.t_settled_s is not None
    assert 30.0 < start.t_settled_s - start.t0_s < 45.0
    assert start.t_end_s == start.t_settled_s
    prompts = [o.text for o in out if isinstance(o, OperatorPrompt)]
    assert prompts[0] == "Press the probe on the tissue until the force reads 16 N"
    assert "Keep pressing: 8.0 N of 16.0 N" in prompts
    assert "Hold 16.0 ± 1.5 N: 15 s left" in prompts
    assert "Hold 16.0 ± 1.5 N: 9 s left" in prompts
    assert "Release the indenter now" in prompts
    assert "Keep the probe still: recovery 0/105 s" in prompts
    assert "Keep the probe still: recovery 14/105 s" in prompts
    assert prompts[-1] == "Analysing the recovery"
    # each prompt is emitted once per change, not once per sample
    assert all(a != b for a, b in itertools.pairwise(prompts))
    s, out = transition(s, AnalysisDone(s.now_s + 1.0), CFG)
    assert s.phase is Phase.DONE and phases(out) == [Phase.DONE]


def test_release_confirmed_by_operator_sets_t0_to_the_button_press() -> None:
    events = synthetic_run(release="operator")
    s, out = run(events)
    start = next(o for o in out if isinstance(o, StartAnalysis))
    press = next(e for e in events if isinstance(e, OperatorRelease))
    assert start.t0_s == press.t_s
    assert s.release_by == "operator"
    assert MeasurementFlag.RELEASE_CONFIRMED_BY_OPERATOR in start.flags
    # the force still read ~16 N when the button was pressed
    assert advisories(out, AdvisoryKind.RELEASE_UNDER_FORCE)


def test_release_from_force_needs_the_debounce() -> None:
    s = state_in(Phase.RELEASE)
    s, _ = run([ForceSample(17.0, 3.0), ForceSample(17.05, 15.0)], state=s)
    assert s.phase is Phase.RELEASE  # one low sample, then back up: a wobble
    s, _ = run([ForceSample(17.1, 3.0), ForceSample(17.15, 3.0), ForceSample(17.25, 3.0)], state=s)
    assert s.phase is Phase.RECOVERY
    # the downward crossing of release_force_n (8 N), interpolated between 15 N and 3 N
    assert s.t_release_s == pytest.approx(17.05 + (15.0 - 8.0) / (15.0 - 3.0) * 0.05)
    assert s.release_by == "force"


def test_early_release_button_is_ignored_with_an_advisory() -> None:
    s = state_in(Phase.PITTING)
    s, out = transition(s, OperatorRelease(7.1), CFG)
    assert s.phase is Phase.PITTING
    (adv,) = advisories(out, AdvisoryKind.EARLY_RELEASE_REQUEST)
    assert "9.0 s of pitting left" in adv.detail


def test_brief_band_excursion_is_a_warning_not_an_abort() -> None:
    s, out = run(synthetic_run(excursions=[(5.0, 0.6, 18.2), (9.0, 0.5, 13.9)]))
    assert s.phase is Phase.ANALYSIS
    warned = advisories(out, AdvisoryKind.FORCE_OUT_OF_BAND)
    assert len(warned) == 2
    assert "18.2 N" in warned[0].detail
    assert MeasurementFlag.FORCE_EXCURSION in s.flags
    assert s.n_excursions == 2
    assert s.oob_total_s == pytest.approx(1.1, abs=0.03)
    prompts = [o.text for o in out if isinstance(o, OperatorPrompt)]
    assert "Force 18.2 N: ease off to 16.0 ± 1.5 N" in prompts
    assert "Force 13.9 N: press harder to 16.0 ± 1.5 N" in prompts


def test_long_continuous_excursion_faults() -> None:
    s, out = run(synthetic_run(excursions=[(5.0, 1.5, 18.5)]))
    assert s.phase is Phase.FORCE_OUT_OF_BAND
    (fault,) = [o for o in out if isinstance(o, Fault)]
    assert "continuously" in fault.reason and "18.5 N" in fault.reason
    # it fired as soon as the excursion passed the 1.0 s grace, not at the next in-band sample
    assert fault.t_s - (s.t_pit_start_s or 0.0) - 5.0 == pytest.approx(1.0, abs=0.015)


def test_cumulative_excursions_fault() -> None:
    exc = [(1.0 + 2.0 * i, 0.8, 18.0) for i in range(5)]  # 5 x 0.8 s: each tolerated, 4 s total
    s, out = run(synthetic_run(excursions=exc))
    assert s.phase is Phase.FORCE_OUT_OF_BAND
    (fault,) = [o for o in out if isinstance(o, Fault)]
    assert "in total" in fault.reason
    assert len(advisories(out, AdvisoryKind.FORCE_OUT_OF_BAND)) == 4  # fault during the 4th


def test_early_release_during_pitting_faults_with_a_clear_reason() -> None:
    s, out = run(synthetic_run(excursions=[(8.0, 5.0, 1.5)]))
    assert s.phase is Phase.FORCE_OUT_OF_BAND
    (fault,) = [o for o in out if isinstance(o, Fault)]
    assert "released early" in fault.reason


def test_overshoot_at_the_start_of_pitting_counts_as_an_excursion() -> None:
    s, out = run([Arm(1.0), ForceSample(1.1, 10.0), ForceSample(1.2, 18.0)])
    assert s.phase is Phase.PITTING and s.t_pit_start_s == 1.2 and s.oob_since_s == 1.2
    assert advisories(out, AdvisoryKind.FORCE_OUT_OF_BAND)
    s, out = run([ForceSample(1.5, 16.0), Tick(2.0)], state=s)
    assert s.oob_since_s is None and s.oob_total_s == pytest.approx(0.3)


@pytest.mark.parametrize("phase", NON_TERMINAL, ids=str)
def test_operator_abort_in_every_phase(phase: Phase) -> None:
    s = state_in(phase)
    s, out = transition(s, OperatorAbort(s.now_s + 0.5), CFG)
    assert s.phase is Phase.ABORTED
    (fault,) = [o for o in out if isinstance(o, Fault)]
    assert fault.kind is Phase.ABORTED and str(phase) in fault.reason
    prompts = [o.text for o in out if isinstance(o, OperatorPrompt)]
    assert prompts[-1] == f"Measurement stopped: aborted by the operator in {phase}"


@pytest.mark.parametrize("phase", NON_TERMINAL, ids=str)
def test_link_loss_per_phase(phase: Phase) -> None:
    s0 = state_in(phase)
    t = s0.now_s
    # a short outage never matters
    s, out = run([LinkLost(t + 0.1), Tick(t + 1.5), LinkRestored(t + 2.0)], state=s0)
    assert s.phase is phase
    if phase is not Phase.ANALYSIS:  # ANALYSIS ignores the watchdogs
        assert s.link_down_since_s is None
        assert advisories(out, AdvisoryKind.LINK_RESTORED)
    # a long one follows the phase's policy
    s, out = run([LinkLost(t + 3.0), Tick(t + 3.0 + CFG.link_loss_limit_s + 0.01)], state=s)
    policy = LINK_POLICY[phase]
    if policy is Policy.FAULT:
        assert s.phase is Phase.LINK_LOST
        assert [o.kind for o in out if isinstance(o, Fault)] == [Phase.LINK_LOST]
    elif policy is Policy.FLAG:
        assert s.phase is phase
        assert advisories(out, AdvisoryKind.LINK_LOST_FLAGGED)
        assert s.flags & {
            MeasurementFlag.LINK_LOST_IN_RECOVERY,
            MeasurementFlag.LINK_LOST_WHILE_IDLE,
        }
    else:
        assert s.phase is phase and not advisories(out, AdvisoryKind.LINK_LOST_FLAGGED)
    assert {Phase.ARMED, Phase.PITTING, Phase.RELEASE} == {
        p for p, v in LINK_POLICY.items() if v is Policy.FAULT
    }
    assert LINK_POLICY[Phase.RECOVERY] is Policy.FLAG


def test_link_lost_in_recovery_still_reaches_analysis_flagged() -> None:
    s = state_in(Phase.RECOVERY)
    s, out = run([LinkLost(20.0), Tick(30.0), Tick(16.5 + 105.0)], state=s)
    assert s.phase is Phase.ANALYSIS
    start = next(o for o in out if isinstance(o, StartAnalysis))
    assert MeasurementFlag.LINK_LOST_IN_RECOVERY in start.flags


def test_link_flag_advisory_kept_when_the_camera_faults_in_the_same_step() -> None:
    # both limits pass at one tick in RECOVERY: the link is flagged, then the camera faults
    s = state_in(Phase.RECOVERY)
    s, out = run(
        [LinkLost(20.0), CameraStalled(20.0), Tick(20.0 + CFG.link_loss_limit_s + 0.5)], state=s
    )
    assert s.phase is Phase.CAMERA_STALLED
    assert MeasurementFlag.LINK_LOST_IN_RECOVERY in s.flags
    flagged = advisories(out, AdvisoryKind.LINK_LOST_FLAGGED)
    assert len(flagged) == 1
    assert out.index(flagged[0]) < next(i for i, o in enumerate(out) if isinstance(o, Fault))


@pytest.mark.parametrize("phase", NON_TERMINAL, ids=str)
def test_camera_stall_per_phase(phase: Phase) -> None:
    s0 = state_in(phase)
    t = s0.now_s
    s, out = run([CameraStalled(t + 0.1), Tick(t + 0.8), CameraRecovered(t + 1.0)], state=s0)
    assert s.phase is phase
    s, out = run([CameraStalled(t + 2.0), Tick(t + 2.0 + CFG.camera_stall_limit_s + 0.01)], state=s)
    policy = CAMERA_POLICY[phase]
    if policy is Policy.FAULT:
        assert s.phase is Phase.CAMERA_STALLED
    elif policy is Policy.FLAG:
        assert s.phase is phase and s.flags & {
            MeasurementFlag.CAMERA_STALLED_WHILE_IDLE,
            MeasurementFlag.CAMERA_STALLED_IN_PITTING,
        }
        assert advisories(out, AdvisoryKind.CAMERA_STALL_FLAGGED)
    else:
        assert s.phase is phase and not advisories(out, AdvisoryKind.CAMERA_STALL_FLAGGED)
    assert CAMERA_POLICY[Phase.RECOVERY] is Policy.FAULT
    assert CAMERA_POLICY[Phase.PITTING] is Policy.FLAG


def test_camera_still_stalled_at_release_faults_there() -> None:
    s = state_in(Phase.PITTING)
    t = s.now_s
    s, out = run([CameraStalled(t + 0.1), Tick(t + 5.0)], state=s)
    assert s.phase is Phase.PITTING and MeasurementFlag.CAMERA_STALLED_IN_PITTING in s.flags
    assert s.t_pit_start_s is not None
    t_end = s.t_pit_start_s + CFG.pitting_duration_s
    s, out = run([ForceSample(t_end + 0.01, 16.0)], state=s)
    assert s.phase is Phase.CAMERA_STALLED
    assert [o.kind for o in out if isinstance(o, Fault)] == [Phase.CAMERA_STALLED]


def test_recovery_times_out_at_105_s_not_settled() -> None:
    s = state_in(Phase.RECOVERY)
    t0 = s.t_release_s
    assert t0 == 16.5
    # S_k keeps rising by more than 2 % every 10 s: never settles
    frames = [FrameSample(t0 + 0.5 * k, 100.0 * 1.05 ** (0.5 * k / 5.0)) for k in range(1, 210)]
    s, out = run([*frames, Tick(t0 + 104.99)], state=s)
    assert s.phase is Phase.RECOVERY
    s, out = transition(s, Tick(t0 + 106.0), CFG)
    assert s.phase is Phase.ANALYSIS
    (start,) = [o for o in out if isinstance(o, StartAnalysis)]
    assert not start.settled and start.t_settled_s is None
    assert start.t_end_s == t0 + 105.0
    assert Flag.NOT_SETTLED in start.flags


def test_recovery_runs_the_full_window_when_stop_when_settled_is_off() -> None:
    cfg = MeasurementConfig(stop_when_settled=False)
    _, out = run(synthetic_run(cfg), cfg)
    start = next(o for o in out if isinstance(o, StartAnalysis))
    assert start.t_end_s - start.t0_s == pytest.approx(105.0)
    # the whole window is the protocol's normal end: no caveat from the machine (the
    # analysis decides whether S_k settled within it)
    assert Flag.NOT_SETTLED not in start.flags
    assert not start.settled


def test_flat_recovery_settles_after_the_hold() -> None:
    s = state_in(Phase.RECOVERY)
    s, _ = run([FrameSample(16.5 + 0.1 * k, 50.0) for k in range(1, 102)], state=s)
    assert s.phase is Phase.ANALYSIS and s.t_settled_s == pytest.approx(16.5 + 10.1)


def test_out_of_order_samples_are_dropped_with_an_advisory() -> None:
    s = state_in(Phase.PITTING)
    s, out = run([ForceSample(3.0, 16.0), ForceSample(2.9, 30.0)], state=s)
    assert s.last_force_n == 16.0 and s.oob_since_s is None
    assert advisories(out, AdvisoryKind.OUT_OF_ORDER_SAMPLE)
    s = state_in(Phase.RECOVERY)
    s, out = run([FrameSample(17.0, 10.0), FrameSample(16.9, 10.0)], state=s)
    assert advisories(out, AdvisoryKind.OUT_OF_ORDER_SAMPLE)


def test_old_event_does_not_move_time_back() -> None:
    s = state_in(Phase.PITTING)
    s2, _ = transition(s, Tick(0.5), CFG)
    assert s2.now_s == s.now_s


def test_pitting_overrun_is_flagged_once() -> None:
    s = state_in(Phase.RELEASE)
    s, out = run([Tick(17.0), Tick(19.2), Tick(25.0)], state=s)
    assert len(advisories(out, AdvisoryKind.RELEASE_OVERRUN)) == 1
    assert MeasurementFlag.PITTING_OVERRUN in s.flags


@pytest.mark.parametrize("phase", list(Phase), ids=str)
def test_close_ends_every_phase_in_a_terminal_one(phase: Phase) -> None:
    s0 = state_in(phase)
    s, out = close(s0, s0.now_s + 1.0, CFG)
    assert s.terminal
    if phase in TERMINAL_PHASES:
        assert s is s0 and out == []
    else:
        assert s.phase is Phase.ABORTED and "session closed" in (s.end_reason or "")


def test_close_after_the_recovery_window_passes_through_analysis() -> None:
    _, out = close(state_in(Phase.RECOVERY), 200.0, CFG)
    assert phases(out) == [Phase.ANALYSIS, Phase.ABORTED]
    assert any(isinstance(o, StartAnalysis) for o in out)


def test_bad_events_and_configs_are_rejected_with_named_fields() -> None:
    with pytest.raises(ValueError, match=r"ForceSample\.force_n must be finite"):
        ForceSample(1.0, math.nan)
    with pytest.raises(ValueError, match=r"Tick\.t_s must be finite"):
        Tick(math.inf)
    with pytest.raises(ValueError, match=r"s_k must be >= 0"):
        FrameSample(1.0, -1.0)
    with pytest.raises(ValidationError, match="contact_force_n"):
        MeasurementConfig(contact_force_n=15.0)
    with pytest.raises(ValidationError, match="release_force_n"):
        MeasurementConfig(release_force_n=14.6)
    with pytest.raises(ValidationError, match="force_tolerance_n"):
        MeasurementConfig(force_tolerance_n=16.0)
    with pytest.raises(ValidationError, match="settle_hold_s"):
        MeasurementConfig(settle_hold_s=200.0)
    with pytest.raises(ValidationError, match="extra"):
        MeasurementConfig(target_force=16.0)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        MeasurementConfig().target_force_n = 12.0  # type: ignore[misc]


# --------------------------------------------------------------------------- fuzzing

FORCES = st.sampled_from([0.0, 1.0, 3.0, 9.0, 14.0, 15.0, 16.0, 17.0, 18.0, 25.0])
STEP = st.floats(min_value=0.0, max_value=3.0, allow_nan=False)


class MachineFuzz(RuleBasedStateMachine):
    """Random event orders; the invariants must hold after every step."""

    def __init__(self) -> None:
        super().__init__()
        self.state = initial_state(0.0)
        self.t = 0.0
        self.last_now = self.state.now_s
        self.terminal_state: MachineState | None = None

    def _apply(self, event: Event) -> None:
        before = self.state
        self.state, out = transition(before, event, CFG)
        changes = [o for o in out if isinstance(o, PhaseChanged)]
        # every phase change is reported, chained old -> new
        if changes:
            assert changes[0].old is before.phase and changes[-1].new is self.state.phase
            for a, b in itertools.pairwise(changes):
                assert a.new is b.old
        else:
            assert self.state.phase is before.phase
        for c in changes:
            hyp_event(f"reached {c.new}")
        faults = [o for o in out if isinstance(o, Fault)]
        assert [f.kind for f in faults] == [c.new for c in changes if c.new in FAULT_PHASES]
        if before.terminal:
            assert self.state is before and out == []

    def _later(self, dt: float) -> float:
        self.t += dt
        return self.t

    @rule(dt=STEP, force=FORCES)
    def force(self, dt: float, force: float) -> None:
        self._apply(ForceSample(self._later(dt), force))

    @rule(dt=STEP, n=st.integers(1, 40), force=FORCES)
    def hold(self, dt: float, n: int, force: float) -> None:
        for _ in range(n):
            self._apply(ForceSample(self._later(dt / 10.0 + 0.01), force))

    @rule(dt=STEP, s_k=st.floats(0.0, 1e4))
    def frame(self, dt: float, s_k: float) -> None:
        self._apply(FrameSample(self._later(dt), s_k))

    @rule(dt=STEP, back=st.floats(0.0, 2.0))
    def late_sample(self, dt: float, back: float) -> None:
        t = self._later(dt)
        self._apply(ForceSample(max(0.0, t - back), 16.0))
        self._apply(FrameSample(max(0.0, t - back), 10.0))

    @rule(dt=STEP, kind=st.sampled_from([Arm, OperatorRelease, OperatorAbort, AnalysisDone]))
    def operator(self, dt: float, kind: type[Event]) -> None:
        self._apply(kind(self._later(dt)))

    @rule(
        dt=STEP,
        kind=st.sampled_from([LinkLost, LinkRestored, CameraStalled, CameraRecovered]),
    )
    def watchdog(self, dt: float, kind: type[Event]) -> None:
        self._apply(kind(self._later(dt)))

    @precondition(lambda self: self.state.phase is Phase.IDLE)
    @rule()
    def arm(self) -> None:
        self._apply(Arm(self._later(0.1)))

    @rule(dt=st.floats(0.0, 150.0))
    def tick(self, dt: float) -> None:
        self._apply(Tick(self._later(dt)))

    # guided rules: make the deep phases (RECOVERY, ANALYSIS, DONE) reachable
    @precondition(lambda self: self.state.phase is Phase.ARMED)
    @rule()
    def reach_the_band(self) -> None:
        self._apply(ForceSample(self._later(0.01), 16.0))

    @precondition(lambda self: self.state.phase is Phase.PITTING)
    @rule(seconds=st.floats(1.0, 16.0))
    def hold_in_band(self, seconds: float) -> None:
        for _ in range(int(seconds / 0.25)):
            self._apply(ForceSample(self._later(0.25), 16.0))

    @precondition(lambda self: self.state.phase is Phase.RELEASE)
    @rule(by_operator=st.booleans())
    def let_go(self, by_operator: bool) -> None:
        if by_operator:
            self._apply(OperatorRelease(self._later(0.1)))
        for _ in range(5):
            self._apply(ForceSample(self._later(0.05), 1.0))

    @precondition(lambda self: self.state.phase is Phase.RECOVERY)
    @rule(seconds=st.floats(1.0, 30.0), level=st.floats(0.0, 1e4))
    def recover(self, seconds: float, level: float) -> None:
        for _ in range(int(seconds / 0.5)):
            self._apply(FrameSample(self._later(0.5), level))

    @precondition(lambda self: self.state.phase is Phase.ANALYSIS)
    @rule()
    def analysis_done(self) -> None:
        self._apply(AnalysisDone(self._later(0.5)))

    @invariant()
    def time_never_goes_backwards(self) -> None:
        assert self.state.now_s >= self.last_now
        self.last_now = self.state.now_s

    @invariant()
    def terminal_is_absorbing(self) -> None:
        if self.terminal_state is not None:
            assert self.state is self.terminal_state
        elif self.state.terminal:
            self.terminal_state = self.state

    @invariant()
    def timestamps_are_ordered(self) -> None:
        s = self.state
        chain = [s.t_pit_start_s, s.t_pit_end_s, s.t_release_s, s.t_recovery_end_s]
        known = [t for t in chain if t is not None]
        assert known == sorted(known)
        if s.t_pit_end_s is not None:
            assert s.t_pit_start_s is not None
            # the hold ends with the timer, or at a force drop inside the grace before it
            held_s = s.t_pit_end_s - s.t_pit_start_s
            assert held_s <= CFG.pitting_duration_s + 1e-9
            assert held_s >= CFG.pitting_duration_s - CFG.out_of_band_grace_s - 1e-9
        if s.t_recovery_end_s is not None:
            assert s.t_release_s is not None
            assert s.t_recovery_end_s - s.t_release_s <= CFG.recovery_max_s + 1e-9

    @invariant()
    def close_always_ends_in_done_or_a_named_fault(self) -> None:
        s, _ = close(self.state, self.t + 1.0, CFG)
        assert s.terminal and (s.phase is Phase.DONE or s.phase in FAULT_PHASES)
        assert s.end_reason


MachineFuzz.TestCase.settings = settings(
    max_examples=120,
    stateful_step_count=100,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
TestMachineFuzz = MachineFuzz.TestCase
