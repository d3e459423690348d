"""Pit/release state machine of one STIP-I measurement, as one pure transition table.

This module owns the *procedure* of the paper's Section IV.B: wait for contact, hold the
pitting force at 16 ± 1.5 N for 15 s, release the indenter, watch the recovery for up to
105 s, then hand the recording to the analysis (T_0 of Eq. (6) is the release time). It
decides phases, timing, faults and operator prompts from timestamped events. It does not
own any I/O, clocks, storage or the analysis itself: the shell passes events in (all
times on the host's monotonic clock [s]) and acts on the returned outputs.

Design (after h11's ``_state.py``):

* The vocabulary lives beside the machine: the settings in
  :mod:`~stipi_daemon.measurement.settings` (:class:`MeasurementConfig`), the inputs in
  :mod:`~stipi_daemon.measurement.events` and the outputs, phases and flags in
  :mod:`~stipi_daemon.measurement.outputs`; this module re-exports them (the machine's
  interface). It owns the state, the policies and the two tables below.
* :func:`transition` ``(state, event, config) -> (state, outputs)`` is pure. It first runs
  the *clock step*: every event carries a time, and time-driven rules - pitting complete,
  recovery timeout, band excursions, release overrun, link and camera limits - fire on
  whatever event brings the time forward, so :class:`Tick` only exists to bring it when
  nothing else arrives. Then it dispatches the event through :data:`TABLE`.
* :data:`TIMER_RULES` lists, per non-terminal phase, the named time-driven rules in the
  order the clock step applies them (the two watchdogs, then the phase's own clock); the
  first rule that changes the phase ends the pass, and the clock step repeats with the new
  phase's rules until the phase stays.
* :data:`TABLE` maps every ``(Phase, event type)`` pair to a handler. A pair is either
  handled, explicitly ignored (:func:`_ignore`, no output), explicitly unexpected
  (:func:`_unexpected`, an :class:`Advisory` and no change) or absorbed by a terminal
  phase (:func:`_absorb`: the state is returned unchanged, no output, no clock step).
* Terminal phases are ``DONE`` and the faults ``LINK_LOST``, ``CAMERA_STALLED``,
  ``FORCE_OUT_OF_BAND`` and ``ABORTED``; they are absorbing. :func:`close` drives any state
  to a terminal one (the session is closed).

Policies (all thresholds are fields of :class:`MeasurementConfig`):

* Pitting starts (T_pit_start) at the first force sample at or above the lower band edge
  ``target - tolerance``; between ``contact_force_n`` and that edge the machine stays
  ARMED (approach ramp). Pitting ends exactly ``pitting_duration_s`` later, whatever the
  force did meanwhile, unless it faulted.
* Force band during PITTING, with the force held between samples (zero-order hold): an
  excursion outside ``target ± tolerance`` is reported (one :class:`Advisory` per
  excursion) and tolerated while it lasts at most ``out_of_band_grace_s`` *continuously*
  and the *cumulative* out-of-band time of the pitting phase stays at or below
  ``out_of_band_limit_s``; breaking either rule is the fault ``FORCE_OUT_OF_BAND``. The
  band is not enforced in RELEASE (the operator is letting go).
* T_0 comes from what was observed, never from a timer. The release time is the force's
  downward crossing of ``release_force_n``, linearly interpolated between the last sample
  at or above it and the first below it; it is *detected* once samples have stayed below
  for ``release_debounce_s`` (counted from the first sample below: only observed samples
  confirm it). A drop during PITTING that the grace would have carried to the end of the
  pitting time (the excursion it starts would still be tolerated then) is the release at
  the end of the hold: PITTING -> RELEASE -> RECOVERY at once, T_0 and the end of the
  hold at the drop, an advisory ``release_before_pitting_end`` and no "press harder"
  prompt. An earlier drop is an early release: the fault after the grace time. A drop
  still being debounced when the pitting time ends keeps its crossing as T_0. A release
  may also be *confirmed* by :class:`OperatorRelease` in RELEASE (T_release = the button's
  time, flag ``release_confirmed_by_operator``).
* Settling decides when the recovery may end before ``recovery_max_s``, from the
  :class:`FrameSample` ``S_k`` values (Eqs. (1)-(2)). The analysis reads T_s of Eq. (6)
  where S_k first reaches ``settle_fraction`` (98 %) of S_max *of the recorded window*,
  so stopping as soon as S_k looks flat lowers S_max and T_r (a first 10 s plateau put
  T_r 8 % low on the simulated grades III-IV). The recovery therefore counts as settled
  at a frame only when all of these hold (the tests are shared with the analysis, see
  :mod:`~stipi_daemon.analysis.settling_rules`; figures in docs/settling.md):

  1. *Plateau*: every S_k since the plateau start p is at or above ``settle_fraction``
     times the peak, the largest S_k since the rise started, which is the S_max the
     analysis will see. The rise starts at the first frame at or after T_0 and starts
     again at any frame below both every S_k since and the band (the end of the release
     transient: the analysis also reads S_0 at its bottom). p is the start
     of the trailing run of frames inside the band, read on a grid of S_k levels a
     twentieth of the band apart (0.1 %;
     :class:`~stipi_daemon.measurement.settling_tracker.SettlingTracker`): at most one grid step
     late, never early. Every frame from p on is inside the band, so the
     analysis' T_s is at or before p: p - T_0 is an upper bound of its T_r.
  2. *Hold*: the plateau has lasted ``settle_hold_s``.
  3. *Truncation bound* (Kelvin-Voigt, Section III.C): with r = S_0 / peak (S_0: S_k at
     the rise start) below ``settle_fraction``, the recovery has lasted at least
     :func:`~stipi_daemon.analysis.settling_rules.truncation_hold_factor` x (p - T_0), which keeps
     the bias of T_r from the early stop at or below ``settle_bias_fraction`` (and of F_r
     at about a tenth of that). Typically 2 x (p - T_0): about 7.6 time constants.
  4. *Not still rising*: the least-squares slope of S_k over the plateau (a running sum,
     O(1) per frame), continued for another p - T_0, stays within the band
     (1 - ``settle_fraction``) x peak - the analysis' own still-rising test with its T_r
     replaced by that upper bound. If the whole rise so far lies inside the band
     (r >= ``settle_fraction``: no recovery, or one within a frame) there is no rise time
     to scale with, and the slope is continued to the end of the recovery window instead.
  5. *The recovery models allow it* (only when 1-4 hold and S_0 lies below the band):
     every recovery model is fitted to the rise so far
     (:func:`~stipi_daemon.analysis.model_checks.early_stop_check`) and, for each model
     with weight, Eq. (6) on its curve recorded to now differs from Eq. (6) recorded to the
     end of the window by at most ``settle_bias_fraction``: the bound of 3-4 for the curve
     the tissue follows (power law, two time constants), not only for a Kelvin-Voigt
     solid. After a refusal the next check waits :data:`MODEL_CHECK_MIN_S` or
     :data:`MODEL_CHECK_FRACTION` of the recovery so far: a fit at a few decision points
     (about 0.1-0.2 s each; at most about 20 per recovery), never per frame.
     ``settle_check`` holds what the latest check found.

  Settling only decides when acquisition may stop; T_s and T_r of Eq. (6) are computed
  by the analysis from the stored series. With ``stop_when_settled=False`` the recovery
  always lasts ``recovery_max_s`` (the paper's fixed 105 s), which is its normal end (no
  flag: whether S_k settled within it is the analysis' ``not_settled``). With
  ``stop_when_settled=True`` a recovery that times out (also one that settles too late
  for an unbiased early stop) goes to ANALYSIS with the machine's flag ``not_settled``.
  The bound holds for the machine's T_0 and the recovery models that fit the rise.
  Frame noise above ~0.3 % of S_k (one standard deviation) keeps the plateau from
  holding: no early stop. A slow second phase (creep) whose rise over p - T_0 stays
  inside the band is not detected, as the analysis' own still-rising test does not
  detect it on the shorter record: watch the whole window if recoveries have one.
* Link (force stream) down longer than ``link_loss_limit_s``: fault ``LINK_LOST`` in
  ARMED, PITTING and RELEASE; in IDLE and RECOVERY only a flag (the camera carries the
  recovery); ignored in ANALYSIS. Camera stalled longer than ``camera_stall_limit_s``:
  fault ``CAMERA_STALLED`` in ARMED, RELEASE and RECOVERY (S_k around T_0 and during the
  recovery is what the analysis needs); a flag in IDLE and PITTING (the pitting phase is
  measured by the load cell; a camera that is back before the release loses nothing the
  analysis uses, and one still stalled when RELEASE begins faults there at once);
  ignored in ANALYSIS. See :data:`LINK_POLICY` and :data:`CAMERA_POLICY`
  (applied by the timer rules :data:`LINK_WATCHDOG` and :data:`CAMERA_WATCHDOG`).
* Time never goes backwards in the state: ``now_s`` is the maximum event time seen. A
  force sample or frame older than the previous one of its kind is dropped with an
  :class:`Advisory` (``out_of_order_sample``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Final, Literal

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.model_checks import early_stop_check
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
from stipi_daemon.measurement.evolve import evolve
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
from stipi_daemon.measurement.settling_tracker import SettlingTracker

#: After the recovery models refused an early stop, the next check waits at least this
#: long [s] ...
MODEL_CHECK_MIN_S: Final = 1.0
#: ... and this fraction of the recovery so far [-]: about 20 checks from 10 to 105 s.
MODEL_CHECK_FRACTION: Final = 0.1

__all__ = [
    "CAMERA_POLICY",
    "CAMERA_WATCHDOG",
    "EVENT_TYPES",
    "FAULT_PHASES",
    "LINK_POLICY",
    "LINK_WATCHDOG",
    "TABLE",
    "TERMINAL_PHASES",
    "TIMER_RULES",
    "Advisory",
    "AdvisoryKind",
    "AnalysisDone",
    "Arm",
    "CameraRecovered",
    "CameraStalled",
    "Event",
    "Fault",
    "ForceSample",
    "FrameSample",
    "LinkLost",
    "LinkRestored",
    "MachineState",
    "MeasurementConfig",
    "MeasurementFlag",
    "OperatorAbort",
    "OperatorPrompt",
    "OperatorRelease",
    "Output",
    "Phase",
    "PhaseChanged",
    "Policy",
    "SessionClosed",
    "StartAnalysis",
    "Tick",
    "TimerRule",
    "Watchdog",
    "close",
    "initial_state",
    "transition",
]


# --------------------------------------------------------------------------- policies


class Policy(StrEnum):
    """What a watchdog limit (link, camera) does in a phase once exceeded."""

    FAULT = "fault"
    FLAG = "flag"
    IGNORE = "ignore"


LINK_POLICY: Final[dict[Phase, Policy]] = {
    Phase.IDLE: Policy.FLAG,
    Phase.ARMED: Policy.FAULT,
    Phase.PITTING: Policy.FAULT,
    Phase.RELEASE: Policy.FAULT,
    Phase.RECOVERY: Policy.FLAG,
    Phase.ANALYSIS: Policy.IGNORE,
}
"""Force-link loss longer than ``link_loss_limit_s``, per non-terminal phase."""

CAMERA_POLICY: Final[dict[Phase, Policy]] = {
    Phase.IDLE: Policy.FLAG,
    Phase.ARMED: Policy.FAULT,
    Phase.PITTING: Policy.FLAG,
    Phase.RELEASE: Policy.FAULT,
    Phase.RECOVERY: Policy.FAULT,
    Phase.ANALYSIS: Policy.IGNORE,
}
"""Camera stall longer than ``camera_stall_limit_s``, per non-terminal phase."""


# --------------------------------------------------------------------------- state


@dataclass(frozen=True)
class MachineState:
    """Everything the machine knows; immutable, replaced on every transition (by
    :func:`~.evolve.evolve`, hence no slots).

    Times are host monotonic [s]; ``None`` means "not yet" / "not active".
    """

    phase: Phase
    now_s: float
    """Latest event time seen; never decreases."""
    phase_entered_s: float
    t_pit_start_s: float | None = None
    t_pit_end_s: float | None = None
    t_release_s: float | None = None
    """T_0 for the analysis (Eq. (6))."""
    t_recovery_end_s: float | None = None
    t_settled_s: float | None = None
    release_by: Literal["force", "operator"] | None = None
    # force stream
    last_force_t_s: float | None = None
    last_force_n: float | None = None
    contact: bool = False
    # band accounting (PITTING)
    oob_since_s: float | None = None
    """Start of the current out-of-band excursion."""
    oob_total_s: float = 0.0
    """Cumulative out-of-band time of the pitting phase [s]."""
    oob_accounted_to_s: float | None = None
    n_excursions: int = 0
    max_excursion_s: float = 0.0
    below_release_since_s: float | None = None
    """Downward crossing of ``release_force_n``, interpolated between samples (T_0 if the
    drop is confirmed)."""
    below_release_first_s: float | None = None
    """First force sample below ``release_force_n`` since that crossing (the debounce
    counts from it: only observed samples confirm a release)."""
    overrun_warned: bool = False
    # watchdogs
    link_down_since_s: float | None = None
    camera_stalled_since_s: float | None = None
    # settling (RECOVERY)
    last_frame_t_s: float | None = None
    settling: SettlingTracker | None = None
    """Rise, peak and plateau of S_k since T_0 (None before the first recovery frame)."""
    settle_check_s: float | None = None
    """Earliest frame time of the next early-stop check by the recovery models (after one
    refused the stop) [s]."""
    settle_check: str | None = None
    """What the latest early-stop check by the recovery models found."""
    # bookkeeping
    flags: frozenset[str] = field(default_factory=frozenset)
    last_prompt: str = ""
    end_reason: str | None = None

    @property
    def terminal(self) -> bool:
        """True in DONE and in every fault phase."""
        return self.phase in TERMINAL_PHASES


def initial_state(t_s: float) -> MachineState:
    """Return the IDLE state at host time ``t_s`` [s]."""
    if not math.isfinite(t_s):
        raise ValueError(f"initial_state t_s must be finite, got {t_s!r}")
    return MachineState(phase=Phase.IDLE, now_s=t_s, phase_entered_s=t_s)


Result = tuple[MachineState, list[Output]]
Handler = Callable[[MachineState, Event, MeasurementConfig], Result]


# --------------------------------------------------------------------------- helpers


def _prompt(state: MachineState, text: str) -> Result:
    """Emit ``text`` unless it is already the current prompt."""
    if text == state.last_prompt:
        return state, []
    return evolve(state, last_prompt=text), [OperatorPrompt(text)]


def _goto(
    state: MachineState,
    new: Phase,
    reason: str,
    config: MeasurementConfig,
    **changes: object,
) -> Result:
    """Enter ``new`` at ``state.now_s``; faults also emit :class:`Fault`."""
    t = state.now_s
    out: list[Output] = [PhaseChanged(state.phase, new, t, reason)]
    nxt = evolve(state, phase=new, phase_entered_s=t, **changes)
    if new in FAULT_PHASES:
        out.append(Fault(new, reason, t))
        nxt = evolve(nxt, end_reason=reason)
    elif new is Phase.DONE:
        nxt = evolve(nxt, end_reason=reason)
    nxt, prompt = _prompt(nxt, _phase_prompt(nxt, config))
    return nxt, out + prompt


def _phase_prompt(state: MachineState, config: MeasurementConfig) -> str:
    """Prompt on entering a phase."""
    if state.phase is Phase.IDLE:
        return "Press Start to arm the probe"
    if state.phase is Phase.ARMED:
        return _press_prompt(config)
    if state.phase is Phase.PITTING:
        assert state.t_pit_start_s is not None
        if state.oob_since_s is not None and state.last_force_n is not None:
            return _band_prompt(state.last_force_n, config)
        left_s = state.t_pit_start_s + config.pitting_duration_s - state.now_s
        return f"Hold {_fmt_band(config)}: {_whole_s_left(left_s)} s left"
    if state.phase is Phase.RELEASE:
        return "Release the indenter now"
    if state.phase is Phase.RECOVERY:
        assert state.t_release_s is not None
        return _recovery_prompt(state.now_s - state.t_release_s, config)
    if state.phase is Phase.ANALYSIS:
        return "Analysing the recovery"
    if state.phase is Phase.DONE:
        return "Measurement complete"
    return f"Measurement stopped: {state.end_reason}"


def _press_prompt(config: MeasurementConfig) -> str:
    return f"Press the probe on the tissue until the force reads {config.target_force_n:g} N"


def _band_prompt(force_n: float, config: MeasurementConfig) -> str:
    hint = "ease off" if force_n > config.band_high_n else "press harder"
    return f"Force {force_n:.1f} N: {hint} to {_fmt_band(config)}"


def _recovery_prompt(elapsed_s: float, config: MeasurementConfig) -> str:
    return (
        f"Keep the probe still: recovery {math.floor(max(elapsed_s, 0.0)):.0f}/"
        f"{config.recovery_max_s:.0f} s"
    )


def _whole_s_left(left_s: float) -> int:
    """Whole seconds left, rounding up but ignoring float noise (15.000000000000002 -> 15)."""
    return math.ceil(left_s - 1e-9)


def _fmt_band(config: MeasurementConfig) -> str:
    return f"{config.target_force_n:.1f} ± {config.force_tolerance_n:.1f} N"


def _in_band(force_n: float, config: MeasurementConfig) -> bool:
    return config.band_low_n <= force_n <= config.band_high_n


def _with_flag(state: MachineState, flag: str) -> MachineState:
    return evolve(state, flags=state.flags | {flag})


# --------------------------------------------------------------------------- timer rules

TimerRule = Callable[[MachineState, MeasurementConfig], Result]
"""A time-driven rule: what ``state.now_s`` implies in the current phase, as a result."""


@dataclass(frozen=True, slots=True)
class Watchdog:
    """A watchdog limit (link or camera) as a timer rule; its policy decides per phase.

    Once the watched stream has been down longer than its limit, the phase's
    :class:`Policy` applies: ``FAULT`` enters the fault phase, ``FLAG`` records the phase's
    flag with one :class:`Advisory`, ``IGNORE`` does nothing.

    Parameters
    ----------
    name : str
        Name of the rule.
    what : str
        The condition in words, the start of the fault reason and the advisory.
    down_since_s : Callable[[MachineState], float | None]
        Host time [s] the stream went down, None while it is up.
    limit_s : Callable[[MeasurementConfig], float]
        Time [s] the stream may be down before the policy applies.
    policy : Mapping[Phase, Policy]
        Policy per non-terminal phase.
    fault : Phase
        Fault phase of the ``FAULT`` policy.
    flags : Mapping[Phase, MeasurementFlag]
        Flag of each phase whose policy is ``FLAG``.
    advisory : AdvisoryKind
        Kind of the advisory that goes with a flag.
    """

    name: str
    what: str
    down_since_s: Callable[[MachineState], float | None]
    limit_s: Callable[[MeasurementConfig], float]
    policy: Mapping[Phase, Policy]
    fault: Phase
    flags: Mapping[Phase, MeasurementFlag]
    advisory: AdvisoryKind

    def __call__(self, state: MachineState, config: MeasurementConfig) -> Result:
        """Apply the phase's policy if the stream has been down past its limit."""
        since, now, phase = self.down_since_s(state), state.now_s, state.phase
        if since is None or not now - since > self.limit_s(config):
            return state, []
        down_s = now - since
        policy = self.policy[phase]
        if policy is Policy.FAULT:
            return _goto(state, self.fault, f"{self.what} for {down_s:.1f} s in {phase}", config)
        if policy is Policy.FLAG and self.flags[phase] not in state.flags:
            state = _with_flag(state, self.flags[phase])
            return state, [Advisory(self.advisory, f"{self.what} for {down_s:.1f} s", now)]
        return state, []


