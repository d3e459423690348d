"""Whether frames are being processed, and what a stretch without them does to the result.

:class:`FrameWatch` is told when each frame is handled (measured, or stored as a gap for
coming too late) and, on every tick of the acquisition loop, the session time and the
measurement's phase. It answers with the lines the operator console shows:

* a warning once no frame has been handled for :data:`FRAME_SILENCE_WARN_S` of session
  time (the ticks come every 0.05 s, so the warning comes within a second of the last
  frame): ``frames not processed for 0.5 s (since 30.02 s): <what it means>``;
* when frames come again, how long the stretch was: ``frames arrive again after 20.0 s
  without (30.02-50.00 s): <what it means>``;
* when frames that came too late to be measured (gap reason ``processing_behind``) are
  followed by a measured one, which captures they were: ``300 frames captured
  30.02-35.00 s came too late to be measured (processing_behind gaps): <meaning>``.

What it means follows the phase (:func:`frame_gap_meaning`): in the recovery, the recovery
time cannot be read inside the gap. Pure: no clock, no I/O. Times are session times [s].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from stipi_daemon.measurement.outputs import Phase

__all__ = ["FRAME_SILENCE_WARN_S", "FrameWatch", "frame_gap_meaning"]

#: Session time without a frame handled after which the console warns [s].
FRAME_SILENCE_WARN_S: Final = 0.5


def frame_gap_meaning(phase: Phase) -> str:
    """What a stretch without measured frames in ``phase`` does to the results."""
    if phase in (Phase.RELEASE, Phase.RECOVERY):
        return (
            "S_k is not measured: the recovery time T_r (and S_max, F_r, the recovery fit) "
            "cannot be read inside this gap"
        )
    if phase is Phase.PITTING:
        return "the pit is not watched: S_0 at the release (D_p, E) cannot be read inside this gap"
    return "no result is read from frames yet"


@dataclass
class FrameWatch:
    """Tracks the frames handled and says when they stop, start again or came too late.

    Parameters
    ----------
    warn_after_s : float
        Session time without a frame handled before the warning [s].
    """

    warn_after_s: float = FRAME_SILENCE_WARN_S
    #: Session time the last frame was handled at [s] (None: none yet).
    last_handled_s: float | None = None
    #: Capture time of the last frame handled [s].
    last_capture_s: float | None = None
    #: Whether the current stretch without frames has been warned of.
    warned: bool = False
    _late: list[float] = field(default_factory=list)

    @property
    def warning(self) -> str | None:
        """The standing warning while frames are not processed (None otherwise)."""
        if not self.warned or self.last_capture_s is None:
            return None
        return f"frames not processed since {self.last_capture_s:.2f} s"

    def tick(self, now_s: float, phase: Phase) -> str | None:
        """The warning line, once per stretch, when no frame was handled for
        :attr:`warn_after_s` before ``now_s``; else None."""
        if self.last_handled_s is None or self.warned:
            return None
        idle_s = now_s - self.last_handled_s
        if idle_s < self.warn_after_s:
            return None
        self.warned = True
        return (
            f"frames not processed for {idle_s:.1f} s (none since the frame captured at "
            f"{self.last_capture_s:.2f} s): {frame_gap_meaning(phase)}"
        )

    def frame(
        self, now_s: float, t_capture_s: float, *, measured: bool, phase: Phase
    ) -> str | None:
        """A frame captured at ``t_capture_s`` was handled at ``now_s``, ``measured`` or
        stored as a gap (too late). Returns the line that ends a warned stretch or a run of
        late frames, else None."""
        lines = []
        if self.warned and self.last_handled_s is not None:
            lines.append(
                f"frames arrive again after {now_s - self.last_handled_s:.1f} s without "
                f"({self.last_handled_s:.2f}-{now_s:.2f} s): {frame_gap_meaning(phase)}"
            )
        self.warned = False
        self.last_handled_s, self.last_capture_s = now_s, t_capture_s
        if not measured:
            self._late.append(t_capture_s)
        elif self._late:
            first, last, n = self._late[0], self._late[-1], len(self._late)
            self._late.clear()
            lines.append(
                f"{n} frame{'s' if n != 1 else ''} captured {first:.2f}-{last:.2f} s came too "
                f"late to be measured (processing_behind gaps): {frame_gap_meaning(phase)}"
            )
        return "; ".join(lines) or None
