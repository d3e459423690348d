"""Edema severity classification from normalised VPR curves (STIP-I paper, Section IV.C).

This module owns the reference curves (the versioned ``data/severity_reference.yaml``,
validated on load), the search for the time window that best separates a mild and a severe
reference grade, the mild/severe threshold, and the classification of one measurement
(mild/severe and nearest grade). It does not own E, eta or tau (see ``vpr`` and
``recovery_fit``).

Normalised depth: n(t) = D(t)/D_p = exp(-r t) with decay rate r = E/eta (Eq. 10), so 1 is
the maximum pitting depth at T_0 and 0 full recovery. The paper's threshold "62 %" is a
recovered fraction: between 11 and 20 s grade II's mean normalised depth is 0.186 and
grade III's 0.573; their mid-point 0.380 is a depth of 38 % of the maximum, i.e. 62 % of the
pit recovered. A measurement is severe when its mean normalised depth over the window is at
or above the threshold depth (it has recovered less than 62 %): "a pitting depth less than
62.0 % from the maximum" reads as "the depth has come down by less than 62 %". Results carry
both ``threshold_depth_fraction`` and ``threshold_recovered_percent``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.recovery_fit import RecoveryFit, settling_time_from_time_constant
from stipi_daemon.analysis.vpr import KPA_PER_N_PER_MM2, VPRModel
from stipi_daemon.errors import AnalysisError, ConfigError
from stipi_daemon.yamlfile import read_utf8

__all__ = [
    "DEFAULT_RANGE_TOLERANCE",
    "REFERENCE_RESOURCE",
    "ReferenceGrade",
    "SeverityReference",
    "SeverityResult",
    "SeverityWindow",
    "WindowSearch",
    "classify_decay_rate",
    "classify_fit",
    "classify_vpr",
    "find_severity_window",
    "load_reference",
    "normalised_depth",
]

#: Relative margin on the decay rate before a measurement counts as beyond the reference
#: grades (see :func:`classify_decay_rate`) [-].
DEFAULT_RANGE_TOLERANCE = 0.01
#: Package resource holding the default reference curves.
REFERENCE_RESOURCE = "data/severity_reference.yaml"

_PositiveFinite = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
_NonNegativeFinite = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]


class ReferenceGrade(BaseModel):
    """One reference edema grade: its VPR parameters (Table II) and clinical class."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    severe: bool
    elasticity_kpa: _PositiveFinite
    viscosity_n_s_per_mm2: _PositiveFinite
    depth_mm: _PositiveFinite | None = None

    @property
    def decay_rate_per_s(self) -> float:
        """E/eta [1/s] of Eq. (10)."""
        return self.elasticity_kpa / KPA_PER_N_PER_MM2 / self.viscosity_n_s_per_mm2


class WindowSearch(BaseModel):
    """Settings of the window search (Section IV.C); times in seconds after T_0."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mild_grade: str = "II"
    severe_grade: str = "III"
    length_s: _PositiveFinite = 10.0
    search_start_s: _NonNegativeFinite = 1.0
    search_end_s: _PositiveFinite = 50.0
    step_s: _PositiveFinite = 1.0

    @model_validator(mode="after")
    def _consistent(self) -> WindowSearch:
        m = self.length_s / self.step_s
        if abs(m - round(m)) > 1e-9 * m or round(m) < 1:
            raise ValueError(
                f"length_s ({self.length_s}) must be a whole number of step_s ({self.step_s})"
            )
        if self.search_start_s + (round(m) - 1) * self.step_s > self.search_end_s * (1 + 1e-12):
            raise ValueError("the search range is shorter than one window")
        return self

    @property
    def samples_per_window(self) -> int:
        """Samples in one window, length_s / step_s."""
        return round(self.length_s / self.step_s)

    def grid_s(self) -> NDArray[np.float64]:
        """Sample times of the search range [s]: search_start_s + k * step_s <= search_end_s."""
        k = math.floor((self.search_end_s - self.search_start_s) / self.step_s + 1e-9)
        return self.search_start_s + self.step_s * np.arange(k + 1, dtype=np.float64)


class SeverityReference(BaseModel):
    """The reference curves file, version 1."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: Literal[1]
    source: str
    grades: tuple[ReferenceGrade, ...] = Field(min_length=2)
    window: WindowSearch = WindowSearch()

    @model_validator(mode="after")
    def _consistent(self) -> SeverityReference:
        names = [g.name for g in self.grades]
        if len(set(names)) != len(names):
            raise ValueError(f"grade names must be unique, got {names}")
        rates = [g.decay_rate_per_s for g in self.grades]
        if any(a <= b for a, b in itertools.pairwise(rates)):
            raise ValueError(
                "grades must be listed from mildest to most severe, i.e. with strictly "
                f"decreasing decay rate E/eta; got rates {[round(r, 6) for r in rates]} 1/s"
            )
        for field in ("mild_grade", "severe_grade"):
            if getattr(self.window, field) not in names:
                raise ValueError(f"window.{field} names no grade in {names}")
        return self

    def grade(self, name: str) -> ReferenceGrade:
        """The grade called ``name``; AnalysisError if none is."""
        for g in self.grades:
            if g.name == name:
                return g
        raise AnalysisError(f"no reference grade {name!r}; have {[g.name for g in self.grades]}")


