"""Demo speed: ``configs/demo.yaml`` at speed 1 and at its run.speed, side by side.

Run: ``./dev python benchmarks/demo_speed.py`` (about 2.5 minutes: the real-time run takes
the demo's 125 s of probe time). Writes the section "Demo speed" of ``docs/performance.md``
(other sections are left alone) and prints it.

Issue 16's goal: the demo (125 s of probe time) runs >= 10x faster than real time on this
2-core machine with results identical to a run at speed 1 (D_p, F_r, T_r, E, eta, severity,
verdict), and its peak RSS is <= 300 MB.

What runs: the demo exactly as ``./dev demo`` runs it (``stipi-daemon --config
configs/demo.yaml`` in a child process: emulated Feather on a pty, simulator camera, FFV1
video of the ROI, the report), once with ``--realtime`` and once at the config's
``run.speed``, each into a temporary sessions root. Per child: wall time from start to exit,
CPU time and peak RSS (``os.wait4``'s rusage of that child), the session's ``run`` stats
(acquisition wall time, frames, late and dropped frames, video frames left out). The
results blocks of the two ``summary.json`` are compared quantity by quantity.

The speed-up is probe time / wall time, for the whole command (start-up, the measurement,
results, report) and for the acquisition alone (``summary.json`` ``run.wall_s``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
SECTION = "## Demo speed"
#: Probe time of the demo scene [s]: 1 s approach + 15.5 s hold + 108 s recovery.
PROBE_TIME_S = 124.5
#: Results compared (summary.json path, label).
QUANTITIES = (
    (("pitting", "depth_mm"), "D_p [mm]"),
    (("pitting", "rebound_force_n"), "F_r [N]"),
    (("pitting", "recovery_time_s"), "T_r [s]"),
    (("applied_force_n",), "F_a [N]"),
    (("paper_estimator", "elasticity_kpa"), "E [kPa]"),
    (("paper_estimator", "viscosity_n_s_per_mm2"), "eta (E*T_r) [N*s/mm^2]"),
    (("fitted_recovery", "tau_s"), "tau [s]"),
    (("fitted_recovery", "model", "viscosity_n_s_per_mm2"), "eta (E*tau) [N*s/mm^2]"),
    (("severity", "paper_estimator", "severity"), "severity (paper)"),
    (("severity", "fitted_recovery", "severity"), "severity (fit)"),
)


def run_demo(tmp: Path, label: str, realtime: bool) -> dict[str, Any]:
    """Run the demo in a child; wall, CPU, peak RSS and the session's summary."""
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    scene = str(ROOT / "configs" / "scenes" / "demo_grade3.yaml")
    cfg["probe"]["transport"]["scene"] = scene
    cfg["camera"]["scene"] = scene
    root = tmp / f"sessions_{label}"
    cfg["storage"]["root"] = str(root)
    path = tmp / f"demo_{label}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    cmd = [sys.executable, "-m", "stipi_daemon", "--config", str(path)]
    if realtime:
        cmd.append("--realtime")
    log = tmp / f"demo_{label}.log"
    with log.open("w") as f:
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        _, status, ru = os.wait4(proc.pid, 0)  # this child's own rusage (peak RSS, CPU)
        wall = time.monotonic() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    session = next(root.iterdir())
    summary = json.loads((session / "summary.json").read_text())
    return {
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "maxrss_mb": ru.ru_maxrss / 1024.0,
        "exit": proc.returncode,
        "summary": summary,
    }


def _get(d: Any, path: tuple[str, ...]) -> Any:
    for k in path:
        d = None if d is None else d.get(k)
    return d


def compare(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, Any, Any, str]]:
    """(quantity, speed-1 value, fast value, difference) of the two results blocks."""
    rows: list[tuple[str, Any, Any, str]] = []
    ra, rb = a.get("results") or {}, b.get("results") or {}
    for path, label in QUANTITIES:
        x, y = _get(ra, path), _get(rb, path)
        if isinstance(x, float) and isinstance(y, float):
            diff = "identical" if x == y else f"{abs(x - y) / max(abs(x), 1e-300):.1e} rel."
            rows.append((label, f"{x:.6g}", f"{y:.6g}", diff))
        else:
            rows.append((label, x, y, "identical" if x == y else "DIFFERENT"))
    va, vb = a["verdict"]["status"], b["verdict"]["status"]
    rows.append(("verdict", va, vb, "identical" if va == vb else "DIFFERENT"))
    return rows


