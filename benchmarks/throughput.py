"""Throughput of the S_k path against its limits: memory floor, JPEG decoding, real time.

For 640x480, 1280x720 and 1920x1080 frames of the simulator's grade-III scene (sensor noise
2 levels), gray, YUYV (packed 4:2:2, ``(H, W, 2)``), BGR and MJPG input, one thread on one
pinned CPU, it measures:

* the read floor of the whole frame: the fastest of several read-only kernels over it
  (``cv2.sumElems``, numpy ``sum`` of a uint64 view, ``cv2.countNonZero``, the compiled
  ``_skcount.read_sum``, a SIMD byte sum) with frames cold from main memory (a pool larger
  than the caches), i.e. the time to read the frame once;
* the read floor of the circle ROI: reading only the bytes inside the ROI's per-row spans,
  where they are in the frame (``_skcount.read_sum`` with the spans, prefetching the rows
  ahead), and for comparison the same number of bytes read as one contiguous block;
* ``FrameProcessor.count`` (S_k) and ``FrameProcessor.measure`` (S_k + saturation, what the
  daemon calls) with the whole frame as ROI and with the scene's circular ROI, and their
  ratio to the matching read floor, measured in the same interleaved passes (goals: gray
  within 2x; YUYV and BGR, gray values computed on the fly, within 1.3x; the circle ROI
  within 1.3x of its span bytes); the same through the OpenCV route the processor falls
  back to when the compiled kernel is not built (``cv2.cvtColor`` for colour,
  ``cv2.threshold`` + ``cv2.countNonZero``);
* MJPG: ``cv2.imdecode(IMREAD_GRAYSCALE)`` alone, and decode + ``measure``; their ratio
  (goal: within 1.2x of decoding alone);
* the real-time factor of a 120 s, 60 FPS recording (7200 frames) and how many 60 FPS
  streams one core sustains.

Run (from the repository root)::

    ./dev python benchmarks/throughput.py           # full run, about a minute
    ./dev python benchmarks/throughput.py --quick   # smoke run: 640x480 only, small pool

Options: ``--out FILE`` (default ``docs/performance.md``). The script replaces only its own
sections of that file (from ``## S_k throughput`` to the next section it does not own),
so other sections (e.g. the live daemon's latency) are kept.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from _machine import cpu_model

from stipi_daemon.analysis import imaging
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, sk_kernel
from stipi_daemon.sim import Pipeline, load_scene

ROOT = Path(__file__).resolve().parent.parent
SIZES = {"640x480": (640, 480), "1280x720": (1280, 720), "1920x1080": (1920, 1080)}
POOL_BYTES = 192 * 1024 * 1024  # larger than the last-level cache: frames come from memory
RECORDING_S, FPS = 120.0, 60.0
SECTION = "## S_k throughput"
JPEG_QUALITY = 95


def pin_one_cpu() -> str:
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpu = sorted(os.sched_getaffinity(0))[-1]
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned"


def best_ms(
    fns: dict[str, Callable[[Any], Any]], items: Sequence[Any], repeats: int
) -> dict[str, float]:
    """Best (least disturbed) time per item [ms] of each function over interleaved passes."""
    runs: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            for it in items:
                fn(it)
            runs[name].append((time.perf_counter() - t0) / len(items) * 1e3)
    return {k: float(np.min(v)) for k, v in runs.items()}


def scene_frames(width: int, height: int, n: int) -> tuple[list[np.ndarray], CircleROI, int]:
    """n distinct BGR frames of the noisy grade-III recovery, the scene's ROI and p."""
    scene = load_scene(ROOT / "configs" / "scenes" / "grade3.yaml")
    scene = scene.with_camera(width=width, height=height).with_effects(
        [{"name": "sensor_noise", "sigma_levels": 2.0}]
    )
    pipe = Pipeline(scene, 1)
    t0 = pipe.model.t0_s
    frames = []
    for k in range(n):
        t = t0 + 0.5 + k * 3.0
        frames.append(next(iter(pipe.frames(t, t))).image)
    return frames, pipe.renderer.roi, scene.probe.threshold


