"""S_k of BGR and YUYV frames counted on the fly by the compiled kernel (``_skcount.c``).

The oracle is OpenCV itself: ``cv2.cvtColor(COLOR_BGR2GRAY)`` and
``cv2.cvtColor(COLOR_YUV2GRAY_YUYV)`` give each pixel's gray value, and S_k counts the ROI
pixels whose gray value is <= p (Eqs. (1)-(2)). Every kernel the CPU runs (``c``, ``sse2``,
``avx2``, forced in turn) must agree with it on every one of the 2**24 BGR values and every
Y value, on random frames, crops, row spans, odd widths, 1-pixel ROIs and ROIs touching the
frame's edges; :class:`FrameProcessor` must give the same S_k and saturation on the kernel
and on the OpenCV route it falls back to.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from stipi_daemon.analysis import imaging
from stipi_daemon.analysis.imaging import (
    CircleROI,
    FrameProcessor,
    RectROI,
    bgr_gray_formula,
    roi_mask,
)
from tests.analysis.test_imaging import roi_strategy

_skcount = imaging._skcount

U8 = npt.NDArray[np.uint8]
FIXED_FIXTURE = [HealthCheck.function_scoped_fixture]

pytestmark = pytest.mark.skipif(_skcount is None, reason="compiled S_k kernel not built")


def _kernels() -> list[str]:
    return [] if _skcount is None else list(_skcount.available_kernels())


@pytest.fixture(params=_kernels())
def kernel(request: pytest.FixtureRequest) -> Iterator[str]:
    assert _skcount is not None
    name = str(request.param)
    assert _skcount.use_kernel(name) == name
    try:
        yield name
    finally:
        _skcount.use_kernel("best")


def weights() -> tuple[int, int, int, int, int]:
    formula = bgr_gray_formula()
    if formula is None:
        pytest.skip("cv2.cvtColor's BGR -> gray formula on this OpenCV build is not a known one")
    return formula.weights


def opencv_gray(image: U8) -> U8:
    """Each pixel's gray value as OpenCV computes it (the oracle)."""
    if image.ndim == 2:
        return image
    code = {1: None, 2: cv2.COLOR_YUV2GRAY_YUYV, 3: cv2.COLOR_BGR2GRAY}[image.shape[2]]
    if code is None:
        return image[:, :, 0]
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), code), dtype=np.uint8)


def kernel_counts(image: U8, p: int, spans: npt.NDArray[np.int32] | None = None) -> tuple[int, int]:
    assert _skcount is not None
    w = weights() if image.ndim == 3 and image.shape[2] == 3 else None
    le = _skcount.count_le(image, p, spans, bgr_weights=w)
    both = _skcount.count_le_and_saturated(image, p, spans, bgr_weights=w)
    assert both[0] == le
    return int(both[0]), int(both[1])


def ref_counts(image: U8, p: int, spans: npt.NDArray[np.int32] | None = None) -> tuple[int, int]:
    gray = opencv_gray(image)
    if spans is not None:
        cols = np.arange(gray.shape[1])[None, :]
        member = (cols >= spans[:, :1]) & (cols < spans[:, 1:])
        gray = gray[member]
    return int(np.count_nonzero(gray <= p)), int(np.count_nonzero(gray == 255))


# --------------------------------------------------------------------------------------------
# The gray formula: every BGR value, every kernel
# --------------------------------------------------------------------------------------------


def all_bgr_by_gray() -> list[U8]:
    """All 2**24 BGR values, grouped by the gray value cv2.cvtColor gives them: entry v is a
    (1, n_v, 3) image whose every pixel cvtColor maps to v."""
    v = np.arange(1 << 24, dtype=np.uint32)
    cube = np.empty((1 << 24, 3), dtype=np.uint8)
    cube[:, 0], cube[:, 1], cube[:, 2] = v & 255, (v >> 8) & 255, v >> 16
    gray = cv2.cvtColor(cube.reshape(4096, 4096, 3), cv2.COLOR_BGR2GRAY).reshape(-1)
    order = np.argsort(gray, kind="stable")
    bounds = np.searchsorted(gray[order], np.arange(257))
    return [cube[order[bounds[g] : bounds[g + 1]]].reshape(1, -1, 3) for g in range(256)]


@pytest.fixture(scope="module")
def bgr_by_gray() -> list[U8]:
    return all_bgr_by_gray()


def test_formula_is_identified_on_this_build() -> None:
    """The x86 builds this project runs on (OpenCV's own code or its IPP HAL) are known."""
    formula = bgr_gray_formula()
    assert formula is not None
    assert formula.name in ("ipp", "opencv")
    cb, cg, cr, d, s = formula.weights
    assert 0 <= d < 1 << s
    assert cb + cg + cr == 1 << s  # white stays 255


