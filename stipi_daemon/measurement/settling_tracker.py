"""Settling of a recovery while it is recorded: may the state machine end it early?

This module owns :class:`SettlingTracker`, the state machine's view of the recovery's S_k
(Eqs. (1)-(2)) frame by frame, and its stop test (:meth:`SettlingTracker.settled`). It
does not own the rules it applies - the still-rising test and the Kelvin-Voigt truncation
bound are the analysis' (:mod:`~stipi_daemon.analysis.settling_rules`), so that an early stop
and the analysis of Eq. (6) agree - nor the phases and timeouts (the state machine). Pure
and immutable: every frame returns a new tracker; a frame costs O(1) (a fixed ladder of
about 20 levels, no history of frames).

What it tracks (times on the host's monotonic clock [s], S_k in pixels):

* The *rise*: it starts at the first recovery frame and starts again at any frame below
  both every S_k since and the settling band (the end of the release transient, where the
  analysis reads S_0; a drop). S_0 of the truncation bound is S_k at the rise start, the
  *peak* the largest S_k since: the S_max the analysis sees.
* The *plateau*: the trailing run of frames at or above ``settle_fraction`` x peak, the
  98 % level of Eq. (6). Because the level rises with the peak, the run's start is read
  on a geometric grid of S_k levels 1/:data:`LEVELS_PER_BAND` of the band apart (0.1 %
  for f = 0.98): for each grid level between the level and the peak the tracker keeps
  the start of the current run of frames at or above it, and the plateau starts where the
  run of the lowest grid level at or above the level starts - at most one grid step late,
  never early. Every frame from the plateau start p on lies inside the band, so the
  analysis' T_s is at or before p: p - T_0 bounds its T_r from above.
* The least-squares sums of S_k since the rise start (:class:`LineSums`), with a
  snapshot at each run start, so the slope over the plateau is a difference of two sums.
* The frames of the rise themselves (:attr:`SettlingTracker.record`, a linked list: one
  cell per frame, O(1)), read only when the state machine asks the recovery models
  whether the rise may end (:meth:`SettlingTracker.frames`, O(frames), at a few decision
  points; :func:`~stipi_daemon.analysis.model_checks.early_stop_check`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from stipi_daemon.analysis.settling_rules import LineSums, still_rising, truncation_hold_factor
from stipi_daemon.measurement.evolve import evolve

__all__ = ["LEVELS_PER_BAND", "FrameCell", "SettlingTracker"]

#: Grid levels per settling band (1 - f) of S_k: the plateau start is found to within
#: (1 - f) / LEVELS_PER_BAND of S_k (0.1 % for f = 0.98) [1].
LEVELS_PER_BAND: Final = 20


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class FrameCell:
    """One frame of the rise and the cell of the frame before it (a linked list; compared
    by identity and not shown, so that neither walks the whole list recursively)."""

    t_s: float
    s_px: float
    before: FrameCell | None


@dataclass(frozen=True, slots=True)
class _Run:
    """A run of frames at or above one grid level."""

    start_s: float
    """Time of the run's first frame [s]."""
    before: LineSums
    """The rise's sums before that frame was added."""


