"""Quality flags attached to analysis results.

A flag says that a result is valid only with a caveat (a lower bound, an extrapolation, a
saturated input). Functions return flags instead of raising when a meaningful, labelled
result still exists; they raise :class:`~stipi_daemon.errors.AnalysisError` when none does.
Flags are strings so that they serialise unchanged into session files and reports.
:data:`FLAG_DESCRIPTIONS` says what each one means, in the words a report shows.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum
from types import MappingProxyType
from typing import Final

__all__ = ["FLAG_DESCRIPTIONS", "Flag"]


class Flag(StrEnum):
    """Every quality flag the analysis core can attach to a result.

    Each one's meaning is in :data:`FLAG_DESCRIPTIONS`.
    """

    # imaging (Eqs. 1-2)
    SATURATED_FRAME = "saturated_frame"
    EMPTY_ROI = "empty_roi"
    ROI_CLIPPED = "roi_clipped"
    IMAGE_QUALITY = "image_quality"
    FORCE_AT_FULL_SCALE = "force_at_full_scale"
    # pitting parameters (Eqs. 3-6)
    NOT_SETTLED = "not_settled"
    SETTLED_WITHIN_ONE_FRAME = "settled_within_one_frame"
    NO_RECOVERY = "no_recovery"
    REBOUND_BELOW_OFFSET = "rebound_below_offset"
    DEPTH_CLIPPED = "depth_clipped"
    CALIBRATION_EXTRAPOLATED = "calibration_extrapolated"
    EARLY_NOISY_CROSSING = "early_noisy_crossing"
    RISE_WITHIN_SETTLING_BAND = "rise_within_settling_band"
    S0_BELOW_CONTACT_FLOOR = "s0_below_contact_floor"
    # what the camera observed (observation.py)
    RELEASE_NOT_OBSERVED = "release_not_observed"
    FRAME_GAP_AT_SETTLING = "frame_gap_at_settling"
    FRAME_GAP_AT_MAXIMUM = "frame_gap_at_maximum"
    OUTLIER_FRAMES = "outlier_frames"
    S0_EXTRAPOLATED = "s0_extrapolated"
    RELEASE_FRAME_OUTLIER = "release_frame_outlier"
    RELEASE_STEP = "release_step"
    # VPR model and recovery fit (Eqs. 7-10)
    FIT_NOT_CONVERGED = "fit_not_converged"
    TIME_CONSTANT_OUTSIDE_WINDOW = "time_constant_outside_window"
    CONSTANT_SERIES = "constant_series"
    NON_FINITE_INPUT = "non_finite_input"
    FRAME_GAPS_IN_FIT = "frame_gaps_in_fit"
    POOR_FIT = "poor_fit"
    # recovery models side by side (recovery_models/)
    KELVIN_VOIGT_REJECTED = "kelvin_voigt_rejected"
    MODEL_SELECTION_UNAVAILABLE = "model_selection_unavailable"
    TOO_FEW_POINTS = "too_few_points"
    PARAMETER_AT_BOUND = "parameter_at_bound"
    NO_CONFIDENCE_INTERVALS = "no_confidence_intervals"
    # the primary quantities against the recovery models (model_checks.py)
    MODEL_NOT_SETTLED = "model_not_settled"
    MODELS_DISAGREE = "models_disagree"
    SETTLED_LEVEL_OFF_MODEL = "settled_level_off_model"
    RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL = "recovery_time_outside_model_interval"
    # uncertainty beyond tolerance (model_checks.py, results.py)
    RECOVERY_TIME_UNCERTAIN = "recovery_time_uncertain"
    TIME_CONSTANT_UNCERTAIN = "time_constant_uncertain"
    SEVERITY_AMBIGUOUS = "severity_ambiguous"
    # severity (Section IV.C)
    OUTSIDE_REFERENCE_RANGE = "outside_reference_range"
    ESTIMATORS_DISAGREE = "estimators_disagree"


#: Flag -> what it means (one or two sentences; the report's flag legend shows them).
FLAG_DESCRIPTIONS: Final[Mapping[Flag, str]] = MappingProxyType(
    {
        # imaging (Eqs. 1-2)
        Flag.SATURATED_FRAME: (
            "Part of the ROI is at the sensor's maximum value; S_k may be biased low."
        ),
        Flag.EMPTY_ROI: "The ROI does not overlap the frame; S_k is 0 by definition.",
        Flag.ROI_CLIPPED: (
            "Part of the ROI lies outside the frame; only its pixels inside the frame are counted."
        ),
        Flag.IMAGE_QUALITY: (
            "Flicker, pixel noise or vignetting measured on the steady frames (or frames at "
            "the sensor's rail) can move this quantity by the amount stated: beyond its "
            "tolerance it is invalid."
        ),
        Flag.FORCE_AT_FULL_SCALE: (
            "Load-cell samples of the pitting hold sit at the ADC's full scale: the force "
            "there is unknown (at least full scale), so F_a, and E with it, is invalid."
        ),
        # pitting parameters (Eqs. 3-6)
        Flag.NOT_SETTLED: (
            "S_k never reached 98 % of S_max inside the window: T_r is a lower bound."
        ),
        Flag.SETTLED_WITHIN_ONE_FRAME: (
            "Recovery finished between two frames: T_r is at most one frame period."
        ),
        Flag.NO_RECOVERY: "S_k did not rise after T_0: there is no recovery to time.",
        Flag.REBOUND_BELOW_OFFSET: (
            "S_max <= C1 (Eq. 5): the rebound force is below what the probe resolves; F_r set to 0."
        ),
        Flag.DEPTH_CLIPPED: (
            "d_s from Eq. 4 fell outside [0, l] and was clipped; D_p is at a bound."
        ),
        Flag.CALIBRATION_EXTRAPOLATED: (
            "S_0 or S_max lies outside the range the calibration was measured over (or S_0 is "
            "past the vertex of Eq. 4): d_s or F_r is an extrapolation."
        ),
        Flag.EARLY_NOISY_CROSSING: (
            "A short excursion crossed 98 % of S_max before the series settled; it was ignored."
        ),
        Flag.RISE_WITHIN_SETTLING_BAND: (
            "S_k rose by less than the settling band (2 % of S_max) after T_0: the 98 % rule "
            "cannot time this recovery, so T_r is not a measurement."
        ),
        Flag.S0_BELOW_CONTACT_FLOOR: (
            "S_0 is below C1 of Eq. 5, the least pixel count a contact image shows: the "
            "release frame is no image of the pit, and D_p (Eq. 4 at no contact: the whole "
            "indenter) is not a measurement."
        ),
        # what the camera observed
        Flag.RELEASE_NOT_OBSERVED: (
            "No usable frame close to T_0 (a gap over the release): S_0, hence D_p and E, "
            "is unknown."
        ),
        Flag.FRAME_GAP_AT_SETTLING: (
            "The 98 % crossing lies in a gap between frames: T_r is uncertain by the gap's length."
        ),
        Flag.FRAME_GAP_AT_MAXIMUM: (
            "A gap between frames is next to the frame that sets S_max: the maximum, hence "
            "F_r, may lie in the gap."
        ),
        Flag.OUTLIER_FRAMES: (
            "Isolated outlier frames (a dark or bright frame) were left out of S_max, T_s and "
            "the fit."
        ),
        Flag.S0_EXTRAPOLATED: (
            "The frame just after the release was lost, NaN or an outlier: S_0 is extrapolated "
            "back to T_0 from the next usable frames."
        ),
        Flag.RELEASE_FRAME_OUTLIER: (
            "The last frame before T_0 is an outlier (a dark or bright frame): the release may "
            "have come a frame earlier, and S_0 may be read a frame late."
        ),
        Flag.RELEASE_STEP: (
            "S_k jumped between the release frame and the next, a step the frames after "
            "it do not continue: an instantaneous recovery (an elastic spring-back, which a "
            "Kelvin-Voigt solid has not) or an outlier frame at the release. S_0 is read "
            "from the release frame alone."
        ),
        # VPR model and recovery fit (Eqs. 7-10)
        Flag.FIT_NOT_CONVERGED: (
            "The Kelvin-Voigt recovery fit did not converge; its parameters are not reported."
        ),
        Flag.TIME_CONSTANT_OUTSIDE_WINDOW: (
            "The fitted time constant is longer than the fit window or shorter than one frame."
        ),
        Flag.CONSTANT_SERIES: "The series has no variation to fit.",
        Flag.NON_FINITE_INPUT: "NaN or inf samples were present and were dropped.",
        Flag.FRAME_GAPS_IN_FIT: (
            "Frame gaps cover more than 10 % of the fitted span or of its first 3 tau: the fit "
            "rests on fewer observations than the window holds."
        ),
        Flag.POOR_FIT: (
            "The Kelvin-Voigt model explains the recovery poorly (R^2 below 0.99 and residuals "
            "beyond 3x the frame noise): the fitted tau is not reported as a result."
        ),
        # recovery models side by side
        Flag.KELVIN_VOIGT_REJECTED: (
            "A recovery model with two time constants or a power-law tail explains the recovery "
            "far better than one exponential (QAICc lower by more than 10): the tissue is not "
            "Kelvin-Voigt, so the fitted tau and the VPR curve describe a shape it does not "
            "follow; read tau, T_r and eta of the best model."
        ),
        Flag.MODEL_SELECTION_UNAVAILABLE: (
            "No recovery model could be weighed (too few samples for AICc, or a constant "
            "series): Kelvin-Voigt is neither confirmed nor rejected."
        ),
        Flag.TOO_FEW_POINTS: (
            "The window holds fewer samples than this recovery model has parameters plus one: "
            "it was not fitted."
        ),
        Flag.PARAMETER_AT_BOUND: (
            "A shape parameter of this recovery model ended at its search bound (a time "
            "constant of 1 ms, i.e. a jump between frames, or 10^4 s; a power-law exponent "
            "of 0.01 or 1000, i.e. an exponential)."
        ),
        Flag.NO_CONFIDENCE_INTERVALS: (
            "This recovery model's 95 % intervals were not computed: fewer than 12 samples, or "
            "more than 10 % of the bootstrap refits failed."
        ),
        # the primary quantities against the recovery models
        Flag.MODEL_NOT_SETTLED: (
            "The best recovery model reaches 98 % of its settled level after the recording "
            "ended: the recovery had not settled, so T_r and S_max (hence F_r) are lower bounds."
        ),
        Flag.MODELS_DISAGREE: (
            "The recovery models with weight (at least 1/8 of the best's) put T_r further "
            "apart than its tolerance (5 % or 2 frames): the data do not decide T_r."
        ),
        Flag.SETTLED_LEVEL_OFF_MODEL: (
            "The measured S_max is off the level the best recovery model reads, by enough to "
            "move the 98 % crossing (T_r) by more than its tolerance."
        ),
        Flag.RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL: (
            "The reported T_r (Eq. 6) lies outside the best recovery model's 95 % interval "
            "by more than T_r's tolerance (5 % or 2 frames)."
        ),
        Flag.RECOVERY_TIME_UNCERTAIN: (
            "T_r's own uncertainty (a frame gap at the 98 % crossing) exceeds its tolerance "
            "(5 % or 2 frames): T_r is not a measurement."
        ),
        Flag.TIME_CONSTANT_UNCERTAIN: (
            "The fitted tau's standard error exceeds its tolerance (5 % or 2 frames): tau is "
            "not a measurement."
        ),
        Flag.SEVERITY_AMBIGUOUS: (
            "The uncertainty of T_r spans more than one severity class or grade: the class "
            "is not named (the reason lists those that remain)."
        ),
        # severity (Section IV.C)
        Flag.OUTSIDE_REFERENCE_RANGE: (
            "The measurement lies beyond the reference grades; the nearest grade is an extreme."
        ),
        Flag.ESTIMATORS_DISAGREE: (
            "The paper's estimator and the fitted recovery give different severity classes."
        ),
    }
)
