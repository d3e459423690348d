"""The live view's cost at 720p60: the real daemon with 0, 1 and 20 viewers, and a reduced
pipeline with none, one and twenty.

Run: ``./dev python benchmarks/liveview_cost.py`` (about 8 minutes; ``--quick``: about a
minute). Writes the section "Live view cost" of ``docs/performance.md`` (other sections are
left alone) and prints it.

Goals (the live view's): with no viewer connected nothing is computed; one viewer adds at
most 5 % CPU to the daemon at 720p60; twenty viewers at once leave the measurement's frame
budget (1/60 s per frame) intact. Every figure is of this one run: the view's cost is a
ratio to the runs without viewers interleaved with it, never to a figure of another
benchmark.

The real daemon (:mod:`benchmarks._liveview_daemon`, which judges the one-viewer goal).
``python -m stipi_daemon --config FILE`` in a process of its own, pinned to one CPU: the
emulated Feather on a pty (a process of its own on the other CPU), a paced 1280x720 60 fps
MJPG video as the camera (each JPEG decoded to gray at its capture time, as from a real
MJPG camera), the session video stored as passthrough, ``run: {clock: wall, speed: 1}``,
the view enabled; 0, 1 or 20 viewers connect (a process on the other CPU); the daemon's
CPU (``/proc/<pid>/stat``) over a window of ``--daemon-seconds`` (default 10 s) of wall
time; ``--daemon-rounds`` rounds (default 6), the order rotating; added CPU = each round's
CPU per second over that round's ``0 viewers``, minus 1; the median over the rounds (and
their range).

The reduced pipeline (the idle check, the view thread's own CPU and the frame budget). One
process, pinned to one CPU, does the daemon's camera-side work on 120 distinct 1280x720
JPEG frames of the grade-III scene (quality 90, as an MJPG camera sends them), paced at 60
fps on wall time: frame k is due at t0 + k/60 s; when due it is decoded to gray
(``cv2.imdecode``), its S_k counted in the waveguide disc
(:class:`~stipi_daemon.analysis.imaging.FrameProcessor`) and, with the view, published
(:meth:`LiveState.frame`, :meth:`LiveState.force_n`, :meth:`LiveState.tick`) to a
:class:`~stipi_daemon.app.liveview.server.ViewServer` running in its thread of that process
(so its CPU, the JPEG encoding included, is counted). This is less than the daemon's whole
work per frame (no video, no probe, no storage): the view's share of it is overstated. The
viewers are another process on the other CPU doing what the page does: a websocket reading
the state and the frames the server pushes (at most ``PREVIEW_RATE_HZ`` a second, the next
once the last has left the server).

Modes, each a paced run of ``--seconds`` (default 5 s, 300 frames): ``off`` (no view),
``idle`` (the view served, nobody connected), ``1 viewer``, ``20 viewers``; run in
``--rounds`` rounds (default 8), the order rotating from round to round. CPU = the
process's ``time.process_time`` (all threads) over the run; the view thread's own CPU
(its ``pthread_getcpuclockid`` clock) alongside. Added CPU of a mode = its CPU over the
same round's ``off`` run's, minus 1; the median over the rounds (and their range).
Frame budget: per frame, wall time from its due time to its S_k counted (the frame's
latency); frames over 1/60 s in each mode against ``off`` in the same rounds (the frames
whose S_k the view delayed, beside those the shared machine delayed anyway), and the CPU
per frame, all threads, against the 16.7 ms a frame may take. Frames/s a viewer got: from
its first frame to its last, the median over the viewers.
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
#: Goal: CPU one viewer adds to the daemon [-].
ONE_VIEWER_GOAL = 0.05
#: Twenty viewers keep the frame budget when the CPU per frame (all threads) is under it
#: and no more frames run over it than twice ``off``'s in the same rounds, or 0.5 % of
#: the frames (the shared machine's own delays come and go) [-].
OVER_BUDGET_RATIO, OVER_BUDGET_FLOOR = 2.0, 0.005


# ----------------------------------------------------------------------------- viewers


async def _viewer(url: str, until: float, counts: dict[str, float]) -> None:
    """One page's traffic: the websocket's states and the frames the server pushes (the
    page asks for none); the wall time of the first and the last frame [s]."""
    import aiohttp

    base, _, query = url.partition("/?")
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(f"{base}/ws?{query}", origin=base) as ws:
            first = last = None
            frames = 0
            while time.monotonic() < until:
                try:
                    msg = await ws.receive(timeout=max(0.01, until - time.monotonic()))
                except TimeoutError:
                    break
                if msg.type == aiohttp.WSMsgType.TEXT:
                    counts["states"] += 1
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    counts["frames"] += 1
                    frames += 1
                    last = time.monotonic()
                    first = last if first is None else first
                else:
                    break
            if first is not None and last is not None and frames > 1:
                counts["rates"].append((frames - 1) / max(1e-9, last - first))


def viewers_main(url: str, n: int, seconds: float, cpus: set[int]) -> None:
    """``n`` viewers of ``url`` for ``seconds``; prints the frames and states they received
    together, the wall time they ran [s] and the frames per second each got from its first
    frame to its last [1/s] (JSON)."""
    os.sched_setaffinity(0, cpus)
    import aiohttp  # noqa: F401  (imported before the clock starts)

    counts: dict[str, Any] = {"frames": 0, "states": 0, "rates": []}
    t0 = time.monotonic()
    until = t0 + seconds

    async def main() -> None:
        await asyncio.gather(*(_viewer(url, until, counts) for _ in range(n)))

    asyncio.run(main())
    counts["seconds"] = time.monotonic() - t0
    rates = counts.pop("rates")
    counts["fps_each"] = statistics.median(rates) if rates else 0.0
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
    """One paced run of ``mode``: the process's and the view thread's CPU [s], per-frame
    latencies [s], what the viewers got, previews encoded."""
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
    view_clock = _view_thread_clock() if server is not None else None
    view0 = 0.0 if view_clock is None else time.clock_gettime(view_clock)
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
    view_cpu = 0.0 if view_clock is None else time.clock_gettime(view_clock) - view0
    got: dict[str, float] = {}
    if proc_viewers is not None:
        out, _ = proc_viewers.communicate(timeout=60)
        got = json.loads(out.strip().splitlines()[-1])
    encoded = 0 if server is None else server.previews_encoded
    if server is not None:
        server.stop()
    return {
        "cpu_s": cpu,
        "view_cpu_s": view_cpu,
        "latencies_s": latencies.tolist(),
        "viewers": got,
        "encoded": encoded,
    }


def _view_thread_clock() -> int:
    """The CPU-time clock of the view server's thread (``stipi-view``)."""
    import threading

    (thread,) = (t for t in threading.enumerate() if t.name == "stipi-view")
    assert thread.ident is not None
    return time.pthread_getcpuclockid(thread.ident)