@dataclass(frozen=True)
class SettlingTracker:
    """Rise, peak and plateau of a recovery's S_k so far (see the module docstring).

    Build it with :meth:`first`, extend it with :meth:`add` (frames in time order), ask
    :meth:`settled`.

    Attributes
    ----------
    settle_fraction : float
        f of Eq. (6), in (0, 1) [1].
    rise_start_s : float
        Time of the frame where the current rise started [s].
    rise_start_px : float
        S_k there: the S_0 of the truncation bound [px].
    floor_px, peak_px : float
        Smallest and largest S_k since the rise start [px].
    last_s : float
        Time of the latest frame [s].
    sums : LineSums
        Least-squares sums of every frame since the rise start, times from
        ``rise_start_s`` [s] and S_k from ``rise_start_px`` [px].
    level_base : int
        Grid index of ``runs[0]``; grid level j is (1 + (1 - f) / LEVELS_PER_BAND)^j px.
    runs : tuple of _Run or None
        For grid levels ``level_base``, ``level_base + 1``, ...: the current run of
        frames at or above the level, None when the latest frame is below it.
        ``runs[0]`` is the lowest grid level at or above f x peak. Empty while
        f x peak is 0 (every frame is then inside the band).
    record : FrameCell
        The latest frame of the rise, linked to the earlier ones (:meth:`frames`).
    """

    settle_fraction: float
    rise_start_s: float
    rise_start_px: float
    floor_px: float
    peak_px: float
    last_s: float
    sums: LineSums
    level_base: int
    runs: tuple[_Run | None, ...]
    record: FrameCell = field(compare=False, repr=False)

    # ------------------------------------------------------------------ building

    @classmethod
    def first(cls, t_s: float, s_px: float, settle_fraction: float) -> SettlingTracker:
        """A tracker whose rise starts with the frame ``(t_s, s_px)``."""
        sums = LineSums().add(0.0, 0.0)
        base, runs = _ladder(s_px, settle_fraction, None, 0, t_s, s_px, LineSums())
        return cls(
            settle_fraction=settle_fraction,
            rise_start_s=t_s,
            rise_start_px=s_px,
            floor_px=s_px,
            peak_px=s_px,
            last_s=t_s,
            sums=sums,
            level_base=base,
            runs=runs,
            record=FrameCell(t_s, s_px, None),
        )

    def add(self, t_s: float, s_px: float) -> SettlingTracker:
        """The tracker with the next frame ``(t_s, s_px)`` added (``t_s`` >= the last)."""
        f = self.settle_fraction
        if s_px < self.floor_px and s_px < f * self.peak_px:
            # below the whole rise and the band: the rise starts again here
            return SettlingTracker.first(t_s, s_px, f)
        peak = max(self.peak_px, s_px)
        before = self.sums
        sums = before.add(t_s - self.rise_start_s, s_px - self.rise_start_px)
        base, runs = _ladder(peak, f, self.runs, self.level_base, t_s, s_px, before)
        return evolve(
            self,
            floor_px=min(self.floor_px, s_px),
            peak_px=peak,
            last_s=t_s,
            sums=sums,
            level_base=base,
            runs=runs,
            record=FrameCell(t_s, s_px, self.record),
        )

    # ------------------------------------------------------------------ reading

    def frames(self) -> tuple[list[float], list[float]]:
        """Times [s] and S_k [px] of every frame of the rise, in time order (O(frames))."""
        times: list[float] = []
        values: list[float] = []
        cell: FrameCell | None = self.record
        while cell is not None:
            times.append(cell.t_s)
            values.append(cell.s_px)
            cell = cell.before
        times.reverse()
        values.reverse()
        return times, values

    @property
    def has_rise(self) -> bool:
        """Whether S_k rose beyond the settling band since the rise start (S_0 below f x
        peak): a rise with a time scale, which the recovery models can time."""
        return self.peak_px > 0.0 and self.rise_start_px < self.settle_fraction * self.peak_px

    @property
    def plateau_start_s(self) -> float | None:
        """Start p of the plateau (every S_k since at or above f x peak) [s]; None if the
        latest frame is below the band."""
        if not self.runs:
            return self.rise_start_s  # the level f x peak is 0: every frame is in the band
        run = self.runs[0]
        return None if run is None else run.start_s

    @property
    def plateau_sums(self) -> LineSums | None:
        """Least-squares sums of the plateau's frames; None without a plateau."""
        if not self.runs:
            return self.sums
        run = self.runs[0]
        return None if run is None else self.sums.since(run.before)

    def settled(
        self,
        t0_s: float,
        *,
        hold_s: float,
        bias_fraction: float,
        window_end_s: float,
    ) -> bool:
        """Whether the recovery may end at the latest frame.

        True when all of these hold (state machine module docstring, tests 1-4):

        1. a plateau exists (the latest frame is inside the band);
        2. it has lasted ``hold_s`` [s];
        3. with r = S_0 / peak < f: the recovery has lasted
           ``truncation_hold_factor(r, f, bias_fraction)`` x (p - T_0) since ``t0_s``, so
           that the relative bias of T_r is at most ``bias_fraction`` for a Kelvin-Voigt
           rise;
        4. the plateau's least-squares slope, continued for another p - T_0 (an upper
           bound of the analysis' T_r), stays inside the band (1 - f) x peak: the
           analysis' still-rising test. With r >= f (the whole rise inside the band, no
           rise time to scale with) the slope is continued to ``window_end_s`` instead.

        Parameters
        ----------
        t0_s : float
            T_0 of Eq. (6), the release [s].
        hold_s : float
            Shortest plateau [s].
        bias_fraction : float
            Largest relative bias of T_r accepted, in (0, 1) [1].
        window_end_s : float
            End of the recovery window, T_0 + the longest recovery [s].
        """
        p, line = self.plateau_start_s, self.plateau_sums
        if p is None or line is None:
            return False  # 1. below the band
        t_s = self.last_s
        if t_s - p < hold_s:
            return False  # 2. plateau too short
        slope = line.slope_px_per_s
        if slope is None:
            return False  # fewer than two frame times (hold_s = 0 only)
        f = self.settle_fraction
        band_px = (1.0 - f) * self.peak_px
        r = self.rise_start_px / self.peak_px if self.peak_px > 0.0 else 1.0
        factor = truncation_hold_factor(r, f, bias_fraction)
        if factor is None:
            # the whole rise lies inside the band: continue the slope to the window's end
            return not still_rising(slope, window_end_s - t_s, band_px)
        rise_s = p - t0_s  # >= the analysis' T_r
        if t_s - t0_s < factor * rise_s:
            return False  # 3. too short for the truncation bound
        return not still_rising(slope, rise_s, band_px)  # 4.