def _format_loc(loc: tuple[int | str, ...]) -> str:
    return ".".join(str(p) for p in loc) or "<root>"


def load_reference(path: str | Path | None = None) -> SeverityReference:
    """Load and validate reference curves.

    Parameters
    ----------
    path : str or Path, optional
        A YAML file in the format of the package's ``data/severity_reference.yaml``;
        default: that file.

    Returns
    -------
    SeverityReference

    Raises
    ------
    ConfigError
        The file cannot be read, is not YAML, or fails validation; the message names the
        file and the field (e.g. ``grades.2.viscosity_n_s_per_mm2``).
    """
    if path is None:
        resource = resources.files("stipi_daemon").joinpath(REFERENCE_RESOURCE)
        where = f"stipi_daemon/{REFERENCE_RESOURCE}"
        try:
            text = resource.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"{where}: cannot read: {exc}") from exc
    else:
        where = str(path)
        text = read_utf8(Path(path), "severity reference")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping at the top level")
    try:
        return SeverityReference.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"field {_format_loc(e['loc'])}: {e['msg']}" for e in exc.errors(include_url=False)
        )
        raise ConfigError(f"{where}: {problems}") from exc


def normalised_depth(t_s: NDArray[np.float64], decay_rate_per_s: float) -> NDArray[np.float64]:
    """Normalised VPR curve exp(-r t) [-] at times ``t_s`` [s] >= 0 (Eq. 10 over D_p)."""
    with np.errstate(under="ignore", over="ignore"):
        out: NDArray[np.float64] = np.exp(-(decay_rate_per_s * t_s))
    return out


@dataclass(frozen=True)
class SeverityWindow:
    """The window separating a mild and a severe grade, and the threshold (Section IV.C).

    Attributes
    ----------
    start_s, end_s : float
        First and last sample of the window [s after T_0] (11 and 20 for the paper).
    sample_times_s : tuple[float, ...]
        The window's samples [s]: ``length_s / step_s`` of them, ``step_s`` apart.
    mild_grade, severe_grade : str
        The two grades compared.
    mild_mean_depth, severe_mean_depth : float
        Their mean normalised depth over the window [-].
    mean_difference : float
        |severe - mild| mean normalised depth, the maximised quantity [-].
    threshold_depth_fraction : float
        Mid-point of the two means, a normalised depth [-] (1 = maximum pit).
    threshold_recovered_percent : float
        The same threshold as a recovered fraction, 100 * (1 - depth) [%] (the paper's 62 %).
    candidate_starts_s, candidate_differences : tuple[float, ...]
        Every window start searched and its mean difference (the paper's Fig. 11).
    """

    start_s: float
    end_s: float
    sample_times_s: tuple[float, ...]
    mild_grade: str
    severe_grade: str
    mild_mean_depth: float
    severe_mean_depth: float
    mean_difference: float
    threshold_depth_fraction: float
    threshold_recovered_percent: float
    candidate_starts_s: tuple[float, ...]
    candidate_differences: tuple[float, ...]


