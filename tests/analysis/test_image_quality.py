"""Image quality measured from the frames (analysis/image_quality.py) and the load cell's rail.

Frames are rendered here from stated physical effects, not by the simulator: a lit
waveguide whose level falls off radially, L(rho) = 200 - 25 rho^2 (rho = r / R_ROI), with a
dark disc (level 70) of the Kelvin-Voigt recovery's area, then

* LED flicker: every level times g_k = 1 + m sin(2 pi f t_k) (the LEDs light the whole
  waveguide, occluded part included);
* pixel noise: plus independent Gaussian N(0, sigma^2) per pixel and frame;
* vignetting: every level times 1 - a rho^2 (cos^4 law to second order);
* clipping: every level times a gain, clipped to the 8-bit rail;

each rounded to 8 bits. S_k is counted here (pixels <= p inside the ROI, Eqs. 1-2 as the
paper writes them), and the truth is the disc's own pixel area.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.image_quality import (
    RINGS,
    FrameLevels,
    FramePictures,
    LevelMeter,
    assess_image_quality,
)
from stipi_daemon.analysis.imaging import CircleROI
from stipi_daemon.analysis.results import (
    AnalysisSettings,
    MeasurementResult,
    analyze_recovery,
    force_at_rail_fraction,
    force_full_scale_n,
)
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import assess_validity

H, W = 120, 160
P = 128
ROI = CircleROI(cx_px=80.3, cy_px=60.2, radius_px=54.0)
#: the paper-scale calibration at 1/16 of the pixel area (a 120-row frame against 480)
AREA = 1.0 / 16.0
CAL = Calibration(
    alpha1_mm_per_px2=1.42e-7 / AREA**2,
    alpha2_mm_per_px=2.556e-3 / AREA,
    c1_px=1500.0 * AREA,
    c2_px_per_n=2500.0 * AREA,
)
T0, TAU, FPS, DURATION = 15.0, 6.0, 15.0, 120.0

_yy, _xx = np.mgrid[0:H, 0:W].astype(np.float64)
_R2 = (_xx - ROI.cx_px) ** 2 + (_yy - ROI.cy_px) ** 2
_IN_ROI = _R2 <= ROI.radius_px**2
_RHO2 = _R2 / ROI.radius_px**2
_ORDER = np.argsort(_R2, axis=None, kind="stable")


def true_area(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Occluded area [px] of a Kelvin-Voigt pit: hold 2500 px, S_0 375 px, S_inf 1109 px."""
    s0, s_inf = 6000.0 * AREA, (1500.0 + 2500.0 * 6.5) * AREA
    rec = s_inf - (s_inf - s0) * np.exp(-np.clip(t - T0, 0.0, None) / TAU)
    out: NDArray[np.float64] = np.round(np.where(t < T0, 40000.0 * AREA, rec)).astype(np.float64)
    return out


def render(
    area_px: float,
    *,
    gain: float = 1.0,
    noise: float = 0.0,
    vignette: float = 0.0,
    rng: np.random.Generator | None = None,
) -> NDArray[np.uint8]:
    """One frame: the area_px nearest pixels to the centre dark (70), the rest lit."""
    level = 200.0 - 25.0 * _RHO2
    flat = level.ravel().copy()
    flat[_ORDER[: int(area_px)]] = 70.0
    img = flat.reshape(H, W) * (1.0 - vignette * _RHO2) * gain
    if noise > 0.0 and rng is not None:
        img = img + rng.normal(0.0, noise, img.shape)
    out: NDArray[np.uint8] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out


def count(frame: NDArray[np.uint8]) -> int:
    """Eqs. (1)-(2): pixels of the ROI at or below p."""
    return int(np.count_nonzero(frame[_IN_ROI] <= P))


