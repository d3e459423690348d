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
    lines.append("")
    return "\n".join(lines)


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