def test_every_bgr_value_has_cvtcolor_gray(kernel: str, bgr_by_gray: list[U8]) -> None:
    """Each pixel's gray value is exactly cvtColor's, for all 2**24 BGR values: the pixels
    cvtColor maps to v are all counted at p = v and none at p = v - 1; saturated iff v = 255."""
    assert _skcount is not None
    w = weights()
    for v, img in enumerate(bgr_by_gray):
        n = img.shape[1]
        assert n > 0
        assert _skcount.count_le_and_saturated(img, v, bgr_weights=w) == (n, n if v == 255 else 0)
        if v > 0:
            assert _skcount.count_le(img, v - 1, bgr_weights=w) == 0, f"gray {v}"


def test_every_y_value_counts_as_cvtcolor_gray(kernel: str) -> None:
    """YUYV: the gray value is the Y byte (cv2.COLOR_YUV2GRAY_YUYV) whatever U and V are."""
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 256, (256, 300, 2), dtype=np.uint8)
    frame[:, :, 0] = np.arange(256, dtype=np.uint8)[:, None]  # row y has Y = y
    assert np.array_equal(opencv_gray(frame), frame[:, :, 0])
    for p in range(256):
        assert kernel_counts(frame, p) == ref_counts(frame, p)


@pytest.mark.parametrize("channels", [2, 3])
@pytest.mark.parametrize("value", [0, 255])
@pytest.mark.parametrize("shape", [(1, 1), (1, 31), (3, 33), (2, 8161), (700, 700)])
def test_uniform_frames_and_lane_overflow(
    kernel: str, channels: int, value: int, shape: tuple[int, int]
) -> None:
    """All-0 and all-255 frames, sizes around the kernels' block lengths (255 steps of 16,
    32 or 64 bytes, of 32 BGR pixels): every 8-bit lane fills up before it is widened."""
    frame = np.full((*shape, channels), value, dtype=np.uint8)
    n = shape[0] * shape[1]
    for p in (0, 1, 254, 255):
        want = (n if value <= p else 0, n if value == 255 else 0)
        assert kernel_counts(frame, p) == want == ref_counts(frame, p)


@pytest.mark.parametrize("channels", [2, 3])
def test_large_frame_counts_exactly(kernel: str, channels: int) -> None:
    """A 4K frame (8.3 Mpx): counts far beyond any 8-, 16- or 32-bit partial sum per lane."""
    rng = np.random.default_rng(11)
    frame = rng.integers(0, 256, (2160, 3840, channels), dtype=np.uint8)
    for p in (0, 90, 128, 255):
        assert kernel_counts(frame, p) == ref_counts(frame, p)


# --------------------------------------------------------------------------------------------
# Random frames, crops, spans
# --------------------------------------------------------------------------------------------


def colour_frames(channels: int) -> st.SearchStrategy[U8]:
    return hnp.arrays(
        np.uint8,
        st.tuples(st.integers(1, 70), st.integers(1, 130), st.just(channels)),
        elements=st.integers(0, 255),
    )


@settings(max_examples=80, deadline=None, suppress_health_check=FIXED_FIXTURE)
@given(
    frame=st.one_of(colour_frames(2), colour_frames(3)),
    p=st.integers(0, 255),
    data=st.data(),
)
def test_random_crops_and_spans(kernel: str, frame: U8, p: int, data: st.DataObject) -> None:
    """A crop of a larger frame (row stride > row, odd column offsets and widths) with
    arbitrary valid row spans: counts equal cvtColor's gray values counted by numpy."""
    h, w, _ = frame.shape
    x0 = data.draw(st.integers(0, w - 1))
    x1 = data.draw(st.integers(x0 + 1, w))
    crop = frame[:, x0:x1]
    assert kernel_counts(crop, p) == ref_counts(crop, p)
    cw = x1 - x0
    starts = data.draw(hnp.arrays(np.int32, h, elements=st.integers(0, cw)))
    lengths = data.draw(hnp.arrays(np.int32, h, elements=st.integers(0, cw)))
    spans = np.stack([starts, np.minimum(starts + lengths, cw).astype(np.int32)], axis=1)
    assert kernel_counts(crop, p, spans) == ref_counts(crop, p, spans)


