"""Tests of the probe calibration: Eqs. (4)-(5), their fits, inverses and the calibration file."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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
from stipi_daemon.analysis.imaging import CircleROI, RectROI, describe_roi, whole_frame_roi
from stipi_daemon.errors import AnalysisError, CalibrationError

# A plausible probe: S0 up to ~60 000 px for d_s up to ~12 mm, C1 ~ 2000 px, C2 ~ 900 px/N.
A1 = 1.5e-9  # mm/px^2
A2 = 2.9e-4  # mm/px
C1 = 2000.0  # px
C2 = 900.0  # px/N


def example_calibration(**changes: Any) -> Calibration:
    kwargs: dict[str, Any] = {
        "alpha1_mm_per_px2": A1,
        "alpha2_mm_per_px": A2,
        "c1_px": C1,
        "c2_px_per_n": C2,
    }
    kwargs.update(changes)
    return Calibration(**kwargs)


def depth_points(n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    s0 = np.linspace(2000.0, 60000.0, n)
    return s0, -A1 * s0**2 + A2 * s0


def force_points(n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    f = np.linspace(1.0, 20.0, n)
    return C1 + C2 * f, f


def fitted_calibration() -> Calibration:
    depth = fit_depth_calibration(*depth_points())
    force = fit_force_calibration(*force_points())
    return calibration_from_fits(
        depth,
        force,
        threshold_p=97,
        probe_id="STIPI-01",
        created_utc=datetime(2024, 5, 1, 12, 30, tzinfo=UTC),
    )


# ---------------------------------------------------------------------------- Eqs. (4)-(5)


def test_eq4_and_eq5_values() -> None:
    cal = example_calibration()
    assert cal.depth_change_mm(0.0) == 0.0
    assert cal.depth_change_mm(40000.0) == pytest.approx(-A1 * 40000.0**2 + A2 * 40000.0)
    assert cal.rebound_force_n(C1 + 5 * C2) == pytest.approx(5.0)
    assert cal.rebound_force_n(C1) == 0.0
    assert cal.rebound_force_n(0.0) == pytest.approx(-C1 / C2)  # unclipped below C1
    assert cal.area_for_force_px(5.0) == pytest.approx(C1 + 5 * C2)
    assert cal.vertex_px == pytest.approx(A2 / (2 * A1))
    assert cal.max_depth_change_mm == pytest.approx(A2**2 / (4 * A1))
    assert cal.indenter_length_mm == 12.0


def test_linear_and_convex_depth_models() -> None:
    lin = example_calibration(alpha1_mm_per_px2=0.0)
    assert lin.vertex_px == math.inf and lin.max_depth_change_mm == math.inf
    assert lin.s0_for_depth_change(5.8) == pytest.approx(5.8 / A2, rel=1e-15)
    convex = example_calibration(alpha1_mm_per_px2=-1e-9)
    s0 = convex.s0_for_depth_change(10.0)
    assert convex.depth_change_mm(s0) == pytest.approx(10.0, rel=1e-14)


def test_inverse_of_eq4_raises_without_solution() -> None:
    cal = example_calibration()
    with pytest.raises(AnalysisError, match=r"exceeds the maximum of Eq\. \(4\)"):
        cal.s0_for_depth_change(cal.max_depth_change_mm * 1.01)
    with pytest.raises(AnalysisError, match="< 0"):
        cal.s0_for_depth_change(-0.1)
    with pytest.raises(AnalysisError, match="finite"):
        cal.s0_for_depth_change(math.nan)
    # at the vertex itself the solution exists
    assert cal.s0_for_depth_change(cal.max_depth_change_mm) == pytest.approx(cal.vertex_px)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_eq4_rejects_bad_s0(bad: float) -> None:
    with pytest.raises(AnalysisError, match="S0"):
        example_calibration().depth_change_mm(bad)


def test_eq5_rejects_non_finite() -> None:
    cal = example_calibration()
    with pytest.raises(AnalysisError, match="S_max"):
        cal.rebound_force_n(math.nan)
    with pytest.raises(AnalysisError, match="force"):
        cal.area_for_force_px(math.inf)


@settings(max_examples=300, deadline=None)
@given(
    s_top=st.floats(1.0, 1e8),
    vertex_factor=st.one_of(st.just(math.inf), st.floats(1.001, 1e12)),
    alpha2=st.floats(1e-12, 1e3),
    fraction=st.floats(0.0, 1.0),
)
def test_eq4_inverse_round_trip(
    s_top: float, vertex_factor: float, alpha2: float, fraction: float
) -> None:
    alpha1 = 0.0 if math.isinf(vertex_factor) else alpha2 / (2.0 * s_top * vertex_factor)
    cal = example_calibration(alpha1_mm_per_px2=alpha1, alpha2_mm_per_px=alpha2)
    s0 = fraction * s_top
    d = cal.depth_change_mm(s0)
    back = cal.s0_for_depth_change(d)
    assert math.isfinite(d) and math.isfinite(back)
    # dS0/dd grows as 1 / (1 - S0/vertex) near the vertex: allow for that amplification.
    amplification = 1.0 / (1.0 - s0 / cal.vertex_px)
    assert back == pytest.approx(s0, rel=1e-12 * amplification, abs=1e-300)


@settings(max_examples=200, deadline=None)
@given(
    c1=st.floats(-1e6, 1e8),
    c2=st.floats(1e-6, 1e8),
    force=st.floats(0.0, 1e3),
)
def test_eq5_inverse_round_trip(c1: float, c2: float, force: float) -> None:
    cal = example_calibration(c1_px=c1, c2_px_per_n=c2)
    s = cal.area_for_force_px(force)
    f_back = cal.rebound_force_n(s)
    assert math.isfinite(f_back)
    # (C1 + C2 F - C1) / C2 loses what C1 + C2 F rounds away from C2 F.
    assert f_back == pytest.approx(force, abs=4e-16 * (abs(c1) + abs(s)) / c2 + 1e-300)


# ---------------------------------------------------------------------------- Calibration checks


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"alpha2_mm_per_px": 0.0}, "field 'alpha2_mm_per_px': must be > 0"),
        ({"c2_px_per_n": -3.0}, "field 'c2_px_per_n': must be > 0"),
        ({"c1_px": math.nan}, "field 'c1_px': must be finite"),
        ({"alpha1_mm_per_px2": math.inf}, "field 'alpha1_mm_per_px2': must be finite"),
        ({"indenter_length_mm": 0.0}, "field 'indenter_length_mm': must be > 0"),
        ({"threshold_p": 256}, "field 'threshold_p'"),
        ({"s0_valid_range_px": (10.0, 1.0)}, "low 10.0 > high 1.0"),
        ({"s0_valid_range_px": (0.0, 1e6)}, "reaches the vertex"),
        ({"force_valid_range_n": (0.0, math.nan)}, "field 'force_valid_range_n'"),
        ({"created_utc": datetime(2024, 1, 1)}, "timezone-aware"),
        ({"frame_size_px": (640, 0)}, "field 'frame_size_px': must be .width, height., two"),
        ({"frame_size_px": (640.0, 480)}, "field 'frame_size_px'"),
        ({"frame_size_px": (True, 480)}, "field 'frame_size_px'"),
        ({"frame_size_px": (640,)}, "field 'frame_size_px'"),
        ({"roi": {"kind": "circle", "cx_px": 1, "cy_px": 2, "radius_px": 3}}, "field 'roi'"),
    ],
)
def test_calibration_rejects_bad_coefficients(changes: dict[str, Any], words: str) -> None:
    with pytest.raises(CalibrationError, match=words.replace("(", r"\(")):
        example_calibration(**changes)


# ---------------------------------------------------------------------------- fits


def test_depth_fit_recovers_known_coefficients_exactly() -> None:
    fit = fit_depth_calibration(*depth_points())
    assert fit.alpha1_mm_per_px2 == pytest.approx(A1, rel=1e-9)
    assert fit.alpha2_mm_per_px == pytest.approx(A2, rel=1e-11)
    assert fit.r_squared == pytest.approx(1.0, abs=1e-12)
    assert max(abs(r) for r in fit.residuals_mm) < 1e-12
    assert fit.alpha1_se_mm_per_px2 < 1e-9 * A1
    assert fit.n_points == 10 and len(fit.residuals_mm) == 10
    assert fit.s0_range_px == (2000.0, 60000.0)
    assert fit.vertex_px == pytest.approx(A2 / (2 * A1), rel=1e-8)


def test_depth_fit_with_huge_pixel_counts() -> None:
    s0 = np.linspace(1e6, 1e8, 7)
    a1, a2 = 1e-16, 1.2e-7  # d_s up to 11 mm at S0 = 1e8 px
    fit = fit_depth_calibration(s0, -a1 * s0**2 + a2 * s0)
    assert fit.alpha1_mm_per_px2 == pytest.approx(a1, rel=1e-8)
    assert fit.alpha2_mm_per_px == pytest.approx(a2, rel=1e-10)


def test_depth_fit_accepts_zero_point_and_linear_data() -> None:
    s0 = np.array([0.0, 1000.0, 2000.0, 3000.0])
    fit = fit_depth_calibration(s0, 3e-3 * s0)
    assert fit.alpha1_mm_per_px2 == pytest.approx(0.0, abs=1e-18)
    assert fit.alpha2_mm_per_px == pytest.approx(3e-3, rel=1e-12)


def test_force_fit_recovers_known_coefficients_exactly() -> None:
    fit = fit_force_calibration(*force_points())
    assert fit.c1_px == pytest.approx(C1, rel=1e-12)
    assert fit.c2_px_per_n == pytest.approx(C2, rel=1e-12)
    assert fit.r_squared == pytest.approx(1.0, abs=1e-12)
    assert fit.force_range_n == (1.0, 20.0)
    assert fit.s_range_px == (C1 + C2, C1 + 20 * C2)


def test_force_fit_with_huge_pixel_counts() -> None:
    f = np.array([0.5, 3.0, 7.0, 11.0, 19.5])
    s = 9.0e7 + 5.0e5 * f  # S about 1e8 px
    fit = fit_force_calibration(s, f)
    assert fit.c1_px == pytest.approx(9.0e7, rel=1e-12)
    assert fit.c2_px_per_n == pytest.approx(5.0e5, rel=1e-10)


def test_standard_errors_match_monte_carlo_spread() -> None:
    """Seeded Monte-Carlo: SEs equal the spread of the estimates, truth lies within 3 SE."""
    rng = np.random.default_rng(12345)
    s0, d_true = depth_points(12)
    f = np.linspace(1.0, 20.0, 10)
    s_true = C1 + C2 * f
    trials = 400
    est = np.empty((trials, 4))
    se = np.empty((trials, 4))
    for i in range(trials):
        dfit = fit_depth_calibration(s0, d_true + rng.normal(0.0, 0.05, s0.size))
        ffit = fit_force_calibration(s_true + rng.normal(0.0, 150.0, f.size), f)
        est[i] = (dfit.alpha1_mm_per_px2, dfit.alpha2_mm_per_px, ffit.c1_px, ffit.c2_px_per_n)
        se[i] = (
            dfit.alpha1_se_mm_per_px2,
            dfit.alpha2_se_mm_per_px,
            ffit.c1_se_px,
            ffit.c2_se_px_per_n,
        )
    truth = np.array([A1, A2, C1, C2])
    spread = est.std(axis=0, ddof=1)
    mean_se = se.mean(axis=0)
    # Mean SE matches the empirical standard deviation within sampling error (~ 8 %).
    assert np.all(np.abs(mean_se / spread - 1.0) < 0.12), (mean_se, spread)
    # Coverage of +- 3 SE (t-distribution with few dof: expect >= ~97 %).
    inside = np.abs(est - truth) <= 3.0 * se
    assert np.all(inside.mean(axis=0) > 0.95)
    # Unbiased.
    assert np.all(np.abs(est.mean(axis=0) - truth) < 4 * spread / math.sqrt(trials))


def test_fit_r_squared_and_correlation_ranges() -> None:
    rng = np.random.default_rng(5)
    s0, d = depth_points()
    fit = fit_depth_calibration(s0, d + rng.normal(0, 0.2, d.size))
    assert 0.9 < fit.r_squared < 1.0
    assert -1.0 <= fit.correlation <= 1.0
    assert fit.rms_residual_mm == pytest.approx(np.sqrt(np.mean(np.square(fit.residuals_mm))))


@pytest.mark.parametrize(
    ("s0", "d", "words"),
    [
        ([1.0, 2.0], [1.0, 2.0], "too few points: 2 given"),
        ([1.0, 2.0, 3.0], [1.0, 2.0], "mismatched lengths: 3 S0 values but 2 depth change"),
        ([5.0, 5.0, 5.0, 5.0], [1.0, 2.0, 3.0, 4.0], "all S0 values are equal"),
        ([0.0, 1.0, 2.0, 2.0], [0.0, 1.0, 2.0, 2.0], "too few distinct S0 values: 2 distinct"),
        ([1.0, 2.0, math.nan, 4.0], [1.0, 2.0, 3.0, 4.0], "non-finite value nan at index 2"),
        ([1.0, 2.0, 3.0, 4.0], [1.0, math.inf, 3.0, 4.0], "depth change: non-finite value inf"),
        ([1.0, -2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0], "negative pixel count -2.0 at index 1"),
        ([1.0, 2.0, 3.0, 4.0], [2.0, 2.0, 2.0, 2.0], "all depth-change values are equal"),
        ([[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]], "one-dimensional"),
    ],
)
def test_depth_fit_refusals(s0: Any, d: Any, words: str) -> None:
    with pytest.raises(CalibrationError, match=words.replace("(", r"\(")):
        fit_depth_calibration(s0, d)


def test_depth_fit_refuses_vertex_inside_range() -> None:
    s0 = np.linspace(1000.0, 100000.0, 8)
    a1, a2 = 2e-9, 2e-4  # vertex at 50 000 px
    with pytest.raises(CalibrationError) as info:
        fit_depth_calibration(s0, -a1 * s0**2 + a2 * s0)
    msg = str(info.value)
    assert "vertex of the depth fit at S0 = 50000 px" in msg
    assert "inside the measured S0 range [1000, 100000] px" in msg
    assert "not invertible" in msg


def test_depth_fit_refuses_decreasing_data() -> None:
    s0 = np.linspace(1000.0, 10000.0, 6)
    with pytest.raises(CalibrationError, match="decreases over the measured S0 range"):
        fit_depth_calibration(s0, -1e-3 * s0)


def test_depth_fit_refuses_decrease_from_zero() -> None:
    s0 = np.linspace(5000.0, 10000.0, 6)
    a1, a2 = -1e-7, -5e-4  # convex, vertex at 2500 px: decreasing below, increasing above
    with pytest.raises(CalibrationError, match="decreases from S0 = 0"):
        fit_depth_calibration(s0, -a1 * s0**2 + a2 * s0)


@pytest.mark.parametrize(
    ("s", "f", "words"),
    [
        ([1.0, 2.0], [1.0, 2.0], "too few points"),
        ([1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0], "mismatched lengths: 4 S values but 3 force"),
        ([10.0, 20.0, 30.0, 40.0], [1.0, 1.0, 2.0, 2.0], "too few distinct force values: 2"),
        ([7.0, 7.0, 7.0], [1.0, 2.0, 3.0], "all S values are equal"),
        ([10.0, 20.0, 30.0], [1.0, math.nan, 3.0], "force: non-finite value nan at index 1"),
        ([30.0, 20.0, 10.0], [1.0, 2.0, 3.0], "non-positive slope C2"),
        ([-1.0, 20.0, 10.0], [1.0, 2.0, 3.0], "S: negative pixel count"),
    ],
)
def test_force_fit_refusals(s: Any, f: Any, words: str) -> None:
    with pytest.raises(CalibrationError, match=words):
        fit_force_calibration(s, f)


def test_calibration_from_fits_carries_ranges_and_reports() -> None:
    cal = fitted_calibration()
    assert cal.s0_valid_range_px == (2000.0, 60000.0)
    assert cal.force_valid_range_n == (1.0, 20.0)
    assert isinstance(cal.depth_fit, DepthFit) and isinstance(cal.force_fit, ForceFit)
    assert cal.threshold_p == 97
    assert cal.rebound_force_n(C1 + 7 * C2) == pytest.approx(7.0, rel=1e-10)


# ---------------------------------------------------------------------------- file


def test_save_load_round_trip(tmp_path: Path) -> None:
    cal = fitted_calibration()
    path = save_calibration(tmp_path / "calib.json", cal)
    loaded = load_calibration(path)
    assert loaded == cal
    doc = json.loads(path.read_text())
    assert doc["format"] == "stipi-calibration" and doc["version"] == 1
    assert doc["c2_px_per_n"] == cal.c2_px_per_n
    assert doc["created_utc"] == "2024-05-01T12:30:00+00:00"
    assert [p.name for p in tmp_path.iterdir()] == ["calib.json"]  # no temp file left


def test_the_frame_size_round_trips_and_is_checked_against_a_frames_size(
    tmp_path: Path,
) -> None:
    """``frame_size_px`` is written, read back and compared: the same size or a
    calibration that records none passes; another size gives a line naming both."""
    cal = dataclasses.replace(fitted_calibration(), frame_size_px=(640, 480))
    path = save_calibration(tmp_path / "calib.json", cal)
    assert json.loads(path.read_text())["frame_size_px"] == [640, 480]
    assert load_calibration(path) == cal
    assert cal.frame_size_problem(640, 480, "the camera") is None
    assert dataclasses.replace(cal, frame_size_px=None).frame_size_problem(9, 9, "x") is None
    for w, h in ((1280, 720), (480, 640), (640, 481)):
        problem = cal.frame_size_problem(w, h, "the camera")
        assert problem is not None
        assert problem.startswith(f"the camera has {w}x{h} px frames, but the calibration")
        assert "made at 640x480 px" in problem


_CIRCLE = {"kind": "circle", "cx_px": 320, "cy_px": 240, "radius_px": 180}


def test_the_roi_round_trips_and_is_checked_against_the_roi_counted_in(
    tmp_path: Path,
) -> None:
    """``roi`` is written as the config's ``imaging.roi``, read back and compared: the same
    ROI or a calibration that records none passes; another ROI (smaller, larger, moved,
    another shape, the whole frame) gives a line naming both."""
    own = CircleROI(kind="circle", cx_px=320, cy_px=240, radius_px=180)
    cal = dataclasses.replace(fitted_calibration(), roi=own)
    path = save_calibration(tmp_path / "calib.json", cal)
    assert json.loads(path.read_text())["roi"] == {**_CIRCLE, "cx_px": 320.0}
    assert load_calibration(path) == cal
    assert cal.roi_problem(CircleROI(**_CIRCLE), "field 'imaging.roi'") is None
    assert fitted_calibration().roi_problem(None, "x") is None  # records none
    rect = RectROI(kind="rect", x_px=140, y_px=60, width_px=360, height_px=360)
    for other in (
        own.model_copy(update={"radius_px": 170.0}),
        own.model_copy(update={"cx_px": 321.0}),
        rect,
        None,
    ):
        problem = cal.roi_problem(other, "field 'imaging.roi'")
        assert problem is not None
        assert problem.startswith(f"field 'imaging.roi' counts S in {describe_roi(other)}, but")
        assert "made in circle centre (320, 240) r 180 px (its field 'roi')" in problem
    # made in the whole frame (calibrate --roi full): the rect of its frame size, which is
    # the same pixels as no ROI or any ROI holding the frame, and no others
    full = dataclasses.replace(
        fitted_calibration(), frame_size_px=(640, 480), roi=whole_frame_roi((640, 480))
    )
    assert load_calibration(save_calibration(tmp_path / "full.json", full)) == full
    for same in (None, RectROI(kind="rect", x_px=-5, y_px=0, width_px=700, height_px=480)):
        assert full.roi_problem(same, "--roi") is None
    problem = full.roi_problem(own, "field 'imaging.roi'")
    assert problem is not None and "made in rect at (0, 0) size 640x480 px" in problem
    # an older file without the field loads with none
    doc = json.loads(path.read_text())
    del doc["roi"]
    path.write_text(json.dumps(doc))
    assert load_calibration(path).roi is None


def test_save_fills_created_timestamp_and_minimal_file_loads(tmp_path: Path) -> None:
    cal = example_calibration()
    path = save_calibration(tmp_path / "c.json", cal)
    loaded = load_calibration(path)
    assert loaded.created_utc is not None
    assert abs((datetime.now(UTC) - loaded.created_utc).total_seconds()) < 60
    assert loaded.depth_fit is None and loaded.probe_id is None
    assert (loaded.alpha1_mm_per_px2, loaded.c1_px) == (A1, C1)


def test_save_replaces_existing_file_atomically(tmp_path: Path) -> None:
    path = tmp_path / "calib.json"
    save_calibration(path, example_calibration(c1_px=1.0))
    save_calibration(path, example_calibration(c1_px=2.0))
    assert load_calibration(path).c1_px == 2.0
    assert sorted(os.listdir(tmp_path)) == ["calib.json"]


def test_save_into_missing_directory_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(OSError):
        save_calibration(tmp_path / "nope" / "calib.json", example_calibration())
    assert list(tmp_path.iterdir()) == []


def write_doc(tmp_path: Path, mutate: Any) -> Path:
    path = save_calibration(tmp_path / "calib.json", fitted_calibration())
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))
    return path


def _set(key: str, value: Any) -> Any:
    def mutate(doc: dict[str, Any]) -> None:
        doc[key] = value

    return mutate


def _delete(key: str) -> Any:
    def mutate(doc: dict[str, Any]) -> None:
        del doc[key]

    return mutate


def _set_fit(key: str, value: Any) -> Any:
    def mutate(doc: dict[str, Any]) -> None:
        doc["depth_fit"][key] = value

    return mutate


@pytest.mark.parametrize(
    ("mutate", "words"),
    [
        (_set("c2_px_per_n", -1.0), "calib.json: field 'c2_px_per_n': must be > 0 (got -1.0)"),
        (_set("alpha2_mm_per_px", 0), "field 'alpha2_mm_per_px': must be > 0"),
        (_set("threshold_p", 300), "field 'threshold_p': must be <= 255"),
        (_set("threshold_p", 12.5), "field 'threshold_p'"),
        (_set("c1_px", "2000"), "field 'c1_px'"),
        (_delete("c1_px"), "field 'c1_px': missing"),
        (_set("colour", "blue"), "field 'colour': unknown field"),
        (_set("version", 2), "field 'version': unsupported version 2"),
        (_set("version", "1"), "unsupported version '1'"),
        (_delete("version"), "field 'version': missing"),
        (_set("format", "something-else"), "not a stipi calibration file"),
        (_set("created_utc", "2024-05-01T12:30:00"), "field 'created_utc'"),
        (_set("s0_valid_range_px", [0.0, 1e9]), "reaches the vertex"),
        (_set_fit("n_points", 11), "field 'depth_fit.residuals': 10 residuals but n_points = 11"),
        (_set_fit("correlation", 1.5), "field 'depth_fit.correlation': must be <= 1"),
        (_set("frame_size_px", [640, 0]), "field 'frame_size_px.1': must be > 0 (got 0)"),
        (_set("frame_size_px", [640, 480.5]), "field 'frame_size_px.1'"),
        (_set("frame_size_px", [640]), "field 'frame_size_px.1': missing"),
        (_set("roi", {**_CIRCLE, "radius_px": 0}), "field 'roi.circle.radius_px': must be > 0"),
        (_set("roi", {**_CIRCLE, "kind": "oval"}), "field 'roi': Input tag 'oval'"),
        (_set("roi", {**_CIRCLE, "cx_px": "320"}), "field 'roi.circle.cx_px'"),
        (_set("roi", [320, 240, 100]), "field 'roi'"),
    ],
)
def test_load_rejects_bad_files(tmp_path: Path, mutate: Any, words: str) -> None:
    path = write_doc(tmp_path, mutate)
    with pytest.raises(CalibrationError) as info:
        load_calibration(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    assert words.split("calib.json: ")[-1] in msg, msg


def test_load_reports_truncated_json_with_position(tmp_path: Path) -> None:
    path = save_calibration(tmp_path / "calib.json", fitted_calibration())
    text = path.read_text()
    path.write_text(text[:200])
    with pytest.raises(CalibrationError, match=r"invalid JSON \(the file looks truncated\)") as e:
        load_calibration(path)
    assert "line " in str(e.value) and "column " in str(e.value) and "(char " in str(e.value)


def test_load_reports_invalid_json_position(tmp_path: Path) -> None:
    path = tmp_path / "calib.json"
    path.write_text('{"format": "stipi-calibration",, "version": 1}')
    with pytest.raises(CalibrationError, match=r"invalid JSON: .* line 1, column 32 \(char 31\)"):
        load_calibration(path)


def test_load_rejects_non_object_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "calib.json"
    path.write_text("[1, 2, 3]")
    with pytest.raises(CalibrationError, match="top level is not a JSON object"):
        load_calibration(path)
    with pytest.raises(CalibrationError, match="cannot read calibration file"):
        load_calibration(tmp_path / "missing.json")
