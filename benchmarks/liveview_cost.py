"""The live view's cost to the measurement at 720p60: none, one viewer, twenty viewers.

Run: ``./dev python benchmarks/liveview_cost.py`` (about 3 minutes; ``--quick``: seconds).
Writes the section "Live view cost" of ``docs/performance.md`` (other sections are left
alone) and prints it.

Goals (the live view's): with no viewer connected nothing is computed; one viewer adds at
most 5 % CPU to the daemon at 720p60; twenty viewers at once leave the measurement's frame
budget (1/60 s per frame) intact.

What runs. One process, pinned to one CPU, does the daemon's camera-side work on 120
distinct 1280x720 JPEG frames of the grade-III scene (quality 90, as an MJPG camera sends
them), paced at 60 fps on wall time: frame k is due at t0 + k/60 s; when due it is decoded
to gray (``cv2.imdecode``), its S_k counted in the waveguide disc
(:class:`~stipi_daemon.analysis.imaging.FrameProcessor`) and, with the view, published
(:meth:`LiveState.frame`, :meth:`LiveState.force_n`, :meth:`LiveState.tick`) to a
:class:`~stipi_daemon.app.liveview.server.ViewServer` running in its thread of that process
(so its CPU, the JPEG encoding included, is counted). This is less than the daemon's whole
work per frame (no video, no probe, no storage), so the ratio overstates the view's share.
The viewers are another process on the other CPU doing what the page does: a websocket
reading the state, on which the next frame is asked for once the last one came, at most
10 a second.

Modes, each a paced run of ``--seconds`` (default 10 s, 600 frames): ``off`` (no view),
``idle`` (the view served, nobody connected), ``1 viewer``, ``20 viewers``; run in
``--rounds`` rounds (default 4), the order rotating from round to round. CPU = the
process's ``time.process_time`` (all threads) over the run; the ratio of each mode to
``off`` is the median of the rounds' ratios. Frame budget: per frame, wall time from its
due time to its S_k counted (the frame's latency); p50, p99 and frames over 1/60 s.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "performance.md"
SECTION = "## Live view cost"
W, H, FPS, N = 1280, 720, 60.0, 120
MODES = ("off", "idle", "1 viewer", "20 viewers")
VIEWERS = {"off": 0, "idle": 0, "1 viewer": 1, "20 viewers": 20}
#: The whole daemon's CPU per frame at 720p60 MJPG [ms] ("Live daemon latency" section of
#: docs/performance.md, benchmarks/daemon_latency.py): the share of it one viewer adds.
DAEMON_720P60_CPU_MS_PER_FRAME = 4.38
#: Goal: CPU one viewer adds to the daemon [-].
ONE_VIEWER_GOAL = 0.05


# ----------------------------------------------------------------------------- viewers


async def _viewer(url: str, until: float, counts: dict[str, int]) -> None:
    """One page's traffic: the websocket's state, and frames asked for one after the other
    (the next once the last came), at most 10 a second."""
    import aiohttp

    base, _, query = url.partition("/?")
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(f"{base}/ws?{query}", origin=base) as ws:
            asked = time.monotonic()
            await ws.send_str("next")
            while time.monotonic() < until:
                try:
                    msg = await ws.receive(timeout=max(0.01, until - time.monotonic()))
                except TimeoutError:
                    break
                if msg.type == aiohttp.WSMsgType.TEXT:
                    counts["states"] += 1
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    counts["frames"] += 1
                    await asyncio.sleep(max(0.0, 0.1 - (time.monotonic() - asked)))
                    asked = time.monotonic()
                    await ws.send_str("next")
                else:
                    break


def viewers_main(url: str, n: int, seconds: float, cpus: set[int]) -> None:
    """``n`` viewers of ``url`` for ``seconds``; prints frames and states received (JSON)."""
    os.sched_setaffinity(0, cpus)
    counts = {"frames": 0, "states": 0}
    until = time.monotonic() + seconds

    async def main() -> None:
        await asyncio.gather(*(_viewer(url, until, counts) for _ in range(n)))

    asyncio.run(main())
    print(json.dumps(counts), flush=True)


# ----------------------------------------------------------------------------- daemon side


def _frames() -> tuple[list[bytes], Any]:
    """N distinct 720p JPEGs of the grade-III scene, and its waveguide ROI."""
    import cv2

    from stipi_daemon.analysis.imaging import CircleROI
    from stipi_daemon.sim.pipeline import Pipeline
    from stipi_daemon.sim.scene import load_scene

    scene = load_scene(ROOT / "configs" / "scenes" / "grade3.yaml")
    doc = scene.model_dump()
    doc["camera"].update({"width": W, "height": H})
    scene = type(scene).model_validate(doc)
    packets: list[bytes] = []
    for f in Pipeline(scene, 1).frames(start_s=15.5):
        packets.append(cv2.imencode(".jpg", f.image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes())
        if len(packets) == N:
            break
    return packets, CircleROI(cx_px=W / 2, cy_px=H / 2, radius_px=0.45 * H)


def run_mode(
    mode: str, packets: list[bytes], roi: Any, seconds: float, viewer_cpus: set[int]
) -> dict[str, Any]:
    """One paced run of ``mode``: CPU [s], per-frame latencies [s], what the viewers got."""
    import cv2
    import numpy as np

    from stipi_daemon.analysis.imaging import FrameProcessor
    from stipi_daemon.app.liveview.server import ViewServer
    from stipi_daemon.app.liveview.state import LiveState, ViewInfo, roi_dict

    state = server = proc_viewers = None
    if mode != "off":
        info = ViewInfo("bench", {}, 100, roi_dict(roi), 15.0, 105.0, (14.5, 17.5))
        state = LiveState(info)
        server = ViewServer(state)
        url = server.start()
    n_viewers = VIEWERS[mode]
    if n_viewers:
        proc_viewers = subprocess.Popen(
            [
                *(sys.executable, __file__, "--viewers", str(n_viewers), "--url", url),
                *("--seconds", repr(seconds + 1.0), "--cpus", ",".join(map(str, viewer_cpus))),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        time.sleep(1.0)  # connected before the timed run
    processor = FrameProcessor((H, W), 100, roi)
    n = int(seconds * FPS)
    latencies = np.empty(n)
    cpu0 = time.process_time()
    t0 = time.monotonic() + 0.05
    for k in range(n):
        due = t0 + k / FPS
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        gray = cv2.imdecode(np.frombuffer(packets[k % N], np.uint8), cv2.IMREAD_GRAYSCALE)
        s_k = int(processor.measure(gray).s_k_px)
        if state is not None:
            state.frame(k, k / FPS, s_k, gray)
            state.force_n(k / FPS, 16.0)
            state.tick(k / FPS, None)
        latencies[k] = time.monotonic() - due
    cpu = time.process_time() - cpu0
    got: dict[str, int] = {}
    if proc_viewers is not None:
        out, _ = proc_viewers.communicate(timeout=60)
        got = json.loads(out.strip().splitlines()[-1])
    encoded = 0 if server is None else server.previews_encoded
    if server is not None:
        server.stop()
    return {"cpu_s": cpu, "latencies_s": latencies.tolist(), "viewers": got, "encoded": encoded}


def measure(seconds: float, rounds: int) -> dict[str, Any]:
    """Every mode, ``rounds`` times, the order rotating; pinned to one CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    mine = {cpus[0]}
    viewer_cpus = set(cpus[1:]) or mine
    os.sched_setaffinity(0, mine)
    packets, roi = _frames()
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in MODES}
    for r in range(rounds):
        order = MODES[r % len(MODES) :] + MODES[: r % len(MODES)]
        for mode in order:
            runs[mode].append(run_mode(mode, packets, roi, seconds, viewer_cpus))
            print(
                f"round {r + 1}/{rounds}: {mode}: {runs[mode][-1]['cpu_s']:.3f} s CPU", flush=True
            )
    return {"runs": runs, "seconds": seconds, "rounds": rounds}


