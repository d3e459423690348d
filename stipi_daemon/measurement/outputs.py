"""Outputs of the pit/release state machine, and the names they use.

This module owns what :func:`~stipi_daemon.measurement.state_machine.transition` reports to
the shell: the measurement's :class:`Phase` (with the fault and terminal sets), the caveats
it records (:class:`MeasurementFlag`), the kinds of non-fatal warnings
(:class:`AdvisoryKind`) and the output types :class:`PhaseChanged`, :class:`OperatorPrompt`,
:class:`Advisory`, :class:`Fault` and :class:`StartAnalysis`. Times are the host's
monotonic clock [s]. It does not own when they are emitted (the machine) nor what the shell
does with them (console, storage, analysis).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Final

__all__ = [
    "FAULT_PHASES",
    "TERMINAL_PHASES",
    "Advisory",
    "AdvisoryKind",
    "Fault",
    "MeasurementFlag",
    "OperatorPrompt",
    "Output",
    "Phase",
    "PhaseChanged",
    "StartAnalysis",
]


class Phase(StrEnum):
    """Phases of a measurement; the last five are terminal (absorbing)."""

    IDLE = "idle"
    ARMED = "armed"
    PITTING = "pitting"
    RELEASE = "release"
    RECOVERY = "recovery"
    ANALYSIS = "analysis"
    DONE = "done"
    LINK_LOST = "link_lost"
    CAMERA_STALLED = "camera_stalled"
    FORCE_OUT_OF_BAND = "force_out_of_band"
    ABORTED = "aborted"


FAULT_PHASES: Final = frozenset(
    {Phase.LINK_LOST, Phase.CAMERA_STALLED, Phase.FORCE_OUT_OF_BAND, Phase.ABORTED}
)
TERMINAL_PHASES: Final = FAULT_PHASES | {Phase.DONE}


class MeasurementFlag(StrEnum):
    """Caveats recorded on a measurement (the analysis' own flags live in ``Flag``)."""

    RELEASE_CONFIRMED_BY_OPERATOR = "release_confirmed_by_operator"
    """T_0 is the operator's button press, not a detected force drop."""
    FORCE_EXCURSION = "force_excursion"
    """The pitting force left the band at least once (tolerated)."""
    PITTING_OVERRUN = "pitting_overrun"
    """The indenter was held longer than ``release_overrun_warn_s`` after pitting ended."""
    LINK_LOST_IN_RECOVERY = "link_lost_in_recovery"
    """The force link was down past its limit during recovery (camera data intact)."""
    LINK_LOST_WHILE_IDLE = "link_lost_while_idle"
    """The force link was down past its limit before arming."""
    CAMERA_STALLED_WHILE_IDLE = "camera_stalled_while_idle"
    """The camera stalled past its limit before arming."""
    CAMERA_STALLED_IN_PITTING = "camera_stalled_in_pitting"
    """The camera stalled past its limit during pitting (and was back before release)."""


class AdvisoryKind(StrEnum):
    """Kinds of non-fatal :class:`Advisory` outputs."""

    FORCE_OUT_OF_BAND = "force_out_of_band"
    RELEASE_OVERRUN = "release_overrun"
    EARLY_RELEASE_REQUEST = "early_release_request"
    RELEASE_UNDER_FORCE = "release_under_force"
    RELEASE_BEFORE_PITTING_END = "release_before_pitting_end"
    LINK_DOWN = "link_down"
    LINK_RESTORED = "link_restored"
    LINK_LOST_FLAGGED = "link_lost_flagged"
    CAMERA_STALLED = "camera_stalled"
    CAMERA_RECOVERED = "camera_recovered"
    CAMERA_STALL_FLAGGED = "camera_stall_flagged"
    OUT_OF_ORDER_SAMPLE = "out_of_order_sample"
    UNEXPECTED_EVENT = "unexpected_event"


@dataclass(frozen=True, slots=True)
class PhaseChanged:
    """The machine moved from ``old`` to ``new`` at ``t_s`` [s] because of ``reason``."""

    old: Phase
    new: Phase
    t_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class OperatorPrompt:
    """What the operator must do next (emitted only when the text changes)."""

    text: str


@dataclass(frozen=True, slots=True)
class Advisory:
    """A non-fatal problem worth recording and showing (a warning)."""

    kind: AdvisoryKind
    detail: str
    t_s: float


@dataclass(frozen=True, slots=True)
class Fault:
    """The measurement stopped in the fault phase ``kind`` at ``t_s`` [s]."""

    kind: Phase
    reason: str
    t_s: float


@dataclass(frozen=True, slots=True)
class StartAnalysis:
    """Start the analysis of the recorded pitting and recovery.

    Parameters
    ----------
    t0_s : float
        Release time T_0 of Eq. (6) [s].
    t_end_s : float
        End of the recovery window [s].
    t_pit_start_s, t_pit_end_s : float
        Pitting interval [s].
    settled : bool
        Whether S_k settled before ``recovery_max_s``.
    t_settled_s : float | None
        Time the settling test passed [s] (the end of the hold), if it did.
    flags : tuple[str, ...]
        Sorted caveats: :class:`MeasurementFlag` values and ``Flag.NOT_SETTLED`` (only
        with ``stop_when_settled``: the window ended before the settling test passed).
    """

    t0_s: float
    t_end_s: float
    t_pit_start_s: float
    t_pit_end_s: float
    settled: bool
    t_settled_s: float | None
    flags: tuple[str, ...]


Output = PhaseChanged | OperatorPrompt | Advisory | Fault | StartAnalysis