LINK_WATCHDOG: Final = Watchdog(
    name="link watchdog",
    what="probe link down",
    down_since_s=lambda state: state.link_down_since_s,
    limit_s=lambda config: config.link_loss_limit_s,
    policy=LINK_POLICY,
    fault=Phase.LINK_LOST,
    flags={
        Phase.IDLE: MeasurementFlag.LINK_LOST_WHILE_IDLE,
        Phase.RECOVERY: MeasurementFlag.LINK_LOST_IN_RECOVERY,
    },
    advisory=AdvisoryKind.LINK_LOST_FLAGGED,
)
"""Force-link loss longer than ``link_loss_limit_s``: :data:`LINK_POLICY`."""

CAMERA_WATCHDOG: Final = Watchdog(
    name="camera watchdog",
    what="camera stalled",
    down_since_s=lambda state: state.camera_stalled_since_s,
    limit_s=lambda config: config.camera_stall_limit_s,
    policy=CAMERA_POLICY,
    fault=Phase.CAMERA_STALLED,
    flags={
        Phase.IDLE: MeasurementFlag.CAMERA_STALLED_WHILE_IDLE,
        Phase.PITTING: MeasurementFlag.CAMERA_STALLED_IN_PITTING,
    },
    advisory=AdvisoryKind.CAMERA_STALL_FLAGGED,
)
"""Camera stall longer than ``camera_stall_limit_s``: :data:`CAMERA_POLICY`."""