@pytest.mark.parametrize("channels", [1, 2, 3])
def test_every_span_start_and_length(kernel: str, channels: int) -> None:
    """Spans starting at each of the first 13 columns with every length up to the row (the
    kernels switch between whole vectors, the first group, overlapping masked last vectors
    and scalar code at 8, 16, 32, 34, 40 and 64 pixels or bytes)."""
    rng = np.random.default_rng(12)
    width = 150
    shape = (2, width) if channels == 1 else (2, width, channels)
    frame = rng.integers(0, 256, shape, dtype=np.uint8)
    frame[rng.random((2, width)) < 0.2] = 255
    gray = opencv_gray(frame)
    for x0 in range(13):
        for x1 in range(x0, width + 1):
            spans = np.array([[x0, x1], [width - x1 + x0, width]], dtype=np.int32)
            part = np.concatenate([gray[0, x0:x1], gray[1, width - x1 + x0 :]])
            for p in (0, 130):
                want = (int(np.count_nonzero(part <= p)), int(np.count_nonzero(part == 255)))
                assert kernel_counts(frame, p, spans) == want, (x0, x1, p)


@pytest.mark.parametrize("channels", [1, 2, 3])
def test_read_sum_reads_the_span_bytes(channels: int) -> None:
    """read_sum (the benchmarks' floor) sums exactly the bytes of the pixels in the spans."""
    assert _skcount is not None
    rng = np.random.default_rng(2)
    shape = (40, 57) if channels == 1 else (40, 57, channels)
    frame = rng.integers(0, 256, shape, dtype=np.uint8)
    starts = rng.integers(0, 57, 40).astype(np.int32)
    spans = np.stack([starts, np.minimum(starts + rng.integers(0, 40, 40), 57)], 1)
    spans = spans.astype(np.int32)
    want = sum(int(frame[r, a:b].sum(dtype=np.uint64)) for r, (a, b) in enumerate(spans))
    assert _skcount.read_sum(frame, spans) == want
    assert _skcount.read_sum(frame) == int(frame.sum(dtype=np.uint64))


# --------------------------------------------------------------------------------------------
# FrameProcessor: kernel on the fly, OpenCV route, identical counts
# --------------------------------------------------------------------------------------------


def processors(
    shape: tuple[int, ...], p: int, roi: RectROI | CircleROI | None
) -> tuple[FrameProcessor, FrameProcessor]:
    """(on the compiled kernel, on the OpenCV route used when it is not built)."""
    fast = FrameProcessor(shape, p, roi)
    saved = imaging._skcount
    imaging._skcount = None
    try:
        slow = FrameProcessor(shape, p, roi)
    finally:
        imaging._skcount = saved
    assert not slow.counts_on_the_fly
    return fast, slow


def reference(frame: U8, p: int, roi: RectROI | CircleROI | None) -> tuple[int, int]:
    gray = opencv_gray(frame)
    member = roi_mask(frame.shape, roi)
    return (
        int(np.count_nonzero((gray <= p) & member)),
        int(np.count_nonzero((gray == 255) & member)),
    )


def check_processor(frame: U8, p: int, roi: RectROI | CircleROI | None) -> None:
    fast, slow = processors(frame.shape, p, roi)
    assert fast.counts_on_the_fly
    want_s, want_sat = reference(frame, p, roi)
    n_roi = fast.roi_pixel_count
    for fp in (fast, slow):
        assert fp.count(frame) == want_s
        m = fp.measure(frame)
        assert m.s_k_px == want_s
        assert m.saturated_fraction == (want_sat / n_roi if n_roi else 0.0)
        assert fp.saturated_pixel_count(frame) == want_sat
    assert fast.measure(frame) == slow.measure(frame)


@settings(max_examples=120, deadline=None, suppress_health_check=FIXED_FIXTURE)
@given(
    frame=hnp.arrays(
        np.uint8,
        st.tuples(st.integers(1, 48), st.integers(1, 64), st.sampled_from([2, 3])),
        elements=st.integers(0, 255),
    ),
    p=st.integers(0, 255),
    roi=roi_strategy,
)
def test_processor_matches_opencv_route(
    kernel: str, frame: U8, p: int, roi: RectROI | CircleROI | None
) -> None:
    check_processor(frame, p, roi)


EDGE_ROIS = [
    RectROI(x_px=0, y_px=0, width_px=1, height_px=1),  # 1 pixel, top-left corner
    RectROI(x_px=36, y_px=24, width_px=1, height_px=1),  # 1 pixel, bottom-right corner
    RectROI(x_px=17, y_px=9, width_px=1, height_px=1),  # 1 pixel at an odd column
    CircleROI(cx_px=17.0, cy_px=9.0, radius_px=0.3),  # 1-pixel circle
    CircleROI(cx_px=0.0, cy_px=0.0, radius_px=8.5),  # quarter disc in a corner
    CircleROI(cx_px=36.0, cy_px=12.0, radius_px=9.0),  # touching the right edge (odd width)
    CircleROI(cx_px=18.0, cy_px=12.5, radius_px=40.0),  # larger than the frame
    RectROI(x_px=-5, y_px=-5, width_px=60, height_px=60),  # the whole frame and beyond
    RectROI(x_px=35, y_px=0, width_px=9, height_px=25),  # last two columns
]


