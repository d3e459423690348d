"""Validity of each reported quantity, and the session's verdict (``summary.json``).

A number is shown as a result only when nothing known makes it untrustworthy. This module
turns one measurement's result (:class:`~stipi_daemon.analysis.results.MeasurementResult`,
whose flags record what was observed: clipped depths, unsettled recoveries, frame gaps,
outlier frames, poor fits...) and how the session ended into

* ``validity``: for each quantity, ``valid``, ``flagged`` (a caveat; the flags that concern
  it are listed) or ``invalid`` (its value cannot be trusted; the reason says why, and the
  value may be recorded but is never shown as a result);
* ``verdict``: ``complete`` only when the session ended DONE and every primary quantity is
  valid, ``flagged`` when none is invalid but some are flagged, ``invalid`` when any primary
  quantity is invalid, ``incomplete`` when the session did not end DONE.

The primary quantities are D_p, F_r, T_r, E, eta (the paper's estimator, Eq. 8) and the
severity class; the secondary ones the fitted tau and F_a. Which flag concerns which
quantity, and whether it invalidates it, is the table :data:`FLAG_RULES`; invalidity then
propagates along the equations (E from D_p, Eq. 7; eta from E and T_r, Eq. 8; the paper's
severity class from E and eta, Section IV.C). The rules are documented in
``docs/analysis.md`` ("Validity of each result"). Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Final, Literal

from stipi_daemon.analysis.flags import Flag

if TYPE_CHECKING:
    from stipi_daemon.analysis.results import MeasurementResult

__all__ = [
    "DEPENDS_ON",
    "FLAG_RULES",
    "FROM_SK",
    "PRIMARY_QUANTITIES",
    "QUANTITY_SYMBOLS",
    "SECONDARY_QUANTITIES",
    "FlagRule",
    "QuantityValidity",
    "Verdict",
    "assess_validity",
    "quantity_validity",
    "verdict",
]

Status = Literal["valid", "flagged", "invalid"]

#: The primary quantities, in the order a verdict names them.
PRIMARY_QUANTITIES: Final = (
    "depth_mm",
    "rebound_force_n",
    "recovery_time_s",
    "elasticity_kpa",
    "viscosity_n_s_per_mm2",
    "severity",
)
#: The secondary quantities (shown, never decisive for the verdict): the fitted recovery's
#: tau, F_a, and what the fitted recovery gives in place of T_r: eta = E*tau (Eq. 8 with tau)
#: and its severity class (Section IV.C on the fitted curve).
SECONDARY_QUANTITIES: Final = (
    "tau_s",
    "applied_force_n",
    "viscosity_fit_n_s_per_mm2",
    "severity_fit",
)
#: Symbol of each quantity in operator lines.
QUANTITY_SYMBOLS: Final[Mapping[str, str]] = MappingProxyType(
    {
        "depth_mm": "D_p",
        "rebound_force_n": "F_r",
        "recovery_time_s": "T_r",
        "elasticity_kpa": "E",
        "viscosity_n_s_per_mm2": "eta",
        "severity": "severity",
        "tau_s": "tau",
        "applied_force_n": "F_a",
        "viscosity_fit_n_s_per_mm2": "eta_tau",
        "severity_fit": "severity (fit)",
    }
)
#: Quantities computed from S_k (every image-side caveat concerns them all).
FROM_SK: Final = (
    "depth_mm",
    "rebound_force_n",
    "recovery_time_s",
    "elasticity_kpa",
    "viscosity_n_s_per_mm2",
    "severity",
    "tau_s",
    "viscosity_fit_n_s_per_mm2",
    "severity_fit",
)
#: What each quantity is computed from: an invalid input makes it invalid (Eqs. 7-8, IV.C).
DEPENDS_ON: Final[Mapping[str, tuple[str, ...]]] = MappingProxyType(
    {
        "elasticity_kpa": ("depth_mm", "applied_force_n"),
        "viscosity_n_s_per_mm2": ("elasticity_kpa", "recovery_time_s"),
        "severity": ("viscosity_n_s_per_mm2",),
        "viscosity_fit_n_s_per_mm2": ("elasticity_kpa", "tau_s"),
        "severity_fit": ("tau_s",),
    }
)
#: The quantities of :data:`DEPENDS_ON`, each after its sources.
_DERIVED: Final = tuple(DEPENDS_ON)


@dataclass(frozen=True)
class FlagRule:
    """What one flag does to the quantities it concerns.

    Attributes
    ----------
    quantities : tuple[str, ...]
        The quantities the flag concerns.
    invalidates : tuple[str, ...]
        Those of them it makes invalid (the others are flagged).
    reason : str
        One line for an invalid quantity's reason or a flagged one's caveat.
    """

    quantities: tuple[str, ...]
    invalidates: tuple[str, ...]
    reason: str


#: Flag -> the quantities it concerns and those it invalidates.
FLAG_RULES: Final[Mapping[Flag, FlagRule]] = MappingProxyType(
    {
        Flag.SATURATED_FRAME: FlagRule(FROM_SK, (), "saturated frames may bias S_k low"),
        Flag.EMPTY_ROI: FlagRule(FROM_SK, FROM_SK, "the ROI does not overlap the frame"),
        Flag.ROI_CLIPPED: FlagRule(FROM_SK, (), "part of the ROI lies outside the frame"),
        # Carried per quantity with its amount by the result's image-quality rules.
        Flag.IMAGE_QUALITY: FlagRule((), (), "the picture can move S_k"),
        Flag.FORCE_AT_FULL_SCALE: FlagRule(
            ("applied_force_n",), ("applied_force_n",), "load-cell samples at full scale"
        ),
        # The settled-level rule: S_max of a recovery that did not settle is not its
        # settled level, so F_r (Eq. 5 at S_max) is a lower bound too (an aborted recovery).
        Flag.NOT_SETTLED: FlagRule(
            ("recovery_time_s", "rebound_force_n"),
            ("recovery_time_s", "rebound_force_n"),
            "recovery did not settle within the window (T_r, and S_max hence F_r, are only "
            "lower bounds)",
        ),
        Flag.SETTLED_WITHIN_ONE_FRAME: FlagRule(
            ("depth_mm", "recovery_time_s"),
            (),
            "the recovery finished within one frame: T_r is an upper bound and S_0 rests on "
            "a single frame",
        ),
        Flag.NO_RECOVERY: FlagRule(
            ("recovery_time_s",), ("recovery_time_s",), "S_k did not rise after T_0"
        ),
        Flag.REBOUND_BELOW_OFFSET: FlagRule(
            ("rebound_force_n",), (), "F_r is below what the probe resolves (set to 0)"
        ),
        Flag.DEPTH_CLIPPED: FlagRule(
            ("depth_mm", "elasticity_kpa"), (), "the depth change was clipped to [0, l]"
        ),
        Flag.S0_BELOW_CONTACT_FLOOR: FlagRule(
            ("depth_mm", "elasticity_kpa"),
            ("depth_mm",),
            "S_0 is below the least count a contact image shows (C1): no image of the pit",
        ),
        Flag.CALIBRATION_EXTRAPOLATED: FlagRule(
            ("depth_mm", "rebound_force_n", "elasticity_kpa"),
            (),
            "S_0 or S_max lies outside the calibrated range",
        ),
        # Informational: the 98 % rule's persistence did its work (noise near the level).
        Flag.EARLY_NOISY_CROSSING: FlagRule(
            (), (), "a short early crossing of the settling level was ignored"
        ),
        Flag.FIT_NOT_CONVERGED: FlagRule(
            ("tau_s",), ("tau_s",), "the recovery fit did not converge"
        ),
        Flag.TIME_CONSTANT_OUTSIDE_WINDOW: FlagRule(
            ("tau_s",), (), "the fitted tau lies outside the fitted span"
        ),
        Flag.CONSTANT_SERIES: FlagRule(("tau_s",), ("tau_s",), "S_k did not vary after T_0"),
        # Informational: a dropped frame is a missing frame, judged where it matters by the
        # gap rules (release, settling crossing, maximum, fit).
        Flag.NON_FINITE_INPUT: FlagRule((), (), "NaN frames were dropped"),
        # (of either estimator: the result's flags do not say which)
        Flag.OUTSIDE_REFERENCE_RANGE: FlagRule(
            ("severity", "severity_fit"), (), "the measurement lies beyond the reference grades"
        ),
        Flag.RISE_WITHIN_SETTLING_BAND: FlagRule(
            ("recovery_time_s",),
            ("recovery_time_s",),
            "S_k rose by less than the settling band: the recovery did not settle within "
            "the window, or there was none to time",
        ),
        Flag.RELEASE_NOT_OBSERVED: FlagRule(
            ("depth_mm", "recovery_time_s", "elasticity_kpa"),
            ("depth_mm",),
            "no usable frame near the release: S_0 is unknown",
        ),
        Flag.S0_EXTRAPOLATED: FlagRule(
            ("depth_mm", "elasticity_kpa"),
            (),
            "the frame after the release is missing or an outlier: S_0 extrapolated",
        ),
        Flag.RELEASE_FRAME_OUTLIER: FlagRule(
            ("depth_mm", "recovery_time_s", "elasticity_kpa"),
            (),
            "the frame before T_0 is an outlier: the release may be a frame earlier and S_0 "
            "a frame late",
        ),
        Flag.RELEASE_STEP: FlagRule(
            ("depth_mm", "elasticity_kpa"),
            (),
            "S_k jumped right after the release frame (an instantaneous spring-back or an "
            "outlier frame): S_0 rests on the release frame alone",
        ),
        Flag.FRAME_GAP_AT_SETTLING: FlagRule(
            ("recovery_time_s",), (), "the 98 % crossing lies in a frame gap"
        ),
        Flag.FRAME_GAP_AT_MAXIMUM: FlagRule(
            ("rebound_force_n",), (), "a frame gap is next to the frame that sets S_max"
        ),
        Flag.OUTLIER_FRAMES: FlagRule(
            ("rebound_force_n", "recovery_time_s", "tau_s"),
            (),
            "outlier frames were left out of S_max, T_s and the fit",
        ),
        Flag.FRAME_GAPS_IN_FIT: FlagRule(
            ("tau_s",), (), "frame gaps cover more than 10 % of the fitted span"
        ),
        Flag.POOR_FIT: FlagRule(
            ("tau_s",), ("tau_s",), "the Kelvin-Voigt model fits the recovery poorly"
        ),
        Flag.KELVIN_VOIGT_REJECTED: FlagRule(
            ("tau_s",),
            (),
            "the recovery is not one exponential: the Kelvin-Voigt tau describes a curve the "
            "tissue does not follow (see the recovery models)",
        ),
        # Informational: they concern one model of the side-by-side comparison, whose entry
        # in summary.json's recovery_models carries them.
        Flag.MODEL_SELECTION_UNAVAILABLE: FlagRule((), (), "no recovery model could be weighed"),
        Flag.TOO_FEW_POINTS: FlagRule((), (), "a recovery model had too few samples to fit"),
        Flag.PARAMETER_AT_BOUND: FlagRule((), (), "a model parameter is at its search bound"),
        Flag.NO_CONFIDENCE_INTERVALS: FlagRule((), (), "a model has no bootstrap intervals"),
        # The primary quantities against the recovery models (model_checks.py); the
        # reasons with the amounts come from the result's checks.
        Flag.MODEL_NOT_SETTLED: FlagRule(
            ("recovery_time_s", "rebound_force_n"),
            ("recovery_time_s", "rebound_force_n"),
            "the best recovery model settles after the record ends: T_r and S_max (F_r) are "
            "lower bounds",
        ),
        Flag.MODELS_DISAGREE: FlagRule(
            ("recovery_time_s",), (), "the recovery models with weight disagree about T_r"
        ),
        Flag.SETTLED_LEVEL_OFF_MODEL: FlagRule(
            ("recovery_time_s",),
            (),
            "S_max is off the best recovery model's level by more than T_r's tolerance",
        ),
        Flag.RECOVERY_TIME_OUTSIDE_MODEL_INTERVAL: FlagRule(
            ("recovery_time_s",), (), "T_r lies outside the best recovery model's 95 % interval"
        ),
        # Uncertainty beyond tolerance is invalid, not a caveat.
        Flag.RECOVERY_TIME_UNCERTAIN: FlagRule(
            ("recovery_time_s",),
            ("recovery_time_s",),
            "T_r's uncertainty (a frame gap at the crossing) exceeds its tolerance",
        ),
        Flag.TIME_CONSTANT_UNCERTAIN: FlagRule(
            ("tau_s",), ("tau_s",), "tau's standard error exceeds its tolerance"
        ),
        Flag.SEVERITY_AMBIGUOUS: FlagRule(
            ("severity",),
            ("severity",),
            "T_r's uncertainty spans more than one severity class",
        ),
        Flag.ESTIMATORS_DISAGREE: FlagRule(
            ("severity", "severity_fit"),
            (),
            "the paper's estimator and the fitted recovery disagree",
        ),
    }
)


@dataclass(frozen=True)
class QuantityValidity:
    """The validity of one quantity (one entry of ``summary.json``'s ``validity``).

    Attributes
    ----------
    status : {"valid", "flagged", "invalid"}
    flags : tuple[str, ...]
        The flags that concern the quantity, sorted.
    reason : str or None
        One line; None exactly when the status is ``valid``.
    """

    status: Status
    flags: tuple[str, ...]
    reason: str | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping ``{"status", "flags", "reason"}``."""
        return {"status": self.status, "flags": list(self.flags), "reason": self.reason}


@dataclass(frozen=True)
class Verdict:
    """The session's verdict (``summary.json``'s ``verdict``).

    Attributes
    ----------
    status : {"complete", "flagged", "invalid", "incomplete"}
    line : str
        One short sentence for the operator.
    """

    status: Literal["complete", "flagged", "invalid", "incomplete"]
    line: str

    def to_dict(self) -> dict[str, str]:
        """JSON-ready mapping ``{"status", "line"}``."""
        return {"status": self.status, "line": self.line}


def _specific_reason(flag: Flag, result: MeasurementResult) -> str | None:
    """A flag's reason with this measurement's facts (times, lengths), when it has them."""
    p, obs = result.pitting, result.pitting.observed
    for check in result.checks:  # rules with their amounts (model_checks.py)
        if check.flag is flag:
            return check.reason
    if flag is Flag.RELEASE_NOT_OBSERVED and obs.release_gap is not None:
        return f"{obs.release_gap.describe()} around the release at {p.t0_s:.2f} s"
    if flag is Flag.FRAME_GAP_AT_SETTLING and obs.settling_gap is not None:
        g = obs.settling_gap
        return (
            f"the 98 % crossing lies in a gap ({g.describe()}): T_r uncertain by {g.length_s:.2f} s"
        )
    if flag is Flag.FRAME_GAP_AT_MAXIMUM and obs.maximum_gap is not None:
        return f"S_max may lie in a gap ({obs.maximum_gap.describe()})"
    if flag is Flag.S0_BELOW_CONTACT_FLOOR:
        return (
            f"S_0 = {p.s0_px:.0f} px is below C1, the least count a contact image shows: no "
            f"image of the pit (D_p = {p.depth_mm:.2f} mm is Eq. 4 at no contact)"
        )
    if flag is Flag.S0_EXTRAPOLATED and obs.s0_frame_s is not None:
        return (
            f"the frame after the release at {p.t0_s:.3f} s is missing or an outlier: S_0 "
            f"extrapolated back to T_0 from the frames at and after {obs.s0_frame_s:.3f} s"
        )
    if flag is Flag.OUTLIER_FRAMES and obs.outlier_times_s:
        n = len(obs.outlier_times_s)
        return f"{n} outlier frame{'s' if n > 1 else ''} left out of S_max, T_s and the fit"
    if flag is Flag.RELEASE_STEP and p.spring_back_px is not None:
        rise = p.s_max_px - p.s0_px
        share = f" ({100 * p.spring_back_px / rise:.0f} % of the recovery)" if rise > 0 else ""
        residual = p.residual_depth_mm
        pit = (
            ""
            if residual is None
            else (
                f": residual pit {residual:.2f} mm against the indentation depth D_p = "
                f"{p.depth_mm:.2f} mm at the release frame"
            )
        )
        return (
            f"an instantaneous spring-back: S_k rose by {p.spring_back_px:.0f} px right after "
            f"the release frame{share}{pit}"
        )
    if flag is Flag.FORCE_AT_FULL_SCALE:
        return (
            f"{100 * result.force_at_rail_fraction:.0f} % of the hold's load-cell samples sit "
            "at full scale: F_a is only a lower bound"
        )
    if flag is Flag.POOR_FIT and result.fit.r_squared is not None:
        return f"the Kelvin-Voigt model fits the recovery poorly (R^2 = {result.fit.r_squared:.2f})"
    if flag is Flag.ESTIMATORS_DISAGREE:
        sp, sf = result.severity_paper, result.severity_fit
        if sp is not None and sf is not None:
            return (
                f"estimators disagree: paper {sp.severity} (grade {sp.nearest_grade}), "
                f"fitted recovery {sf.severity} (grade {sf.nearest_grade})"
            )
    return None


def _value_missing(result: MeasurementResult, quantity: str) -> str | None:
    """Why ``quantity`` has no value in ``result`` (None when it has one)."""
    p = result.pitting
    missing = {
        "recovery_time_s": p.recovery_time_s is None,
        "elasticity_kpa": result.paper_model is None,
        "viscosity_n_s_per_mm2": result.paper_model is None,
        "severity": result.severity_paper is None,
        "tau_s": result.fit.tau_s is None,
        "viscosity_fit_n_s_per_mm2": result.fit_model is None,
        "severity_fit": result.severity_fit is None,
    }
    if not missing.get(quantity, False):
        return None
    return "not computed: " + ("; ".join(result.notes) or "undefined for this series")


def quantity_validity(
    result: MeasurementResult,
    extra_reasons: Mapping[str, str] | None = None,
    extra_caveats: Mapping[str, str] | None = None,
    extra_flags: Sequence[str] = (),
) -> dict[str, QuantityValidity]:
    """The validity of every primary and secondary quantity of one measurement.

    Parameters
    ----------
    result : MeasurementResult
        The measurement; its flags (and those of its parts) are applied per
        :data:`FLAG_RULES`, then invalidity and caveats propagate along
        :data:`DEPENDS_ON`.
    extra_reasons : mapping, optional
        Quantity -> reason that makes it invalid, for facts not carried by a result flag
        (e.g. the release as the measurement pipeline observed it).
    extra_caveats : mapping, optional
        Quantity -> caveat that flags it, likewise.
    extra_flags : sequence of str
        Flag values attached to every quantity named in ``extra_reasons`` or
        ``extra_caveats``.

    Returns
    -------
    dict[str, QuantityValidity]
        Keyed by quantity, primary ones first.
    """
    flags: dict[str, set[str]] = {q: set() for q in (*PRIMARY_QUANTITIES, *SECONDARY_QUANTITIES)}
    invalid: dict[str, list[str]] = {q: [] for q in flags}
    caveats: dict[str, list[str]] = {q: [] for q in flags}
    for flag in sorted(result.flags):
        rule = FLAG_RULES.get(flag)
        if rule is None:
            continue
        reason = _specific_reason(flag, result) or rule.reason
        for q in rule.quantities:
            flags[q].add(str(flag))
            (invalid if q in rule.invalidates else caveats)[q].append(reason)
    for qrule in result.quality_rules:
        flags[qrule.quantity].add(str(Flag.IMAGE_QUALITY))
        (invalid if qrule.invalid else caveats)[qrule.quantity].append(qrule.reason)
    for extra, into in ((extra_reasons, invalid), (extra_caveats, caveats)):
        for q, reason in (extra or {}).items():
            into[q].append(reason)
            flags[q].update(extra_flags)
    for q in flags:
        why = _value_missing(result, q)
        if why is not None:
            invalid[q].append(why)
    # Derived quantities name the root cause: "D_p is invalid: no frame between ...".
    root = {q: f"{QUANTITY_SYMBOLS[q]} is invalid: {why[0]}" for q, why in invalid.items() if why}
    for q in _DERIVED:
        for source in DEPENDS_ON[q]:
            if invalid[source] and not invalid[q]:
                invalid[q].append(root[source])
                root[q] = root[source]
            elif caveats[source] and not caveats[q]:
                caveats[q].append(f"{QUANTITY_SYMBOLS[source]} is flagged: {caveats[source][0]}")
            if invalid[source] or caveats[source]:
                flags[q] |= flags[source]
    out: dict[str, QuantityValidity] = {}
    for q, fl in flags.items():
        if invalid[q]:
            out[q] = QuantityValidity("invalid", tuple(sorted(fl)), invalid[q][0])
        elif fl or caveats[q]:
            out[q] = QuantityValidity("flagged", tuple(sorted(fl)), "; ".join(caveats[q]))
        else:
            out[q] = QuantityValidity("valid", (), None)
    return out


def verdict(
    validity: Mapping[str, QuantityValidity],
    *,
    ended_done: bool,
    end_reason: str | None = None,
) -> Verdict:
    """The session's verdict from its quantities' validity and how it ended.

    Parameters
    ----------
    validity : mapping
        :func:`quantity_validity`'s output (may be empty when there are no results).
    ended_done : bool
        True when the state machine ended DONE.
    end_reason : str or None
        Why it ended otherwise (shown in an incomplete verdict's line).
    """
    bad = [q for q in PRIMARY_QUANTITIES if q not in validity or validity[q].status == "invalid"]
    caveat = [q for q in PRIMARY_QUANTITIES if q in validity and validity[q].status == "flagged"]

    def names(qs: list[str]) -> str:
        return ", ".join(QUANTITY_SYMBOLS[q] for q in qs)

    if not ended_done:
        why = end_reason or "the session did not finish"
        shown = "no results" if not validity else "results computed from the data recorded"
        return Verdict("incomplete", f"Session incomplete ({why}): {shown}.")
    if not validity:
        return Verdict("invalid", "No results: the analysis could not run or failed.")
    if bad:
        first = validity[bad[0]].reason if bad[0] in validity else None
        return Verdict("invalid", f"Not valid: {names(bad)} ({first or 'no value'}).")
    if caveat:
        return Verdict("flagged", f"Complete with caveats on {names(caveat)}.")
    # the secondary quantities do not decide the verdict, but the line never calls a
    # flagged or invalid one valid
    others = [q for q in SECONDARY_QUANTITIES if q in validity and validity[q].status != "valid"]
    # one derived from another listed (eta_tau = E*tau from tau) adds nothing to the line
    others = [q for q in others if not set(DEPENDS_ON.get(q, ())) & set(others)]
    if others:
        said = ", ".join(f"{QUANTITY_SYMBOLS[q]} {validity[q].status}" for q in others)
        return Verdict("complete", f"Complete: every primary result is valid ({said}).")
    return Verdict("complete", "Complete: every result is valid.")


def assess_validity(
    result: MeasurementResult | None,
    *,
    ended_done: bool,
    end_reason: str | None = None,
    analysis_error: str | None = None,
    invalid_reasons: Mapping[str, str] | None = None,
    caveats: Mapping[str, str] | None = None,
    extra_flags: Sequence[str] = (),
) -> dict[str, Any]:
    """``summary.json``'s ``validity`` and ``verdict`` entries for one session.

    Parameters
    ----------
    result : MeasurementResult or None
        The measurement's results (None when the analysis did not run or failed).
    ended_done : bool
        True when the state machine ended DONE.
    end_reason : str or None
        Why the session ended, for an incomplete verdict.
    analysis_error : str or None
        Why the analysis failed (the reason of every quantity when there is no result).
    invalid_reasons, caveats, extra_flags
        Facts observed outside the analysis result (quantity -> reason that invalidates
        it, quantity -> caveat, and the flag values they carry), e.g. the measurement
        pipeline's release observation; see :func:`quantity_validity`.

    Returns
    -------
    dict
        ``{"validity": {quantity: {"status", "flags", "reason"}}, "verdict": {"status",
        "line"}}``; without a result every quantity is invalid with the reason.
    """
    if result is None:
        why = f"no result: {analysis_error or 'the analysis did not run'}"
        validity = {
            q: QuantityValidity("invalid", (), why)
            for q in (*PRIMARY_QUANTITIES, *SECONDARY_QUANTITIES)
        }
        v = verdict({}, ended_done=ended_done, end_reason=end_reason)
    else:
        validity = quantity_validity(result, invalid_reasons, caveats, extra_flags)
        v = verdict(validity, ended_done=ended_done, end_reason=end_reason)
    return {
        "validity": {q: qv.to_dict() for q, qv in validity.items()},
        "verdict": v.to_dict(),
    }