def measure(seconds: float, rounds: int, daemon_s: float, daemon_rounds: int) -> dict[str, Any]:
    """The reduced pipeline's every mode, ``rounds`` times, then the real daemon's
    (:mod:`benchmarks._liveview_daemon`) ``daemon_rounds`` times with a CPU window of
    ``daemon_s`` [s], the order rotating; pinned to one CPU, the viewers on the others."""
    import tempfile

    from benchmarks._liveview_daemon import measure_daemon

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
    with tempfile.TemporaryDirectory(prefix="stipi-liveview-bench-") as tmp:
        daemon_runs = measure_daemon(Path(tmp), daemon_s, daemon_rounds, viewer_cpus)
    return {
        "runs": runs,
        "seconds": seconds,
        "rounds": rounds,
        "daemon_runs": daemon_runs,
        "daemon_s": daemon_s,
        "daemon_rounds": daemon_rounds,
    }


# ----------------------------------------------------------------------------- report


def _pct(v: float) -> str:
    return f"{100 * v:+.1f} %"


def _figures(runs: dict[str, list[dict[str, Any]]], mode: str, seconds: float) -> dict[str, Any]:
    """One mode's figures over the rounds, each round against the same round's ``off``."""
    import numpy as np

    pairs = list(zip(runs[mode], runs["off"], strict=True))
    ratios = [r["cpu_s"] / o["cpu_s"] - 1.0 for r, o in pairs]
    lat_ms = np.concatenate([np.asarray(r["latencies_s"]) for r in runs[mode]]) * 1e3
    got = [r["viewers"] for r in runs[mode] if r["viewers"]]
    return {
        "cpu_ms_per_frame": 1e3
        * statistics.median(r["cpu_s"] for r in runs[mode])
        / (seconds * FPS),
        "added": statistics.median(ratios),
        "added_range": (min(ratios), max(ratios)),
        "added_ms_per_s": 1e3
        * statistics.median((r["cpu_s"] - o["cpu_s"]) / seconds for r, o in pairs),
        "view_ms_per_s": 1e3 * statistics.median(r["view_cpu_s"] for r in runs[mode]) / seconds,
        "view_share": statistics.median(r["view_cpu_s"] / o["cpu_s"] for r, o in pairs),
        "p50_ms": float(np.percentile(lat_ms, 50)),
        "p99_ms": float(np.percentile(lat_ms, 99)),
        "over": int((lat_ms > 1e3 / FPS).sum()),
        "frames": int(lat_ms.size),
        "fps_each": statistics.median(g["fps_each"] for g in got) if got else None,
        "encoded_per_s": statistics.median(r["encoded"] for r in runs[mode]) / seconds,
    }


