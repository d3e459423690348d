"""Tests of the compiled single-pass S_k kernel (``_skcount.c``) and of the processor's use of it.

Every kernel the CPU runs (``c``, ``sse2``, ``avx2``) is checked against numpy's count on
random images, crops with a row stride larger than the width, and circle row spans; the
counts must also survive the kernels' 8-bit lane accumulators overflowing (blocks of 255
vectors). :class:`FrameProcessor` must give the same S_k and saturation with the kernel and
with the OpenCV fallback used when the extension is not built.
"""

from __future__ import annotations

import os
import platform
import threading
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from stipi_daemon.analysis import imaging
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, RectROI, roi_mask, sk_kernel
from tests.analysis.test_imaging import roi_strategy

_skcount = imaging._skcount

U8 = npt.NDArray[np.uint8]

# The kernel/backend fixtures select a routine once per test; every generated example runs
# with that same selection, which is what these tests want.
FIXED_FIXTURE = [HealthCheck.function_scoped_fixture]


def test_compiled_kernel_is_built() -> None:
    """``pip install`` builds the kernel; CI (STIPI_REQUIRE_TOOLCHAIN=1) must not fall back."""
    if _skcount is None:
        msg = "the compiled S_k kernel (stipi_daemon.analysis._skcount) was not built"
        if os.environ.get("STIPI_REQUIRE_TOOLCHAIN") == "1":
            pytest.fail(msg + " (STIPI_REQUIRE_TOOLCHAIN=1)")
        pytest.skip(msg)
    assert sk_kernel() in _skcount.available_kernels()
    assert sk_kernel() == _skcount.available_kernels()[-1]  # the best one is in use
    if platform.machine() in ("x86_64", "AMD64"):
        assert "sse2" in _skcount.available_kernels()


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


def ref_spans_count(image: U8, p: int, spans: npt.NDArray[np.int32]) -> tuple[int, int]:
    le = sat = 0
    for row, (x0, x1) in zip(image, spans, strict=True):
        part = row[x0:x1]
        le += int(np.count_nonzero(part <= p))
        sat += int(np.count_nonzero(part == 255))
    return le, sat


# --------------------------------------------------------------------------------------------
# The kernels against numpy
# --------------------------------------------------------------------------------------------

images = hnp.arrays(
    np.uint8,
    hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=300),
    elements=st.integers(0, 255),
)


@settings(max_examples=150, suppress_health_check=FIXED_FIXTURE)
@given(image=images, p=st.integers(0, 255))
def test_count_le_matches_numpy(kernel: str, image: U8, p: int) -> None:
    assert _skcount is not None
    assert _skcount.count_le(image, p) == int(np.count_nonzero(image <= p))
    le, sat = _skcount.count_le_and_saturated(image, p)
    assert (le, sat) == (int(np.count_nonzero(image <= p)), int(np.count_nonzero(image == 255)))
    assert _skcount.read_sum(image) == int(image.sum(dtype=np.uint64))


@settings(max_examples=150, suppress_health_check=FIXED_FIXTURE)
@given(
    image=images,
    p=st.integers(0, 255),
    data=st.data(),
)
def test_crop_with_row_stride_and_spans(
    kernel: str, image: U8, p: int, data: st.DataObject
) -> None:
    """A crop of a larger frame (row stride > width) and arbitrary valid row spans."""
    h, w = image.shape
    x0 = data.draw(st.integers(0, w - 1))
    x1 = data.draw(st.integers(x0 + 1, w))
    crop = image[:, x0:x1]
    assert crop.strides == (w, 1)
    cw = x1 - x0
    assert _skcount.count_le(crop, p) == int(np.count_nonzero(crop <= p))  # type: ignore[union-attr]
    starts = data.draw(hnp.arrays(np.int32, h, elements=st.integers(0, cw)))
    lengths = data.draw(hnp.arrays(np.int32, h, elements=st.integers(0, cw)))
    ends = np.minimum(starts + lengths, cw).astype(np.int32)
    spans = np.stack([starts, ends], axis=1)
    assert _skcount is not None
    assert _skcount.count_le(crop, p, spans) == ref_spans_count(crop, p, spans)[0]
    assert _skcount.count_le_and_saturated(crop, p, spans) == ref_spans_count(crop, p, spans)