def _pitting_clock(state: MachineState, config: MeasurementConfig) -> Result:
    """PITTING: band accounting up to ``now`` (or the end of pitting), faults, completion."""
    assert state.t_pit_start_s is not None and state.oob_accounted_to_s is not None
    now = state.now_s
    accounted_s = state.oob_accounted_to_s
    t_complete = state.t_pit_start_s + config.pitting_duration_s
    t_acc = min(now, t_complete)
    if state.oob_since_s is not None and t_acc > accounted_s:
        total = state.oob_total_s + (t_acc - accounted_s)
        run = t_acc - state.oob_since_s
        state = evolve(
            state,
            oob_total_s=total,
            oob_accounted_to_s=t_acc,
            max_excursion_s=max(state.max_excursion_s, run),
        )
        force = f"{state.last_force_n:.1f} N" if state.last_force_n is not None else "unknown"
        early = (
            " (below the release threshold: indenter released early?)"
            if state.last_force_n is not None and state.last_force_n < config.release_force_n
            else ""
        )
        if run > config.out_of_band_grace_s:
            return _goto(
                state,
                Phase.FORCE_OUT_OF_BAND,
                f"force {force} outside {_fmt_band(config)} for {run:.2f} s continuously "
                f"(limit {config.out_of_band_grace_s:.2f} s){early}",
                config,
            )
        if total > config.out_of_band_limit_s:
            return _goto(
                state,
                Phase.FORCE_OUT_OF_BAND,
                f"force outside {_fmt_band(config)} for {total:.2f} s in total during pitting "
                f"(limit {config.out_of_band_limit_s:.2f} s){early}",
                config,
            )
    else:
        state = evolve(state, oob_accounted_to_s=max(accounted_s, t_acc))
    if now >= t_complete:
        # a force already below the release threshold ended the hold where it dropped
        dropped = state.below_release_since_s
        state, out = _goto(
            state,
            Phase.RELEASE,
            f"pitting complete ({config.pitting_duration_s:.1f} s)",
            config,
            t_pit_end_s=t_complete if dropped is None else min(dropped, t_complete),
            oob_since_s=None,
        )
        return state, out
    left_s = t_complete - now
    if state.oob_since_s is None:
        return _prompt(state, f"Hold {_fmt_band(config)}: {_whole_s_left(left_s)} s left")
    return state, []