def _grid_step(settle_fraction: float) -> float:
    """ln of the ratio between neighbouring grid levels [1]."""
    return math.log1p((1.0 - settle_fraction) / LEVELS_PER_BAND)


def _grid_level_px(j: int, step: float) -> float:
    """S_k of grid level ``j`` [px] (inf beyond the float range)."""
    x = j * step
    return math.exp(x) if x < 709.0 else math.inf


def _lowest_level(level_px: float, step: float) -> int:
    """Index of the lowest grid level at or above ``level_px`` (> 0)."""
    j = math.ceil(math.log(level_px) / step)
    while _grid_level_px(j, step) < level_px:  # rounding of log/exp: never below the level
        j += 1
    while _grid_level_px(j - 1, step) >= level_px:
        j -= 1
    return j


def _ladder(
    peak_px: float,
    settle_fraction: float,
    old: tuple[_Run | None, ...] | None,
    old_base: int,
    t_s: float,
    s_px: float,
    before: LineSums,
) -> tuple[int, tuple[_Run | None, ...]]:
    """The runs of the grid levels from f x peak to above the peak after the frame.

    Levels new to the ladder lie above every earlier frame of the rise (the ladder
    always reaches above the peak), so their runs start with this frame if it reaches
    them.
    """
    level_px = settle_fraction * peak_px
    if not level_px > 0.0:
        return 0, ()  # S_k has been 0 (or below the float range) since the rise started
    step = _grid_step(settle_fraction)
    size = math.ceil(-math.log(settle_fraction) / step) + 2
    base = _lowest_level(level_px, step)
    runs: list[_Run | None] = []
    for j in range(base, base + size):
        k = j - old_base
        run = old[k] if old is not None and 0 <= k < len(old) else None
        if s_px >= _grid_level_px(j, step):
            runs.append(run if run is not None else _Run(t_s, before))
        else:
            runs.append(None)
    return base, tuple(runs)