@pytest.mark.parametrize("shape", [(1, 1), (1, 17), (3, 64), (1, 16320), (2, 16383), (700, 700)])
def test_lane_accumulators_do_not_overflow(kernel: str, shape: tuple[int, int]) -> None:
    """Every pixel matches: each 8-bit lane fills to 255 before it is widened, and sizes
    around the kernels' block lengths (255 x 16, 255 x 32, 255 x 64 bytes) are covered."""
    assert _skcount is not None
    dark = np.zeros(shape, dtype=np.uint8)
    bright = np.full(shape, 255, dtype=np.uint8)
    n = shape[0] * shape[1]
    assert _skcount.count_le(dark, 0) == n
    assert _skcount.count_le(bright, 254) == 0
    assert _skcount.count_le(bright, 255) == n
    assert _skcount.count_le_and_saturated(bright, 255) == (n, n)
    assert _skcount.count_le_and_saturated(dark, 255) == (n, 0)
    assert _skcount.read_sum(bright) == 255 * n


def test_large_frame_counts_exactly(kernel: str) -> None:
    """A 4K frame (8.3 Mpx, far beyond any 8- or 16-bit partial count)."""
    assert _skcount is not None
    rng = np.random.default_rng(7)
    frame = rng.integers(0, 256, (2160, 3840), dtype=np.uint8)
    for p in (0, 37, 128, 254, 255):
        assert _skcount.count_le(frame, p) == int(np.count_nonzero(frame <= p))
    assert _skcount.count_le_and_saturated(frame, 100)[1] == int(np.count_nonzero(frame == 255))


def test_threads_count_concurrently() -> None:
    """The kernel releases the GIL and keeps no state: threads get exact counts."""
    assert_built()
    assert _skcount is not None
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(4)]
    want = [int(np.count_nonzero(f <= 90)) for f in frames]
    errors: list[str] = []

    def work(i: int) -> None:
        for _ in range(50):
            got = _skcount.count_le(frames[i], 90)  # type: ignore[union-attr]
            if got != want[i]:
                errors.append(f"thread {i}: {got} != {want[i]}")

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


# --------------------------------------------------------------------------------------------
# Bad input: clear errors naming the problem
# --------------------------------------------------------------------------------------------


def assert_built() -> None:
    if _skcount is None:
        pytest.skip("compiled S_k kernel not built (see test_compiled_kernel_is_built)")


@pytest.mark.parametrize(
    ("image", "p", "error", "match"),
    [
        (np.zeros((4, 4), np.uint16), 10, TypeError, "uint8"),
        (np.zeros((4, 4), np.float32), 10, TypeError, "uint8"),
        (np.zeros((4, 4, 4), np.uint8), 10, ValueError, "2 \\(YUYV\\) or 3 \\(BGR\\) channels"),
        (np.zeros((4, 4, 3), np.uint8), 10, ValueError, "needs bgr_weights"),
        (np.zeros(16, np.uint8), 10, ValueError, "2-D"),
        (np.zeros((4, 8), np.uint8)[:, ::2], 10, ValueError, "column stride 2"),
        (np.zeros((4, 4), np.uint8)[::-1], 10, ValueError, "row stride -4"),
        (np.zeros((4, 4), np.uint8), 256, ValueError, "0..255, got 256"),
        (np.zeros((4, 4), np.uint8), -1, ValueError, "0..255, got -1"),
        (b"abcd", 10, ValueError, "2-D"),
    ],
)
def test_bad_images(image: object, p: int, error: type[Exception], match: str) -> None:
    assert_built()
    assert _skcount is not None
    with pytest.raises(error, match=match):
        _skcount.count_le(image, p)


