"""Every registered recovery model states its equation, parameters (units, bounds) and source,
and its curve is a pure function of time that stays finite inside its bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.recovery_models import MODELS, known_models
from stipi_daemon.analysis.recovery_models.base import LINEAR_PARAMETERS
from stipi_daemon.errors import AnalysisError

UNITS = {"s", "1", "series"}


def test_registry_lists_kelvin_voigt_first_and_three_models() -> None:
    assert known_models() == ("kelvin_voigt", "two_exponential", "power_law")


@pytest.mark.parametrize("name", known_models())
def test_model_metadata(name: str) -> None:
    model = MODELS[name]
    assert model.NAME == name
    assert model.TITLE and model.TAU_MEANING
    assert "g(x) =" in model.EQUATION
    assert any(ch.isdigit() for ch in model.SOURCE) and "(" in model.SOURCE  # a dated source
    doc = type(model).__module__
    module_doc = __import__(doc, fromlist=["x"]).__doc__ or ""
    assert "Source:" in module_doc
    # The module docstring shows the equation's right-hand side.
    rhs = model.EQUATION.split("=", 1)[1].split(";")[0].strip()
    assert rhs.replace(" ", "") in module_doc.replace(" ", "").replace("\n", "")
    assert model.parameters[:2] == LINEAR_PARAMETERS
    names = [p.name for p in model.parameters]
    assert len(set(names)) == len(names)
    for p in model.SHAPE_PARAMETERS:
        assert p.unit in UNITS and p.description
        assert math.isfinite(p.lower) and math.isfinite(p.upper) and p.lower < p.upper
        assert (p.unit == "s") == p.name.endswith("_s"), p.name
        if p.transform == "log":
            assert p.lower > 0.0
    assert model.n_parameters == len(model.parameters)


@pytest.mark.parametrize("name", known_models())
def test_curve_is_finite_at_every_corner_of_the_bounds(name: str) -> None:
    model = MODELS[name]
    t = np.concatenate([[10.0], 10.0 + np.logspace(-6, 4, 50)])
    corners = np.array(
        np.meshgrid(*[[p.lower, p.upper] for p in model.SHAPE_PARAMETERS])
    ).T.reshape(-1, len(model.SHAPE_PARAMETERS))
    for c in corners:
        params = {"offset": 1.0, "amplitude": 1.0}
        params |= {p.name: float(v) for p, v in zip(model.SHAPE_PARAMETERS, c, strict=True)}
        y = model.curve(t, 10.0, **params)
        assert np.all(np.isfinite(y)) and np.all(y >= -1e-12) and np.all(y <= 1.0 + 1e-12)
        assert y[0] == pytest.approx(0.0, abs=1e-12)  # g(0) = 1
        u = np.array(
            [p.to_solver(float(v)) for p, v in zip(model.SHAPE_PARAMETERS, c, strict=True)]
        )
        tau = model.time_to_remaining(u, math.exp(-1.0))
        assert tau > 0.0 and not math.isnan(tau)


@pytest.mark.parametrize("name", known_models())
def test_curve_refuses_bad_input(name: str) -> None:
    model = MODELS[name]
    good = {"offset": 1.0, "amplitude": 1.0} | {
        p.name: p.lower if p.transform == "linear" else math.sqrt(p.lower * p.upper)
        for p in model.SHAPE_PARAMETERS
    }
    with pytest.raises(AnalysisError, match="t0_s"):
        model.curve([0.0, 1.0], 0.5, **good)
    with pytest.raises(AnalysisError, match="parameters must be"):
        model.curve([1.0], 0.0, offset=1.0)
    first = model.SHAPE_PARAMETERS[0]
    with pytest.raises(AnalysisError, match=first.name):
        model.curve([1.0], 0.0, **(good | {first.name: first.upper * 10}))


def test_kelvin_voigt_curve_is_recovery_fit_equation() -> None:
    from stipi_daemon.analysis.recovery_fit import kelvin_voigt_recovery

    t = np.linspace(2.0, 50.0, 30)
    a = MODELS["kelvin_voigt"].curve(t, 2.0, offset=5.0, amplitude=3.0, tau_s=4.0)
    assert np.allclose(a, kelvin_voigt_recovery(t, 2.0, 5.0, 3.0, 4.0), rtol=1e-14)