def _release_overrun(state: MachineState, config: MeasurementConfig) -> Result:
    """RELEASE: one advisory and a flag once the indenter is held past the warning time."""
    assert state.t_pit_end_s is not None
    waited_s = state.now_s - state.t_pit_end_s
    if state.overrun_warned or not waited_s > config.release_overrun_warn_s:
        return state, []
    state = evolve(_with_flag(state, MeasurementFlag.PITTING_OVERRUN), overrun_warned=True)
    return state, [
        Advisory(
            AdvisoryKind.RELEASE_OVERRUN,
            f"indenter still held {waited_s:.1f} s after the pitting time ended",
            state.now_s,
        )
    ]


def _recovery_window(state: MachineState, config: MeasurementConfig) -> Result:
    """RECOVERY: the window ends ``recovery_max_s`` after T_0 (ANALYSIS), else a countdown."""
    assert state.t_release_s is not None
    # compared with the end time itself, not the elapsed time: (t + w) - t can round below
    # w, and a tick at the end time (MeasurementPipeline.close) must end the window
    t_end_s = state.t_release_s + config.recovery_max_s
    if state.now_s >= t_end_s:
        return _start_analysis(state, t_end_s, config, settled=False)
    return _prompt(state, _recovery_prompt(state.now_s - state.t_release_s, config))