@pytest.mark.parametrize(
    ("spans", "error", "match"),
    [
        (np.zeros((3, 2), np.int32), ValueError, r"2 x 4 int32.*got 6"),
        (np.zeros((4, 2), np.int64), TypeError, "int32"),
        (np.array([[0, 4], [0, 5], [0, 0], [0, 0]], np.int32), ValueError, r"row 1 is \[0, 5\)"),
        (np.array([[0, 4], [0, 4], [-1, 2], [0, 0]], np.int32), ValueError, r"row 2 is \[-1, 2\)"),
    ],
)
def test_bad_spans(spans: object, error: type[Exception], match: str) -> None:
    assert_built()
    assert _skcount is not None
    with pytest.raises(error, match=match):
        _skcount.count_le(np.zeros((4, 4), np.uint8), 10, spans)


def test_unknown_kernel_is_refused() -> None:
    assert_built()
    assert _skcount is not None
    with pytest.raises(ValueError, match="'neon' is not available"):
        _skcount.use_kernel("neon")
    assert _skcount.kernel() == _skcount.available_kernels()[-1]


# --------------------------------------------------------------------------------------------
# FrameProcessor: compiled kernel and OpenCV fallback agree
# --------------------------------------------------------------------------------------------


@pytest.fixture(params=["compiled", "opencv"])
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    if request.param == "opencv":
        monkeypatch.setattr(imaging, "_skcount", None)
        assert sk_kernel() == "opencv"
    else:
        assert_built()
    return str(request.param)


@settings(max_examples=120, suppress_health_check=FIXED_FIXTURE)
@given(
    frame=hnp.arrays(
        np.uint8,
        st.sampled_from([(48, 64), (48, 64, 1), (48, 64, 3), (50, 70, 4)]),
        elements=st.sampled_from([0, 1, 40, 99, 100, 101, 200, 254, 255]),
    ),
    p=st.integers(0, 255),
    roi=roi_strategy,
)
def test_processor_matches_reference_on_both_backends(
    backend: str, frame: U8, p: int, roi: RectROI | CircleROI | None
) -> None:
    gray = imaging.to_gray(frame)
    member = roi_mask(frame.shape, roi)
    fp = FrameProcessor(frame.shape, p, roi)
    want_s = int(np.count_nonzero((gray <= p) & member))
    want_sat = int(np.count_nonzero((gray == 255) & member))
    assert fp.count(frame) == want_s
    m = fp.measure(frame)
    assert m.s_k_px == want_s
    n_roi = int(member.sum())
    assert m.saturated_fraction == (want_sat / n_roi if n_roi else 0.0)
    assert fp.saturated_pixel_count(frame) == want_sat
    if n_roi and want_sat / n_roi > 0.01:
        assert Flag.SATURATED_FRAME in m.flags


def test_processor_accepts_frames_with_strided_columns(backend: str) -> None:
    """A gray view with a column stride (e.g. every other column of a wider buffer) is
    counted from a contiguous copy; the result is the same."""
    rng = np.random.default_rng(1)
    wide = rng.integers(0, 256, (60, 160), dtype=np.uint8)
    frame = wide[:, ::2]
    fp = FrameProcessor(frame.shape, 120, CircleROI(cx_px=40.0, cy_px=30.0, radius_px=25.0))
    member = roi_mask(frame.shape, fp.roi)
    assert fp.count(frame) == int(np.count_nonzero((frame <= 120) & member))


@settings(max_examples=200)
@given(
    cx=st.floats(-50, 150, allow_nan=False),
    cy=st.floats(-50, 150, allow_nan=False),
    r=st.floats(0.2, 120, allow_nan=False),
)
def test_circle_row_spans_describe_the_mask(cx: float, cy: float, r: float) -> None:
    """The per-row spans the kernel reads cover exactly the circle's member pixels."""
    roi = CircleROI(cx_px=cx, cy_px=cy, radius_px=r)
    fp = FrameProcessor((100, 120), 0, roi)
    if fp.roi_is_empty:
        return
    y0, _, x0, _ = fp.bounding_box
    spans = fp._spans
    assert spans is not None
    rebuilt = np.zeros((100, 120), dtype=bool)
    for row, (a, b) in enumerate(spans):
        rebuilt[y0 + row, x0 + a : x0 + b] = True
    assert np.array_equal(rebuilt, roi_mask((100, 120), roi))