# ----------------------------------------------------------------------------- report


def _pct(v: float) -> str:
    return f"{100 * v:+.1f} %"


def report(result: dict[str, Any]) -> str:
    import cv2
    import numpy as np

    runs, seconds, rounds = result["runs"], result["seconds"], result["rounds"]
    n = int(seconds * FPS)
    rows = []
    for mode in MODES:
        cpu = [r["cpu_s"] for r in runs[mode]]
        ratios = [c / o["cpu_s"] - 1.0 for c, o in zip(cpu, runs["off"], strict=True)]
        added = [(c - o["cpu_s"]) / seconds for c, o in zip(cpu, runs["off"], strict=True)]
        lat = np.concatenate([np.asarray(r["latencies_s"]) for r in runs[mode]]) * 1e3
        over = int((lat > 1e3 / FPS).sum())
        got = [r["viewers"] for r in runs[mode] if r["viewers"]]
        per_viewer = (
            "-"
            if not got
            else f"{statistics.median(g['frames'] for g in got) / VIEWERS[mode] / seconds:.1f}"
        )
        encoded = statistics.median(r["encoded"] for r in runs[mode]) / seconds
        rows.append(
            f"| {mode} | {1e3 * statistics.median(cpu) / n:.2f} | "
            f"{'-' if mode == 'off' else _pct(statistics.median(ratios))} | "
            f"{'-' if mode == 'off' else f'{1e3 * statistics.median(added):+.1f}'} | "
            f"{np.percentile(lat, 50):.2f} | {np.percentile(lat, 99):.2f} | {over} of {lat.size} | "
            f"{per_viewer} | {encoded:.1f} |"
        )
    one = statistics.median(
        c["cpu_s"] / o["cpu_s"] - 1.0 for c, o in zip(runs["1 viewer"], runs["off"], strict=True)
    )
    verdict = "met" if one <= ONE_VIEWER_GOAL else "NOT met"
    one_ms = statistics.median(
        (c["cpu_s"] - o["cpu_s"]) / seconds
        for c, o in zip(runs["1 viewer"], runs["off"], strict=True)
    )
    from benchmarks._machine import cpu_model

    return "\n".join(
        [
            SECTION,
            "",
            "Goals: with no viewer nothing is computed; one viewer adds at most 5 % CPU to the "
            "daemon at 720p60; 20 viewers leave the frame budget (16.7 ms per frame) intact. "
            "Command: `./dev python benchmarks/liveview_cost.py` (one process pinned to one CPU "
            "doing the camera side's work per frame - JPEG decode to gray, S_k in the disc ROI, "
            "published to the view - paced at 60 fps for "
            f"{seconds:g} s per run, the view's server in a thread of that process; the viewers, "
            "a websocket each, the next frame asked for once the last came, at most 10/s, as the "
            f"page does, in another process on the other CPU; {rounds} rounds, the order of the "
            "modes rotating; CPU = `time.process_time` of the whole process; the added CPU is the "
            "median of the rounds' ratios to `off`). The work per frame here is less than the "
            "daemon's (no video, probe or storage), so the ratios overstate the view's share.",
            "",
            f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"OpenCV {cv2.__version__}; load average at the end "
            f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} (a shared machine).",
            "",
            "| mode | CPU per frame [ms] | added CPU | added CPU [ms/s] | latency p50 [ms] | "
            "latency p99 [ms] | frames over 16.7 ms | frames/s each viewer got | "
            "previews encoded/s |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
            *rows,
            "",
            f"One viewer: **{_pct(one)}** CPU of this pipeline (goal <= +5 %: {verdict}); "
            f"{1e3 * one_ms:+.1f} ms of CPU per second, which is "
            f"{_pct(one_ms / (DAEMON_720P60_CPU_MS_PER_FRAME * 1e-3 * FPS))} of the whole "
            f"daemon's CPU at 720p60 ({DAEMON_720P60_CPU_MS_PER_FRAME} ms per frame, "
            '"Live daemon latency", another run).',
            "",
            "Latency here is the machine's: with other work on the CPU the pinned process is "
            "descheduled for tens to hundreds of ms in every mode (compare `off`); the "
            "load average above says how busy the machine was.",
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short round (smoke test)")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of one run [s]")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--out", type=Path, default=DOC)
    ap.add_argument("--viewers", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--url", help=argparse.SUPPRESS)
    ap.add_argument("--cpus", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.viewers:
        viewers_main(args.url, args.viewers, args.seconds, {int(c) for c in args.cpus.split(",")})
        return 0
    seconds, rounds = (2.0, 1) if args.quick else (args.seconds, args.rounds)
    from benchmarks._doc import write_section

    text = report(measure(seconds, rounds))
    write_section(args.out, SECTION, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