_WATCHDOGS: Final[tuple[TimerRule, ...]] = (LINK_WATCHDOG, CAMERA_WATCHDOG)

TIMER_RULES: Final[dict[Phase, tuple[TimerRule, ...]]] = {
    Phase.IDLE: _WATCHDOGS,
    Phase.ARMED: _WATCHDOGS,
    Phase.PITTING: (*_WATCHDOGS, _pitting_clock),
    Phase.RELEASE: (*_WATCHDOGS, _release_overrun),
    Phase.RECOVERY: (*_WATCHDOGS, _recovery_window),
    Phase.ANALYSIS: _WATCHDOGS,
}
"""Time-driven rules of every non-terminal phase, in the order the clock step applies them."""


def _advance(state: MachineState, config: MeasurementConfig) -> Result:
    """Apply the phase's :data:`TIMER_RULES` up to ``state.now_s``, until one changes it."""
    phase = state.phase
    out: list[Output] = []
    for rule in TIMER_RULES[phase]:
        state, more = rule(state, config)
        out += more
        if state.phase is not phase:
            break
    return state, out


def _start_analysis(
    state: MachineState, t_end_s: float, config: MeasurementConfig, *, settled: bool
) -> Result:
    t0_s, pit_start_s, pit_end_s = state.t_release_s, state.t_pit_start_s, state.t_pit_end_s
    assert t0_s is not None and pit_start_s is not None and pit_end_s is not None
    if settled:
        reason = "recovery settled"
        if state.settle_check is not None:
            reason += f" (recovery models: {state.settle_check})"
    elif config.stop_when_settled:
        # the machine watched for settling and did not see it within the window
        state = _with_flag(state, Flag.NOT_SETTLED)
        reason = "recovery window ended before S_k settled"
    else:
        # the paper's protocol: the whole window is the normal end; whether S_k settled in
        # it is the analysis' call (Eq. (6), its own NOT_SETTLED flag)
        reason = f"recovery window complete ({config.recovery_max_s:g} s)"
    state = evolve(state, t_recovery_end_s=t_end_s)
    state, out = _goto(state, Phase.ANALYSIS, reason, config)
    start = StartAnalysis(
        t0_s=t0_s,
        t_end_s=t_end_s,
        t_pit_start_s=pit_start_s,
        t_pit_end_s=pit_end_s,
        settled=settled,
        t_settled_s=state.t_settled_s,
        flags=tuple(sorted(state.flags)),
    )
    return state, [out[0], start, *out[1:]]


# --------------------------------------------------------------------------- handlers


