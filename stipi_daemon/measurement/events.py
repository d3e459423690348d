"""Inputs of the pit/release state machine: timestamped events.

This module owns the event types the shell feeds to
:func:`~stipi_daemon.measurement.state_machine.transition`: operator actions (:class:`Arm`,
:class:`OperatorRelease`, :class:`OperatorAbort`), samples (:class:`ForceSample`,
:class:`FrameSample`), watchdog reports (:class:`LinkLost`, :class:`LinkRestored`,
:class:`CameraStalled`, :class:`CameraRecovered`), :class:`Tick` (time passes),
:class:`AnalysisDone` and :class:`SessionClosed`. Every event carries ``t_s``, the host's
monotonic time [s]; values are checked when an event is built (finite, S_k >= 0). It does
not own what an event does in a phase (the machine's transition table).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

__all__ = [
    "EVENT_TYPES",
    "AnalysisDone",
    "Arm",
    "CameraRecovered",
    "CameraStalled",
    "Event",
    "ForceSample",
    "FrameSample",
    "LinkLost",
    "LinkRestored",
    "OperatorAbort",
    "OperatorRelease",
    "SessionClosed",
    "Tick",
]


def _finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")


@dataclass(frozen=True, slots=True)
class _Timed:
    t_s: float
    """Host monotonic time of the event [s]."""

    def __post_init__(self) -> None:
        _finite(f"{type(self).__name__}.t_s", self.t_s)


@dataclass(frozen=True, slots=True)
class Arm(_Timed):
    """The operator starts a measurement."""


@dataclass(frozen=True, slots=True)
class ForceSample(_Timed):
    """One load-cell reading at ``t_s`` [s]: ``force_n`` [N] (finite; may be negative)."""

    force_n: float

    def __post_init__(self) -> None:
        _finite("ForceSample.t_s", self.t_s)
        _finite("ForceSample.force_n", self.force_n)


@dataclass(frozen=True, slots=True)
class FrameSample(_Timed):
    """One camera frame at ``t_s`` [s] with its occluded-pixel sum ``s_k`` (Eq. (2)) [px]."""

    s_k: float

    def __post_init__(self) -> None:
        _finite("FrameSample.t_s", self.t_s)
        _finite("FrameSample.s_k", self.s_k)
        if self.s_k < 0.0:
            raise ValueError(f"FrameSample.s_k must be >= 0 (a pixel sum), got {self.s_k!r}")


@dataclass(frozen=True, slots=True)
class OperatorRelease(_Timed):
    """The operator confirms that the indenter has been released."""


@dataclass(frozen=True, slots=True)
class OperatorAbort(_Timed):
    """The operator aborts the measurement."""


@dataclass(frozen=True, slots=True)
class LinkLost(_Timed):
    """The link watchdog saw no frame from the probe (force stream stopped)."""


@dataclass(frozen=True, slots=True)
class LinkRestored(_Timed):
    """Frames from the probe arrive again."""


@dataclass(frozen=True, slots=True)
class CameraStalled(_Timed):
    """The camera watchdog saw no frame."""


@dataclass(frozen=True, slots=True)
class CameraRecovered(_Timed):
    """Camera frames arrive again."""


@dataclass(frozen=True, slots=True)
class Tick(_Timed):
    """Time passes (drives timeouts when no other event arrives)."""


@dataclass(frozen=True, slots=True)
class AnalysisDone(_Timed):
    """The analysis started by :class:`StartAnalysis` has finished (success or flagged)."""


@dataclass(frozen=True, slots=True)
class SessionClosed(_Timed):
    """The session is closed; any non-terminal phase ends (see :func:`close`)."""


Event = (
    Arm
    | ForceSample
    | FrameSample
    | OperatorRelease
    | OperatorAbort
    | LinkLost
    | LinkRestored
    | CameraStalled
    | CameraRecovered
    | Tick
    | AnalysisDone
    | SessionClosed
)

EVENT_TYPES: Final[tuple[type[Event], ...]] = (
    Arm,
    ForceSample,
    FrameSample,
    OperatorRelease,
    OperatorAbort,
    LinkLost,
    LinkRestored,
    CameraStalled,
    CameraRecovered,
    Tick,
    AnalysisDone,
    SessionClosed,
)
"""Every event type, in the order of the transition table's rows."""
