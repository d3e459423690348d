"""Tests of Eqs. (1)-(2): thresholding, S_k, ROIs, frame checks and Otsu's threshold."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import (
    ROI,
    CircleROI,
    FrameProcessor,
    RectROI,
    covers_frame,
    occluded_area_subpixel,
    occluded_pixel_count,
    otsu_threshold,
    roi_mask,
    same_roi,
    subpixel_membership_lut,
    threshold_binary_inverted,
    to_gray,
    whole_frame_roi,
)
from stipi_daemon.errors import AnalysisError

U8 = npt.NDArray[np.uint8]


def reference_mask(height: int, width: int, roi: RectROI | CircleROI | None) -> np.ndarray:
    """ROI membership written out pixel by pixel from the module's stated definition."""
    mask = np.zeros((height, width), dtype=bool)
    for y in range(height):
        for x in range(width):
            if roi is None:
                inside = True
            elif isinstance(roi, RectROI):
                inside = (
                    roi.x_px <= x < roi.x_px + roi.width_px
                    and roi.y_px <= y < roi.y_px + roi.height_px
                )
            else:
                dx, dy = x - roi.cx_px, y - roi.cy_px
                inside = dx * dx + dy * dy <= roi.radius_px * roi.radius_px
            mask[y, x] = inside
    return mask


def disc_frame(
    shape: tuple[int, int], centre: tuple[int, int], radius: int, inside: int, outside: int
) -> U8:
    frame = np.full(shape, outside, dtype=np.uint8)
    cv2.circle(frame, centre, radius, inside, thickness=-1)
    return frame


# ---------------------------------------------------------------------------- Eq. (1)


def test_eq1_binary_inverted_on_hand_built_array() -> None:
    gray = np.array([[0, 50, 99], [100, 101, 255]], dtype=np.uint8)
    assert threshold_binary_inverted(gray, 100).tolist() == [[1, 1, 1], [1, 0, 0]]
    out = threshold_binary_inverted(gray, 100)
    assert out.dtype == np.uint8 and out.shape == gray.shape


def test_eq1_edges_p0_and_p255() -> None:
    gray = np.array([[0, 1, 254, 255]], dtype=np.uint8)
    assert threshold_binary_inverted(gray, 0).tolist() == [[1, 0, 0, 0]]
    assert threshold_binary_inverted(gray, 255).tolist() == [[1, 1, 1, 1]]
    assert threshold_binary_inverted(gray, 254).tolist() == [[1, 1, 1, 0]]


@pytest.mark.parametrize("p", [-1, 256, 1.5, True, "10"])
def test_eq1_rejects_bad_threshold(p: object) -> None:
    with pytest.raises(AnalysisError, match="threshold p"):
        threshold_binary_inverted(np.zeros((2, 2), np.uint8), p)  # type: ignore[arg-type]


def test_eq1_rejects_colour_input() -> None:
    with pytest.raises(AnalysisError, match="2-D uint8"):
        threshold_binary_inverted(np.zeros((2, 2, 3), np.uint8), 10)


# ---------------------------------------------------------------------------- Eq. (2)


def test_eq2_exact_count_whole_frame_and_rect() -> None:
    gray = np.array(
        [
            [10, 200, 30, 40],
            [200, 200, 200, 90],
            [80, 81, 200, 200],
        ],
        dtype=np.uint8,
    )
    assert occluded_pixel_count(gray, 80) == 4  # 10, 30, 40, 80
    assert occluded_pixel_count(gray, 90) == 6
    roi = RectROI(x_px=1, y_px=1, width_px=3, height_px=2)  # rows 1-2, cols 1-3
    assert occluded_pixel_count(gray, 90, roi) == 2  # 90, 81
    assert occluded_pixel_count(gray, 0) == 0
    assert occluded_pixel_count(gray, 255) == gray.size