@pytest.mark.parametrize("channels", [2, 3])
@pytest.mark.parametrize("roi", EDGE_ROIS, ids=repr)
def test_processor_edge_rois_odd_width(
    kernel: str, channels: int, roi: RectROI | CircleROI
) -> None:
    """Odd width (37 px), 1-pixel ROIs and ROIs touching or crossing every edge."""
    rng = np.random.default_rng(4)
    frame = rng.integers(0, 256, (25, 37, channels), dtype=np.uint8)
    frame[rng.random((25, 37)) < 0.1] = 255
    for p in (0, 127, 254, 255):
        check_processor(frame, p, roi)


def test_scene_frame_on_the_fly_equals_opencv_route(kernel: str) -> None:
    """A BGR probe image (dark disc on a bright waveguide) and its YUYV version."""
    h, w = 120, 161
    yy, xx = np.mgrid[0:h, 0:w]
    gray = np.where((xx - 80) ** 2 + (yy - 60) ** 2 <= 30**2, 60, 200).astype(np.uint8)
    bgr = np.dstack([gray, (gray * 0.9).astype(np.uint8), np.clip(gray * 1.1, 0, 255)])
    bgr = bgr.astype(np.uint8)
    yuyv = np.dstack([gray, np.full_like(gray, 128)])
    roi = CircleROI(cx_px=80.0, cy_px=60.0, radius_px=55.0)
    for frame in (bgr, yuyv):
        for p in (59, 60, 100, 128, 199, 200):
            check_processor(frame, p, roi)


def test_unknown_formula_falls_back_to_cvtcolor(monkeypatch: pytest.MonkeyPatch) -> None:
    """On an OpenCV build whose BGR -> gray rounding is not a known formula, BGR frames are
    converted with cv2.cvtColor first (never counted with a formula that may differ)."""
    monkeypatch.setattr(imaging, "bgr_gray_formula", lambda: None)
    rng = np.random.default_rng(8)
    frame = rng.integers(0, 256, (30, 41, 3), dtype=np.uint8)
    roi = CircleROI(cx_px=20.0, cy_px=15.0, radius_px=12.0)
    fp = FrameProcessor(frame.shape, 128, roi)
    assert not fp.counts_on_the_fly
    assert (fp.count(frame), fp.saturated_pixel_count(frame)) == reference(frame, 128, roi)
    assert FrameProcessor((30, 41, 2), 128, roi).counts_on_the_fly  # YUYV needs no formula


def test_processor_takes_frames_with_padded_rows(kernel: str) -> None:
    """Frames that are views with padded rows (a wider buffer) and non-contiguous
    channels are counted as their pixel values say."""
    rng = np.random.default_rng(9)
    wide = rng.integers(0, 256, (30, 50, 4), dtype=np.uint8)
    roi = CircleROI(cx_px=20.0, cy_px=14.0, radius_px=11.0)
    for frame in (wide[:, 3:44, :3], wide[:, 3:44, :2], wide[:, :, 1:]):
        want = reference(np.ascontiguousarray(frame), 111, roi)
        fp = FrameProcessor(frame.shape, 111, roi)
        assert (fp.count(frame), fp.saturated_pixel_count(frame)) == want


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("w", "match"),
    [
        (None, "needs bgr_weights"),
        ((1, 2, 3), "5 integers"),
        ((3735, 19235, 9798, 16384, 14), "not a fixed-point gray formula"),
        ((3735, 19235, 9798, 32768, 15), "not a fixed-point gray formula"),
        ((40000, 0, 0, 0, 15), "not a fixed-point gray formula"),
        ((-1, 19236, 9798, 0, 15), "not a fixed-point gray formula"),
    ],
)
def test_bad_bgr_weights(w: object, match: str) -> None:
    assert _skcount is not None
    with pytest.raises((ValueError, TypeError), match=match):
        _skcount.count_le(np.zeros((4, 4, 3), np.uint8), 10, None, bgr_weights=w)


def test_weights_on_gray_or_yuyv_are_refused() -> None:
    assert _skcount is not None
    with pytest.raises(ValueError, match="3-channel"):
        _skcount.count_le(np.zeros((4, 4, 2), np.uint8), 10, bgr_weights=weights())


def test_pixels_must_be_contiguous() -> None:
    assert _skcount is not None
    planar = np.zeros((3, 4, 4), np.uint8).transpose(1, 2, 0)  # channel stride 16
    with pytest.raises(ValueError, match="channel stride 16"):
        _skcount.count_le(planar, 10, bgr_weights=weights())
    every_other = np.zeros((4, 8, 2), np.uint8)[:, ::2]
    with pytest.raises(ValueError, match="column stride 4, expected 2"):
        _skcount.count_le(every_other, 10)
