"""The C heap's settings and a frame's CPU: decode + S_k of 1080p JPEGs under each policy.

Run: ``./dev python benchmarks/heap_policy.py`` (about a minute). Writes the section "Heap
settings and frame CPU" of ``docs/performance.md`` (other sections are left alone) and
prints it.

Why: the daemon sets glibc's allocator for the acquisition (:mod:`stipi_daemon.app.memory`).
A decoded 1080p gray frame is a 2 MB buffer, allocated and freed 60 times a second; if it is
mmapped (the threshold below its size) or trimmed from the heap's top after each frame, every
frame's 512 pages are faulted in and zeroed again, which costs CPU in the capture thread.

What runs: 120 distinct 1920x1080 JPEGs of the simulator's grade-III scene with sensor noise
(quality 90, as an MJPG camera sends them; :func:`benchmarks.video_recording._frames`),
decoded straight to gray (``cv2.imdecode``) and counted in the waveguide disc
(:class:`~stipi_daemon.analysis.imaging.FrameProcessor`), one frame every 1/60 s with the
thread sleeping between (as a camera's frames come), in a child process per policy pinned
to one CPU (``mallopt`` changes a process for good): glibc's defaults; the threshold held at
128 kB (the daemon's setting before this benchmark); :func:`~stipi_daemon.app.memory.hold_heap`
(the daemon's acquisition). The policies run in rounds, in turn, so that a drift of the
machine weighs on each alike; figures are the medians over the rounds of each run's median
thread CPU per frame, and the minor page faults per frame (``ru_minflt``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._doc import write_section  # noqa: E402

DOC = ROOT / "docs" / "performance.md"
SECTION = "## Heap settings and frame CPU"
POLICIES = ("glibc default", "threshold held at 128 kB", "hold_heap()")
FPS = 60.0


def child(policy: str, jpeg_dir: Path, frames: int, cpu: int) -> dict[str, float]:
    """Decode + count ``frames`` JPEGs paced at :data:`FPS` under ``policy``."""
    os.sched_setaffinity(0, {cpu})
    import ctypes
    import ctypes.util

    if policy == POLICIES[1]:
        ctypes.CDLL(ctypes.util.find_library("c")).mallopt(-3, 128 * 1024)
    elif policy == POLICIES[2]:
        from stipi_daemon.app.memory import hold_heap

        assert hold_heap()
    import resource

    import cv2
    import numpy as np

    from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor

    roi = CircleROI.model_validate_json((jpeg_dir / "roi.json").read_text())
    proc = FrameProcessor((1080, 1920), 128, roi)
    jpegs = [np.fromfile(p, dtype=np.uint8) for p in sorted(jpeg_dir.glob("*.jpg"))]
    cpu_ms: list[float] = []
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for k in range(frames):
        t0 = time.thread_time()
        gray = np.asarray(cv2.imdecode(jpegs[k % len(jpegs)], cv2.IMREAD_GRAYSCALE), np.uint8)
        proc.measure(gray)
        cpu_ms.append((time.thread_time() - t0) * 1e3)
        del gray
        time.sleep(1.0 / FPS)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0
    return {"cpu_ms": statistics.median(cpu_ms[20:]), "faults": faults / frames}


def prepare(tmp: Path) -> None:
    """The JPEGs and the scene's ROI, as files for the children."""
    from benchmarks.video_recording import _frames

    jpegs, roi = _frames()
    for k, data in enumerate(jpegs):
        (tmp / f"{k:04d}.jpg").write_bytes(data)
    (tmp / "roi.json").write_text(roi.model_dump_json())


def run(tmp: Path, rounds: int, frames: int, cpu: int) -> dict[str, list[dict[str, float]]]:
    got: dict[str, list[dict[str, float]]] = {p: [] for p in POLICIES}
    for k in range(rounds):
        order = POLICIES if k % 2 == 0 else POLICIES[::-1]
        for policy in order:
            out = subprocess.run(
                [
                    *(sys.executable, __file__, "--child", policy, "--dir", str(tmp)),
                    *("--frames", str(frames), "--cpu", str(cpu)),
                ],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            got[policy].append(json.loads(out))
            print(policy, got[policy][-1], flush=True)
    return got


def markdown(got: dict[str, list[dict[str, float]]], rounds: int, frames: int) -> str:
    from benchmarks._machine import cpu_model

    base = statistics.median(r["cpu_ms"] for r in got[POLICIES[0]])
    lines = [
        SECTION,
        "",
        "Command: `./dev python benchmarks/heap_policy.py` (see its docstring). Machine: "
        f"{cpu_model()}, {os.cpu_count()} CPUs; load average at the end "
        f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}. {rounds} rounds of {frames} "
        "frames per policy, 1920x1080 JPEGs decoded to gray and counted, one every 1/60 s.",
        "",
        "| policy | CPU per frame [ms] (median of rounds; range) | vs glibc default "
        "| minor page faults per frame |",
        "|---|---:|---:|---:|",
    ]
    for policy in POLICIES:
        cpu = [r["cpu_ms"] for r in got[policy]]
        med = statistics.median(cpu)
        faults = statistics.median(r["faults"] for r in got[policy])
        lines.append(
            f"| {policy} | {med:.2f} ({min(cpu):.2f}-{max(cpu):.2f}) | {med / base:.2f}x "
            f"| {faults:.0f} |"
        )
    lines += [
        "",
        "The daemon's acquisition runs with `hold_heap()`: frames up to 8 MB from the heap and "
        "free memory at a heap's top kept up to 8 MB, two arenas "
        "(`stipi_daemon/app/memory.py`); the analysis and the report after it with both "
        "thresholds at 128 kB, so that their large arrays go back as soon as they are freed "
        '(the demo\'s peak RSS is in its report: "Demo speed").',
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--child", choices=POLICIES, help=argparse.SUPPRESS)
    parser.add_argument("--dir", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)))
    parser.add_argument("--rounds", type=int, default=3, help="rounds of every policy")
    parser.add_argument("--frames", type=int, default=300, help="frames per run")
    parser.add_argument("--no-doc", action="store_true", help="print only, leave the doc alone")
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child, args.dir, args.frames, args.cpu)))
        return
    with tempfile.TemporaryDirectory(prefix="stipi-heap-") as name:
        print("rendering the frames ...", flush=True)
        prepare(Path(name))
        got: dict[str, Any] = run(Path(name), args.rounds, args.frames, args.cpu)
    text = markdown(got, args.rounds, args.frames)
    print(text)
    if not args.no_doc:
        write_section(DOC, SECTION, text)


if __name__ == "__main__":
    main()