def session(
    *,
    flicker: float = 0.0,
    noise: float = 0.0,
    vignette: float = 0.0,
    gain: float = 1.0,
    seed: int = 1,
    flicker_hz: float = 3.3,
    every: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], FramePictures]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION, 1.0 / FPS)
    meter = LevelMeter((H, W), P, ROI)
    s, levels = [], []
    for k, (tk, area) in enumerate(zip(t, true_area(t), strict=True)):
        g = gain * (1.0 + flicker * math.sin(2.0 * math.pi * flicker_hz * tk))
        frame = render(area, gain=g, noise=noise, vignette=vignette, rng=rng)
        s.append(count(frame))
        if k % every == 0:  # the statistics of one frame in ``every``
            levels.append(meter.measure(frame))
    pictures = FramePictures(
        times_s=tuple(float(x) for x in t[::every]),
        levels=tuple(levels),
        p=P,
        roi_pixel_count=int(np.count_nonzero(_IN_ROI)),
        hold_s=(1.0, T0),
    )
    return t, np.asarray(s, dtype=np.float64), pictures


def analyse(
    t: NDArray[np.float64], s: NDArray[np.float64], pictures: FramePictures | None
) -> MeasurementResult:
    settings = AnalysisSettings(bootstrap_replicates=0)
    return analyze_recovery(t, s, T0, CAL, 16.0, settings, load_reference(), pictures=pictures)


def truth_depth_mm() -> float:
    return CAL.indenter_length_mm - CAL.depth_change_mm(float(true_area(np.array([T0]))[0]))


def status(result: MeasurementResult) -> dict[str, str]:
    v = assess_validity(result, ended_done=True)["validity"]
    return {q: x["status"] for q, x in v.items()}


# -- the estimators against the rendered effects -----------------------------------------


def steady_quality(**effects: float) -> tuple[object, list[NDArray[np.uint8]]]:
    rng = np.random.default_rng(3)
    meter = LevelMeter((H, W), P, ROI)
    frames, levels = [], []
    for k in range(60):
        g = 1.0 + effects.get("flicker", 0.0) * math.sin(2.0 * math.pi * 3.3 * k / FPS)
        f = render(
            1109,
            gain=g,
            noise=effects.get("noise", 0.0),
            vignette=effects.get("vignette", 0.0),
            rng=rng,
        )
        frames.append(f)
        levels.append(meter.measure(f))
    q = assess_image_quality(levels, [1] * len(levels), P, int(np.count_nonzero(_IN_ROI)))
    return q, frames


def test_flicker_amplitude_is_measured() -> None:
    q, _ = steady_quality(flicker=0.2)
    # 95th percentile of |0.2 sin(phase)| over phases spread evenly: 0.2 sin(0.95 pi/2)
    assert q.flicker == pytest.approx(0.2 * math.sin(0.95 * math.pi / 2), rel=0.1)  # type: ignore[attr-defined]


@pytest.mark.parametrize("sigma", [5.0, 10.0, 20.0])
def test_pixel_noise_is_measured(sigma: float) -> None:
    q, _ = steady_quality(noise=sigma)
    assert q.noise_levels == pytest.approx(sigma, rel=0.1)  # type: ignore[attr-defined]


def test_noise_is_told_apart_from_flicker() -> None:
    q, _ = steady_quality(noise=10.0, flicker=0.2)
    assert q.noise_levels == pytest.approx(10.0, rel=0.15)  # type: ignore[attr-defined]


def test_vignetting_is_measured() -> None:
    q, _ = steady_quality(vignette=0.3)

    def ring(k: int) -> tuple[float, float]:
        """Share above p and mean level above p of L(rho) (1 - a rho^2) over ring k, u =
        rho^2 in [k/8, (k+1)/8] (pixels are uniform in u); the disc darkens u < 0.121."""
        u = np.linspace(k / RINGS, (k + 1) / RINGS, 20001)
        level = np.where(
            u < 1109.0 / np.count_nonzero(_IN_ROI), 70.0, (200 - 25 * u) * (1 - 0.3 * u)
        )
        lit = level > P
        return float(np.mean(lit)), float(np.mean(level[lit])) if lit.any() else float(P)

    rings = [ring(k) for k in range(RINGS)]
    for k, (_, mean) in enumerate(rings):
        assert q.ring_levels[k] == pytest.approx(mean, abs=2.0)  # type: ignore[attr-defined]
    lit = [mean for share, mean in rings if share >= 0.5]
    assert q.vignetting == pytest.approx(1 - lit[-1] / lit[0], abs=0.01)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "effects",
    [{"flicker": 0.4}, {"noise": 20.0}, {"vignette": 0.3}],
    ids=["flicker", "noise", "vignetting"],
)
def test_the_bias_estimate_matches_the_count(effects: dict[str, float]) -> None:
    """The estimated bias of S_k (steady, worst frame) against the count on rendered frames
    (the disc's true area is 1109 px)."""
    q, frames = steady_quality(**effects)
    errors = np.array([count(f) for f in frames], dtype=np.float64) - 1109.0
    steady, worst = q.bias_px()  # type: ignore[attr-defined]
    assert float(np.max(errors)) > 10.0  # the effect moves S_k ...
    assert worst >= 0.5 * float(np.max(errors))  # ... and the estimate sees it
    assert steady == pytest.approx(float(np.median(errors)), rel=0.6, abs=30.0)


