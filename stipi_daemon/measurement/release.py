"""Where the recovery starts: T_0 and S_0 of Eq. (6) from what was observed.

This module owns the rule that places T_0 (the start of the recovery, Eq. (6)) and picks
the frame S_0 (Eqs. (3)-(4)) is read from, given the release the state machine detected
and the recorded series. It does not own the release detection itself (the state machine:
the force's downward crossing of ``release_force_n``, interpolated between samples) nor
the pitting parameters (:mod:`~stipi_daemon.analysis.pitting`). Pure: no I/O, no clock.

The rule (docs/analysis.md, "Where the recovery starts"):

* T_0 comes from what was observed, never from a timer: the force drop (the machine's
  interpolated crossing) or, for a release the operator confirmed, the button's time.
* The image jump is the largest step of S_k between consecutive valid frames within
  ``search_s`` of the release; it agrees with the release when the step's span (from the
  frame before it to the frame after it) meets the bound around the release, and it
  counts when it exceeds :data:`JUMP_NOISE_FACTOR` robust
  standard deviations of the frame-to-frame steps there (so it works whether S_k is high
  during pitting, the tip carrying the applied force, or about 0, the locked indenter
  leaving the waveguide clear, Fig. 4 (a)).
* The bound: the force drop is known to one force-sample interval (the two samples around
  the crossing), the first frame showing the release comes within one frame period, and
  one unmeasurable frame there is tolerated: ``bound = force interval + 2 frame periods +``
  :data:`CLOCK_SLACK_S`.
* S_0 is read from a frame, never interpolated across the release. When the image jump
  lies within the bound of the force drop, S_0 is the frame after the jump, followed
  onward while S_k keeps falling by more than the jump threshold (the bottom of a release
  transient). Otherwise S_0 is the first valid frame at or after the force drop, and when
  the image jump lies outside the bound, T_0 stays at the force drop and is flagged
  ``t0_image_force_disagree``. T_0 is then that frame's time (at most the bound after the
  drop), so that S_k at T_0 is a measured value.
* When the frame that shows the release was lost (the S_0 frame comes after lost frames
  and the release lies between it and the usable frame before), T_0 stays at the release:
  the analysis then reads S_0 there from the frames after it, extrapolated and flagged
  (:mod:`~stipi_daemon.analysis.pitting`, ``s0_extrapolated``).
* When no valid frame lies within the bound after the release (a camera gap, unmeasurable
  frames), S_0 was not observed: T_0
  stays at the release, the flag is ``s0_not_observed`` and D_p (with E, eta and the class
  that follow from it) is invalid.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CLOCK_SLACK_S",
    "JUMP_NOISE_FACTOR",
    "S0_NOT_OBSERVED",
    "T0_IMAGE_FORCE_DISAGREE",
    "ReleaseObservation",
    "observe_release",
]

#: Slack for the force/camera clock mapping and exposure timing in the bound [s].
CLOCK_SLACK_S: Final = 0.005
#: A step of S_k counts as the image jump when larger than this many robust standard
#: deviations of the frame-to-frame steps near the release [-].
JUMP_NOISE_FACTOR: Final = 6.0
#: Flag: no valid frame within the bound after the release; S_0 not observed.
S0_NOT_OBSERVED: Final = "s0_not_observed"
#: Flag: the image jump lies outside the bound of the force drop; T_0 kept at the force.
T0_IMAGE_FORCE_DISAGREE: Final = "t0_image_force_disagree"

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ReleaseObservation:
    """How T_0 and S_0 were observed (all times on the recording's clock [s]).

    Attributes
    ----------
    t0_s : float
        T_0 handed to the analysis: the S_0 frame's time when S_0 was observed, else the
        release.
    source : {"force", "operator"}
        What the release came from: the force drop, or the operator's confirmation.
    t_release_s : float
        The release the state machine reported (the force crossing, or the button).
    s0_frame_t_s : float or None
        Time of the frame S_0 is read from; None when S_0 was not observed.
    s0_observed : bool
        Whether a valid frame lies within ``bound_s`` after the release.
    s0_gap_s : float or None
        Time from the release to the first valid frame at or after it (None: none).
    bound_s : float
        The bound between the release and the S_0 frame (see the module docstring).
    t_image_jump_s : float or None
        Time of the frame after the image jump, when one was seen.
    image_agrees : bool or None
        Whether the image jump lies within the bound of the release; None when no jump
        was seen (nothing to compare).
    flags : tuple[str, ...]
        :data:`S0_NOT_OBSERVED`, :data:`T0_IMAGE_FORCE_DISAGREE`.
    reason : str or None
        One line for the flags; None without flags.
    """

    t0_s: float
    source: Literal["force", "operator"]
    t_release_s: float
    s0_frame_t_s: float | None
    s0_observed: bool
    s0_gap_s: float | None
    bound_s: float
    t_image_jump_s: float | None
    image_agrees: bool | None
    flags: tuple[str, ...]
    reason: str | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping of every field (``flags`` as a list)."""
        return asdict(self) | {"flags": list(self.flags)}

    def invalid_reasons(self) -> dict[str, str]:
        """Quantity -> why it is invalid: D_p when S_0 was not observed (E, eta and the
        class follow from D_p by the validity rules' propagation)."""
        if self.s0_observed:
            return {}
        return {"depth_mm": self.reason or "S_0 not observed"}

    def caveats(self) -> dict[str, str]:
        """Quantity -> caveat: D_p and T_r when the image and the force disagree on T_0."""
        if T0_IMAGE_FORCE_DISAGREE not in self.flags:
            return {}
        why = self.reason or "the image and the force disagree on T_0"
        return {"depth_mm": why, "recovery_time_s": why}


def _median_step(t: FloatArray) -> float:
    return float(np.median(np.diff(t))) if t.size >= 2 else 0.0


def _force_interval_s(force_t: FloatArray, t_release_s: float) -> float:
    """Interval [s] between the force samples around the release (the crossing's
    uncertainty), at least the median sample interval; 0 without samples."""
    if force_t.size < 2:
        return 0.0
    j = int(np.searchsorted(force_t, t_release_s, side="left"))
    j = min(max(j, 1), force_t.size - 1)
    return max(float(force_t[j] - force_t[j - 1]), _median_step(force_t))


def _image_jump(
    tv: FloatArray, sv: FloatArray, t_release_s: float, search_s: float
) -> tuple[int | None, float]:
    """Index (into ``tv``) of the frame after the largest significant step of S_k within
    ``search_s`` of the release, or None; and the step threshold [px]."""
    idx = np.flatnonzero((tv >= t_release_s - search_s) & (tv <= t_release_s + search_s))
    if idx.size < 3:
        return None, math.inf
    steps = np.diff(sv[idx])
    sigma = 1.4826 * float(np.median(np.abs(steps - np.median(steps))))
    threshold = JUMP_NOISE_FACTOR * sigma
    k = int(np.argmax(np.abs(steps)))
    if not abs(float(steps[k])) > threshold:
        return None, threshold
    return int(idx[k + 1]), threshold


def _transient_bottom(
    tv: FloatArray, sv: FloatArray, i: int, threshold: float, t_stop_s: float
) -> int:
    """Follow the frames after ``i`` while S_k keeps falling by more than ``threshold``
    [px], up to ``t_stop_s`` [s]: the bottom of the release transient."""
    while i + 1 < tv.size and tv[i + 1] <= t_stop_s and sv[i + 1] < sv[i] - threshold:
        i += 1
    return i


def _after_lost_frames(frame_t: FloatArray, tv: FloatArray, i: int) -> bool:
    """Whether frames were lost just before usable frame ``i`` (into ``tv``): the usable
    frame before it lies more than 1.5 frame periods earlier."""
    period = _median_step(frame_t)
    return period > 0.0 and bool(tv[i] - tv[i - 1] > 1.5 * period)


def observe_release(
    frame_t: FloatArray,
    frame_s: FloatArray,
    force_t: FloatArray,
    t_release_s: float,
    *,
    source: Literal["force", "operator"],
    search_s: float,
) -> ReleaseObservation:
    """T_0 and the S_0 frame from the reported release and the recorded series.

    Parameters
    ----------
    frame_t, frame_s : numpy.ndarray
        Frame times [s] (increasing) and S_k [px]; NaN S_k marks an unmeasurable frame.
    force_t : numpy.ndarray
        Force sample times [s] (increasing).
    t_release_s : float
        The release the state machine reported [s].
    source : {"force", "operator"}
        What the release came from.
    search_s : float
        How far around the release the image jump is looked for [s] (> 0).

    Returns
    -------
    ReleaseObservation
        See the module docstring for the rule.
    """
    valid = np.isfinite(frame_s)
    tv, sv = frame_t[valid], frame_s[valid]
    bound = _force_interval_s(force_t, t_release_s) + 2.0 * _median_step(frame_t) + CLOCK_SLACK_S
    if source == "operator":
        # a button press is no sharper than the search span
        bound = max(bound, search_s)
    jump, threshold = _image_jump(tv, sv, t_release_s, max(search_s, bound))
    t_jump = None if jump is None else float(tv[jump])
    agrees: bool | None = None
    if jump is not None and t_jump is not None:
        # the release may lie anywhere between the two frames of the step (a gap)
        agrees = t_jump >= t_release_s - bound and float(tv[jump - 1]) <= t_release_s + bound
    after = int(np.searchsorted(tv, t_release_s, side="left"))
    gap = float(tv[after] - t_release_s) if after < tv.size else None
    flags: list[str] = []
    reasons: list[str] = []
    s0_index: int | None = None
    if jump is not None and agrees:
        if t_jump is not None and t_jump - t_release_s <= bound:
            stop_s = t_release_s + max(search_s, bound)
            s0_index = _transient_bottom(tv, sv, jump, threshold, stop_s)
    elif gap is not None and gap <= bound:
        s0_index = after
    if t_jump is not None and not agrees:
        flags.append(T0_IMAGE_FORCE_DISAGREE)
        reasons.append(
            f"the image jump at {t_jump:.3f} s lies {t_jump - t_release_s:+.3f} s from the "
            f"release at {t_release_s:.3f} s (bound {bound * 1e3:.0f} ms): T_0 kept at the "
            f"{source} release"
        )
    if s0_index is None and S0_NOT_OBSERVED not in flags:
        flags.append(S0_NOT_OBSERVED)
        before = float(tv[after - 1]) if after > 0 else math.nan
        end = f"{tv[after]:.3f}" if after < tv.size else "the end of the recording"
        reasons.append(
            f"no valid frame between {before:.3f} and {end} s around the release at "
            f"{t_release_s:.3f} s (bound {bound * 1e3:.0f} ms): S_0 not observed"
        )
    s0_t = None if s0_index is None else float(tv[s0_index])
    t0 = t_release_s if s0_t is None else s0_t
    if s0_index is not None and s0_index > 0 and _after_lost_frames(frame_t, tv, s0_index):
        if tv[s0_index - 1] < t_release_s < tv[s0_index]:
            # the frame showing the release was lost: T_0 stays at the release, where the
            # analysis extrapolates S_0 from the frames after it (and flags it)
            t0 = t_release_s
    return ReleaseObservation(
        t0_s=t0,
        source=source,
        t_release_s=t_release_s,
        s0_frame_t_s=s0_t,
        s0_observed=s0_t is not None,
        s0_gap_s=gap,
        bound_s=bound,
        t_image_jump_s=t_jump,
        image_agrees=agrees,
        flags=tuple(flags),
        reason="; ".join(reasons) or None,
    )