def _row(mode: str, f: dict[str, Any]) -> str:
    """One mode's row of the table."""
    lo, hi = f["added_range"]
    cells = [
        mode,
        f"{f['cpu_ms_per_frame']:.2f}",
        f"{100 * f['cpu_ms_per_frame'] * FPS / 1e3:.0f} %",
        "-" if mode == "off" else f"{_pct(f['added'])} ({_pct(lo)} to {_pct(hi)})",
        "-" if mode == "off" else f"{f['added_ms_per_s']:+.1f}",
        "-" if mode == "off" else f"{f['view_ms_per_s']:.1f}",
        f"{f['p50_ms']:.2f}",
        f"{f['p99_ms']:.2f}",
        f"{f['over']} of {f['frames']}",
        "-" if f["fps_each"] is None else f"{f['fps_each']:.1f}",
        f"{f['encoded_per_s']:.1f}",
    ]
    return "| " + " | ".join(cells) + " |"


def _verdicts(fig: dict[str, dict[str, Any]], rounds: int) -> list[str]:
    """The goals' lines: met or NOT met, from this run's figures only."""
    idle, one, many, off = fig["idle"], fig["1 viewer"], fig["20 viewers"], fig["off"]
    lo, hi = one["added_range"]
    budget_ms = 1e3 / FPS
    allowed = max(OVER_BUDGET_RATIO * off["over"], OVER_BUDGET_FLOOR * many["frames"])
    kept = many["cpu_ms_per_frame"] < budget_ms and many["over"] <= allowed
    # the goal is judged on the larger of the process's added CPU (noisy on a shared machine)
    # and the view thread's own CPU (a floor of what the view adds), both against `off`
    one_added = max(one["added"], one["view_share"])
    nothing = idle["encoded_per_s"] == 0 and idle["view_ms_per_s"] < 0.1
    over_ratio = f"{many['over'] / off['over']:.2f}x `off`'s" if off["over"] else "`off` had none"
    return [
        f"No viewer (`idle`): {idle['encoded_per_s']:.1f} previews encoded per second, the "
        f"view's thread {idle['view_ms_per_s']:.2f} ms of CPU per second, added CPU "
        f"{_pct(idle['added'])} (rounds {_pct(idle['added_range'][0])} to "
        f"{_pct(idle['added_range'][1])}: the noise of this machine) - nothing computed: "
        f"**{'met' if nothing else 'NOT met'}**.",
        "",
        f"One viewer, reduced pipeline: **{_pct(one['added'])}** CPU of this pipeline, the base "
        "being the same "
        f"rounds' `off` (median of {rounds} rounds; rounds {_pct(lo)} to {_pct(hi)}; "
        f"{one['added_ms_per_s']:+.1f} ms of CPU per second, of which the view's thread "
        f"{one['view_ms_per_s']:.1f} ms/s = {_pct(one['view_share'])} of `off`'s CPU); "
        f"{one['fps_each']:.1f} frames/s shown - within 5 % of this pipeline (the larger of the "
        f"two, {_pct(one_added)}): **{'yes' if one_added <= ONE_VIEWER_GOAL else 'no'}**. "
        "The daemon does more per frame than this pipeline (video, probe, storage, console), "
        "so the view's share of the daemon's CPU is smaller than this: the goal is judged on "
        "the real daemon below.",
        "",
        f"Twenty viewers: {many['cpu_ms_per_frame']:.2f} ms of CPU per frame, all threads "
        f"({100 * many['cpu_ms_per_frame'] / budget_ms:.0f} % of the {budget_ms:.1f} ms "
        f"budget); frames over the budget {many['over']} of {many['frames']} against "
        f"{off['over']} of {off['frames']} in `off` ({over_ratio}); each viewer got "
        f"{many['fps_each']:.1f} frames/s - frame budget intact: "
        f"**{'met' if kept else 'NOT met'}** (CPU per frame under the budget, and frames "
        "over it at most twice `off`'s or 0.5 % of the frames).",
    ]


