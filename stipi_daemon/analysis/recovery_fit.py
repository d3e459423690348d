"""Second estimator of the recovery: a Kelvin-Voigt recovery fitted to the whole series.

The paper (Eq. 8) takes viscosity from T_r, a 98 % settling time read at one crossing of
one noisy series. This module fits y(t) = offset - amplitude * exp(-(t - T_0)/tau) to every
sample of the recovery window instead and reports the Kelvin-Voigt time constant tau with
standard errors, so that eta = E * tau can be compared with the paper's eta = E * T_r.
It also converts between the two: for a recovery that starts at S_0 and settles at S_inf,
the paper's T_r = tau * ln((S_inf - S_0) / ((1 - f) S_inf)) with f = 0.98, i.e.
tau * ln(50 (1 - S_0/S_inf)) (about 3.9 tau when S_0 << S_inf): T_r is not a time constant.
It does not own T_r itself (see ``pitting``) nor Eq. (7) (see ``vpr``). The same fit is the
Kelvin-Voigt entry of the side-by-side model comparison
(:mod:`~stipi_daemon.analysis.recovery_models`), which starts and solves it with
:func:`grid_start` and :func:`solve_scaled`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.pitting import DEFAULT_SETTLE_FRACTION, DEFAULT_WINDOW_S
from stipi_daemon.analysis.tolerances import recovery_time_tolerance_s
from stipi_daemon.analysis.vpr import KPA_PER_N_PER_MM2, VPRModel, elasticity_kpa
from stipi_daemon.errors import AnalysisError

__all__ = [
    "MAX_ABS_VALUE",
    "MIN_FIT_POINTS",
    "TAU_SEARCH_RANGE_S",
    "RecoveryFit",
    "check_value_domain",
    "fit_recovery",
    "fit_window",
    "grid_start",
    "kelvin_voigt_recovery",
    "settling_time_from_time_constant",
    "solve_scaled",
    "time_constant_from_settling_time",
]

#: Range of time constants the fit searches [s]: 1 ms (well below a 60 fps frame) to 1e4 s
#: (two orders of magnitude beyond the paper's 105 s recovery window).
TAU_SEARCH_RANGE_S = (1e-3, 1e4)
#: Fewest finite samples in the window for a 3-parameter fit with one degree of freedom left.
MIN_FIT_POINTS = 4
#: Largest |value| of a fitted series [series unit]: squared residuals and ranges of values
#: up to it stay finite in float64 (1e150^2 = 1e300 < 1.8e308); S_k is a pixel count far
#: below it, so a larger value is a unit or data error, not a tissue.
MAX_ABS_VALUE = 1e150
#: Points of the log-spaced tau grid used to find the starting point (variable projection).
_GRID_POINTS = 121


def kelvin_voigt_recovery(
    t_s: ArrayLike, t0_s: float, offset: float, amplitude: float, tau_s: float
) -> NDArray[np.float64]:
    """Kelvin-Voigt recovery y(t) = offset - amplitude * exp(-(t - T_0)/tau).

    Parameters
    ----------
    t_s : array_like
        Times [s], >= ``t0_s`` (earlier times would make the exponential grow).
    t0_s : float
        Start of the recovery T_0 [s].
    offset : float
        Settled value y(inf), in the unit of the fitted series (S_k [px] or depth [mm]).
    amplitude : float
        Recovered amount y(inf) - y(T_0), same unit.
    tau_s : float
        Time constant tau [s], > 0.

    Returns
    -------
    numpy.ndarray
        y(t), same shape as ``t_s``.

    Raises
    ------
    AnalysisError
        ``tau_s`` <= 0 or non-finite, or a time precedes ``t0_s``.
    """
    if not (math.isfinite(tau_s) and tau_s > 0.0):
        raise AnalysisError(f"tau_s must be finite and > 0, got {tau_s}")
    x = np.asarray(t_s, dtype=np.float64) - float(t0_s)
    if np.any(~(x >= 0.0)):
        raise AnalysisError(f"times must be finite and >= t0_s = {t0_s} s")
    with np.errstate(under="ignore", over="ignore"):
        decay = np.exp(-(x / tau_s))
    out: NDArray[np.float64] = offset - amplitude * decay
    return out


@dataclass(frozen=True)
class RecoveryFit:
    """A Kelvin-Voigt recovery fitted to a series (see :func:`fit_recovery`).

    Parameters are None when the fit has none to report: all three with
    ``FIT_NOT_CONVERGED``; tau with ``CONSTANT_SERIES`` (offset is then the constant,
    amplitude 0). Standard errors are None also when the data do not determine them (the
    scaled Jacobian's condition number exceeds 1e6, e.g. tau far below one frame period).

    Attributes
    ----------
    tau_s : float or None
        Time constant tau [s].
    amplitude : float or None
        y(inf) - y(T_0), unit of the fitted series.
    offset : float or None
        y(inf), unit of the fitted series.
    tau_se_s, amplitude_se, offset_se : float or None
        One-sigma standard errors (linearised, residual variance from the fit); for an
        integer-valued series (S_k) offset's and amplitude's also hold the rounding of the
        settled level, a uniform +-0.5 count (variance 1/12). tau of one exponential does
        not depend on where T_0 lies within a frame, so its error has no timing term.
    t0_s : float
        T_0 the model is anchored at [s].
    t_start_s, t_end_s : float
        First and last fitted sample times [s].
    n_points : int
        Finite samples fitted.
    rmse : float
        Root-mean-square residual, unit of the series.
    r_squared : float or None
        Coefficient of determination; None for a constant series.
    flags : frozenset[Flag]
        ``FIT_NOT_CONVERGED``, ``TIME_CONSTANT_OUTSIDE_WINDOW``, ``CONSTANT_SERIES``,
        ``NON_FINITE_INPUT``.
    """

    tau_s: float | None
    amplitude: float | None
    offset: float | None
    tau_se_s: float | None
    amplitude_se: float | None
    offset_se: float | None
    t0_s: float
    t_start_s: float
    t_end_s: float
    n_points: int
    rmse: float
    r_squared: float | None
    flags: frozenset[Flag]

    def _tau(self) -> float:
        if self.tau_s is None:
            raise AnalysisError(
                f"the recovery fit has no time constant (flags: {sorted(self.flags)})"
            )
        return self.tau_s

    @property
    def decay_rate_per_s(self) -> float:
        """1/tau [1/s], the E/eta of a Kelvin-Voigt recovery. Raises if tau is None."""
        return 1.0 / self._tau()

    def viscosity_n_s_per_mm2(self, elasticity_kpa: float) -> float:
        """eta = E * tau [N*s/mm^2] for an elasticity E [kPa] (compare Eq. 8's E * T_r).

        Raises
        ------
        AnalysisError
            No time constant, or E is not finite and > 0.
        """
        if not (math.isfinite(elasticity_kpa) and elasticity_kpa > 0.0):
            raise AnalysisError(f"elasticity_kpa must be finite and > 0, got {elasticity_kpa}")
        eta = elasticity_kpa * self._tau() / KPA_PER_N_PER_MM2
        if not math.isfinite(eta):
            raise AnalysisError(f"viscosity overflows for E={elasticity_kpa} kPa")
        return eta

    def to_vpr(
        self, depth_mm: float, *, applied_force_n: float, indenter_radius_mm: float
    ) -> VPRModel:
        """VPR model (Eq. 10) with E from Eq. (7) and eta = E * tau from this fit.

        Its decay rate is 1/tau, where the paper's model decays at 1/T_r.
        """
        e = elasticity_kpa(applied_force_n, depth_mm, indenter_radius_mm)
        return VPRModel(
            elasticity_kpa=e,
            viscosity_n_s_per_mm2=self.viscosity_n_s_per_mm2(e),
            depth_mm=float(depth_mm),
            applied_force_n=float(applied_force_n),
            indenter_radius_mm=float(indenter_radius_mm),
            flags=self.flags,
        )


def settling_time_from_time_constant(
    tau_s: float,
    s0_px: float,
    s_inf_px: float,
    settle_fraction: float = DEFAULT_SETTLE_FRACTION,
) -> float:
    """The paper's T_r (Eq. 6) of an ideal Kelvin-Voigt recovery with time constant tau.

    S(t) = S_inf - (S_inf - S_0) exp(-t/tau) reaches f * S_inf when
    (S_inf - S_0) exp(-T_r/tau) = (1 - f) S_inf, so
    T_r = tau * ln((S_inf - S_0) / ((1 - f) S_inf)); with f = 0.98 that is
    tau * ln(50 (1 - S_0/S_inf)). It is 0 when S_0 >= f * S_inf. This assumes S_max = S_inf
    (the window reaches the plateau).

    Parameters
    ----------
    tau_s : float
        Time constant [s], > 0.
    s0_px : float
        S_0 [px], >= 0.
    s_inf_px : float
        Settled S_k (S_max) [px], > 0.
    settle_fraction : float
        f in (0, 1) [-].

    Returns
    -------
    float
        T_r [s], >= 0.

    Raises
    ------
    AnalysisError
        An input outside its domain.
    """
    _check_conversion(tau_s, "tau_s", s0_px, s_inf_px, settle_fraction)
    ratio = (s_inf_px - s0_px) / ((1.0 - settle_fraction) * s_inf_px)
    if ratio <= 1.0:
        return 0.0
    return tau_s * math.log(ratio)


def time_constant_from_settling_time(
    recovery_time_s: float,
    s0_px: float,
    s_max_px: float,
    settle_fraction: float = DEFAULT_SETTLE_FRACTION,
) -> float:
    """Inverse of :func:`settling_time_from_time_constant`: tau [s] from the paper's T_r.

    Raises
    ------
    AnalysisError
        An input outside its domain, or S_0 >= f * S_max (T_r then carries no information
        on tau).
    """
    _check_conversion(recovery_time_s, "recovery_time_s", s0_px, s_max_px, settle_fraction)
    ratio = (s_max_px - s0_px) / ((1.0 - settle_fraction) * s_max_px)
    if ratio <= 1.0:
        raise AnalysisError(
            f"S_0 = {s0_px} px is already at or above {settle_fraction} * S_max "
            f"= {settle_fraction * s_max_px} px: T_r does not determine tau"
        )
    return recovery_time_s / math.log(ratio)


def _check_conversion(
    time_s: float, name: str, s0_px: float, s_inf_px: float, settle_fraction: float
) -> None:
    if not (math.isfinite(time_s) and time_s > 0.0):
        raise AnalysisError(f"{name} must be finite and > 0, got {time_s}")
    if not (math.isfinite(s0_px) and s0_px >= 0.0):
        raise AnalysisError(f"s0_px must be finite and >= 0, got {s0_px}")
    if not (math.isfinite(s_inf_px) and s_inf_px > 0.0):
        raise AnalysisError(f"S_inf/S_max must be finite and > 0, got {s_inf_px}")
    if not 0.0 < settle_fraction < 1.0:
        raise AnalysisError(f"settle_fraction must be in (0, 1), got {settle_fraction}")


def check_value_domain(y_lo: float, y_hi: float) -> None:
    """Raise :class:`AnalysisError` when a series' smallest ``y_lo`` or largest ``y_hi``
    value lies outside +-:data:`MAX_ABS_VALUE` (the fits' domain) or is not finite."""
    for name, v in (("smallest", y_lo), ("largest", y_hi)):
        if not (math.isfinite(v) and abs(v) <= MAX_ABS_VALUE):
            raise AnalysisError(
                f"the {name} value {v:g} is outside the fits' domain |value| <= "
                f"{MAX_ABS_VALUE:g} (series unit): squared residuals would overflow"
            )


def grid_start(x: NDArray[np.float64], z: NDArray[np.float64]) -> tuple[float, float, float]:
    """Best (offset, amplitude, log tau) on a log tau grid; linear least squares per tau."""
    log_taus = np.linspace(
        math.log(TAU_SEARCH_RANGE_S[0]), math.log(TAU_SEARCH_RANGE_S[1]), _GRID_POINTS
    )
    with np.errstate(under="ignore"):
        basis = np.exp(-x[None, :] / np.exp(log_taus)[:, None])  # (grid, n), in [0, 1]
    b_mean = basis.mean(axis=1)
    z_mean = float(z.mean())
    db = basis - b_mean[:, None]
    dz = z - z_mean
    var_b = np.einsum("ij,ij->i", db, db)
    cov_bz = db @ dz
    sst = float(dz @ dz)
    ok = var_b > 1e-12 * x.size
    slope = np.where(ok, cov_bz / np.where(ok, var_b, 1.0), 0.0)  # z ~ z_mean + slope * db
    ssr = np.where(ok, sst - slope * cov_bz, sst)
    best = int(np.argmin(ssr))
    amplitude = -float(slope[best])
    offset = z_mean + amplitude * float(b_mean[best])
    return offset, amplitude, float(log_taus[best])


def fit_recovery(
    times_s: ArrayLike,
    values: ArrayLike,
    t0_s: float,
    window_s: float = DEFAULT_WINDOW_S,
) -> RecoveryFit:
    """Fit y(t) = offset - amplitude * exp(-(t - T_0)/tau) over the recovery window.

    The samples with T_0 <= t <= T_0 + ``window_s`` are fitted by least squares
    (``scipy.optimize.least_squares``, trust-region reflective) in the parameters
    (offset, amplitude, ln tau), with ln tau bounded to :data:`TAU_SEARCH_RANGE_S` and the
    values scaled to [0, 1] for conditioning. The starting point is the best of a log-spaced
    grid of tau (for each tau, offset and amplitude follow from linear least squares), so the
    fit does not depend on a hand-made initial guess. Standard errors come from the Jacobian
    at the solution and the residual variance (n - 3 degrees of freedom); tau's via the
    delta method, se(tau) = tau * se(ln tau).

    Parameters
    ----------
    times_s : array_like
        Sample times [s], finite and strictly increasing.
    values : array_like
        Series to fit: S_k [px] (rising recovery, amplitude > 0) or a depth [mm] (falling,
        amplitude < 0). NaN/inf samples are dropped and flagged ``NON_FINITE_INPUT``.
    t0_s : float
        Start of the recovery T_0 [s] (the model's time origin).
    window_s : float
        Length of the fitted window after T_0 [s], > 0.

    Returns
    -------
    RecoveryFit
        Flagged ``CONSTANT_SERIES`` when the window's values do not vary,
        ``TIME_CONSTANT_OUTSIDE_WINDOW`` when tau is longer than the fitted span or shorter
        than the median sample interval, ``FIT_NOT_CONVERGED`` when the solver fails.

    Raises
    ------
    AnalysisError
        Bad shapes, non-finite or non-increasing times, non-finite T_0 or window, fewer than
        :data:`MIN_FIT_POINTS` finite samples in the window, or a value outside
        |value| <= :data:`MAX_ABS_VALUE`.
    """
    tw, yw, flags = fit_window(times_s, values, t0_s, window_s)
    n = int(tw.size)
    x = tw - t0_s
    y_lo = float(np.min(yw))
    check_value_domain(y_lo, float(np.max(yw)))
    y_span = float(np.max(yw)) - y_lo

    base = RecoveryFit(
        tau_s=None,
        amplitude=None,
        offset=None,
        tau_se_s=None,
        amplitude_se=None,
        offset_se=None,
        t0_s=float(t0_s),
        t_start_s=float(tw[0]),
        t_end_s=float(tw[-1]),
        n_points=n,
        rmse=0.0,
        r_squared=None,
        flags=frozenset(flags),
    )

    scale = max(abs(y_lo), abs(float(np.max(yw))))
    if y_span <= 1e-12 * scale or y_span == 0.0:
        flags.add(Flag.CONSTANT_SERIES)
        mean = float(np.mean(yw))
        rmse = float(np.sqrt(np.mean(np.square(yw - mean))))
        return replace(base, offset=mean, amplitude=0.0, rmse=rmse, flags=frozenset(flags))

    z = (yw - y_lo) / y_span
    p = solve_scaled(x, z)
    if p is None:
        flags.add(Flag.FIT_NOT_CONVERGED)
        return replace(base, flags=frozenset(flags))

    r = _residuals(p, x, z)
    ssr = float(r @ r)
    sst = float(np.sum(np.square(z - z.mean())))
    tau = math.exp(p[2])
    offset_se, amplitude_se, tau_se = _standard_errors(_jacobian(p, x, z), ssr, y_span, tau)
    # an integer series (S_k) is rounded: its settled level by up to half a count, which no
    # average of the rounded samples removes (docs/analysis.md, "Error model of the
    # intervals"); offset and amplitude (= offset - S_0) carry it
    quantum_var = 1.0 / 12.0 if bool(np.all(yw == np.round(yw))) else 0.0
    if offset_se is not None:
        offset_se = math.hypot(offset_se, math.sqrt(quantum_var))
    if amplitude_se is not None:
        amplitude_se = math.hypot(amplitude_se, math.sqrt(quantum_var))

    span = float(x[-1])
    frame = float(np.median(np.diff(tw))) if n > 1 else span
    if tau > span or tau < frame:
        flags.add(Flag.TIME_CONSTANT_OUTSIDE_WINDOW)
    if tau_se is None or not tau_se <= recovery_time_tolerance_s(tau, frame):
        flags.add(Flag.TIME_CONSTANT_UNCERTAIN)  # its own uncertainty exceeds its tolerance
    return replace(
        base,
        tau_s=tau,
        amplitude=y_span * float(p[1]),
        offset=y_lo + y_span * float(p[0]),
        tau_se_s=tau_se,
        amplitude_se=amplitude_se,
        offset_se=offset_se,
        rmse=y_span * math.sqrt(ssr / n),
        r_squared=1.0 - ssr / sst if sst > 0.0 else None,
        flags=frozenset(flags),
    )


def fit_window(
    times_s: ArrayLike, values: ArrayLike, t0_s: float, window_s: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], set[Flag]]:
    """Check :func:`fit_recovery`'s inputs; return the window's times [s], values and flags.

    The window holds the finite samples with T_0 <= t <= T_0 + ``window_s``; the flags are
    ``NON_FINITE_INPUT`` when any value (inside the window or not) was dropped.

    Raises
    ------
    AnalysisError
        As listed in :func:`fit_recovery`, except the values' range overflow.
    """
    t = np.asarray(times_s, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if t.ndim != 1 or t.shape != y.shape:
        raise AnalysisError(
            f"times_s and values must be one-dimensional and of equal length, got shapes "
            f"{t.shape} and {y.shape}"
        )
    bad_t = np.flatnonzero(~np.isfinite(t))
    if bad_t.size:
        raise AnalysisError(f"times_s[{bad_t[0]}] is {t[bad_t[0]]}: sample times must be finite")
    if t.size > 1 and np.any(~(np.diff(t) > 0.0)):
        i = int(np.flatnonzero(~(np.diff(t) > 0.0))[0]) + 1
        raise AnalysisError(f"times_s must be strictly increasing (at index {i})")
    if not math.isfinite(t0_s):
        raise AnalysisError(f"t0_s must be finite, got {t0_s}")
    if not (math.isfinite(window_s) and window_s > 0.0):
        raise AnalysisError(f"window_s must be finite and > 0, got {window_s}")

    flags: set[Flag] = set()
    finite = np.isfinite(y)
    if not finite.all():
        flags.add(Flag.NON_FINITE_INPUT)
    keep = finite & (t >= t0_s) & (t <= t0_s + window_s)
    tw, yw = t[keep], y[keep]
    if tw.size < MIN_FIT_POINTS:
        raise AnalysisError(
            f"need at least {MIN_FIT_POINTS} finite samples in the fit window "
            f"[{t0_s}, {t0_s + window_s}] s, got {int(tw.size)}"
        )
    return tw, yw, flags


def _decay(p: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """exp(-x / tau) with tau = exp(p[2]); x = t - T_0 [s]."""
    with np.errstate(under="ignore"):
        out: NDArray[np.float64] = np.exp(-x * math.exp(-p[2]))
    return out


def _residuals(
    p: NDArray[np.float64], x: NDArray[np.float64], z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Model minus data on the scaled values z, p = (offset, amplitude, ln tau)."""
    out: NDArray[np.float64] = p[0] - p[1] * _decay(p, x) - z
    return out


def _jacobian(
    p: NDArray[np.float64], x: NDArray[np.float64], z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Jacobian of :func:`_residuals` in p, shape (n, 3); ``z`` is unused (solver's args)."""
    e = _decay(p, x)
    jac = np.empty((x.size, 3))
    jac[:, 0] = 1.0
    jac[:, 1] = -e
    with np.errstate(under="ignore"):
        jac[:, 2] = -p[1] * e * x * math.exp(-p[2])
    return jac


def solve_scaled(x: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Least-squares (offset, amplitude, ln tau) of the scaled values z; None if not converged.

    Starts at the best point of :func:`grid_start` (ln tau clipped to
    :data:`TAU_SEARCH_RANGE_S`) and runs the trust-region reflective solver within it.
    """
    start = grid_start(x, z)
    lo_u, hi_u = math.log(TAU_SEARCH_RANGE_S[0]), math.log(TAU_SEARCH_RANGE_S[1])
    x_start = np.array([start[0], start[1], min(max(start[2], lo_u), hi_u)])
    from scipy.optimize import least_squares  # scipy: imported where used

    sol = least_squares(
        _residuals,
        x_start,
        jac=_jacobian,
        bounds=([-np.inf, -np.inf, lo_u], [np.inf, np.inf, hi_u]),
        method="trf",
        x_scale="jac",
        max_nfev=200,
        args=(x, z),
    )
    p = np.asarray(sol.x, dtype=np.float64)
    if not sol.success or not np.all(np.isfinite(p)):
        return None
    return p


def _standard_errors(
    jac: NDArray[np.float64], ssr: float, y_span: float, tau_s: float
) -> tuple[float | None, float | None, float | None]:
    """Standard errors of (offset, amplitude, tau [s]) in the values' units.

    From the Jacobian at the solution and the residual variance ``ssr / (n - 3)`` of the
    scaled fit; tau's by the delta method, se(tau) = tau * se(ln tau). None where a
    parameter is (nearly) undetermined by the data or the error is not finite.
    """
    se: list[float | None] = [None, None, None]
    sv = np.linalg.svd(jac, compute_uv=False)
    if sv[-1] > 1e-6 * sv[0]:  # otherwise a parameter is (nearly) undetermined by the data
        cov = np.linalg.inv(jac.T @ jac) * (ssr / (jac.shape[0] - 3))
        diag = np.diag(cov)
        se = [math.sqrt(v) if math.isfinite(v) and v >= 0.0 else None for v in diag]
    offset_se = None if se[0] is None else y_span * se[0]
    amplitude_se = None if se[1] is None else y_span * se[1]
    tau_se = None if se[2] is None else tau_s * se[2]
    if tau_se is not None and not math.isfinite(tau_se):
        tau_se = None
    return offset_se, amplitude_se, tau_se