def test_clean_frames_move_nothing() -> None:
    q, _ = steady_quality()
    assert q.noise_levels < 1.0  # type: ignore[attr-defined]
    assert q.misclassified_px(1.0) < 1e-3  # type: ignore[attr-defined]


def test_bgr_frames_give_the_gray_levels() -> None:
    gray = render(800)
    bgr = np.repeat(gray[:, :, None], 3, axis=2)
    a = LevelMeter((H, W), P, ROI).measure(gray)
    b = LevelMeter((H, W, 3), P, ROI).measure(bgr)
    assert a == b
    assert FrameLevels.from_list(a.to_list()) == a


# -- through the analysis: wrong results are not valid ------------------------------------


def test_clean_session_stays_valid() -> None:
    t, s, pictures = session()
    r = analyse(t, s, pictures)
    assert r.pitting.depth_mm == pytest.approx(truth_depth_mm(), rel=0.02)
    st = status(r)
    assert st["depth_mm"] == st["rebound_force_n"] == st["recovery_time_s"] == "valid"
    assert r.quality_rules == ()


def test_mild_noise_stays_valid() -> None:
    t, s, pictures = session(noise=8.0)
    r = analyse(t, s, pictures)
    assert r.pitting.depth_mm == pytest.approx(truth_depth_mm(), rel=0.05)
    assert status(r)["depth_mm"] == "valid"


def truth() -> dict[str, float]:
    """D_p [mm], F_r [N], T_r [s] of the rendered Kelvin-Voigt pit (Eqs. 3-6 on the true
    area; S_max is the area at the window's end)."""
    s0, s_max = (float(x) for x in true_area(np.array([T0, T0 + 105.0])))
    s_inf = (1500.0 + 2500.0 * 6.5) * AREA
    return {
        "depth_mm": truth_depth_mm(),
        "rebound_force_n": (s_max - CAL.c1_px) / CAL.c2_px_per_n,
        "recovery_time_s": TAU * math.log((s_inf - s0) / (s_inf - 0.98 * s_max)),
    }


@pytest.mark.parametrize(
    "effects",
    [{"flicker": 0.4, "flicker_hz": 0.5}, {"noise": 20.0}, {"vignette": 0.4}],
    ids=["flicker", "noise", "vignetting"],
)
def test_an_effect_that_moves_a_result_beyond_tolerance_invalidates_it(
    effects: dict[str, float],
) -> None:
    t, s, pictures = session(**effects)  # type: ignore[arg-type]
    r = analyse(t, s, pictures)
    measured = {
        "depth_mm": r.pitting.depth_mm,
        "rebound_force_n": r.pitting.rebound_force_n,
        "recovery_time_s": r.pitting.recovery_time_s,
    }
    tolerance = {"depth_mm": 0.05, "rebound_force_n": 0.05, "recovery_time_s": 0.05}
    st = status(r)
    spoiled = []
    for q, true in truth().items():
        value = measured[q]
        off = math.inf if value is None else abs(value - true)
        allowed = tolerance[q] * true
        if q == "recovery_time_s":
            allowed = max(allowed, 2.0 / FPS)
        if off > allowed:
            spoiled.append(q)
            assert st[q] == "invalid", (q, value, true, r.quality_rules)
    assert spoiled  # the effect really spoils a result
    # the picture's own rule fired for every spoiled quantity (the reason validity shows
    # first may be another rule's: flicker at 0.5 Hz also darkens S_0 below C1, the
    # contact floor)
    judged = {q.quantity for q in r.quality_rules if q.invalid}
    assert set(spoiled) <= judged, (spoiled, r.quality_rules)