def _daemon_figures(runs: dict[str, list[dict[str, Any]]], mode: str) -> dict[str, Any]:
    """One mode of the real daemon over the rounds, each round against the same round's
    ``0 viewers``."""
    from benchmarks._liveview_daemon import DAEMON_MODES

    base = "0 viewers"
    pairs = list(zip(runs[mode], runs[base], strict=True))
    ratios = [r["cpu_s"] / r["wall_s"] / (o["cpu_s"] / o["wall_s"]) - 1.0 for r, o in pairs]
    got = [r["viewers"] for r in runs[mode] if r["viewers"]]
    return {
        "cpu_pct": 100 * statistics.median(r["cpu_s"] / r["wall_s"] for r in runs[mode]),
        "cpu_ms_per_frame": 1e3
        * statistics.median(r["cpu_s"] / r["wall_s"] for r in runs[mode])
        / FPS,
        "added": statistics.median(ratios),
        "added_range": (min(ratios), max(ratios)),
        "total_cpu_s": statistics.median(r["total_cpu_s"] for r in runs[mode]),
        "fps_each": statistics.median(g["fps_each"] for g in got) if got else None,
        "messages_per_s": (
            statistics.median((g["frames"] + g["states"]) / g["seconds"] for g in got)
            / DAEMON_MODES[mode]
            if got
            else None
        ),
    }


def _daemon_lines(result: dict[str, Any], view_ms_per_s: float) -> list[str]:
    """The real daemon's table and its verdict on the one-viewer goal: the larger of its
    added CPU (noisy on a shared machine) and ``view_ms_per_s``, the view thread's own CPU
    with one viewer in the reduced pipeline of this run [ms/s], over the daemon's."""
    from benchmarks._liveview_daemon import DAEMON_MODES, WARM_S

    runs, rounds, window_s = result["daemon_runs"], result["daemon_rounds"], result["daemon_s"]
    fig = {mode: _daemon_figures(runs, mode) for mode in DAEMON_MODES}
    one = fig["1 viewer"]
    lo, hi = one["added_range"]
    rows = []
    for mode, f in fig.items():
        base = mode == "0 viewers"
        cells = [
            mode,
            f"{f['cpu_pct']:.1f} %",
            f"{f['cpu_ms_per_frame']:.2f}",
            "-"
            if base
            else f"{_pct(f['added'])} ({_pct(f['added_range'][0])} to {_pct(f['added_range'][1])})",
            "-" if f["fps_each"] is None else f"{f['fps_each']:.1f}",
            "-" if f["messages_per_s"] is None else f"{f['messages_per_s']:.1f}",
        ]
        rows.append("| " + " | ".join(cells) + " |")
    thread_share = view_ms_per_s / (10.0 * fig["0 viewers"]["cpu_pct"])
    judged = max(one["added"], thread_share)
    met = judged <= ONE_VIEWER_GOAL
    noisy = (
        f" The rounds spread over {100 * (hi - lo):.0f} points, wider than the goal: the "
        "machine's load moves the daemon's CPU from run to run, the median and the view "
        "thread's own CPU are the figures."
        if hi - lo > ONE_VIEWER_GOAL
        else ""
    )
    return [
        "### The real daemon at 720p60",
        "",
        "`python -m stipi_daemon --config FILE --quiet` as a process of its own on the "
        "benchmark's CPU: the probe the emulated Feather playing the grade-III scene (100 "
        "Hz) in a process of its own on the other CPU, on a pty the daemon opens as "
        "`probe.transport: {kind: serial}` (as a real probe's firmware runs on its MCU), a "
        "paced MJPG video of 1280x720 at 60 fps as the camera "
        "(`camera: {kind: file, pace: true, loop: true}`: each JPEG decoded to gray at its "
        "capture time, as from a real MJPG camera; rendered once by `stipi-daemon simulate` "
        "from a 2 s excerpt of the grade-III scene with sensor noise), `storage.video: "
        "passthrough`, `run: {clock: wall, speed: 1}`, `view.enabled: true`. After its "
        f"address is printed and {WARM_S:g} s for the viewers (a process on the other CPU) "
        "to connect, its CPU (`utime + stime` of `/proc/<pid>/stat`, every thread) over "
        f"{window_s:g} s of wall time; {rounds} rounds, the order rotating; added CPU = "
        "each round's CPU per second over the same round's `0 viewers`, minus 1; the "
        "median and the range.",
        "",
        "| viewers | daemon CPU (of one core) | CPU per frame [ms] | added CPU (rounds' "
        "range) | frames/s each viewer got | messages/s each viewer got |",
        "|---|---:|---:|---:|---:|---:|",
        *rows,
        "",
        f"One viewer, the real daemon: **{_pct(one['added'])}** CPU (median of {rounds} "
        f"rounds; rounds {_pct(lo)} to {_pct(hi)}), {one['fps_each']:.1f} frames/s shown, "
        f"{one['messages_per_s']:.1f} messages/s; the view thread's own CPU with one viewer "
        f"(reduced pipeline above, {view_ms_per_s:.1f} ms/s) is {_pct(thread_share)} of the "
        f"daemon's - goal <= +5 % (judged on the larger of the two, {_pct(judged)}): "
        f"**{'met' if met else 'NOT met'}**.{noisy} Twenty viewers: "
        f"{_pct(fig['20 viewers']['added'])}, {fig['20 viewers']['fps_each']:.1f} frames/s "
        "each.",
    ]