def _absorb(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    """Terminal phases: the state is returned unchanged, nothing is emitted."""
    return state, []


def _ignore(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    """Explicitly ignored (the clock step has already run)."""
    return state, []


def _unexpected(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    """Not meaningful in this phase: reported, no change."""
    return state, [
        Advisory(
            AdvisoryKind.UNEXPECTED_EVENT,
            f"{type(event).__name__} ignored in phase {state.phase}",
            state.now_s,
        )
    ]


def _arm(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    return _goto(state, Phase.ARMED, "armed by the operator", config)


def _abort(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    return _goto(state, Phase.ABORTED, f"aborted by the operator in {state.phase}", config)


def _session_closed(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    return _goto(state, Phase.ABORTED, f"session closed in {state.phase}", config)


def _link_lost(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    if state.link_down_since_s is not None:
        return state, []
    state = evolve(state, link_down_since_s=event.t_s)
    return state, [Advisory(AdvisoryKind.LINK_DOWN, f"probe link down in {state.phase}", event.t_s)]


def _link_restored(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    if state.link_down_since_s is None:
        return state, []
    down_s = state.now_s - state.link_down_since_s
    state = evolve(state, link_down_since_s=None)
    return state, [
        Advisory(AdvisoryKind.LINK_RESTORED, f"probe link back after {down_s:.2f} s", state.now_s)
    ]


def _camera_stalled(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    if state.camera_stalled_since_s is not None:
        return state, []
    state = evolve(state, camera_stalled_since_s=event.t_s)
    return state, [
        Advisory(AdvisoryKind.CAMERA_STALLED, f"camera stalled in {state.phase}", event.t_s)
    ]


def _camera_recovered(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    if state.camera_stalled_since_s is None:
        return state, []
    stall_s = state.now_s - state.camera_stalled_since_s
    state = evolve(state, camera_stalled_since_s=None)
    return state, [
        Advisory(AdvisoryKind.CAMERA_RECOVERED, f"camera back after {stall_s:.2f} s", state.now_s)
    ]


def _take_force(state: MachineState, event: Event) -> tuple[MachineState, list[Output], bool]:
    """Record a force sample; returns ``ok=False`` (with an advisory) if out of order."""
    assert isinstance(event, ForceSample)
    if state.last_force_t_s is not None and event.t_s < state.last_force_t_s:
        return (
            state,
            [
                Advisory(
                    AdvisoryKind.OUT_OF_ORDER_SAMPLE,
                    f"force sample at {event.t_s:.6f} s is older than the previous one "
                    f"({state.last_force_t_s:.6f} s); dropped",
                    state.now_s,
                )
            ],
            False,
        )
    return evolve(state, last_force_t_s=event.t_s, last_force_n=event.force_n), [], True


def _force_idle(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    state, out, _ = _take_force(state, event)
    return state, out


def _force_armed(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    state, out, ok = _take_force(state, event)
    if not ok:
        return state, out
    assert isinstance(event, ForceSample)
    f = event.force_n
    if f >= config.band_low_n:
        # pitting starts at this sample; the clock and band accounting start here
        oob = None if f <= config.band_high_n else event.t_s
        state, more = _goto(
            evolve(state, contact=True),
            Phase.PITTING,
            f"force reached the band ({f:.1f} N)",
            config,
            t_pit_start_s=event.t_s,
            oob_since_s=oob,
            oob_accounted_to_s=event.t_s,
            n_excursions=1 if oob is not None else 0,
        )
        out += more
        state, more = _pitting_clock(state, config)
        out += more
        if oob is not None and state.phase is Phase.PITTING:
            out.append(
                Advisory(
                    AdvisoryKind.FORCE_OUT_OF_BAND,
                    f"force {f:.1f} N above {_fmt_band(config)} at the start of pitting",
                    event.t_s,
                )
            )
            state = _with_flag(state, MeasurementFlag.FORCE_EXCURSION)
        return state, out
    if f >= config.contact_force_n:
        state, more = _prompt(
            evolve(state, contact=True),
            f"Keep pressing: {f:.1f} N of {config.target_force_n:.1f} N",
        )
        return state, out + more
    state, more = _prompt(evolve(state, contact=False), _press_prompt(config))
    return state, out + more


def _force_pitting(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    before = state
    state, out, ok = _take_force(state, event)
    if not ok:
        return state, out
    assert isinstance(event, ForceSample)
    f = event.force_n
    state = _track_release_crossing(before, state, event, config)
    if _in_band(f, config):
        if state.oob_since_s is not None:
            state = evolve(state, oob_since_s=None)
        state, more = _pitting_clock(state, config)
        return state, out + more
    if state.oob_since_s is None:
        state = _with_flag(
            evolve(
                state,
                oob_since_s=event.t_s,
                oob_accounted_to_s=max(event.t_s, state.oob_accounted_to_s or event.t_s),
                n_excursions=state.n_excursions + 1,
            ),
            MeasurementFlag.FORCE_EXCURSION,
        )
        out.append(
            Advisory(
                AdvisoryKind.FORCE_OUT_OF_BAND,
                f"force {f:.1f} N outside {_fmt_band(config)} "
                f"(excursion {state.n_excursions}, {state.oob_total_s:.2f} s out so far)",
                event.t_s,
            )
        )
    since = state.below_release_since_s
    if since is not None and _release_within_grace(state, since, config):
        if _release_debounced(state, event.t_s, config):
            state, more = _release_before_timer(state, since, config)
            return state, out + more
        # the operator is letting go at the end of the hold: no "press harder"
        return state, out
    state, more = _prompt(state, _band_prompt(f, config))
    return state, out + more


def _release_crossing_s(
    before: MachineState, event: ForceSample, config: MeasurementConfig
) -> float:
    """Time [s] the force crossed ``release_force_n`` downward, linearly interpolated
    between the previous sample (at or above the threshold) and ``event`` (below it);
    ``event.t_s`` when there is no previous sample above the threshold."""
    t_prev, f_prev = before.last_force_t_s, before.last_force_n
    thr = config.release_force_n
    if t_prev is None or f_prev is None or f_prev < thr or not event.t_s > t_prev:
        return event.t_s
    return t_prev + (f_prev - thr) / (f_prev - event.force_n) * (event.t_s - t_prev)


def _track_release_crossing(
    before: MachineState, state: MachineState, event: ForceSample, config: MeasurementConfig
) -> MachineState:
    """``state`` with ``below_release_since_s`` at the force's downward crossing of
    ``release_force_n`` (None again once the force is back at or above it)."""
    if event.force_n >= config.release_force_n:
        return evolve(state, below_release_since_s=None, below_release_first_s=None)
    if state.below_release_since_s is not None:
        return state
    return evolve(
        state,
        below_release_since_s=_release_crossing_s(before, event, config),
        below_release_first_s=event.t_s,
    )


def _release_debounced(state: MachineState, t_s: float, config: MeasurementConfig) -> bool:
    """Whether the force has been observed below ``release_force_n`` for the debounce."""
    first = state.below_release_first_s
    return first is not None and t_s - first >= config.release_debounce_s


def _release_within_grace(state: MachineState, t_drop_s: float, config: MeasurementConfig) -> bool:
    """Whether a force drop at ``t_drop_s`` [s] during PITTING is a release at the end of
    the hold: had the force stayed down until the pitting time ended, the excursion it
    began would still have been tolerated (continuous run <= ``out_of_band_grace_s``,
    cumulative out-of-band time <= ``out_of_band_limit_s``)."""
    assert state.t_pit_start_s is not None
    t_complete = state.t_pit_start_s + config.pitting_duration_s
    oob_since = state.oob_since_s if state.oob_since_s is not None else t_drop_s
    accounted = state.oob_accounted_to_s if state.oob_accounted_to_s is not None else t_drop_s
    run_s = t_complete - oob_since
    total_s = state.oob_total_s + max(t_complete - accounted, 0.0)
    return run_s <= config.out_of_band_grace_s and total_s <= config.out_of_band_limit_s


def _release_before_timer(
    state: MachineState, t_drop_s: float, config: MeasurementConfig
) -> Result:
    """PITTING -> RELEASE -> RECOVERY for a release inside the grace: T_0 and the end of
    the hold are the observed force drop ``t_drop_s`` [s], never the timer's end."""
    assert state.t_pit_start_s is not None
    early_s = state.t_pit_start_s + config.pitting_duration_s - t_drop_s
    advisory = Advisory(
        AdvisoryKind.RELEASE_BEFORE_PITTING_END,
        f"force below {config.release_force_n:.1f} N {early_s:.2f} s before the pitting time "
        f"ended (within the {config.out_of_band_grace_s:.2f} s grace): T_0 at the force drop",
        state.now_s,
    )
    state, out = _goto(
        state,
        Phase.RELEASE,
        f"released {early_s:.2f} s before the pitting time ended",
        config,
        t_pit_end_s=t_drop_s,
        oob_since_s=None,
    )
    state, more = _goto(
        state,
        Phase.RECOVERY,
        f"release detected: force below {config.release_force_n:.1f} N "
        f"for {state.now_s - t_drop_s:.2f} s",
        config,
        t_release_s=t_drop_s,
        release_by="force",
    )
    return state, [advisory, *out, *more]


def _force_release(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    before = state
    state, out, ok = _take_force(state, event)
    if not ok:
        return state, out
    assert isinstance(event, ForceSample)
    state = _track_release_crossing(before, state, event, config)
    since = state.below_release_since_s
    if since is None:
        return state, out
    if _release_debounced(state, event.t_s, config):
        state, more = _goto(
            state,
            Phase.RECOVERY,
            f"release detected: force below {config.release_force_n:.1f} N "
            f"for {event.t_s - since:.2f} s",
            config,
            t_release_s=since,
            release_by="force",
        )
        return state, out + more
    return state, out


def _force_recovery(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    """The rebound force is recorded by the shell; the machine only keeps order."""
    state, out, _ = _take_force(state, event)
    return state, out


def _operator_release_early(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    assert state.t_pit_start_s is not None
    left_s = state.t_pit_start_s + config.pitting_duration_s - state.now_s
    return state, [
        Advisory(
            AdvisoryKind.EARLY_RELEASE_REQUEST,
            f"release button ignored: {left_s:.1f} s of pitting left",
            state.now_s,
        )
    ]


def _operator_release(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    out: list[Output] = []
    if state.last_force_n is not None and state.last_force_n >= config.release_force_n:
        out.append(
            Advisory(
                AdvisoryKind.RELEASE_UNDER_FORCE,
                f"operator confirmed release while the force reads {state.last_force_n:.1f} N",
                state.now_s,
            )
        )
    state = _with_flag(state, MeasurementFlag.RELEASE_CONFIRMED_BY_OPERATOR)
    state, more = _goto(
        state,
        Phase.RECOVERY,
        "release confirmed by the operator",
        config,
        t_release_s=event.t_s,
        release_by="operator",
    )
    return state, out + more


def _frame_recovery(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    assert isinstance(event, FrameSample) and state.t_release_s is not None
    if state.last_frame_t_s is not None and event.t_s < state.last_frame_t_s:
        return state, [
            Advisory(
                AdvisoryKind.OUT_OF_ORDER_SAMPLE,
                f"frame at {event.t_s:.6f} s is older than the previous one "
                f"({state.last_frame_t_s:.6f} s); dropped",
                state.now_s,
            )
        ]
    t0_s = state.t_release_s
    if event.t_s < t0_s:
        # a frame taken before T_0 that arrived late: not part of the recovery
        return evolve(state, last_frame_t_s=event.t_s), []
    tracker = state.settling
    tracker = (
        SettlingTracker.first(event.t_s, event.s_k, config.settle_fraction)
        if tracker is None
        else tracker.add(event.t_s, event.s_k)
    )
    state = evolve(state, last_frame_t_s=event.t_s, settling=tracker)
    if config.stop_when_settled and tracker.settled(
        t0_s,
        hold_s=config.settle_hold_s,
        bias_fraction=config.settle_bias_fraction,
        window_end_s=t0_s + config.recovery_max_s,
    ):
        return _models_allow_stop(state, tracker, event.t_s, config)
    return state, []


def _models_allow_stop(
    state: MachineState, tracker: SettlingTracker, t_s: float, config: MeasurementConfig
) -> Result:
    """Test 5 (module docstring): the recovery models that fit the rise allow the stop.

    Runs at most once per :data:`MODEL_CHECK_MIN_S`, or :data:`MODEL_CHECK_FRACTION` of
    the recovery so far, after a refusal: a fit of every recovery model (no bootstrap) at a
    few decision points, never per frame.
    """
    t0_s = state.t_release_s
    assert t0_s is not None
    if not tracker.has_rise:  # nothing to time (no recovery, or one within a frame)
        state = evolve(state, t_settled_s=t_s)
        return _start_analysis(state, t_s, config, settled=True)
    if state.settle_check_s is not None and t_s < state.settle_check_s:
        return state, []
    times, values = tracker.frames()
    check = early_stop_check(
        times,
        values,
        t0_s,
        t0_s + config.recovery_max_s,
        settle_fraction=config.settle_fraction,
        bias_fraction=config.settle_bias_fraction,
    )
    if not check.allowed:
        wait_s = max(MODEL_CHECK_MIN_S, MODEL_CHECK_FRACTION * (t_s - t0_s))
        return evolve(state, settle_check_s=t_s + wait_s, settle_check=check.reason), []
    state = evolve(state, t_settled_s=t_s, settle_check=check.reason)
    return _start_analysis(state, t_s, config, settled=True)


def _analysis_done(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    return _goto(state, Phase.DONE, "analysis finished", config)


# --------------------------------------------------------------------------- the table

_P = Phase

TABLE: Final[dict[tuple[Phase, type[Event]], Handler]] = {
    # IDLE: nothing measured yet
    (_P.IDLE, Arm): _arm,
    (_P.IDLE, ForceSample): _force_idle,
    (_P.IDLE, FrameSample): _ignore,
    (_P.IDLE, OperatorRelease): _unexpected,
    (_P.IDLE, OperatorAbort): _abort,
    (_P.IDLE, LinkLost): _link_lost,
    (_P.IDLE, LinkRestored): _link_restored,
    (_P.IDLE, CameraStalled): _camera_stalled,
    (_P.IDLE, CameraRecovered): _camera_recovered,
    (_P.IDLE, Tick): _ignore,
    (_P.IDLE, AnalysisDone): _unexpected,
    (_P.IDLE, SessionClosed): _session_closed,
    # ARMED: waiting for contact and the approach ramp
    (_P.ARMED, Arm): _unexpected,
    (_P.ARMED, ForceSample): _force_armed,
    (_P.ARMED, FrameSample): _ignore,
    (_P.ARMED, OperatorRelease): _unexpected,
    (_P.ARMED, OperatorAbort): _abort,
    (_P.ARMED, LinkLost): _link_lost,
    (_P.ARMED, LinkRestored): _link_restored,
    (_P.ARMED, CameraStalled): _camera_stalled,
    (_P.ARMED, CameraRecovered): _camera_recovered,
    (_P.ARMED, Tick): _ignore,
    (_P.ARMED, AnalysisDone): _unexpected,
    (_P.ARMED, SessionClosed): _session_closed,
    # PITTING: force held in the band for pitting_duration_s
    (_P.PITTING, Arm): _unexpected,
    (_P.PITTING, ForceSample): _force_pitting,
    (_P.PITTING, FrameSample): _ignore,
    (_P.PITTING, OperatorRelease): _operator_release_early,
    (_P.PITTING, OperatorAbort): _abort,
    (_P.PITTING, LinkLost): _link_lost,
    (_P.PITTING, LinkRestored): _link_restored,
    (_P.PITTING, CameraStalled): _camera_stalled,
    (_P.PITTING, CameraRecovered): _camera_recovered,
    (_P.PITTING, Tick): _ignore,
    (_P.PITTING, AnalysisDone): _unexpected,
    (_P.PITTING, SessionClosed): _session_closed,
    # RELEASE: the operator has been asked to release
    (_P.RELEASE, Arm): _unexpected,
    (_P.RELEASE, ForceSample): _force_release,
    (_P.RELEASE, FrameSample): _ignore,
    (_P.RELEASE, OperatorRelease): _operator_release,
    (_P.RELEASE, OperatorAbort): _abort,
    (_P.RELEASE, LinkLost): _link_lost,
    (_P.RELEASE, LinkRestored): _link_restored,
    (_P.RELEASE, CameraStalled): _camera_stalled,
    (_P.RELEASE, CameraRecovered): _camera_recovered,
    (_P.RELEASE, Tick): _ignore,
    (_P.RELEASE, AnalysisDone): _unexpected,
    (_P.RELEASE, SessionClosed): _session_closed,
    # RECOVERY: the camera watches the pit recover
    (_P.RECOVERY, Arm): _unexpected,
    (_P.RECOVERY, ForceSample): _force_recovery,
    (_P.RECOVERY, FrameSample): _frame_recovery,
    (_P.RECOVERY, OperatorRelease): _ignore,
    (_P.RECOVERY, OperatorAbort): _abort,
    (_P.RECOVERY, LinkLost): _link_lost,
    (_P.RECOVERY, LinkRestored): _link_restored,
    (_P.RECOVERY, CameraStalled): _camera_stalled,
    (_P.RECOVERY, CameraRecovered): _camera_recovered,
    (_P.RECOVERY, Tick): _ignore,
    (_P.RECOVERY, AnalysisDone): _unexpected,
    (_P.RECOVERY, SessionClosed): _session_closed,
    # ANALYSIS: data complete, waiting for the analysis
    (_P.ANALYSIS, Arm): _unexpected,
    (_P.ANALYSIS, ForceSample): _ignore,
    (_P.ANALYSIS, FrameSample): _ignore,
    (_P.ANALYSIS, OperatorRelease): _ignore,
    (_P.ANALYSIS, OperatorAbort): _abort,
    (_P.ANALYSIS, LinkLost): _ignore,
    (_P.ANALYSIS, LinkRestored): _ignore,
    (_P.ANALYSIS, CameraStalled): _ignore,
    (_P.ANALYSIS, CameraRecovered): _ignore,
    (_P.ANALYSIS, Tick): _ignore,
    (_P.ANALYSIS, AnalysisDone): _analysis_done,
    (_P.ANALYSIS, SessionClosed): _session_closed,
    # terminal phases absorb every event
    **{(p, e): _absorb for p in sorted(TERMINAL_PHASES) for e in EVENT_TYPES},
}
"""Every ``(phase, event type)`` pair and its handler; nothing is implicit."""


# --------------------------------------------------------------------------- entry points


def transition(state: MachineState, event: Event, config: MeasurementConfig) -> Result:
    """Apply one event; pure.

    Parameters
    ----------
    state : MachineState
        Current state.
    event : Event
        The event; its ``t_s`` [s] may be older than ``state.now_s`` (time then stays).
    config : MeasurementConfig
        Thresholds.

    Returns
    -------
    tuple[MachineState, list[Output]]
        The next state and what happened, in order.

    Raises
    ------
    KeyError
        Only if ``event`` is not one of :data:`EVENT_TYPES` (a programming error).
    """
    handler = TABLE[(state.phase, type(event))]
    if state.terminal:
        return handler(state, event, config)
    out: list[Output] = []
    if event.t_s > state.now_s:
        state = evolve(state, now_s=event.t_s)
    # clock step: time-driven rules, repeated while they change the phase
    while True:
        before = state.phase
        state, more = _advance(state, config)
        out += more
        if state.phase is before or state.terminal:
            break
    handler = TABLE[(state.phase, type(event))]
    state, more = handler(state, event, config)
    return state, out + more


def close(state: MachineState, t_s: float, config: MeasurementConfig) -> Result:
    """Close the session at ``t_s`` [s]: any non-terminal phase ends in a terminal one.

    Time-driven rules still apply first (a recovery whose window has passed goes to
    ANALYSIS), then ``SessionClosed`` ends every non-terminal phase in ``ABORTED`` (reason
    "session closed in <phase>"); recorded data is the shell's and is kept. A terminal
    state is returned unchanged.
    """
    return transition(state, SessionClosed(max(t_s, state.now_s)), config)