def test_gray_and_bgr_give_identical_counts() -> None:
    rng = np.random.default_rng(1)
    gray = rng.integers(0, 256, (37, 53), dtype=np.uint8)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    bgra = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGRA)
    assert np.array_equal(to_gray(bgr), gray)
    roi = CircleROI(cx_px=20.0, cy_px=15.5, radius_px=11.2)
    for p in (0, 17, 128, 254, 255):
        expected = occluded_pixel_count(gray, p, roi)
        assert occluded_pixel_count(bgr, p, roi) == expected
        assert occluded_pixel_count(bgra, p, roi) == expected
        assert occluded_pixel_count(gray[:, :, None], p, roi) == expected


def test_bgr_uses_opencv_luma_weights() -> None:
    bgr = np.zeros((1, 3, 3), np.uint8)
    bgr[0, 0] = (255, 0, 0)  # blue: Y = 0.114 * 255 = 29
    bgr[0, 1] = (0, 255, 0)  # green: 150
    bgr[0, 2] = (0, 0, 255)  # red: 76
    assert to_gray(bgr).tolist() == [[29, 150, 76]]


def test_circle_roi_area_close_to_pi_r_squared() -> None:
    for radius in (5.0, 20.0, 50.5, 120.0):
        size = int(2 * radius) + 11
        c = size // 2
        fp = FrameProcessor((size, size), 255, CircleROI(cx_px=c, cy_px=c, radius_px=radius))
        # Lattice points in a disc differ from its area by less than its perimeter.
        assert abs(fp.roi_pixel_count - math.pi * radius**2) <= 2 * math.pi * radius
        assert fp.count(np.zeros((size, size), np.uint8)) == fp.roi_pixel_count
        assert not fp.roi_is_clipped


def test_circle_roi_exact_small_counts() -> None:
    frame = np.zeros((9, 9), np.uint8)
    # radius 1 around a pixel centre: the centre and its 4 neighbours.
    assert occluded_pixel_count(frame, 0, CircleROI(cx_px=4, cy_px=4, radius_px=1.0)) == 5
    # radius sqrt(2): the full 3 x 3 block.
    assert occluded_pixel_count(frame, 0, CircleROI(cx_px=4, cy_px=4, radius_px=2**0.5)) == 9
    # centred between four pixels, radius 0.75: those four.
    assert occluded_pixel_count(frame, 0, CircleROI(cx_px=3.5, cy_px=3.5, radius_px=0.75)) == 4


roi_strategy = st.one_of(
    st.none(),
    st.builds(
        RectROI,
        x_px=st.integers(-30, 40),
        y_px=st.integers(-30, 40),
        width_px=st.integers(1, 50),
        height_px=st.integers(1, 50),
    ),
    st.builds(
        CircleROI,
        cx_px=st.floats(-20, 50, allow_nan=False),
        cy_px=st.floats(-20, 50, allow_nan=False),
        radius_px=st.floats(0.01, 40, allow_nan=False),
    ),
)


@settings(max_examples=150, deadline=None)
@given(
    frame=hnp.arrays(
        np.uint8,
        st.tuples(st.integers(1, 30), st.integers(1, 30)),
        elements=st.integers(0, 255),
    ),
    roi=roi_strategy,
    p=st.integers(0, 255),
    layout=st.sampled_from(["gray", "bgr", "bgra"]),
)
def test_processor_matches_numpy_reference(
    frame: U8, roi: RectROI | CircleROI | None, p: int, layout: str
) -> None:
    h, w = frame.shape
    mask = reference_mask(h, w, roi)
    expected = int(np.count_nonzero(frame[mask] <= p))
    if layout == "bgr":
        image = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    elif layout == "bgra":
        image = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGRA)
    else:
        image = frame
    fp = FrameProcessor(image.shape, p, roi)
    assert fp.count(image) == expected
    assert fp.count(image) == expected  # scratch buffers reused: same answer twice
    assert fp.roi_pixel_count == int(mask.sum())
    assert np.array_equal(roi_mask(image.shape, roi), mask)
    m = fp.measure(image)
    assert m.s_k_px == expected
    assert m.saturated_fraction == pytest.approx(
        np.count_nonzero(frame[mask] == 255) / mask.sum() if mask.any() else 0.0
    )
    assert (Flag.EMPTY_ROI in m.flags) == (not mask.any())


