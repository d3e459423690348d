"""Per-frame cost of S_k (Eqs. 1-2) with :class:`FrameProcessor`, frames read cold from memory.

Run: ``./dev python benchmarks/bench_imaging.py`` (or ``./dev bench``). Prints a Markdown
table and writes it to ``docs/bench_imaging.md``. Frames cycle through a pool larger than
the CPU caches, so each count reads its frame from main memory, as a camera stream does.
Compare with docs in ``shared/reference/performance.md`` (read floor, raw OpenCV route).
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, RectROI, sk_kernel

POOL_BYTES = 160 * 1024 * 1024
REPEATS = 7


def interleaved_ms(fns: list[Callable[[np.ndarray], Any]], frames: list[np.ndarray]) -> list[float]:
    """Median time per frame [ms] of each function; passes interleaved so load hits all alike."""
    runs: list[list[float]] = [[] for _ in fns]
    for _ in range(REPEATS):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            for f in frames:
                fn(f)
            runs[i].append((time.perf_counter() - t0) / len(frames) * 1e3)
    return [float(np.median(r)) for r in runs]


def raw_route(frame: np.ndarray) -> int:
    """The reference route of shared/reference/performance.md (threshold + countNonZero) on the
    whole frame, without any checks."""
    return int(cv2.countNonZero(cv2.threshold(frame, 100, 1, cv2.THRESH_BINARY_INV)[1]))


def raw_route_bgr(frame: np.ndarray) -> int:
    return raw_route(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))


def main() -> None:
    rng = np.random.default_rng(0)
    rows = []
    for name, (h, w) in {"720p": (720, 1280), "1080p": (1080, 1920)}.items():
        r = h // 2 - 20
        rois = {
            "whole frame": None,
            "rect 2r x 2r": RectROI(
                x_px=w // 2 - r, y_px=h // 2 - r, width_px=2 * r, height_px=2 * r
            ),
            "circle r": CircleROI(cx_px=w / 2, cy_px=h / 2, radius_px=r),
        }
        for layout, channels in (("gray", 1), ("BGR", 3)):
            shape = (h, w) if channels == 1 else (h, w, 3)
            n = max(8, POOL_BYTES // (h * w * channels))
            base = rng.integers(0, 256, shape, dtype=np.uint8)
            frames = [np.roll(base, i, axis=0) for i in range(n)]
            raw = raw_route if channels == 1 else raw_route_bgr
            for roi_name, roi in rois.items():
                fp = FrameProcessor(shape, 100, roi)
                floor, t, tm = interleaved_ms([raw, fp.count, fp.measure], frames)
                rows.append((name, layout, roi_name, t, tm, floor))
    header = (
        f"# FrameProcessor cost per frame\n\nMachine: {platform.processor() or platform.machine()},"
        f" Python {platform.python_version()}, OpenCV {cv2.__version__}, numpy {np.__version__};"
        " median of 7 interleaved passes over a frame pool larger than the caches. Raw route ="
        " `cv2.threshold(THRESH_BINARY_INV, maxval=1)` + `cv2.countNonZero` (after `cvtColor`"
        " for BGR) on the whole frame with no validation, the two-pass OpenCV route;"
        f" FrameProcessor counts with the compiled single-pass kernel `{sk_kernel()}`"
        " (docs/analysis.md)."
        f" Absolute times depend on machine load (1-min load average at the end:"
        f" {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs).\n\n"
        "| frame | layout | ROI | count [ms] | measure [ms] | raw cv2 route, whole frame [ms] |\n"
        "|---|---|---|---:|---:|---:|\n"
    )
    body = "".join(
        f"| {a} | {b} | {c} | {t:.3f} | {m:.3f} | {f:.3f} |\n" for a, b, c, t, m, f in rows
    )
    text = header + body
    print(text)
    out = Path(__file__).resolve().parent.parent / "docs" / "bench_imaging.md"
    out.write_text(text)


if __name__ == "__main__":
    main()
