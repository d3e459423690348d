"""Common ground of the recovery models: parameters with units and bounds, the model API,
and the least-squares solvers every model shares.

A recovery model is a curve ``y(t) = offset - amplitude * g(t - T_0; theta)`` where
``g`` is the model's *remaining fraction* of the recovery (1 at T_0, decreasing to 0, as
the simulator's tissue models define it) and ``offset`` (y at infinity) and ``amplitude``
(y(inf) - y(T_0)) are in the unit of the fitted series (S_k [px] or depth [mm]). Only the
shape parameters ``theta`` differ between models. This module owns:

* :class:`ModelParameter` (name with unit, bounds, meaning) and :class:`RecoveryModel`
  (what each model module implements: its shape ``g`` and derivatives in the solver's
  coordinates, a start-value rule, the time at which ``g`` falls to a level);
* :func:`solve_scaled` (one fit, ``scipy.optimize.least_squares``, trust-region
  reflective) and :func:`solve_batch` (many refits at once for the bootstrap: a projected
  Levenberg-Marquardt iteration vectorised over replicates, checked against
  ``least_squares`` in the tests).

Coordinates. Fits work on the series scaled to [0, 1] (``z = (y - min y) / range``) and on
transformed shape parameters ``u`` (log of a time, log of an exponent, a weight as is),
each bounded by :attr:`ModelParameter.lower`/``upper`` mapped through the transform, so
that no exponential can overflow: every time lies in ``TAU_SEARCH_RANGE_S`` = [1e-3, 1e4] s.
It computes no model itself and does no I/O.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.analysis.recovery_fit import TAU_SEARCH_RANGE_S
from stipi_daemon.errors import AnalysisError

__all__ = [
    "LINEAR_PARAMETERS",
    "TAU_SEARCH_RANGE_S",
    "FloatArray",
    "ModelParameter",
    "RecoveryModel",
    "linear_least_squares_grid",
    "solve_batch",
    "solve_scaled",
    "time_parameter",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ModelParameter:
    """One fitted parameter of a recovery model.

    Attributes
    ----------
    name : str
        Key in the results (``summary.json``), ending in its unit (``_s``) where it has one.
    unit : str
        ``"s"``, ``"1"`` (dimensionless) or ``"series"`` (the fitted series' unit: px for
        S_k, mm for a depth).
    description : str
        What it is, in one line.
    lower, upper : float
        Bounds of the search (``-inf``/``inf`` for the linear ``offset`` and ``amplitude``).
    transform : {"log", "linear"}
        Solver coordinate: ``log`` fits ln(value) (positive parameters), ``linear`` the
        value itself.
    """

    name: str
    unit: str
    description: str
    lower: float
    upper: float
    transform: Literal["log", "linear"] = "linear"

    def to_solver(self, value: float) -> float:
        """The value in solver coordinates."""
        return math.log(value) if self.transform == "log" else float(value)

    def from_solver(self, u: FloatArray) -> FloatArray:
        """Solver coordinates back to the value (array)."""
        if self.transform == "log":
            with np.errstate(over="ignore", under="ignore"):
                out: FloatArray = np.exp(u)
            return out
        return np.asarray(u, dtype=np.float64)

    @property
    def solver_bounds(self) -> tuple[float, float]:
        """(lower, upper) in solver coordinates."""
        if self.transform == "log":
            return math.log(self.lower), math.log(self.upper)
        return self.lower, self.upper


def time_parameter(name: str, description: str) -> ModelParameter:
    """A time [s] searched over :data:`TAU_SEARCH_RANGE_S` in log coordinates."""
    return ModelParameter(name, "s", description, *TAU_SEARCH_RANGE_S, transform="log")


#: The two linear parameters every model shares (first in every parameter list).
LINEAR_PARAMETERS: tuple[ModelParameter, ModelParameter] = (
    ModelParameter("offset", "series", "settled value y(inf)", -math.inf, math.inf),
    ModelParameter("amplitude", "series", "recovered amount y(inf) - y(T_0)", -math.inf, math.inf),
)


class RecoveryModel(ABC):
    """A recovery model: ``y(t) = offset - amplitude * g(t - T_0; theta)`` (module docstring).

    Subclasses set the class attributes and implement :meth:`shape`, :meth:`start` and
    :meth:`time_to_remaining`. Instances carry no state: the registry holds one each.
    """

    #: Registry name (a key of ``summary.json``'s ``recovery_models``).
    NAME: ClassVar[str]
    #: Human-readable name.
    TITLE: ClassVar[str]
    #: The remaining fraction g(x), x = t - T_0 [s], in plain text.
    EQUATION: ClassVar[str]
    #: Literature source.
    SOURCE: ClassVar[str]
    #: Shape parameters theta (after offset and amplitude), in solver order.
    SHAPE_PARAMETERS: ClassVar[tuple[ModelParameter, ...]]
    #: What its effective time constant (1 - 1/e of the recovery done) is, in words.
    TAU_MEANING: ClassVar[str]

    @property
    def parameters(self) -> tuple[ModelParameter, ...]:
        """Every parameter: offset, amplitude, then the shape parameters."""
        return (*LINEAR_PARAMETERS, *self.SHAPE_PARAMETERS)

    @property
    def n_parameters(self) -> int:
        """Parameters of the curve (the noise variance not counted)."""
        return 2 + len(self.SHAPE_PARAMETERS)

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """Solver-coordinate bounds of (offset, amplitude, u...)."""
        lo = [-np.inf, -np.inf] + [p.solver_bounds[0] for p in self.SHAPE_PARAMETERS]
        hi = [np.inf, np.inf] + [p.solver_bounds[1] for p in self.SHAPE_PARAMETERS]
        return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    def natural(self, u: FloatArray) -> dict[str, float]:
        """Shape parameters by name from solver coordinates ``u`` (one set)."""
        return {
            p.name: float(p.from_solver(np.asarray(ui)))
            for p, ui in zip(self.SHAPE_PARAMETERS, u, strict=False)
        }

    def canonical(self, u: FloatArray) -> FloatArray:
        """One representative of equivalent solver points (override to order terms)."""
        return u

    def nested_start(self, kelvin_voigt: FloatArray) -> FloatArray | None:
        """The point of this model that is (nearly) the Kelvin-Voigt fit ``kelvin_voigt``
        = (offset, amplitude, ln tau), if the model contains Kelvin-Voigt; else None."""
        return None

    @abstractmethod
    def shape(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        """g and dg/du for a batch of parameter sets.

        Parameters
        ----------
        x : ndarray, shape (n,)
            Times since T_0 [s], >= 0.
        u : ndarray, shape (B, m)
            Shape parameters in solver coordinates, inside :meth:`bounds`.

        Returns
        -------
        g : ndarray, shape (B, n)
            Remaining fraction in [0, 1].
        dg : ndarray, shape (B, n, m)
            Its derivative in u (finite).
        """

    @abstractmethod
    def start(self, x: FloatArray, z: FloatArray) -> FloatArray:
        """Start-value rule: (offset, amplitude, u...) for the scaled series z (in [0, 1])."""

    @abstractmethod
    def time_to_remaining(self, u: FloatArray, level: float) -> float:
        """Earliest x [s] with g(x) = ``level`` in (0, 1); finite or ``inf``."""

    def curve(self, t_s: ArrayLike, t0_s: float, **parameters: float) -> FloatArray:
        """The model as a pure function of time: offset - amplitude * g(t - T_0).

        Parameters
        ----------
        t_s : array_like
            Times [s], finite and >= ``t0_s``.
        t0_s : float
            T_0 [s].
        **parameters : float
            Every name of :attr:`parameters` (offset and amplitude in the series' unit).

        Raises
        ------
        AnalysisError
            A time before T_0 or non-finite, a parameter missing, unknown or outside its
            bounds.
        """
        names = [p.name for p in self.parameters]
        if sorted(parameters) != sorted(names):
            raise AnalysisError(
                f"{self.NAME}: parameters must be {', '.join(names)}, got "
                f"{', '.join(sorted(parameters))}"
            )
        for p in self.parameters:
            v = float(parameters[p.name])
            if not (math.isfinite(v) and p.lower <= v <= p.upper):
                raise AnalysisError(
                    f"{self.NAME}: {p.name} = {v} is outside [{p.lower:g}, {p.upper:g}]"
                )
        x = np.asarray(t_s, dtype=np.float64) - float(t0_s)
        if np.any(~(x >= 0.0)):
            raise AnalysisError(f"{self.NAME}: times must be finite and >= t0_s = {t0_s} s")
        u = np.asarray(
            [[p.to_solver(float(parameters[p.name])) for p in self.SHAPE_PARAMETERS]],
            dtype=np.float64,
        )
        g, _ = self.shape(x.ravel(), u)
        out: FloatArray = parameters["offset"] - parameters["amplitude"] * g[0].reshape(x.shape)
        return out

    def residuals_batch(
        self, p: FloatArray, x: FloatArray, z: FloatArray, *, with_jacobian: bool = True
    ) -> tuple[FloatArray, FloatArray | None]:
        """Residuals model - z, shape (B, n), and their Jacobian (B, n, 2 + m)."""
        g, dg = self.shape(x, p[:, 2:])
        r: FloatArray = p[:, :1] - p[:, 1:2] * g - z
        if not with_jacobian:
            return r, None
        jac = np.empty((*g.shape, p.shape[1]))
        jac[:, :, 0] = 1.0
        jac[:, :, 1] = -g
        jac[:, :, 2:] = -p[:, 1, None, None] * dg
        return r, jac


def linear_least_squares_grid(
    basis: FloatArray, z: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Least squares of z on ``1 - basis`` for every candidate shape (variable projection).

    Parameters
    ----------
    basis : ndarray, shape (G, n)
        g(x) of G candidate shapes.
    z : ndarray, shape (n,)
        Scaled series.

    Returns
    -------
    ssr, offset, amplitude : ndarray, shape (G,)
        Residual sum of squares and the linear parameters of each candidate (a candidate
        whose g barely varies gets amplitude 0 and the mean as offset).
    """
    n = z.size
    b_mean = basis.mean(axis=1)
    z_mean = float(z.mean())
    db = basis - b_mean[:, None]
    dz = z - z_mean
    var_b = np.einsum("ij,ij->i", db, db)
    cov_bz = db @ dz
    sst = float(dz @ dz)
    ok = var_b > 1e-12 * n
    slope = np.where(ok, cov_bz / np.where(ok, var_b, 1.0), 0.0)
    ssr = np.maximum(np.where(ok, sst - slope * cov_bz, sst), 0.0)
    amplitude = -slope
    offset = z_mean + amplitude * b_mean
    return ssr, offset, amplitude


def solve_scaled(
    model: RecoveryModel, x: FloatArray, z: FloatArray, start: FloatArray
) -> FloatArray | None:
    """Least-squares (offset, amplitude, u...) of the scaled series z; None if not converged.

    Trust-region reflective (``scipy.optimize.least_squares``) within :meth:`~RecoveryModel.
    bounds`, analytic Jacobian, from ``start`` (clipped into the bounds).
    """
    lo, hi = model.bounds()
    x0 = np.clip(np.asarray(start, dtype=np.float64), lo, hi)
    # trf needs a strictly interior start.
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    x0 = np.clip(x0, lo + 1e-10 * span, hi - 1e-10 * span)

    def fun(p: FloatArray) -> FloatArray:
        r, _ = model.residuals_batch(p[None, :], x, z[None, :], with_jacobian=False)
        out: FloatArray = r[0]
        return out

    def jac(p: FloatArray) -> FloatArray:
        j = model.residuals_batch(p[None, :], x, z[None, :])[1]
        assert j is not None
        out: FloatArray = j[0]
        return out

    from scipy.optimize import least_squares  # scipy: imported where used

    sol = least_squares(
        fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=400
    )
    p = np.asarray(sol.x, dtype=np.float64)
    if not sol.success or not np.all(np.isfinite(p)):
        return None
    return np.concatenate([p[:2], model.canonical(p[2:])])


def _damped_step(
    jac: FloatArray,
    r: FloatArray,
    lam: FloatArray,
    p: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
) -> FloatArray:
    """Levenberg-Marquardt steps of a batch, parameters pinned at a bound held there.

    A parameter at a bound whose unconstrained step points outward is fixed (its row and
    column of the system replaced by the identity, its gradient by 0) and the step solved
    again, so the free parameters still move (projected Levenberg-Marquardt).
    """
    jt = jac.transpose(0, 2, 1)
    a = jt @ jac  # (B, m, m)
    grad = (jt @ r[:, :, None])[:, :, 0]
    m = a.shape[1]
    diag = np.einsum("bii->bi", a)
    floor = 1e-12 * np.maximum(diag.max(axis=1, keepdims=True), 1e-300)
    eye = np.eye(m)[None]
    system = a + (lam[:, None] * np.maximum(diag, floor) + floor)[:, :, None] * eye
    step = np.linalg.solve(system, -grad[:, :, None])[:, :, 0]
    pinned = ((p <= lo) & (step < 0.0)) | ((p >= hi) & (step > 0.0))
    if pinned.any():
        keep = ~pinned
        mask = keep[:, :, None] & keep[:, None, :]
        system = np.where(mask, system, 0.0) + pinned[:, :, None] * eye
        step = np.linalg.solve(system, np.where(keep, -grad, 0.0)[:, :, None])[:, :, 0]
    return step


def solve_batch(
    model: RecoveryModel,
    x: FloatArray,
    z: FloatArray,
    start: FloatArray,
    *,
    max_iterations: int = 100,
    tolerance: float = 1e-6,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Refit B series at once: projected Levenberg-Marquardt, vectorised over replicates.

    Each replicate b minimises ``||model(p_b) - z_b||^2`` from ``start`` (the point
    estimate; replicates differ from it by noise, so few iterations are needed). A step
    solves ``(J^T J + lambda diag(J^T J)) d = -J^T r`` (Marquardt's scaling; a floor of
    1e-12 times the largest diagonal keeps it positive definite when a parameter is
    undetermined, e.g. the weight of two equal time constants), with parameters pinned at a
    bound held there (:func:`_damped_step`), is clipped to the bounds and kept only when it
    lowers the cost; lambda shrinks tenfold after a kept step and grows tenfold otherwise.
    A replicate has converged when a step (kept or not) changes its cost by less than
    ``tolerance`` relative, or when lambda reaches 1e10 without a lower cost (no descent
    left: a minimum, possibly on a bound). The default 1e-6 is precise enough for an
    interval: a cost within 1e-6 of the minimum puts a parameter within
    sqrt(1e-6 n) ~ 0.1 of its standard error of the optimum for n <= 10^4 samples.

    Parameters
    ----------
    model : RecoveryModel
    x : ndarray, shape (n,)
        Times since T_0 [s].
    z : ndarray, shape (B, n)
        Scaled series.
    start : ndarray, shape (2 + m,)
        Start for every replicate (solver coordinates).

    Returns
    -------
    p : ndarray, shape (B, 2 + m)
        Solutions (canonical).
    converged : ndarray of bool, shape (B,)
    """
    lo, hi = model.bounds()
    b = z.shape[0]
    p = np.tile(np.clip(start, lo, hi), (b, 1))
    lam = np.full(b, 1e-5)
    done = np.zeros(b, dtype=bool)
    r, jac = model.residuals_batch(p, x, z)
    assert jac is not None
    cost = np.einsum("bn,bn->b", r, r)
    for _ in range(max_iterations):
        idx = np.flatnonzero(~done)
        if idx.size == 0:
            break
        step = _damped_step(jac[idx], r[idx], lam[idx], p[idx], lo, hi)
        trial = np.clip(p[idx] + step, lo, hi)
        r_new, j_new = model.residuals_batch(trial, x, z[idx])
        assert j_new is not None
        cost_new = np.einsum("bn,bn->b", r_new, r_new)
        better = np.isfinite(cost_new) & (cost_new < cost[idx])
        change = np.where(np.isfinite(cost_new), np.abs(cost[idx] - cost_new), np.inf)
        kept = idx[better]
        if kept.size:
            p[kept] = trial[better]
            r[kept], jac[kept] = r_new[better], j_new[better]
            cost[kept] = cost_new[better]
        lam[idx] = np.where(better, lam[idx] / 10.0, lam[idx] * 10.0)
        converged = (change <= tolerance * np.maximum(cost[idx], 1e-300)) | (cost[idx] == 0.0)
        converged |= ~better & (lam[idx] >= 1e10)
        done[idx[converged]] = True
    out = np.empty_like(p)
    out[:, :2] = p[:, :2]
    for i in range(b):
        out[i, 2:] = model.canonical(p[i, 2:])
    return out, done