def test_processor_on_non_contiguous_frame_view() -> None:
    rng = np.random.default_rng(2)
    big = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    view = big[5:45, 10:70]  # strided rows, as a camera buffer crop would be
    roi = RectROI(x_px=3, y_px=4, width_px=40, height_px=30)
    fp = FrameProcessor(view.shape, 120, roi)
    gray = cv2.cvtColor(np.ascontiguousarray(view), cv2.COLOR_BGR2GRAY)
    assert fp.count(view) == int(np.count_nonzero(gray[4:34, 3:43] <= 120))


# ---------------------------------------------------------------------------- ROI edges


def test_roi_partially_outside_is_clipped_and_flagged() -> None:
    frame = np.zeros((10, 10), np.uint8)
    rect = RectROI(x_px=-3, y_px=7, width_px=5, height_px=10)  # cols 0-1, rows 7-9 inside
    fp = FrameProcessor(frame.shape, 0, rect)
    assert fp.count(frame) == 2 * 3
    assert fp.roi_is_clipped and not fp.roi_is_empty
    assert fp.measure(frame).flags == frozenset({Flag.ROI_CLIPPED})
    circle = CircleROI(cx_px=0, cy_px=0, radius_px=3)  # a quarter disc inside
    fpc = FrameProcessor(frame.shape, 0, circle)
    assert fpc.count(frame) == int(reference_mask(10, 10, circle).sum())
    assert fpc.measure(frame).flags == frozenset({Flag.ROI_CLIPPED})


def test_roi_inside_is_not_flagged() -> None:
    frame = np.zeros((10, 10), np.uint8)
    for roi in (
        RectROI(x_px=0, y_px=0, width_px=10, height_px=10),
        CircleROI(cx_px=4.5, cy_px=4.5, radius_px=4.5),
    ):
        assert FrameProcessor(frame.shape, 0, roi).measure(frame).flags == frozenset()


@pytest.mark.parametrize(
    "roi",
    [
        RectROI(x_px=10, y_px=0, width_px=5, height_px=5),
        RectROI(x_px=-5, y_px=0, width_px=5, height_px=5),
        RectROI(x_px=0, y_px=-100, width_px=5, height_px=99),
        CircleROI(cx_px=-10, cy_px=-10, radius_px=5),
        CircleROI(cx_px=0.5, cy_px=0.5, radius_px=0.2),  # between pixel centres
    ],
)
def test_roi_fully_outside_gives_zero_and_empty_flag(roi: RectROI | CircleROI) -> None:
    frame = np.zeros((10, 10, 3), np.uint8)
    fp = FrameProcessor(frame.shape, 255, roi)
    assert fp.roi_is_empty and fp.roi_pixel_count == 0
    assert fp.count(frame) == 0
    assert occluded_pixel_count(frame, 255, roi) == 0
    m = fp.measure(frame)
    assert m.s_k_px == 0 and m.saturated_fraction == 0.0
    assert m.flags == frozenset({Flag.EMPTY_ROI})
    assert fp.saturation_fraction(frame) == 0.0


