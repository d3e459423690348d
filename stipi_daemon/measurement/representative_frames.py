"""Representative camera frames of a measurement: which raw frames to keep (pure).

A session stores S_k for every frame but no video, so a report could not show what was
counted. This module owns the choice of three raw frames while the daemon records
(:class:`RepresentativeFrames`): the middle of the pitting hold (``pitting``); the frame
with the smallest S_k from the hold on (``recovery_start``: nearest S_0, the deepest pit
seen); the frame with the largest S_k once the release is detected (``recovered``: S_max,
the recovered tissue); each a :class:`RepresentativeFrame`. The daemon offers every frame
on the camera side, where the image is, so images never travel further than this keeper.
It does no I/O: storing the chosen frames as PNGs, reading them back and drawing them
belong to :mod:`stipi_daemon.report.frames` and :mod:`stipi_daemon.report.render`; counting
pixels to :mod:`stipi_daemon.analysis.imaging`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stipi_daemon.measurement.state_machine import Phase

__all__ = ["RepresentativeFrame", "RepresentativeFrames"]


@dataclass(frozen=True)
class RepresentativeFrame:
    """One representative raw frame.

    Attributes
    ----------
    kind : str
        ``pitting``, ``recovery_start`` or ``recovered`` (see the module docstring;
        :data:`stipi_daemon.report.frames.KINDS` holds their captions).
    seq : int
        The camera's frame number (the ``frames`` table's ``seq``).
    t_s : float
        Capture time on the session clock [s].
    s_k_px : int
        S_k measured live for this frame, Eq. (2) [px].
    image : numpy.ndarray
        The raw ``uint8`` frame, gray ``(H, W)`` or BGR ``(H, W, 3)``.
    """

    kind: str
    seq: int
    t_s: float
    s_k_px: int
    image: npt.NDArray[np.uint8]


class RepresentativeFrames:
    """Keeps the representative frames while frames stream in (pure, no I/O).

    Each :meth:`offer` is a few comparisons; images are kept by reference (a camera frame
    is owned by its receiver and never reused), so nothing is copied per frame.

    Parameters
    ----------
    pitting_duration_s : float
        Planned pitting hold [s]; the pitting frame is the one nearest to its middle.
    """

    def __init__(self, pitting_duration_s: float) -> None:
        if not (math.isfinite(pitting_duration_s) and pitting_duration_s > 0.0):
            raise ValueError(f"pitting_duration_s must be finite and > 0, got {pitting_duration_s}")
        self._half_hold_s = 0.5 * pitting_duration_s
        self._pitting: tuple[float, RepresentativeFrame] | None = None
        self._low: RepresentativeFrame | None = None
        self._high: RepresentativeFrame | None = None

    def offer(
        self,
        seq: int,
        t_s: float,
        image: npt.NDArray[np.uint8],
        s_k_px: int,
        phase: Phase,
        t_pit_start_s: float | None,
        t_release_s: float | None,
    ) -> None:
        """Consider one frame.

        Parameters
        ----------
        seq, t_s, image, s_k_px
            The frame: number, capture time [s], pixels, S_k [px].
        phase : Phase
            The measurement's phase when the frame is measured (it may lag the frame's
            capture by the merge hold: the choices above do not depend on the lag).
        t_pit_start_s, t_release_s : float or None
            Start of the pitting hold and the release [s], once known.
        """
        if phase == Phase.PITTING and t_pit_start_s is not None:
            distance = abs(t_s - (t_pit_start_s + self._half_hold_s))
            if self._pitting is None or distance < self._pitting[0]:
                frame = RepresentativeFrame("pitting", seq, t_s, s_k_px, image)
                self._pitting = (distance, frame)
        # S_k follows the force on the probe (Eq. 5): high through the hold, lowest just
        # after the lift (S_0), then rising with the rebound. Its minimum from the hold on
        # is therefore the frame nearest S_0, whatever the phase lag of the offer.
        held = phase in (Phase.PITTING, Phase.RELEASE, Phase.RECOVERY)
        if held and (self._low is None or s_k_px < self._low.s_k_px):
            self._low = RepresentativeFrame("recovery_start", seq, t_s, s_k_px, image)
        recovering = phase == Phase.RECOVERY and t_release_s is not None and t_s >= t_release_s
        if recovering and (self._high is None or s_k_px > self._high.s_k_px):
            self._high = RepresentativeFrame("recovered", seq, t_s, s_k_px, image)

    def selected(self) -> tuple[RepresentativeFrame, ...]:
        """The frames chosen so far: ``pitting``, ``recovery_start``, ``recovered``."""
        out = [] if self._pitting is None else [self._pitting[1]]
        out += [f for f in (self._low, self._high) if f is not None]
        return tuple(out)