def render(runs: dict[str, dict[str, Any]], speed: float) -> str:
    slow, fast = runs["speed 1"], runs["fast"]
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    lines = [
        SECTION,
        "",
        "Issue 16's goal: the demo (125 s of probe time) runs >= 10x faster than real time on "
        "this 2-core machine with results identical to a run at speed 1, peak RSS <= 300 MB. "
        "Command: `./dev python benchmarks/demo_speed.py` (the demo as `./dev demo` runs it, "
        "in a child process, once with `--realtime` and once at `run.speed` "
        f"{speed:g} of configs/demo.yaml; wall time from start to exit, CPU and peak RSS from "
        "the child's own rusage).",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}; niceness {nice:+d}; load average at the end "
        f"{load} (other jobs shared the machine).",
        "",
        "| run | wall, whole command [s] | probe time / wall | acquisition wall [s] "
        "| probe time / acquisition wall | CPU [s] | peak RSS [MB] | frames | late / dropped "
        "| video frames left out | exit |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in (("speed 1 (`--realtime`)", slow), (f"speed {speed:g}", fast)):
        run = r["summary"]["run"]
        video = run.get("video") or {}
        lines.append(
            f"| {name} | {r['wall_s']:.1f} | {PROBE_TIME_S / r['wall_s']:.1f}x "
            f"| {run['wall_s']:.1f} | {PROBE_TIME_S / run['wall_s']:.1f}x | {r['cpu_s']:.1f} "
            f"| {r['maxrss_mb']:.0f} | {run['frames']} "
            f"| {run['late_frames']} / {run['dropped_frames']} | {video.get('left_out', '-')} "
            f"| {r['exit']} |"
        )
    lines += [
        "",
        f"Results of the two runs (`summary.json`), speed 1 against speed {speed:g}:",
        "",
        "| quantity | speed 1 | fast | difference |",
        "|---|---|---|---|",
    ]
    for label, x, y, diff in compare(slow["summary"], fast["summary"]):
        lines.append(f"| {label} | {x} | {y} | {diff} |")
    lines += ["", *_verdicts(slow, fast, speed), "", *NOTES, ""]
    return "\n".join(lines)


def _verdicts(slow: dict[str, Any], fast: dict[str, Any], speed: float) -> list[str]:
    """The issue's goals against this run's figures."""
    whole = PROBE_TIME_S / fast["wall_s"]
    acq = PROBE_TIME_S / fast["summary"]["run"]["wall_s"]
    rss = max(slow["maxrss_mb"], fast["maxrss_mb"])
    floor_s = PROBE_TIME_S / speed
    return [
        f"**Speed >= 10x: {'met' if whole >= 10 else 'missed'}**, {whole:.1f}x for the "
        f"whole command and {acq:.1f}x for the acquisition. At `run.speed` {speed:g} the "
        f"acquisition alone cannot take less than {floor_s:.1f} s ({PROBE_TIME_S:g} s of "
        "probe time), plus the scene's 1 s lead, the start-up and the report (together "
        "about 5 s of wall time), so the whole command stays under 10x at this speed by "
        "construction; 10x needs a demo speed of about 20 and an acquisition that keeps up "
        "with it on the 2 CPUs, which this one does not yet (its acquisition takes "
        f"{fast['summary']['run']['wall_s']:.1f} s at speed {speed:g}).",
        "",
        f"**Peak RSS <= 300 MB: {'met' if rss <= 300 else 'missed'}** "
        f"({fast['maxrss_mb']:.0f} MB at speed {speed:g}, {slow['maxrss_mb']:.0f} MB at "
        "speed 1).",
    ]


