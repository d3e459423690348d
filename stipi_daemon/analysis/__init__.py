"""Pure analysis core: the paper's Eqs. 1-10, calibration and the severity classification.

One module per concern (see ``docs/analysis.md``, ``docs/calibration.md``):

* :mod:`.imaging` - Eqs. (1)-(2): ROI, inverted threshold, occluded pixel count S_k.
* :mod:`.calibration` - Eqs. (4)-(5): fits of alpha1, alpha2, C1, C2 and calibration files.
* :mod:`.calibration_procedure` - Section IV.B: calibration points from recorded runs,
  fit report.
* :mod:`.pitting` - Eqs. (3), (5), (6): D_p, F_r, T_r of a recovery series.
* :mod:`.vpr` - Eqs. (7)-(10): elasticity, viscosity, the VPR recovery curve.
* :mod:`.recovery_fit` - a Kelvin-Voigt recovery fitted to the whole series.
* :mod:`.settling_rules` - when a recovery counts as settled (shared with the state
  machine's early end).
* :mod:`.severity` - Section IV.C: severity window, threshold, nearest grade.
* :mod:`.results` - all of the above for one measurement, both estimators.
* :mod:`.flags` - the quality flags attached to results.
* :mod:`.validity` - each reported quantity valid, flagged or invalid; the verdict.
* :mod:`.truth_comparison` - results against a simulator's ground truth.
* :mod:`.summary_diff` - differences between a stored and a recomputed summary.

Nothing in this package does I/O except the explicit load/save functions of
:mod:`~stipi_daemon.analysis.calibration` and :mod:`~stipi_daemon.analysis.severity`, and
it imports no other layer of the package but :mod:`stipi_daemon.errors`.
The names below are the public API.
"""

from stipi_daemon.analysis.calibration import (
    Calibration,
    DepthFit,
    ForceFit,
    calibration_from_fits,
    fit_depth_calibration,
    fit_force_calibration,
    load_calibration,
    save_calibration,
)
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import (
    ROI,
    CircleROI,
    FrameProcessor,
    RectROI,
    occluded_area_subpixel,
    occluded_pixel_count,
    otsu_threshold,
    threshold_binary_inverted,
    to_gray,
)
from stipi_daemon.analysis.pitting import (
    PittingParameters,
    compute_pitting_parameters,
    detect_recovery_start,
    pitting_depth_mm,
    rebound_force_n,
    recovery_time,
)
from stipi_daemon.analysis.recovery_fit import RecoveryFit, fit_recovery
from stipi_daemon.analysis.results import (
    AnalysisSettings,
    MeasurementResult,
    analyze_recovery,
    applied_force_n_from_samples,
)
from stipi_daemon.analysis.severity import (
    SeverityReference,
    SeverityResult,
    classify_fit,
    classify_vpr,
    find_severity_window,
    load_reference,
)
from stipi_daemon.analysis.vpr import (
    VPRModel,
    elasticity_kpa,
    viscosity_n_s_per_mm2,
    vpr_depth_mm,
)

__all__ = [
    "ROI",
    "AnalysisSettings",
    "Calibration",
    "CircleROI",
    "DepthFit",
    "Flag",
    "ForceFit",
    "FrameProcessor",
    "MeasurementResult",
    "PittingParameters",
    "RecoveryFit",
    "RectROI",
    "SeverityReference",
    "SeverityResult",
    "VPRModel",
    "analyze_recovery",
    "applied_force_n_from_samples",
    "calibration_from_fits",
    "classify_fit",
    "classify_vpr",
    "compute_pitting_parameters",
    "detect_recovery_start",
    "elasticity_kpa",
    "find_severity_window",
    "fit_depth_calibration",
    "fit_force_calibration",
    "fit_recovery",
    "load_calibration",
    "load_reference",
    "occluded_area_subpixel",
    "occluded_pixel_count",
    "otsu_threshold",
    "pitting_depth_mm",
    "rebound_force_n",
    "recovery_time",
    "save_calibration",
    "threshold_binary_inverted",
    "to_gray",
    "viscosity_n_s_per_mm2",
    "vpr_depth_mm",
]