def pool(frames: list[np.ndarray], quick: bool) -> list[np.ndarray]:
    """Copies of the frames filling the pool (each its own memory)."""
    budget = POOL_BYTES // (8 if quick else 1)
    n = max(len(frames), budget // frames[0].nbytes)
    return [frames[i % len(frames)].copy() for i in range(n)]


def yuyv_frames(bgr: list[np.ndarray]) -> list[np.ndarray]:
    """The frames as a YUYV camera delivers them: (H, W, 2), Y then U (even x) / V (odd x)."""
    out = []
    for f in bgr:
        yuv = cv2.cvtColor(f, cv2.COLOR_BGR2YUV)
        packed = np.empty((*f.shape[:2], 2), dtype=np.uint8)
        packed[:, :, 0] = yuv[:, :, 0]
        packed[:, 0::2, 1] = yuv[:, 0::2, 1]
        packed[:, 1::2, 1] = yuv[:, 0::2, 2]
        out.append(packed)
    return out


FLOOR = "floor: "


def roi_floor_kernel(fp: FrameProcessor) -> tuple[Callable[[Any], Any], int]:
    """The circle ROI's read floor as a kernel over whole frames (its span bytes read in
    place, nothing else) and that number of bytes."""
    y0, y1, x0, x1 = fp.bounding_box
    spans = fp.row_spans
    assert spans is not None and imaging._skcount is not None
    sk = imaging._skcount
    pixel = fp.frame_shape[2] if len(fp.frame_shape) == 3 else 1
    n_bytes = int((spans[:, 1] - spans[:, 0]).sum()) * pixel
    return (lambda f: sk.read_sum(f[y0:y1, x0:x1], spans)), n_bytes


def contiguous_floor(n_bytes: int, repeats: int, quick: bool) -> float:
    """Time to read n_bytes as one contiguous block, cold [ms] (for comparison)."""
    rng = np.random.default_rng(0)
    n_blocks = max(8, (POOL_BYTES // (8 if quick else 1)) // n_bytes)
    block = -(-n_bytes // 64) * 64  # whole cache lines (the uint64 view needs a multiple of 8)
    blocks = [rng.integers(0, 256, (1, block), dtype=np.uint8) for _ in range(n_blocks)]
    t = best_ms(read_kernels(blocks[0]), blocks, repeats)
    return min(t.values())


def read_kernels(frame: np.ndarray) -> dict[str, Callable[[Any], Any]]:
    """Read-only passes over a whole frame, the candidates for its read floor."""
    kernels: dict[str, Callable[[Any], Any]] = {
        "cv2.sumElems": cv2.sumElems,
        "numpy sum (uint64 view)": lambda f: f.reshape(-1).view(np.uint64).sum(),
    }
    if frame.ndim == 2:
        kernels["cv2.countNonZero"] = cv2.countNonZero
    if imaging._skcount is not None:
        kernels["_skcount.read_sum"] = lambda f: imaging._skcount.read_sum(f.reshape(len(f), -1))
    return kernels


def opencv_processor(*args: Any) -> FrameProcessor:
    """A processor on the OpenCV route (what runs when the compiled kernel is not built)."""
    saved = imaging._skcount
    imaging._skcount = None
    try:
        return FrameProcessor(*args)
    finally:
        imaging._skcount = saved


def measure_size(label: str, width: int, height: int, quick: bool) -> list[dict[str, Any]]:
    repeats = 3 if quick else 11
    bgr, roi, p = scene_frames(width, height, 8)
    gray = [np.ascontiguousarray(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)) for f in bgr]
    rows: list[dict[str, Any]] = []
    for layout, base in (("gray", gray), ("YUYV", yuyv_frames(bgr)), ("BGR", bgr)):
        frames = pool(base, quick)
        procs = {
            "whole frame": FrameProcessor(base[0].shape, p, None),
            "circle ROI": FrameProcessor(base[0].shape, p, roi),
        }
        assert all(fp.counts_on_the_fly for fp in procs.values()) or imaging._skcount is None
        # The floors run interleaved with the routines they bound, in the same passes.
        fns = {FLOOR + k: fn for k, fn in read_kernels(base[0]).items()}
        roi_read, roi_bytes = roi_floor_kernel(procs["circle ROI"])
        fns[FLOOR + "ROI"] = roi_read
        for roi_name, fp in procs.items():
            fns[f"count, {roi_name}"] = fp.count
            fns[f"measure, {roi_name}"] = fp.measure
        for roi_name, roi_arg in (("whole frame", None), ("circle ROI", roi)):
            fp_cv = opencv_processor(base[0].shape, p, roi_arg)
            fns[f"OpenCV route: count, {roi_name}"] = fp_cv.count
            fns[f"OpenCV route: measure, {roi_name}"] = fp_cv.measure
        t = best_ms(fns, frames, repeats)
        roi_floor = t.pop(FLOOR + "ROI")
        floors = {k.removeprefix(FLOOR): t.pop(k) for k in list(t) if k.startswith(FLOOR)}
        kernel = min(floors, key=lambda k: floors[k])
        floor = floors[kernel]
        roi_contiguous = contiguous_floor(roi_bytes, repeats, quick)
        for name, ms in t.items():
            circle = "circle" in name
            f_ms = roi_floor if circle else floor
            rows.append(
                {
                    "size": label,
                    "input": layout,
                    "route": name,
                    "ms": ms,
                    "floor_ms": f_ms,
                    "floor_kernel": "ROI span bytes in place" if circle else kernel,
                    "ratio": ms / f_ms,
                    "contiguous_ratio": ms / roi_contiguous if circle else None,
                    "roi_bytes": roi_bytes if circle else None,
                    "roi_contiguous_ms": roi_contiguous if circle else None,
                }
            )
    # MJPG: decode straight to gray, then the daemon's measure().
    packets = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1] for f in bgr]
    n_pk = 16 if quick else 40
    items = [packets[i % len(packets)].copy() for i in range(n_pk)]
    fp = FrameProcessor(gray[0].shape, p, roi)
    fp_whole = FrameProcessor(gray[0].shape, p, None)
    t = best_ms(
        {
            "decode": lambda a: cv2.imdecode(a, cv2.IMREAD_GRAYSCALE),
            "decode + measure, circle ROI": lambda a: fp.measure(
                cv2.imdecode(a, cv2.IMREAD_GRAYSCALE)
            ),
            "decode + measure, whole frame": lambda a: fp_whole.measure(
                cv2.imdecode(a, cv2.IMREAD_GRAYSCALE)
            ),
        },
        items,
        4 * repeats,
    )
    kb = float(np.mean([len(x) for x in packets])) / 1024
    for name in ("decode + measure, circle ROI", "decode + measure, whole frame"):
        rows.append(
            {
                "size": label,
                "input": f"MJPG ({kb:.0f} kB)",
                "route": name,
                "ms": t[name],
                "floor_ms": t["decode"],
                "floor_kernel": "imdecode(IMREAD_GRAYSCALE)",
                "ratio": t[name] / t["decode"],
            }
        )
    return rows


def _goal(rows: list[dict[str, Any]], limit: float, label: Callable[[dict[str, Any]], str]) -> str:
    return ", ".join(
        f"{label(r)} {r['ratio']:.2f}x ({'met' if r['ratio'] <= limit else 'missed'})" for r in rows
    )


def render_goals(rows: list[dict[str, Any]]) -> list[str]:
    def kernel_rows(layouts: tuple[str, ...], op: str, where: str) -> list[dict[str, Any]]:
        return [r for r in rows if r["input"] in layouts and r["route"] == f"{op}, {where}"]

    gray = kernel_rows(("gray",), "count", "whole frame") + kernel_rows(
        ("gray",), "count", "circle ROI"
    )
    colour = kernel_rows(("YUYV", "BGR"), "count", "whole frame")
    colour_m = kernel_rows(("YUYV", "BGR"), "measure", "whole frame")
    circle = kernel_rows(("gray", "YUYV", "BGR"), "count", "circle ROI")
    circle_m = kernel_rows(("gray", "YUYV", "BGR"), "measure", "circle ROI")
    mjpg = [r for r in rows if r["input"].startswith("MJPG") and "circle" in r["route"]]
    where = {"whole frame": "whole frame", "circle ROI": "circle ROI"}
    out = ["Goals:\n"]
    out.append(
        "- S_k (`count`) on raw gray frames within 2x of the read floor: "
        + _goal(gray, 2.0, lambda r: f"{r['size']} {where[r['route'].split(', ')[1]]}")
        + "."
    )
    out.append(
        "- S_k (`count`) on YUYV and BGR frames, gray values computed on the fly, within 1.3x "
        "of their own read floor: "
        + _goal(colour, 1.3, lambda r: f"{r['size']} {r['input']}")
        + ". With the saturation count (`measure`): "
        + _goal(colour_m, 1.3, lambda r: f"{r['size']} {r['input']}")
        + "."
    )
    out.append(
        "- Circle ROI (`count`) within 1.3x of reading its span bytes in place: "
        + _goal(circle, 1.3, lambda r: f"{r['size']} {r['input']}")
        + ". With `measure`: "
        + _goal(circle_m, 1.3, lambda r: f"{r['size']} {r['input']}")
        + ". Against the same number of bytes read as one contiguous block: "
        + ", ".join(f"{r['size']} {r['input']} {r['contiguous_ratio']:.2f}x" for r in circle)
        + "."
    )
    out.append(
        "- MJPG pipeline (decode + `measure`, circle ROI) within 1.2x of decoding alone: "
        + _goal(mjpg, 1.2, lambda r: r["size"])
        + ".\n"
    )
    return out


def render(rows: list[dict[str, Any]], quick: bool, pinned: str, wall_s: float) -> str:
    frames = RECORDING_S * FPS
    out = [SECTION, ""]
    out.append(
        "Generated by `./dev python benchmarks/throughput.py"
        f"{' --quick' if quick else ''}` (do not edit this section by hand). "
        f"Machine: {platform.machine()} ({cpu_model()}), {os.cpu_count()} CPUs "
        f"({pinned}, `cv2.setNumThreads(1)`), Python {platform.python_version()}, OpenCV "
        f"{cv2.__version__}, numpy {np.__version__}; S_k kernel `{sk_kernel()}`, BGR gray "
        f"formula `{_formula_name()}`; niceness {os.nice(0)}; 1-min load average "
        f"{os.getloadavg()[0]:.1f}; wall time {wall_s:.0f} s. Frames: the simulator's "
        "grade-III scene with sensor noise 2 levels (YUYV: its Y, U and V, packed 4:2:2), "
        "read cold from a pool larger than the caches; best of several interleaved passes "
        "(the least disturbed by other load). The floor of raw frames is the fastest "
        "read-only kernel over the whole frame (time to read it once); for the circle ROI it "
        "is reading only the bytes of the ROI's per-row spans, in place (`x contiguous` "
        "compares with reading the same number of bytes as one block); the floor of MJPG is "
        "decoding alone. Real-time factor = 120 s / (7200 frames x time per frame); streams "
        "= 60 FPS streams one core sustains (the two are equal at 60 FPS by definition: both "
        "are 1 / (60 FPS x time per frame)).\n"
    )
    out.append(
        "| frame | input | route | ms/frame | floor [ms] | x floor | x contiguous | "
        "real-time factor (120 s @ 60 FPS) | 60 FPS streams/core |"
    )
    out.append("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        rtf = RECORDING_S / (frames * r["ms"] * 1e-3)
        streams = 1e3 / (FPS * r["ms"])
        contiguous = "" if r.get("contiguous_ratio") is None else f"{r['contiguous_ratio']:.2f}"
        out.append(
            f"| {r['size']} | {r['input']} | {r['route']} | {r['ms']:.3f} | "
            f"{r['floor_ms']:.3f} | {r['ratio']:.2f} | {contiguous} | {rtf:.0f} | {streams:.0f} |"
        )
    out.append("")
    kernels = {
        f"{r['size']} {r['input']}: {r['floor_kernel']}": None
        for r in rows
        if "MJPG" not in r["input"] and "circle" not in r["route"]
    }
    out.append("Fastest read kernel of the whole frame: " + "; ".join(kernels) + ".")
    spans = {
        f"{r['size']} {r['input']}: {r['roi_bytes'] / 1e3:.0f} kB, in place "
        f"{r['floor_ms']:.3f} ms, contiguous {r['roi_contiguous_ms']:.3f} ms": None
        for r in rows
        if r.get("roi_bytes") is not None
    }
    out.append("Circle ROI span bytes: " + "; ".join(spans) + ".\n")
    out += render_goals(rows)
    return "\n".join(out)


def _formula_name() -> str:
    formula = imaging.bgr_gray_formula()
    return "none (cvtColor first)" if formula is None else formula.name


def splice(path: Path, section: str) -> str:
    """The file's text with our section replaced (or appended); other sections kept."""
    text = path.read_text() if path.exists() else "# Performance\n"
    start = text.find(SECTION)
    if start < 0:
        return text.rstrip("\n") + "\n\n" + section + "\n"
    nxt = text.find("\n## ", start + len(SECTION))
    end = len(text) if nxt < 0 else nxt + 1
    return text[:start] + section + "\n" + text[end:]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: 640x480, small pool")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "performance.md")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    pinned = pin_one_cpu()
    sizes = {"640x480": SIZES["640x480"]} if args.quick else SIZES
    rows: list[dict[str, Any]] = []
    for label, (w, h) in sizes.items():
        rows += measure_size(label, w, h, args.quick)
    section = render(rows, args.quick, pinned, time.perf_counter() - t_start)
    print(section)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(splice(args.out, section))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
