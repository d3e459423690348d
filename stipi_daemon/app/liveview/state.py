"""What the live view shows, as the daemon publishes it while it measures.

:class:`LiveState` is written by the daemon's event loop (the acquisition's handlers: the
phase, the operator's prompt, force and S_k, the live parameters, the link's and the
camera's health) and read by the view server's thread (:mod:`.server`). Each write is an
append to a list or an assignment of one reference: nothing is copied, converted or encoded
here, so publishing costs the measurement a few hundred nanoseconds per event whether or
not anyone watches. The newest camera frame is kept by reference only (latest wins); a
viewer's thread makes a JPEG of it when it wants one (:mod:`.preview`).

Readers take the lists' lengths first and slice up to them (a list append is atomic under
the GIL), so a reader never sees a half-written entry. Nothing here is stored in the
session or stamped with wall time. All times are on the session clock [s].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.measurement.pipeline import LiveParameters

__all__ = ["LiveState", "PreviewFrame", "Trace", "ViewInfo", "roi_dict"]


@dataclass(frozen=True, slots=True)
class PreviewFrame:
    """A camera frame to show, by reference (never copied here).

    Attributes
    ----------
    seq : int
        The camera's frame number.
    t_capture_s : float
        Capture time [s].
    s_k : int
        Its S_k, Eq. (2) [px].
    image : ndarray of uint8
        The frame as S_k was counted on it (gray or BGR).
    """

    seq: int
    t_capture_s: float
    s_k: int
    image: npt.NDArray[np.uint8]


@dataclass
class Trace:
    """A growing time series: parallel lists of times [s] and values."""

    t_s: list[float] = field(default_factory=list)
    value: list[float] = field(default_factory=list)

    def add(self, t_s: float, value: float) -> None:
        """Append one point (the value first: a reader slices by ``len(t_s)``)."""
        self.value.append(value)
        self.t_s.append(t_s)

    def since(self, start: int) -> tuple[int, list[list[float]]]:
        """The points from index ``start`` on as ``[[t_s, value], ...]``, and the new end."""
        end = len(self.t_s)
        return end, [[self.t_s[i], self.value[i]] for i in range(start, end)]


def roi_dict(roi: CircleROI | RectROI | None) -> dict[str, Any] | None:
    """The ROI as the page draws it (pixel coordinates of the camera frame)."""
    return None if roi is None else roi.model_dump()


@dataclass(frozen=True)
class ViewInfo:
    """What does not change during a run: identity, imaging and phase settings.

    Attributes
    ----------
    session_id : str
        The session's id.
    metadata : dict
        Subject, site, operator, note (shown as text, never as markup).
    threshold_p : int
        Threshold p of Eq. (1) [8-bit intensity].
    roi : dict or None
        The ROI (:func:`roi_dict`); None: the whole frame.
    pitting_duration_s, recovery_max_s : float
        The hold and the longest recovery [s] (the countdowns).
    force_band_n : tuple of float
        The force band the hold must stay in [N].
    """

    session_id: str
    metadata: dict[str, str | None]
    threshold_p: int
    roi: dict[str, Any] | None
    pitting_duration_s: float
    recovery_max_s: float
    force_band_n: tuple[float, float]

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "session_id": self.session_id,
            "metadata": dict(self.metadata),
            "threshold_p": self.threshold_p,
            "roi": self.roi,
            "pitting_duration_s": self.pitting_duration_s,
            "recovery_max_s": self.recovery_max_s,
            "force_band_n": list(self.force_band_n),
        }


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


class LiveState:
    """The live view's data (see the module docstring).

    Parameters
    ----------
    info : ViewInfo
        What does not change during the run.
    """

    def __init__(self, info: ViewInfo) -> None:
        self.view_info = info
        self.force = Trace()
        self.s_k = Trace()
        #: ``[t_s, old, new, reason]`` per phase change.
        self.transitions: list[list[Any]] = []
        self.phase = "idle"
        self.phase_since_s = 0.0
        self.now_s = 0.0
        self.prompt = ""
        self.t_release_s: float | None = None
        self.params: dict[str, Any] | None = None
        self.health: dict[str, Any] = {}
        self.notes: list[str] = []
        # the newest frame as (seq, t_capture_s, s_k, image), the image by reference: one
        # tuple a frame; the PreviewFrame is made only when a viewer asks (preview_frame)
        self._latest: tuple[int, float, int, npt.NDArray[np.uint8]] | None = None
        self.finished = False

    # ------------------------------------------------------------ writes (event loop)

    def frame(self, seq: int, t_capture_s: float, s_k: int, image: npt.NDArray[np.uint8]) -> None:
        """A measured frame: its S_k joins the trace and it becomes the newest frame."""
        self.s_k.add(t_capture_s, float(s_k))
        self._latest = (seq, t_capture_s, s_k, image)

    def force_n(self, t_s: float, force_n: float) -> None:
        """A force reading [N] at ``t_s`` [s]."""
        self.force.add(t_s, force_n)

    def phase_changed(self, t_s: float, old: str, new: str, reason: str) -> None:
        """A phase change at ``t_s`` [s]; the release (T_0) when the recovery starts."""
        self.transitions.append([t_s, old, new, reason])
        self.phase, self.phase_since_s = new, t_s

    def set_prompt(self, text: str) -> None:
        """The operator's current instruction."""
        self.prompt = text

    def note(self, text: str) -> None:
        """An advisory or a fault, in one line."""
        self.notes.append(text)

    def tick(self, now_s: float, t_release_s: float | None) -> None:
        """The measurement's current time [s] and T_0 [s] once known."""
        self.now_s = now_s
        self.t_release_s = t_release_s

    def live_parameters(self, params: LiveParameters, flags: dict[str, str]) -> None:
        """The live parameters, each with its status (``ok``, ``provisional``, ``flagged``)."""
        self.params = {
            "elapsed_s": params.elapsed_s,
            "settled": params.settled,
            "values": {
                "depth_mm": _finite(params.depth_mm),
                "rebound_force_n": _finite(params.rebound_force_n),
                "recovery_time_s": _finite(params.recovery_time_s),
                "elasticity_kpa": _finite(params.elasticity_kpa),
                "tau_s": _finite(params.tau_s),
                "viscosity_n_s_per_mm2": _finite(params.viscosity_n_s_per_mm2),
                "viscosity_from_time_constant_n_s_per_mm2": _finite(
                    params.viscosity_from_time_constant_n_s_per_mm2
                ),
            },
            "status": dict(flags),
        }

    def set_health(self, **health: Any) -> None:
        """The link's and the camera's health (frame rate, drops, gaps, clock offset...)."""
        self.health = {k: _finite(v) if isinstance(v, float) else v for k, v in health.items()}

    def finish(self) -> None:
        """The measurement has ended."""
        self.finished = True

    # ------------------------------------------------------------ reads (server thread)

    def info(self) -> dict[str, Any]:
        """What does not change during the run, and the mode (``live``)."""
        return {**self.view_info.to_dict(), "mode": "live"}

    @property
    def latest(self) -> PreviewFrame | None:
        """The newest frame (its image by reference), or None before the first."""
        latest = self._latest
        return None if latest is None else PreviewFrame(*latest)

    def preview_frame(self, seq: int | None) -> PreviewFrame | None:
        """The newest frame (live: ``seq`` is ignored, latest wins)."""
        return self.latest

    def snapshot(self, cursor: dict[str, int]) -> dict[str, Any]:
        """The state, with the traces' and the transitions' entries past ``cursor`` (which
        is advanced): what one viewer has not been sent yet."""
        f_end, force = self.force.since(cursor.get("force", 0))
        s_end, s_k = self.s_k.since(cursor.get("s_k", 0))
        n_tr = len(self.transitions)
        transitions = self.transitions[cursor.get("transitions", 0) : n_tr]
        n_notes = len(self.notes)
        notes = self.notes[cursor.get("notes", 0) : n_notes]
        cursor.update(force=f_end, s_k=s_end, transitions=n_tr, notes=n_notes)
        latest = self._latest
        return {
            "mode": "live",
            "now_s": self.now_s,
            "phase": self.phase,
            "phase_since_s": self.phase_since_s,
            "prompt": self.prompt,
            "t_release_s": self.t_release_s,
            "params": self.params,
            "health": self.health,
            "finished": self.finished,
            "frame_seq": None if latest is None else latest[0],
            "force": force,
            "s_k": s_k,
            "transitions": transitions,
            "notes": notes,
        }