#: What limited the demo and what was done (fixed text; the figures above are measured).
NOTES = (
    "Everything computed from the frames (D_p, F_r, T_r, tau, the severities, the verdict) "
    "agrees to the rounding of the session-time origin. F_a, and with it E and both "
    "viscosities, differs in the 5th digit between *any* two runs, also two at speed 1: the "
    "probe's sample timer starts when STREAM_START arrives, so its phase against the "
    "scene's force ramp is random (as on a real probe), and the first in-band sample of the "
    "hold, which F_a averages, differs. `tests/daemon/test_speed_identity.py` checks the "
    "same on a short scene at speed 1 and 8.",
    "",
    "What limited the demo at speed 4 and above (py-spy and per-thread CPU of a whole run):",
    "",
    "* the event loop's per-frame Python work: S_k counted on the loop, one SQLite commit "
    "per frame, the console updated per frame, every row validated through the slow path, "
    "the recovery series converted from lists to arrays at every live update. Now S_k is "
    "counted in the camera's capture thread (`ThreadedCamera.frame_hook`), frame rows are "
    "committed when the loop's queue is empty (at most every 5 ms of wall time), the console "
    "takes a frame's S_k at most every 50 ms, rows of exact types skip the slow checks, and "
    "the series grow in place; the per-frame hand-off wakes the capture thread once per "
    "half queue instead of per frame; the camera stream waits with `asyncio.timeout` "
    "instead of a task per frame (`wait_for`);",
    "* OpenBLAS's worker threads spinning after the live fits' small solves (2.5 s of CPU in "
    "a demo at speed 10): BLAS is single-threaded while the daemon measures (threadpoolctl);",
    "* the FFV1 encoder thread at nice 19: any other program's ordinary load starved it, and "
    "it left out most frames. It now runs 5 nice levels below the daemon: at 10 (before), "
    "even in real time a 640x480 simulated recording left 104 of 1,127 frames out with "
    "nothing else running (the daemon's own threads and the renderer took the CPU) and 630 "
    "beside one `yes > /dev/null` per CPU; at 5, 0 and 0, and 2 beside three busy "
    "processes (`ENCODER_NICE`; the short grade-I scene at 640x480, `storage.video: "
    "lossless`, speed 1). At speed 10 how many frames it leaves out depends on the "
    "machine's other load, and the frames it keeps cost the acquisition CPU: in the runs "
    "of this change 225 to 5,635 left out, and in the two benchmark runs 5,635 with the "
    "acquisition at 15.0 s (13.9 s of CPU) and 536 at 17.1 s (25.1 s of CPU). FFV1 of the "
    "ROI's 420x420 gray box costs about 1.1 ms per frame (FFmpeg's floor for this codec: the "
    "Golomb-Rice and range coders, slices and threads all measured within 10 %), 0.7 of a "
    "core at speed 10: on a machine shared with other jobs it still leaves frames out "
    "(counted in `run.video.left_out`, never the measurement);",
    "* session-time timeouts meeting wall-time hiccups: a camera stall timeout of 0.5 s of "
    "session time is 50 ms of wall time at speed 10. The stall timeout now has a floor of "
    "0.125 s of wall time (`cameras.stream.STALL_MIN_WALL_S`), the demo allows a lag of "
    "30 s of session time (`run.max_lag_s`, 3 s of wall time), and `import av` happens when "
    "the recorder is made, not at the first frame on the loop.",
    "",
    "Not in the acquisition: start-up (imports, the scene rendered for the ground truth and "
    "the emulated probe) and the report (matplotlib, about 3 s) take about 5 s of the whole "
    "command's wall time, and the scene starts 1 s of wall time after start-up "
    "(`SCENE_LEAD_WALL_S`).",
    "",
    "Peak RSS: the peak came in the final analysis, where the power-law recovery model's "
    "starting grid (310 (tau, n) pairs x the frames of the 105 s recovery) built five "
    "arrays of 16 MB at once, one of them 31 MB of derivatives it threw away; the grid is "
    "now computed without the derivatives and in place (the same values bit for bit), about"
    " 46 MB less.",
    "",
    'The live fit runs on a thread beside the event loop ("Live daemon latency"); at '
    "speed 10 it shares the same 2 CPUs, so the acquisition is not shorter for it. Not "
    "tried yet: the emulated probe in a process of its own for the demo, a shorter scene "
    "lead (`SCENE_LEAD_WALL_S`) and a cheaper start-up.",
)


def write_section(text: str) -> None:
    """Replace (or add, after "Live daemon latency") the section, keeping the others."""
    old = DOC.read_text()
    start = old.find(SECTION)
    if start < 0:
        anchor = old.find("\n## ", old.find("## Live daemon latency") + 1)
        new = (
            old[:anchor] + "\n\n" + text.rstrip("\n") + old[anchor:] if anchor >= 0 else old + text
        )
    else:
        nxt = old.find("\n## ", start + len(SECTION))
        new = old[:start] + text + ("" if nxt < 0 else old[nxt:])
    DOC.write_text(new.rstrip("\n") + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    speed = float(yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())["run"]["speed"])
    with tempfile.TemporaryDirectory(prefix="stipi-demo-speed-") as tmp_name:
        tmp = Path(tmp_name)
        runs = {}
        for label, realtime in (("fast", False), ("speed 1", True)):
            print(f"demo, {label} ...", flush=True)
            runs[label] = run_demo(tmp, label.replace(" ", ""), realtime)
    text = render(runs, speed)
    print(text)
    if not args.no_write:
        write_section(text)


if __name__ == "__main__":
    main()