def test_roi_models_validate_and_discriminate() -> None:
    adapter: TypeAdapter[RectROI | CircleROI] = TypeAdapter(ROI)
    rect = adapter.validate_python(
        {"kind": "rect", "x_px": 1, "y_px": 2, "width_px": 3, "height_px": 4}
    )
    assert isinstance(rect, RectROI)
    circle = adapter.validate_python({"kind": "circle", "cx_px": 1, "cy_px": 2.5, "radius_px": 3})
    assert isinstance(circle, CircleROI)
    with pytest.raises(ValidationError, match="greater than 0"):
        RectROI(x_px=0, y_px=0, width_px=0, height_px=4)
    with pytest.raises(ValidationError, match="greater than 0"):
        CircleROI(cx_px=0, cy_px=0, radius_px=-1)
    with pytest.raises(ValidationError, match="Extra inputs"):
        adapter.validate_python(
            {"kind": "rect", "x_px": 1, "y_px": 2, "width_px": 3, "height_px": 4, "r": 1}
        )
    with pytest.raises(ValidationError, match="does not match any of the expected tags"):
        adapter.validate_python({"kind": "ellipse", "cx_px": 1})
    with pytest.raises(ValidationError):
        CircleROI(cx_px=math.nan, cy_px=0, radius_px=1)
    with pytest.raises(ValidationError):
        rect.x_px = 5  # type: ignore[misc]  # frozen


# ---------------------------------------------------------------------------- saturation


def test_saturated_frame_flagged() -> None:
    frame = np.full((20, 20), 200, np.uint8)
    frame[:4, :] = 255  # 80 of 400 pixels = 20 %
    fp = FrameProcessor(frame.shape, 100)
    assert fp.saturated_pixel_count(frame) == 80
    assert fp.saturation_fraction(frame) == pytest.approx(0.2)
    assert Flag.SATURATED_FRAME in fp.measure(frame).flags
    # ROI that avoids the clipped rows: not saturated.
    fp_roi = FrameProcessor(frame.shape, 100, RectROI(x_px=0, y_px=4, width_px=20, height_px=16))
    assert fp_roi.measure(frame).flags == frozenset()


def test_saturation_limit_is_a_strict_upper_bound() -> None:
    frame = np.full((10, 10), 100, np.uint8)
    frame[0, 0] = 255  # exactly 1 %
    assert Flag.SATURATED_FRAME not in FrameProcessor(frame.shape, 50).measure(frame).flags
    frame[0, 1] = 255  # 2 %
    assert Flag.SATURATED_FRAME in FrameProcessor(frame.shape, 50).measure(frame).flags
    fp = FrameProcessor(frame.shape, 50, saturation_limit_fraction=0.05)
    assert Flag.SATURATED_FRAME not in fp.measure(frame).flags
    with pytest.raises(AnalysisError, match="saturation_limit_fraction"):
        FrameProcessor(frame.shape, 50, saturation_limit_fraction=1.5)


def test_saturation_uses_gray_value_of_colour_frames() -> None:
    frame = np.zeros((4, 4, 3), np.uint8)
    frame[0] = (255, 255, 255)  # gray 255: saturated
    frame[1] = (0, 0, 255)  # only red clipped: gray 76, not saturated
    assert FrameProcessor(frame.shape, 10).saturation_fraction(frame) == pytest.approx(0.25)


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("frame", "words"),
    [
        (np.zeros((4, 4), np.uint16), "uint16 is not accepted"),
        (np.zeros((4, 4), np.float32), "dtype float32 is not supported"),
        (np.zeros((4, 4), np.bool_), "dtype bool is not supported"),
        (np.zeros((4,), np.uint8), r"shape \(4,\) is not supported"),
        (np.zeros((4, 4, 5), np.uint8), r"shape \(4, 4, 5\) is not supported"),
        (np.zeros((2, 4, 4, 3), np.uint8), "is not supported"),
        (np.zeros((0, 4), np.uint8), "empty"),
    ],
)
def test_bad_frames_raise_clear_errors(frame: np.ndarray, words: str) -> None:
    with pytest.raises(AnalysisError, match=words):
        to_gray(frame)
    with pytest.raises(AnalysisError, match=words):
        occluded_pixel_count(frame, 10)