def find_severity_window(
    reference: SeverityReference,
    search: WindowSearch | None = None,
) -> SeverityWindow:
    """Find the window with the largest mean difference between two grades (Section IV.C).

    Each window is a closed set of ``length_s / step_s`` samples ``step_s`` apart starting at
    a whole step of the search range; with the default 1 s step a 10 s window starting at
    11 s holds the ten samples 11, 12, ..., 20 s, the paper's "11 - 20 sec" window. Windows
    lie inside [search_start_s, search_end_s] (1-50 s: starts 1 to 41 s). The mean absolute
    difference of the two grades' normalised depths is maximised (ties: earliest window) and
    the threshold is the mid-point of the two means over that window.

    Parameters
    ----------
    reference : SeverityReference
        Reference grades.
    search : WindowSearch, optional
        Search settings; default ``reference.window``.

    Returns
    -------
    SeverityWindow

    Raises
    ------
    AnalysisError
        A grade named by the search is not in the reference.
    """
    s = reference.window if search is None else search
    mild = reference.grade(s.mild_grade)
    severe = reference.grade(s.severe_grade)
    grid = s.grid_s()
    m = s.samples_per_window
    n_windows = grid.size - m + 1
    mild_curve = normalised_depth(grid, mild.decay_rate_per_s)
    severe_curve = normalised_depth(grid, severe.decay_rate_per_s)
    kernel = np.full(m, 1.0 / m)
    mild_means = np.convolve(mild_curve, kernel, mode="valid")
    severe_means = np.convolve(severe_curve, kernel, mode="valid")
    differences = np.abs(severe_means - mild_means)
    best = int(np.argmax(differences))
    threshold = 0.5 * float(mild_means[best] + severe_means[best])
    samples = grid[best : best + m]
    return SeverityWindow(
        start_s=float(samples[0]),
        end_s=float(samples[-1]),
        sample_times_s=tuple(float(v) for v in samples),
        mild_grade=mild.name,
        severe_grade=severe.name,
        mild_mean_depth=float(mild_means[best]),
        severe_mean_depth=float(severe_means[best]),
        mean_difference=float(differences[best]),
        threshold_depth_fraction=threshold,
        threshold_recovered_percent=100.0 * (1.0 - threshold),
        candidate_starts_s=tuple(float(v) for v in grid[:n_windows]),
        candidate_differences=tuple(float(v) for v in differences),
    )


@dataclass(frozen=True)
class SeverityResult:
    """Classification of one measurement.

    Attributes
    ----------
    severity : {"mild", "severe"}
        Severe when ``window_mean_depth_fraction >= threshold_depth_fraction``.
    decay_rate_per_s : float
        Decay rate r of the measurement's normalised curve exp(-r t) [1/s].
    window_mean_depth_fraction : float
        Mean normalised depth over the window samples [-].
    recovered_percent : float
        100 * (1 - window_mean_depth_fraction) [%].
    threshold_depth_fraction, threshold_recovered_percent : float
        The threshold used, as depth fraction [-] and recovered percentage [%].
    window_start_s, window_end_s : float
        First and last window sample [s after T_0].
    nearest_grade : str
        Reference grade whose normalised curve is closest (RMS over the search grid).
    grade_distances : tuple[tuple[str, float], ...]
        (grade, RMS distance [-]) for every reference grade, in reference order.
    flags : frozenset[Flag]
        ``OUTSIDE_REFERENCE_RANGE`` when r is faster than the mildest or slower than the
        most severe reference grade (beyond a 1 % margin by default), plus flags carried
        over from the input.
    """

    severity: Literal["mild", "severe"]
    decay_rate_per_s: float
    window_mean_depth_fraction: float
    recovered_percent: float
    threshold_depth_fraction: float
    threshold_recovered_percent: float
    window_start_s: float
    window_end_s: float
    nearest_grade: str
    grade_distances: tuple[tuple[str, float], ...]
    flags: frozenset[Flag]