def report(result: dict[str, Any]) -> str:
    """The section "Live view cost" (Markdown) of one run's figures."""
    import cv2

    from benchmarks._machine import cpu_model
    from stipi_daemon.app.liveview.server import PREVIEW_RATE_HZ

    runs, seconds, rounds = result["runs"], result["seconds"], result["rounds"]
    fig = {mode: _figures(runs, mode, seconds) for mode in MODES}
    return "\n".join(
        [
            SECTION,
            "",
            "Goals: with no viewer nothing is computed; one viewer adds at most 5 % CPU to the "
            "daemon at 720p60; 20 viewers leave the frame budget (16.7 ms per frame) intact. "
            "Command: `./dev python benchmarks/liveview_cost.py`. The one-viewer goal is judged "
            "on the real daemon (below, after the reduced pipeline). Reduced pipeline: one "
            "process pinned to one CPU "
            "doing the camera side's work per frame - JPEG decode to gray, S_k in the disc ROI, "
            "published to the view - paced at 60 fps for "
            f"{seconds:g} s per run, the view's server in a thread of that process; the viewers, "
            "a websocket each taking the frames the server pushes (at most "
            f"{PREVIEW_RATE_HZ:g}/s), as the "
            f"page does, in another process on the other CPU; {rounds} rounds, the order of the "
            "modes rotating; CPU = `time.process_time` of the whole process, the view thread's "
            "own CPU beside it; added CPU = each round's ratio to the same round's `off`, the "
            "median and the range over the rounds). Every figure is of this run. The work per "
            "frame here is less than the daemon's (no video, probe or storage), so the ratios "
            "overstate the view's share.",
            "",
            f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"OpenCV {cv2.__version__}; load average at the end "
            f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} (a shared machine).",
            "",
            "| mode | CPU per frame [ms] | of the frame budget | added CPU (rounds' range) | "
            "added CPU [ms/s] | view thread CPU [ms/s] | latency p50 [ms] | latency p99 [ms] | "
            "frames over 16.7 ms | frames/s each viewer got | previews encoded/s |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
            *(_row(mode, fig[mode]) for mode in MODES),
            "",
            *_verdicts(fig, rounds),
            "",
            *_daemon_lines(result, fig["1 viewer"]["view_ms_per_s"]),
            "",
            "Latency here is the machine's as much as the view's: with other work on the CPU the "
            "pinned process is descheduled for tens to hundreds of ms in every mode (compare "
            "`off`); the load average above says how busy the machine was.",
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short round (smoke test)")
    ap.add_argument("--seconds", type=float, default=5.0, help="length of one run [s]")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument(
        "--daemon-seconds", type=float, default=10.0, help="the real daemon's CPU window [s]"
    )
    ap.add_argument("--daemon-rounds", type=int, default=6)
    ap.add_argument("--out", type=Path, default=DOC)
    ap.add_argument("--viewers", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--url", help=argparse.SUPPRESS)
    ap.add_argument("--cpus", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.viewers:
        viewers_main(args.url, args.viewers, args.seconds, {int(c) for c in args.cpus.split(",")})
        return 0
    seconds, rounds = (2.0, 1) if args.quick else (args.seconds, args.rounds)
    daemon_s, daemon_rounds = (3.0, 1) if args.quick else (args.daemon_seconds, args.daemon_rounds)
    from benchmarks._doc import write_section

    text = report(measure(seconds, rounds, daemon_s, daemon_rounds))
    write_section(args.out, SECTION, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
