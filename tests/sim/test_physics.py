"""Closed-form mechanics: Kelvin-Voigt ODE, Eqs. (4)/(5)/(7) consistency, resolution scaling."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.scene import Scene, TissueSpec, load_scene

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"


def _scene(e_kpa: float, tau_s: float, loading_tau_s: float | None = None) -> Scene:
    base = load_scene(SCENES / "grade3.yaml")
    tissue = TissueSpec(e_kpa=e_kpa, tau_s=tau_s, loading_tau_s=loading_tau_s)
    return base.model_copy(update={"tissue": tissue})


@settings(max_examples=30, deadline=None)
@given(e=st.floats(150.0, 400.0), tau=st.floats(0.2, 30.0))
def test_kelvin_voigt_ode_holds(e: float, tau: float) -> None:
    m = SceneModel(_scene(e, tau))
    k = m.stiffness_n_per_mm
    fp = m.scene.force_profile
    # Pitting phase: c D' + k D = F_a(t), away from the breakpoints (end of the approach,
    # the release at T_0).
    t = np.linspace(fp.pre_s + fp.approach_s + 0.2, m.t0_s - 0.2, 50)
    h = 1e-5
    d_dot = (m.depth_mm(t + h) - m.depth_mm(t - h)) / (2 * h)
    lhs = k * tau * d_dot + k * m.depth_mm(t)
    np.testing.assert_allclose(lhs, m.applied_force_profile_n(t), rtol=1e-5, atol=1e-5)
    # Recovery: c D' + k D = F(t) (the tip force), and F = F_0 + k_p (D_p - D).
    t = np.linspace(m.t0_s + 0.01, m.t0_s + 45.0, 50)
    d_dot = (m.depth_mm(t + h) - m.depth_mm(t - h)) / (2 * h)
    lhs = k * tau * d_dot + k * m.depth_mm(t)
    np.testing.assert_allclose(lhs, m.tip_force_n(t), rtol=1e-5, atol=1e-5)
    kp = m.tip_stiffness_n_per_mm
    np.testing.assert_allclose(
        m.tip_force_n(t), m.f0_n + kp * (m.depth_at_release_mm - m.depth_mm(t)), rtol=1e-9
    )


def test_s0_encodes_depth_and_s_is_continuous_at_release() -> None:
    m = SceneModel(load_scene(SCENES / "grade2.yaml"))
    cal = m.calibration
    s0 = float(m.occluded_area_px(np.asarray([m.t0_s]))[0])
    assert s0 == pytest.approx(m.s0_px, rel=1e-12)
    assert cal.depth_change_mm(s0) == pytest.approx(12.0 - m.depth_at_release_mm, rel=1e-12)
    after = float(m.occluded_area_px(np.asarray([m.t0_s + 1e-9]))[0])
    assert after == pytest.approx(s0, rel=1e-6)
    # S follows Eq. (5) of the tip force during recovery.
    t = np.linspace(m.t0_s, m.end_s, 11)
    np.testing.assert_allclose(
        m.occluded_area_px(t), cal.c1_px + cal.c2_px_per_n * m.tip_force_n(t), rtol=1e-12
    )


def test_eq7_recovers_modulus_after_full_creep() -> None:
    m = SceneModel(_scene(221.35, 8.0, loading_tau_s=0.5))
    e = 3e3 / (math.pi**2 * m.indenter_radius_mm) * m.applied_force_n / m.depth_at_release_mm
    assert e == pytest.approx(221.35, rel=1e-9)


def test_incomplete_creep_raises_eq7_modulus() -> None:
    m = SceneModel(_scene(200.0, 20.0))
    creep = m.depth_at_release_mm * m.stiffness_n_per_mm / m.applied_force_n
    # The linear approach loads as a step at its middle, to first order.
    fp = m.scene.force_profile
    loaded_s = fp.hold_s + fp.approach_s / 2
    assert creep == pytest.approx(1 - math.exp(-loaded_s / 20.0), rel=0.02)


def test_calibration_scales_with_pixel_area() -> None:
    base = load_scene(SCENES / "grade3.yaml")
    m1 = SceneModel(base)
    m2 = SceneModel(base.with_camera(width=1280, height=720))
    assert m2.area_scale == pytest.approx(2.25)
    assert m2.s0_px == pytest.approx(2.25 * m1.s0_px, rel=1e-12)
    assert m2.depth_at_release_mm == m1.depth_at_release_mm
    assert m2.calibration.depth_change_mm(m2.s0_px) == pytest.approx(
        m1.calibration.depth_change_mm(m1.s0_px), rel=1e-12
    )


def test_depth_beyond_calibration_is_config_error() -> None:
    with pytest.raises(ConfigError, match=r"probe\.calibration"):
        SceneModel(_scene(2000.0, 1.0, loading_tau_s=0.5))
    with pytest.raises(ConfigError, match="outside"):
        SceneModel(_scene(20.0, 1.0, loading_tau_s=0.5))
