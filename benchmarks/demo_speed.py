"""Demo speed: ``configs/demo.yaml`` at speed 1 and at its run.speed, side by side.

Run: ``./dev python benchmarks/demo_speed.py`` (about 2.5 minutes: the real-time run takes
the demo's 125 s of probe time). Writes the section "Demo speed" of ``docs/performance.md``
(other sections are left alone) and prints it.

Issue 16's goal: the demo (125 s of probe time) runs >= 10x faster than real time on this
2-core machine with results identical to a run at speed 1 (D_p, F_r, T_r, E, eta, severity,
verdict), and its peak RSS is <= 300 MB; the session holds its video (every frame).

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
import threading
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._doc import write_section  # noqa: E402

DOC = ROOT / "docs" / "performance.md"
SECTION = "## Demo speed"
#: Interval of the child's memory samples [s].
SAMPLE_S = 0.02
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
        sampler = RssSampler(proc.pid)
        sampler.start()
        _, status, ru = os.wait4(proc.pid, 0)  # this child's own rusage (peak RSS, CPU)
        wall = time.monotonic() - t0
        sampler.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    session = next(root.iterdir())
    summary = json.loads((session / "summary.json").read_text())
    return {
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "maxrss_mib": ru.ru_maxrss / 1024.0,  # ru_maxrss is in KiB on Linux
        "sampled": sampler.peak,
        "exit": proc.returncode,
        "summary": summary,
    }


class RssSampler(threading.Thread):
    """Reads a child's ``/proc/PID/status`` every :data:`SAMPLE_S`: at the largest VmRSS
    seen, its anonymous and file-backed parts [MiB] (``RssAnon``, ``RssFile``: the
    latter is the shared libraries' pages, whose count depends on the page cache, e.g.
    how recently the libraries were installed), and the largest ``RssAnon`` [MiB]."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self._path = Path(f"/proc/{pid}/status")
        self.peak = {"rss_mib": 0.0, "anon_mib": 0.0, "file_mib": 0.0, "max_anon_mib": 0.0}

    def run(self) -> None:
        while True:
            try:
                fields = dict(
                    (line.split(":")[0], int(line.split()[1]) / 1024.0)
                    for line in self._path.read_text().splitlines()
                    if line.startswith(("VmRSS", "RssAnon", "RssFile"))
                )
            except (OSError, ValueError, IndexError):  # the child has exited
                return
            if len(fields) == 3:  # a zombie has no memory lines
                peak = self.peak
                peak["max_anon_mib"] = max(peak["max_anon_mib"], fields["RssAnon"])
                if fields["VmRSS"] > peak["rss_mib"]:
                    peak.update(
                        rss_mib=fields["VmRSS"],
                        anon_mib=fields["RssAnon"],
                        file_mib=fields["RssFile"],
                    )
            time.sleep(SAMPLE_S)


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
        "| probe time / acquisition wall | CPU [s] | peak RSS [MiB] | of it anonymous / "
        "file-backed [MiB] | frames | late / dropped | video frames left out | exit |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in (("speed 1 (`--realtime`)", slow), (f"speed {speed:g}", fast)):
        run = r["summary"]["run"]
        video = run.get("video") or {}
        lines.append(
            f"| {name} | {r['wall_s']:.1f} | {PROBE_TIME_S / r['wall_s']:.1f}x "
            f"| {run['wall_s']:.1f} | {PROBE_TIME_S / run['wall_s']:.1f}x | {r['cpu_s']:.1f} "
            f"| {r['maxrss_mib']:.0f} | {r['sampled']['anon_mib']:.0f} / "
            f"{r['sampled']['file_mib']:.0f} | {run['frames']} "
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
    rss = max(slow["maxrss_mib"], fast["maxrss_mib"])
    anon = max(slow["sampled"]["max_anon_mib"], fast["sampled"]["max_anon_mib"])
    budget_s = 2 * PROBE_TIME_S / 10  # CPU-seconds of 2 CPUs in a 10x demo's wall time
    video = fast["summary"]["run"].get("video") or {}
    return [
        f"**Speed >= 10x: {'met' if whole >= 10 else 'missed'}**, {whole:.1f}x for the "
        f"whole command and {acq:.1f}x for the acquisition, with every frame in the "
        f"session's lossless video ({video.get('frames', 0)} frames, "
        f"{video.get('left_out', '-')} left out). The whole demo costs {fast['cpu_s']:.1f} s "
        f"of CPU; in the {PROBE_TIME_S / 10:.2f} s of a 10x demo the 2 CPUs give "
        f"{budget_s:.1f} s, and only if both are busy from start to end, while the start-up "
        "and the report run on one (about 6 s of wall time). The CPU is mostly the FFV1 "
        "encoding of each distinct frame (1.4 to 2.7 ms per 420x420 frame on this machine, "
        "with the rendering and the measurement beside it), so 10x would need either a "
        "video with frames left out (as before: half of them at speed 10) or a faster "
        "lossless codec than FFV1; `run.speed` "
        f"{speed:g} is what keeps every frame with a margin on this machine.",
        "",
        f"**Peak RSS <= 300 MB: {'met' if rss <= 300 else 'missed'}** in MiB, the unit of "
        f"this project's figures ({fast['maxrss_mib']:.0f} MiB at speed {speed:g}, "
        f"{slow['maxrss_mib']:.0f} MiB at speed 1; {rss * 1.048576:.0f} MB in decimal "
        f"megabytes). The demo's own memory, the anonymous part, peaks at {anon:.0f} MiB; "
        "the rest are the shared libraries' pages mapped into the process (OpenCV, FFmpeg, "
        "NumPy, SciPy, Python), whose count depends on the page cache: right after `./dev` "
        "installed them the same demo peaked at 293-294 MiB (file-backed about 140 MiB; "
        "307-308 MB in decimal megabytes, over the goal if MB is read that way), hours "
        "later at 232-239 MiB (about 80 MiB; `/usr/bin/time ./dev demo` in a fresh clone "
        "and in an older one, measured side by side, the anonymous part alike).",
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
    "How the demo keeps its whole video at speed:",
    "",
    "* each frame is measured, stored in the video and its row committed in the camera's "
    "capture thread (`stipi_daemon.app.frame_measurer`); the simulated camera waits for the "
    "video's encoders (at most 0.1 s of wall time per frame, `ENCODER_WAIT_MAX_S`, below a "
    "camera stall) instead of leaving frames out, so a machine that cannot keep up falls "
    "behind (`run.lag_s`), visibly, rather than losing video;",
    "* FFV1 frames are encoded by two encoders at once, each in a thread of its own at the "
    "daemon's niceness + 5 (`storage.ordered_workers`), and FFmpeg starts no slice threads "
    "(they cost 1.8x the CPU and ran at the daemon's priority);",
    "* a clean scene's frame whose pixel count round(S) equals the previous frame's is that "
    "frame's picture again: rendered once (`Pipeline._clean_frames`) and encoded once, its "
    "packet stored again with the new time (the same bytes encoding gives, tested): 72 % of "
    "the demo's 7,470 frames, the late recovery creeping by less than a pixel per frame;",
    "* the state machine's records are copied by `measurement.evolve` (0.7 us) instead of "
    "`dataclasses.replace` (17.5 us), two to three times per sample and frame;",
    "* BLAS is single-threaded while the daemon measures (OpenBLAS's spinning workers took "
    "2.5 s of CPU in a demo at speed 10), and the stall timeout has a floor of 0.125 s of "
    "wall time (`cameras.stream.STALL_MIN_WALL_S`).",
    "",
    "Not in the acquisition: start-up (imports, the scene rendered for the ground truth and "
    "the emulated probe) and the report (matplotlib, about 3 s) take about 6 s of the whole "
    "command's wall time, and the scene starts 1 s of wall time after start-up "
    "(`SCENE_LEAD_WALL_S`).",
)


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
        write_section(DOC, SECTION, text, after="## Live daemon latency")


if __name__ == "__main__":
    main()
