"""The tolerances a result is judged by: how far from the truth a valid result may be.

The numbers are those of docs/fault_matrix.json ("tolerances"): T_r 5 % or 2 frame
periods, whichever is larger; the fitted tau takes T_r's (on a Kelvin-Voigt curve Eq. (6)
gives T_r = tau ln((1 - r)/(1 - f)), so tau scales T_r). A quantity whose own stated
uncertainty exceeds its tolerance is invalid (docs/analysis.md, "Validity of each
result"). Pure; no imports from the rest of the analysis.
"""

from __future__ import annotations

from typing import Final

__all__ = ["TR_TOLERANCE_FRACTION", "TR_TOLERANCE_FRAMES", "recovery_time_tolerance_s"]

#: T_r's tolerance: this fraction of T_r ... [-]
TR_TOLERANCE_FRACTION: Final = 0.05
#: ... or this many frame periods, whichever is larger [frames].
TR_TOLERANCE_FRAMES: Final = 2.0


def recovery_time_tolerance_s(recovery_time_s: float, frame_period_s: float) -> float:
    """T_r's (and tau's) tolerance [s]: max(5 % of |T_r|, 2 frame periods)."""
    return max(TR_TOLERANCE_FRACTION * abs(recovery_time_s), TR_TOLERANCE_FRAMES * frame_period_s)