@pytest.mark.parametrize(("noise", "expected"), [(0.0, "valid"), (20.0, "invalid")])
def test_statistics_of_one_frame_in_four_judge_alike(noise: float, expected: str) -> None:
    t, s, pictures = session(noise=noise, every=4)
    assert status(analyse(t, s, pictures))["depth_mm"] == expected


def test_clipped_frames_at_the_rail_invalidate_what_they_carry() -> None:
    t, s, pictures = session(gain=2.2)  # the dark disc 70 * 2.2 = 154 > p: S_k collapses
    r = analyse(t, s, pictures) if np.any(s > 0) else None
    if r is None:  # every frame shows no occlusion: the analysis itself has nothing
        return
    st = status(r)
    assert st["depth_mm"] == "invalid"
    assert st["elasticity_kpa"] == "invalid"
    v = assess_validity(r, ended_done=True)["validity"]
    assert Flag.IMAGE_QUALITY in v["depth_mm"]["flags"]


def test_partly_clipped_frames_flag_the_saturation() -> None:
    t, s, pictures = session(gain=1.4)  # lit 200 * 1.4 clips; the disc stays dark
    r = analyse(t, s, pictures)
    st = status(r)
    assert st["depth_mm"] == "invalid"
    assert "saturated" in (
        assess_validity(r, ended_done=True)["validity"]["depth_mm"]["reason"] or ""
    )


# -- the load cell at its rail -----------------------------------------------------------


def test_force_at_full_scale_invalidates_fa_and_e() -> None:
    # FC22-like 10-bit readout: 54.3 mN per count, full scale at 15.74 N (rail of a
    # smaller cell); the operator pressed 18 N
    step = 0.0543
    full = 290 * step
    ft = np.arange(0.0, 16.0, 0.01)
    true_f = np.where(ft < 1.0, 18.0 * ft, 18.0)
    read = np.minimum(np.round(true_f / step) * step, full)
    frac = force_at_rail_fraction(ft, read, 1.0, 15.9, full, step)
    assert frac > 0.9
    t, s, pictures = session()
    settings = AnalysisSettings(bootstrap_replicates=0)
    f_a = float(np.mean(read[(ft >= 1.0) & (ft <= 15.9)]))
    assert f_a < 18.0 * 0.95  # the mean at the rail is wrong
    r = analyze_recovery(
        t,
        s,
        T0,
        CAL,
        f_a,
        settings,
        load_reference(),
        pictures=pictures,
        force_rail_fraction=frac,
    )
    st = status(r)
    assert st["applied_force_n"] == "invalid"
    assert st["elasticity_kpa"] == "invalid"
    assert st["depth_mm"] == "valid"


def test_force_below_full_scale_is_not_at_the_rail() -> None:
    ft = np.arange(0.0, 16.0, 0.01)
    f = np.full_like(ft, 16.0)
    assert force_at_rail_fraction(ft, f, 1.0, 15.0, 44.48, 0.0543) == 0.0
    assert force_at_rail_fraction(ft, f, 1.0, 15.0, math.inf, 0.0543) == 0.0


def test_full_scale_is_the_adc_top_code_of_the_probe_info() -> None:
    # FC22 10 lbf (44.48 N): V = 5 (0.1 + 0.8 F / 44.48), divided by 0.66 onto a 3.3 V
    # 10-bit ADC (1024 codes); the top code 1023 is reached at
    volts = 1023 / 1024 * 3.3 / 0.66
    top_n = (volts / 5 - 0.1) / 0.8 * 44.48
    info = {"adc_bits": 10, "zero_counts": 102, "span_un_per_count": 54297}
    full = force_full_scale_n(info)
    assert full is not None
    assert full[0] == pytest.approx(top_n, rel=0.005)
    assert full[1] == pytest.approx(0.054297)
    used = force_full_scale_n({**info, "zero_counts_used": 110, "span_un_per_count_used": 50000})
    assert used == pytest.approx(((1023 - 110) * 0.05, 0.05))
    assert force_full_scale_n({"adc_bits": 10}) is None
    assert force_full_scale_n(None) is None