def classify_decay_rate(
    decay_rate_per_s: float,
    reference: SeverityReference,
    window: SeverityWindow | None = None,
    *,
    flags: frozenset[Flag] = frozenset(),
    range_tolerance: float = DEFAULT_RANGE_TOLERANCE,
) -> SeverityResult:
    """Classify the normalised curve exp(-r t) as mild/severe and find its nearest grade.

    The curve is compared with the threshold by its mean over the window samples. The
    nearest grade minimises the root-mean-square difference between the two normalised
    curves sampled on the search grid (``reference.window``: 1 to 50 s every 1 s).

    Parameters
    ----------
    decay_rate_per_s : float
        r = E/eta [1/s] (1/T_r for the paper's estimator), finite and > 0.
    reference : SeverityReference
        Reference grades.
    window : SeverityWindow, optional
        Window and threshold; default :func:`find_severity_window` on ``reference``.
    flags : frozenset[Flag]
        Flags of the input to carry over.
    range_tolerance : float
        Relative margin on the decay rate before ``OUTSIDE_REFERENCE_RANGE`` is set, >= 0:
        r > r_mildest * (1 + tol) or r < r_most_severe / (1 + tol). The default 1 % keeps
        the paper's own rounded Table I/II values (grade IV: 1/44.4 s against
        196.32/8.70 kPa*mm^2/(N*s), 0.2 % apart) inside the range.

    Returns
    -------
    SeverityResult

    Raises
    ------
    AnalysisError
        ``decay_rate_per_s`` is not finite and > 0.
    """
    rate = float(decay_rate_per_s)
    if not (math.isfinite(rate) and rate > 0.0):
        raise AnalysisError(f"decay_rate_per_s must be finite and > 0, got {rate}")
    if not (math.isfinite(range_tolerance) and range_tolerance >= 0.0):
        raise AnalysisError(f"range_tolerance must be finite and >= 0, got {range_tolerance}")
    win = find_severity_window(reference) if window is None else window
    mean_depth = float(np.mean(normalised_depth(np.asarray(win.sample_times_s), rate)))
    grid = reference.window.grid_s()
    curve = normalised_depth(grid, rate)
    distances = tuple(
        (
            g.name,
            float(np.sqrt(np.mean(np.square(curve - normalised_depth(grid, g.decay_rate_per_s))))),
        )
        for g in reference.grades
    )
    nearest = min(distances, key=lambda item: item[1])[0]
    out_flags = set(flags)
    fastest = reference.grades[0].decay_rate_per_s * (1.0 + range_tolerance)
    slowest = reference.grades[-1].decay_rate_per_s / (1.0 + range_tolerance)
    if rate > fastest or rate < slowest:
        out_flags.add(Flag.OUTSIDE_REFERENCE_RANGE)
    return SeverityResult(
        severity="severe" if mean_depth >= win.threshold_depth_fraction else "mild",
        decay_rate_per_s=rate,
        window_mean_depth_fraction=mean_depth,
        recovered_percent=100.0 * (1.0 - mean_depth),
        threshold_depth_fraction=win.threshold_depth_fraction,
        threshold_recovered_percent=win.threshold_recovered_percent,
        window_start_s=win.start_s,
        window_end_s=win.end_s,
        nearest_grade=nearest,
        grade_distances=distances,
        flags=frozenset(out_flags),
    )


def classify_vpr(
    model: VPRModel, reference: SeverityReference, window: SeverityWindow | None = None
) -> SeverityResult:
    """Classify a :class:`~stipi_daemon.analysis.vpr.VPRModel` by its decay rate E/eta.

    This is the paper's route: with eta from Eq. (8), E/eta = 1/T_r, the same quantity the
    reference curves are built from.
    """
    return classify_decay_rate(model.decay_rate_per_s, reference, window, flags=model.flags)


def classify_fit(
    fit: RecoveryFit,
    reference: SeverityReference,
    window: SeverityWindow | None = None,
    *,
    time_base: Literal["settling_time", "time_constant"] = "settling_time",
) -> SeverityResult:
    """Classify a fitted Kelvin-Voigt recovery of S_k.

    The paper's reference curves decay at 1/T_r, where T_r is a 98 % settling time, not a
    time constant. With ``time_base="settling_time"`` (default) the fitted tau is first
    converted to the T_r an ideal recovery with this tau, S_0 = offset - amplitude and
    S_inf = offset would show (:func:`~stipi_daemon.analysis.recovery_fit.
    settling_time_from_time_constant`), so that the measurement and the references are on
    the same scale. ``time_base="time_constant"`` uses 1/tau directly, for references built
    from fitted time constants.

    Raises
    ------
    AnalysisError
        The fit has no time constant, or (settling_time) it does not describe a rising S_k
        recovery (offset > 0, S_0 >= 0) that ever crosses 98 % of S_inf.
    """
    if fit.tau_s is None or fit.offset is None or fit.amplitude is None:
        raise AnalysisError(f"the recovery fit has no time constant (flags: {sorted(fit.flags)})")
    if time_base == "time_constant":
        return classify_decay_rate(1.0 / fit.tau_s, reference, window, flags=fit.flags)
    s_inf = fit.offset
    s0 = fit.offset - fit.amplitude
    if not (fit.amplitude > 0.0 and s_inf > 0.0 and s0 >= 0.0):
        raise AnalysisError(
            "settling_time base needs a rising S_k fit (amplitude > 0, S_inf > 0, S_0 >= 0), "
            f"got amplitude={fit.amplitude}, S_inf={s_inf}, S_0={s0}"
        )
    t_r = settling_time_from_time_constant(fit.tau_s, s0, s_inf)
    if t_r <= 0.0:
        raise AnalysisError(
            f"S_0={s0} px is already within 2 % of S_inf={s_inf} px: no settling time"
        )
    return classify_decay_rate(1.0 / t_r, reference, window, flags=fit.flags)
