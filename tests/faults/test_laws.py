"""The literature laws, the test's renderer and the law group's truth, without the daemon:
each checked against a closed form or limit of its own (issue 37)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.analysis.imaging import occluded_pixel_count
from stipi_daemon.sim.scene import parse_scene

from .law_matrix import PIT, LawCase, law_cases, law_truth, world_of
from .laws import (
    FrameRenderer,
    Optics,
    Tissue,
    crossing_s,
    findley_recovered,
    kv_recovered,
    kww_recovered,
    sls_recovered,
    terzaghi_recovered,
)
from .matrix import TOLERANCES


def test_terzaghi_series_starts_at_zero_and_ends_on_its_first_term() -> None:
    # U(0+) -> 0 (the coefficients 8 / ((2n+1)^2 pi^2) sum to 1); late, only n = 0 is left
    assert terzaghi_recovered(np.asarray([1e-4]), 25.0)[0] == pytest.approx(0.0, abs=0.01)
    t = np.asarray([40.0, 80.0])
    one_term = 1.0 - 8.0 / math.pi**2 * np.exp(-(math.pi**2) * t / (4.0 * 25.0))
    assert terzaghi_recovered(t, 25.0) == pytest.approx(one_term, rel=1e-9)
    # early: U ~ 2 sqrt(t / (pi tau_p)) (the semi-infinite solution's limit)
    early = terzaghi_recovered(np.asarray([0.05]), 25.0, terms=2000)[0]
    assert early == pytest.approx(2.0 * math.sqrt(0.05 / (math.pi * 25.0)), rel=0.01)


def test_findley_recovery_limits() -> None:
    t1, n = 15.0, 0.3
    assert findley_recovered(np.asarray([0.0]), t1, n)[0] == 0.0
    late = np.asarray([1e5])
    # (t1 + t)^n - t^n ~ n t1 t^(n - 1) for t >> t1
    expected = 1.0 - n * t1 * late ** (n - 1.0) / t1**n
    assert findley_recovered(late, t1, n) == pytest.approx(expected, rel=1e-4)
    grid = np.linspace(0.0, 105.0, 1001)
    assert np.all(np.diff(findley_recovered(grid, t1, n)) > 0.0)


def test_kww_with_beta_one_is_kelvin_voigt_and_sls_jumps_at_the_release() -> None:
    t = np.linspace(0.0, 50.0, 11)
    assert kww_recovered(t, 7.0, 1.0) == pytest.approx(kv_recovered(t, 7.0))
    r = sls_recovered(np.asarray([0.0, 1e-9, 8.0]), 8.0, 0.5)
    assert r[0] == 0.0 and r[1] == pytest.approx(0.5)
    assert r[2] == pytest.approx(0.5 + 0.5 * (1.0 - math.exp(-1.0)))


def test_crossing_of_an_exponential() -> None:
    tis = Tissue("kv", tau_s=5.0, s0_px=0.0, s_inf_px=1000.0)
    # S = 1000 (1 - exp(-t / 5)) reaches 500 at 5 ln 2
    assert crossing_s(tis.area_px, 500.0, 60.0) == pytest.approx(5.0 * math.log(2.0), abs=2e-6)


@pytest.mark.parametrize("s_px", [0.0, 1.0, 1215.0, 4462.5, 10375.0])
def test_renderer_draws_round_s_pixels_below_the_threshold(s_px: float) -> None:
    frame = FrameRenderer(Optics()).frame(0, 0.0, s_px)
    assert occluded_pixel_count(frame, 128) - occluded_pixel_count(
        FrameRenderer(Optics()).frame(0, 0.0, 0.0), 128
    ) == round(s_px)


def test_camera_effects_do_what_they_are_named() -> None:
    s = 2000.0
    clean = FrameRenderer(Optics()).frame(0, 0.0, s).astype(float)
    trough = 0.25 / 13.0  # sin = 1: the flicker's trough
    dim = FrameRenderer(Optics(flicker_depth=0.4)).frame(0, trough, s).astype(float)
    assert dim.max() == pytest.approx(0.6 * clean.max(), abs=1.0)
    noisy = FrameRenderer(Optics(noise_sigma=20.0)).frame(3, 0.0, s).astype(float)
    inside = (clean > 100) & (clean < 255)
    assert np.std((noisy - clean)[inside]) == pytest.approx(20.0, rel=0.05)
    saturated = FrameRenderer(Optics(gain=4.0)).frame(0, 0.0, s)
    assert np.all(saturated[clean > 50] == 255)
    vig = FrameRenderer(Optics(vignetting=0.6)).frame(0, 0.0, s)
    assert vig[120, 160] == 70 and vig[120, 160 + 105] < 128  # the rim falls below p


def test_truth_of_the_kelvin_voigt_control_is_its_closed_form() -> None:
    case = next(c for c in law_cases() if c.name == "law-kv-control")
    scene = parse_scene(case.scene_doc(), case.name)
    t = law_truth(case, scene)
    tau, s0, s_inf = case.tissue.tau_s, PIT["s0_px"], PIT["s_inf_px"]
    s_max = s_inf - (s_inf - s0) * math.exp(-105.0 / tau)
    tr = -tau * math.log((s_inf - 0.98 * s_max) / (s_inf - s0))
    assert t["recovery_time_s"]["value"] == pytest.approx(tr, abs=2e-6)
    assert t["rebound_force_n"]["value"] == pytest.approx((s_max - 375.0) / 625.0)
    d_p = 12.0 - (-2.272e-6 * s0**2 + 0.010224 * s0)  # Eqs. (3)-(4), 320x240 coefficients
    assert t["depth_mm"]["value"] == pytest.approx(d_p)
    e = 1e3 * 3.0 * 16.0 / (math.pi**2 * 7.5 * d_p)  # Eq. (7)
    assert t["elasticity_kpa"]["value"] == pytest.approx(e)
    assert t["viscosity_n_s_per_mm2"]["value"] == pytest.approx(1e-3 * e * tr)  # Eq. (8)
    assert t["severity"]["value"] == "severe"  # T_r 27.5 s: grade III's


def test_springback_truth_is_the_hold_pit_not_the_first_frame() -> None:
    case = next(c for c in law_cases() if c.name == "law-sls-springback-0.5")
    t = law_truth(case, parse_scene(case.scene_doc(), case.name))
    first_frame_s0 = float(case.tissue.area_px(np.asarray([1.0 / 60.0]))[0])
    d_first = 12.0 - (-2.272e-6 * first_frame_s0**2 + 0.010224 * first_frame_s0)
    assert d_first < t["depth_mm"]["low"]  # the sprung-back frame's D_p is outside


def test_world_force_is_the_hold_then_eq5_of_the_law() -> None:
    case = LawCase("x", Tissue("kww", tau_s=6.0, shape=0.5, **PIT))
    world = world_of(case, parse_scene(case.scene_doc(), "x"))
    t0 = case.t0_s
    f = world.force_n(np.asarray([0.5, t0 - 0.01, t0 + 10.0]))
    s_after = float(case.tissue.area_px(np.asarray([10.0]))[0])
    assert f == pytest.approx([8.0, 16.0, (s_after - 375.0) / 625.0])
    assert world.area_px(np.asarray([t0 - 0.01]))[0] == pytest.approx(375.0 + 625.0 * 16.0)


def test_law_cases_have_unique_names_and_every_truth_range_holds_its_value() -> None:
    cases = law_cases()
    assert len({c.name for c in cases}) == len(cases) == 18
    for c in cases:
        t = law_truth(c, parse_scene(c.scene_doc(), c.name))
        for q in TOLERANCES:
            if q != "severity":
                assert t[q]["low"] <= t[q]["value"] <= t[q]["high"], (c.name, q)
