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
    occluded_pixel_count,
    otsu_threshold,
    roi_mask,
    threshold_binary_inverted,
    to_gray,
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
        (np.zeros((4, 4, 2), np.uint8), r"shape \(4, 4, 2\) is not supported"),
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
        FrameProcessor((10, 10, 2), 10)


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
