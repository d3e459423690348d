"""Every tissue model over its whole parameter domain: remaining(t) finite, in [0, 1],
non-increasing, 1 at t = 0; the recovery times finite; no warning (numpy's included)."""

from __future__ import annotations

import math
import warnings

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.tissue import build_tissue_model, known_tissue_models, tissue_model_class
from stipi_daemon.sim.tissue.base import Parameter


def _value(p: Parameter) -> st.SearchStrategy[float]:
    """Values across the domain: its edges, and log-uniform (times) or uniform draws."""
    edges = [v for v, inside in ((p.lower, p.lower_inclusive), (p.upper, p.upper_inclusive))]
    if p.lower > 0.0:
        lo, hi = math.log10(p.lower), math.log10(p.upper)
        inner = st.floats(lo, hi).map(lambda e: min(max(10.0**e, p.lower), p.upper))
    else:
        inner = st.floats(p.lower, p.upper)
    return st.one_of(st.sampled_from(edges), inner)


@st.composite
def models(draw: st.DrawFn) -> tuple[str, dict[str, float]]:
    name = draw(st.sampled_from(known_tissue_models()))
    params = {p.name: draw(_value(p)) for p in tissue_model_class(name).PARAMETERS}
    if name == "zener":
        # Joint domain tau_epsilon < tau_sigma: draw the ratio in [0, 1).
        ratio = draw(st.one_of(st.just(0.0), st.floats(0.0, 1.0, exclude_max=True)))
        params["tau_epsilon_s"] = ratio * params["tau_sigma_s"]
    return name, params


TIMES = st.lists(
    st.one_of(
        st.just(0.0),
        st.floats(0.0, 1e-6),
        st.floats(-9.0, 7.5).map(lambda e: 10.0**e),
        st.just(1e300),
    ),
    min_size=1,
    max_size=30,
)


@given(models(), TIMES, st.floats(0.0, 1.0, exclude_max=True))
def test_every_model_is_finite_bounded_and_monotone(
    spec: tuple[str, dict[str, float]], times: list[float], fraction: float
) -> None:
    name, params = spec
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(all="raise"):
            model = build_tissue_model(name, params)
            t = np.sort(np.asarray(times, dtype=np.float64))
            r = model.remaining(t)
            assert r.shape == t.shape
            assert np.all(np.isfinite(r)), (model, t, r)
            assert np.all((r >= 0.0) & (r <= 1.0)), (model, t, r)
            assert np.all(np.diff(r) <= 1e-15), (model, t, r)
            assert float(model.remaining(0.0)) == 1.0
            tau = model.effective_time_constant_s()
            try:
                t_f = model.time_to_recover(fraction)
            except ConfigError as exc:  # a typed error, only where the time overflows
                assert name == "power_law" and "reached only after more than" in str(exc)
                assert params["exponent_n"] * 650.0 < -math.log1p(-fraction)
                return
            assert math.isfinite(tau) and tau >= 0.0, model
            assert math.isfinite(t_f) and t_f >= 0.0, (model, fraction)
            if t_f > 0.0 and fraction > 0.0:
                # Not reached before t_f (up to the root's tolerance).
                assert float(model.recovered(t_f * (1 - 1e-9))) <= fraction + 1e-9