def test_non_array_frame_rejected() -> None:
    with pytest.raises(AnalysisError, match="numpy array"):
        to_gray([[1, 2], [3, 4]])  # type: ignore[arg-type]


def test_processor_rejects_frame_of_other_shape() -> None:
    fp = FrameProcessor((10, 10), 10)
    with pytest.raises(AnalysisError, match=r"built for shape \(10, 10\)"):
        fp.count(np.zeros((10, 11), np.uint8))
    with pytest.raises(AnalysisError, match="dtype uint16"):
        fp.count(np.zeros((10, 10), np.uint16))
    with pytest.raises(AnalysisError, match="threshold p"):
        FrameProcessor((10, 10), 300)
    with pytest.raises(AnalysisError, match="is not supported"):
        FrameProcessor((10, 10, 5), 10)


# ---------------------------------------------------------------------------- Otsu


@pytest.mark.parametrize(("dark", "bright"), [(40, 210), (90, 140), (0, 255), (200, 230)])
def test_otsu_threshold_separates_two_levels(dark: int, bright: int) -> None:
    frame = disc_frame((120, 160), (80, 60), 30, dark, bright)
    p = otsu_threshold(frame)
    assert dark <= p < bright
    fp = FrameProcessor(frame.shape, p)
    assert fp.count(frame) == int(np.count_nonzero(frame == dark))


def test_otsu_threshold_on_noisy_disc_with_circle_roi() -> None:
    rng = np.random.default_rng(3)
    frame = disc_frame((200, 200), (100, 100), 40, 70, 190).astype(np.float64)
    frame += rng.normal(0.0, 8.0, frame.shape)
    noisy = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
    bgr = cv2.cvtColor(noisy, cv2.COLOR_GRAY2BGR)
    roi = CircleROI(cx_px=100, cy_px=100, radius_px=80)
    p = otsu_threshold(bgr, roi)
    assert 100 < p < 160
    s_k = occluded_pixel_count(bgr, p, roi)
    assert abs(s_k - math.pi * 40**2) < 0.03 * math.pi * 40**2


def test_otsu_threshold_refuses_uniform_frame() -> None:
    with pytest.raises(AnalysisError, match="no bimodality, all 400 ROI pixels have intensity 128"):
        otsu_threshold(np.full((20, 20), 128, np.uint8))


def test_otsu_threshold_refuses_unimodal_noise() -> None:
    rng = np.random.default_rng(4)
    frame = np.clip(rng.normal(128, 20, (100, 100)), 0, 255).astype(np.uint8)
    with pytest.raises(AnalysisError, match="no clear bimodality"):
        otsu_threshold(frame)


def test_otsu_threshold_refuses_empty_roi() -> None:
    frame = disc_frame((50, 50), (25, 25), 10, 40, 200)
    with pytest.raises(AnalysisError, match="no pixel inside the frame"):
        otsu_threshold(frame, RectROI(x_px=100, y_px=0, width_px=5, height_px=5))


# ---------------------------------------------------------------------------- sub-pixel area


