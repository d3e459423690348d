"""The release: T_0 at the observed force drop (machine) and S_0 read from a frame
(:mod:`stipi_daemon.measurement.release`)."""

from __future__ import annotations

import numpy as np
import pytest

from stipi_daemon.measurement.events import Arm, ForceSample
from stipi_daemon.measurement.outputs import (
    Advisory,
    AdvisoryKind,
    OperatorPrompt,
    Output,
    Phase,
    PhaseChanged,
)
from stipi_daemon.measurement.release import (
    S0_NOT_OBSERVED,
    T0_IMAGE_FORCE_DISAGREE,
    observe_release,
)
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.measurement.state_machine import MachineState, initial_state, transition

CFG = MeasurementConfig()


def _press_and_drop(t_drop_s: float, low_n: float = 1.5) -> tuple[MachineState, list[Output]]:
    """Arm at 0, 16 N from 1.0 s every 10 ms, the force at ``low_n`` from ``t_drop_s``."""
    s, out = transition(initial_state(0.0), Arm(0.0), CFG)
    for t in np.arange(1.0, t_drop_s + 3.0, 0.01):
        f = 16.0 if t < t_drop_s else low_n
        s, o = transition(s, ForceSample(float(t), f), CFG)
        out += o
    return s, out


@pytest.mark.parametrize("early_s", [0.05, 0.5, 0.9])
def test_a_drop_inside_the_grace_is_the_release_at_the_drop(early_s: float) -> None:
    t_drop = 1.0 + CFG.pitting_duration_s - early_s + 0.003  # between two samples
    s, out = _press_and_drop(t_drop)
    assert s.phase is Phase.RECOVERY
    # interpolated between the last 16 N sample and the first 1.5 N sample
    t_prev = 1.0 + np.floor((t_drop - 1.0) / 0.01 + 1e-9) * 0.01
    expected = t_prev + (16.0 - 8.0) / (16.0 - 1.5) * 0.01
    assert s.t_release_s == pytest.approx(expected, abs=1e-9)
    assert s.t_pit_end_s == s.t_release_s
    news = [c.new for c in out if isinstance(c, PhaseChanged)]
    assert news == [Phase.ARMED, Phase.PITTING, Phase.RELEASE, Phase.RECOVERY]
    kinds = [o.kind for o in out if isinstance(o, Advisory)]
    assert AdvisoryKind.RELEASE_BEFORE_PITTING_END in kinds or early_s < CFG.release_debounce_s
    # never "press harder" once the operator let go at the end of the hold
    prompts = [o.text for o in out if isinstance(o, OperatorPrompt)]
    assert not any("press harder" in p for p in prompts)


def test_a_drop_too_early_for_the_grace_is_still_a_fault() -> None:
    s, _ = _press_and_drop(1.0 + CFG.pitting_duration_s - 2.0)
    assert s.phase is Phase.FORCE_OUT_OF_BAND
    assert "released early" in (s.end_reason or "")


def test_a_rebound_above_the_release_threshold_waits_for_the_timer() -> None:
    # 10 N after the drop: out of the band but not released; the grace carries it to the
    # timer's end, and RELEASE waits for the force to go below 8 N
    s, _ = _press_and_drop(1.0 + CFG.pitting_duration_s - 0.5, low_n=10.0)
    assert s.phase is Phase.RELEASE


# ----------------------------------------------------------------------- observe_release

FRAME_S = 1.0 / 60.0


def _series(
    jump_at_s: float, *, before: float, nan_at: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tv = np.arange(0.0, 3.0, FRAME_S) + 0.004
    sv = np.where(tv < jump_at_s, before, 5000.0 + 100.0 * (tv - jump_at_s))
    first = int(np.searchsorted(tv, jump_at_s))
    for k in nan_at:
        sv[first + k] = np.nan
    tf = np.arange(0.0, 3.0, 0.01)
    return tv, sv, tf


@pytest.mark.parametrize("before", [0.0, 41500.0])
def test_s0_is_the_first_frame_showing_the_release(before: float) -> None:
    tv, sv, tf = _series(1.5, before=before)
    obs = observe_release(tv, sv, tf, 1.5, source="force", search_s=0.5)
    first = float(tv[np.searchsorted(tv, 1.5)])
    assert obs.t0_s == first and obs.s0_observed and obs.image_agrees
    assert obs.flags == () and obs.reason is None
    assert obs.invalid_reasons() == {} and obs.caveats() == {}
    assert obs.to_dict()["flags"] == []


def test_a_release_transient_is_followed_to_its_bottom() -> None:
    tv, sv, tf = _series(1.5, before=41500.0)
    first = int(np.searchsorted(tv, 1.5))
    sv[first : first + 4] = [30000.0, 20000.0, 10000.0, 4000.0]
    obs = observe_release(tv, sv, tf, 1.5, source="force", search_s=0.5)
    assert obs.t0_s == float(tv[first + 3])


def test_one_lost_frame_at_the_release_is_within_the_bound() -> None:
    tv, sv, tf = _series(1.5, before=0.0, nan_at=(0,))
    obs = observe_release(tv, sv, tf, 1.5, source="force", search_s=0.5)
    # the frame that shows the release was lost: T_0 stays at the release (the analysis
    # extrapolates S_0 there from the frames after it)
    assert obs.s0_observed and obs.t0_s == 1.5
    assert obs.s0_frame_t_s == float(tv[np.searchsorted(tv, 1.5) + 1])


def test_frames_lost_over_the_release_leave_s0_not_observed() -> None:
    tv, sv, tf = _series(1.5, before=0.0, nan_at=tuple(range(-3, 5)))
    obs = observe_release(tv, sv, tf, 1.5, source="force", search_s=0.5)
    assert not obs.s0_observed and obs.t0_s == 1.5
    assert obs.flags == (S0_NOT_OBSERVED,)
    assert "S_0 not observed" in (obs.reason or "")
    assert set(obs.invalid_reasons()) == {"depth_mm"}


def test_an_image_jump_far_from_the_force_drop_is_flagged() -> None:
    tv, sv, tf = _series(1.9, before=0.0)
    obs = observe_release(tv, sv, tf, 1.5, source="force", search_s=0.5)
    assert obs.flags == (T0_IMAGE_FORCE_DISAGREE,)
    assert obs.image_agrees is False
    assert abs(obs.t0_s - 1.5) <= obs.bound_s
    assert set(obs.caveats()) == {"depth_mm", "recovery_time_s"}


def test_an_operator_release_takes_the_image_jump_within_the_search() -> None:
    tv, sv, tf = _series(1.7, before=41500.0)
    obs = observe_release(tv, sv, tf, 1.5, source="operator", search_s=0.5)
    assert obs.t0_s == float(tv[np.searchsorted(tv, 1.7)]) and obs.flags == ()