def hard_disc(shape: tuple[int, int], cx: float, cy: float, r: float, dark: int, bright: int) -> U8:
    """A disc drawn by pixel-centre membership: no intermediate level anywhere."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    inside = (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    return np.where(inside, dark, bright).astype(np.uint8)


def antialiased_disc(
    shape: tuple[int, int], cx: float, cy: float, r: float, dark: int, bright: int, sub: int = 16
) -> tuple[U8, float]:
    """A disc whose edge pixels hold the covered fraction c as ``bright - c (bright - dark)``.

    Coverage from ``sub x sub`` samples per pixel; returns the frame and the area the
    8-bit frame represents (sum of the covered fractions) [px].
    """
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    ys = (np.arange(shape[0])[:, None] + offs[None, :]).reshape(-1)
    xs = (np.arange(shape[1])[:, None] + offs[None, :]).reshape(-1)
    inside = (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2 <= r * r
    cover = inside.reshape(shape[0], sub, shape[1], sub).mean(axis=(1, 3))
    frame = np.rint(bright - cover * (bright - dark)).astype(np.uint8)
    return frame, float(cover.sum())


def test_membership_lut_is_binary_for_narrow_band_and_linear_inside() -> None:
    binary = subpixel_membership_lut(100, 1.0)
    assert np.array_equal(binary, (np.arange(256) <= 100).astype(np.float64))
    lut = subpixel_membership_lut(135, 129.0)
    levels = np.arange(71, 201)
    assert np.allclose(lut[levels], (200 - levels) / 129.0)
    assert lut[0] == 1.0 and lut[255] == 0.0
    assert np.all(np.diff(lut) <= 0.0)


@settings(max_examples=40, deadline=None)
@given(
    r=st.floats(3.0, 40.0),
    cx=st.floats(50.0, 51.0),
    cy=st.floats(45.0, 46.0),
    dark=st.integers(0, 90),
    bright=st.integers(170, 255),
)
def test_subpixel_area_exact_on_hard_edged_disc(
    r: float, cx: float, cy: float, dark: int, bright: int
) -> None:
    frame = hard_disc((96, 104), cx, cy, r, dark, bright)
    n_inside = int(np.count_nonzero(frame == dark))
    area = occluded_area_subpixel(frame, 128, edge_width_levels=64.0)
    assert area == n_inside == occluded_pixel_count(frame, 128)
    # Lattice points in a disc of radius r: |N - pi r^2| <= sqrt(2) pi r + pi / 2.
    assert abs(area - math.pi * r * r) <= math.sqrt(2.0) * math.pi * r + math.pi / 2


def test_subpixel_area_beats_binary_count_on_antialiased_edges() -> None:
    rng = np.random.default_rng(7)
    dark, bright, p = 71, 200, 135  # p + 0.5 is the mid level; w = contrast reads coverage
    soft_err, binary_err = [], []
    for r in np.linspace(4.0, 30.0, 24):
        cx, cy = 40.0 + rng.random(), 38.0 + rng.random()
        frame, area = antialiased_disc((80, 84), cx, cy, float(r), dark, bright)
        soft = occluded_area_subpixel(frame, p, edge_width_levels=float(bright - dark))
        binary = occluded_pixel_count(frame, p)
        edge_px = int(np.count_nonzero((frame > dark) & (frame < bright)))
        # Only the 8-bit rounding of each edge pixel (<= 0.5 level of 129) remains.
        assert abs(soft - area) <= edge_px * 0.5 / 129.0 + 1e-6
        soft_err.append(abs(soft - area))
        binary_err.append(abs(binary - area))
    assert max(soft_err) < 0.5
    assert np.mean(binary_err) > 10.0 * np.mean(soft_err)


def test_subpixel_area_processor_roi_and_colour() -> None:
    frame, _ = antialiased_disc((60, 64), 30.3, 28.7, 12.0, 70, 200, sub=8)
    roi = CircleROI(cx_px=30.0, cy_px=29.0, radius_px=20.0)
    proc = FrameProcessor(frame.shape, 128, roi, edge_width_levels=50.0)
    a = proc.occluded_area_subpixel(frame)
    assert a == occluded_area_subpixel(frame, 128, roi, edge_width_levels=50.0)
    bgr = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    assert occluded_area_subpixel(bgr, 128, roi, edge_width_levels=50.0) == a
    # Reference: the membership summed in float64 over the ROI mask.
    lut = subpixel_membership_lut(128, 50.0)
    expected = float(lut[frame][roi_mask(frame.shape, roi)].sum())
    assert a == pytest.approx(expected, abs=1e-4 * max(1.0, expected) + 0.01)
    # A pixel inside the ROI box but outside the circle must not count.
    corner = frame.copy()
    corner[10, 10] = 0
    assert proc.occluded_area_subpixel(corner) == a
    outside = FrameProcessor(frame.shape, 128, RectROI(x_px=500, y_px=0, width_px=5, height_px=5))
    assert outside.occluded_area_subpixel(frame) == 0.0


@settings(max_examples=60, deadline=None)
@given(
    frame=hnp.arrays(np.uint8, (17, 23)),
    p=st.integers(0, 255),
    w=st.floats(0.01, 1.0),
)
def test_subpixel_area_with_narrow_band_equals_binary_count(frame: U8, p: int, w: float) -> None:
    assert occluded_area_subpixel(frame, p, edge_width_levels=w) == occluded_pixel_count(frame, p)


@pytest.mark.parametrize("w", [0.0, -1.0, 256.0, math.nan, math.inf, True, "5"])
def test_subpixel_area_rejects_bad_edge_width(w: object) -> None:
    frame = np.zeros((4, 4), dtype=np.uint8)
    with pytest.raises(AnalysisError, match="edge_width_levels"):
        occluded_area_subpixel(frame, 10, edge_width_levels=w)  # type: ignore[arg-type]
    with pytest.raises(AnalysisError, match="edge_width_levels"):
        FrameProcessor(frame.shape, 10, edge_width_levels=w)  # type: ignore[arg-type]


@settings(max_examples=150, deadline=None)
@given(
    width=st.integers(1, 24),
    height=st.integers(1, 24),
    shape=st.sampled_from(["rect", "circle"]),
    a=st.floats(-8.0, 32.0),
    b=st.floats(-8.0, 32.0),
    c=st.floats(0.5, 40.0),
    d=st.floats(0.5, 40.0),
)
def test_covers_frame_is_true_exactly_when_the_s_kernel_counts_the_whole_frame(
    width: int, height: int, shape: str, a: float, b: float, c: float, d: float
) -> None:
    """An ROI covers the frame when S counted in it is S of the whole frame: checked by
    the counting kernel itself on an all-dark frame (every pixel occluded, Eq. (1)), where
    S is the number of frame pixels in the ROI. Edges: a rect just short of or past a
    border, a circle through the farthest pixel centre."""
    roi: RectROI | CircleROI
    if shape == "rect":
        roi = RectROI(kind="rect", x_px=round(a), y_px=round(b), width_px=round(c) or 1,
                      height_px=round(d) or 1)  # fmt: skip
    else:
        roi = CircleROI(kind="circle", cx_px=a, cy_px=b, radius_px=c)
    dark = np.zeros((height, width), np.uint8)
    whole = occluded_pixel_count(dark, 128, roi) == width * height
    assert covers_frame(roi, (width, height)) is whole
    assert same_roi(roi, None, (width, height)) is whole
    assert same_roi(roi, None, None) is False  # the frame size unknown: only equal ROIs


def test_whole_frame_roi_and_same_roi_edges() -> None:
    full = whole_frame_roi((640, 480))
    assert full == RectROI(kind="rect", x_px=0, y_px=0, width_px=640, height_px=480)
    assert same_roi(full, None, (640, 480)) and covers_frame(None, (640, 480))
    assert not same_roi(full, None, (641, 480))  # a pixel column outside it
    assert not same_roi(whole_frame_roi((639, 480)), None, (640, 480))
    # the circle through the corner pixel centres (0, 0) and (639, 479) holds the frame
    r = math.hypot(319.5, 239.5)
    assert covers_frame(CircleROI(kind="circle", cx_px=319.5, cy_px=239.5, radius_px=r),
                        (640, 480))  # fmt: skip
    assert not covers_frame(
        CircleROI(kind="circle", cx_px=319.5, cy_px=239.5, radius_px=r - 1e-9), (640, 480)
    )
    disc = CircleROI(kind="circle", cx_px=320, cy_px=240, radius_px=180)
    assert same_roi(disc, disc, None) and not same_roi(disc, full, (640, 480))
