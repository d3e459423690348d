"""Demo speed and the same answer: ``configs/demo.yaml`` at several paces and loads.

Run: ``./dev python benchmarks/demo_speed.py`` (about 4 minutes: the real-time run takes the
demo's 125 s of probe time). Writes the section "Demo speed" of ``docs/performance.md``
(other sections are left alone) and prints it. ``--short`` runs the demo once, unloaded,
and checks its rows against a second run (what CI runs: that it still runs, no timings
judged).

What runs: the demo exactly as ``./dev demo`` runs it (``stipi-daemon --config
configs/demo.yaml`` in a child process: emulated Feather on a pty, simulator camera, FFV1
video of the ROI, the report), each into a temporary sessions root: with ``--realtime``
(pace 1), at the config's ``run.speed`` (0: unpaced), at ``run.speed`` 20, and at the
config's speed beside two busy processes (``while True: pass``, one per CPU of this
machine). Per child: wall time from start to exit, CPU time and peak RSS (``os.wait4``'s
rusage of that child; CPU includes the child's threads and any process it waited for),
probe seconds per CPU second (the demo's throughput: :data:`PROBE_TIME_S` over that CPU
time), and what it stored: every row of every table and ``summary.json``, compared with the
first run's, bit for bit. Every device of the demo is simulated in the daemon's process,
so its clock waits for the daemon (:class:`stipi_daemon.clock.VirtualClock`): the stored
rows and the results must be identical in every run; only the wall time may differ.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import platform
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
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


def run_demo(tmp: Path, label: str, realtime: bool, speed: float | None) -> dict[str, Any]:
    """Run the demo in a child; wall, CPU, peak RSS and what the session stored."""
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    scene = str(ROOT / "configs" / "scenes" / "demo_grade3.yaml")
    cfg["probe"]["transport"]["scene"] = scene
    cfg["camera"]["scene"] = scene
    if speed is not None:
        cfg["run"]["speed"] = speed
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
    session = next(root.iterdir())
    stored = stored_record(session)
    return {
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "maxrss_mib": ru.ru_maxrss / 1024.0,  # ru_maxrss is in KiB on Linux
        "sampled": sampler.peak,
        "exit": os.waitstatus_to_exitcode(status),
        "load": os.getloadavg()[0],
        **stored,
    }


def stored_record(session: Path) -> dict[str, Any]:
    """Row counts and a digest of every row of every table, and of ``summary.json``."""
    con = sqlite3.connect(f"file:{session / 'session.sqlite'}?mode=ro", uri=True)
    counts: dict[str, int] = {}
    digest = hashlib.sha256()
    try:
        names = [
            n
            for (n,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            if n != "meta"
        ]
        for name in sorted(names):
            rows = con.execute(f"SELECT * FROM {name} ORDER BY id").fetchall()
            counts[name] = len(rows)
            digest.update(repr((name, rows)).encode())
        wall = dict(con.execute("SELECT key, value FROM meta WHERE key = 'wall_s'").fetchall())
    finally:
        con.close()
    summary_bytes = (session / "summary.json").read_bytes()
    return {
        "counts": counts,
        "rows_sha256": digest.hexdigest(),
        "summary_sha256": hashlib.sha256(summary_bytes).hexdigest(),
        "summary": json.loads(summary_bytes),
        "acquisition_wall_s": float(wall.get("wall_s", "nan")),
    }


@contextlib.contextmanager
def busy(n: int) -> Iterator[None]:
    """``n`` processes that keep a CPU busy each, for the duration of the block."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


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


def render(runs: dict[str, dict[str, Any]]) -> str:
    first = next(iter(runs.values()))
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    lines = [
        SECTION,
        "",
        "What must hold: the demo's `summary.json` and stored rows are identical in every "
        "run below (at each `run.speed`, 0 being unpaced, and beside two busy loops). Command: "
        "`./dev python benchmarks/demo_speed.py` (the demo as `./dev demo` runs it, in a "
        "child process per row; wall time from start to exit, CPU and peak RSS from the "
        "child's own rusage; rows: every row of every table of `session.sqlite`, digested "
        "with SHA-256).",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}; niceness {nice:+d}.",
        "",
        "| run | load average (1 min) at its end | wall, whole command [s] | probe time / wall "
        "| acquisition wall [s] | CPU [s] | probe time / CPU | peak RSS [MiB] | frames "
        "| force samples | events | rows (SHA-256, first 12) | summary.json (SHA-256, first 12) "
        "| exit |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for name, r in runs.items():
        c = r["counts"]
        lines.append(
            f"| {name} | {r['load']:.1f} | {r['wall_s']:.1f} | {PROBE_TIME_S / r['wall_s']:.1f}x "
            f"| {r['acquisition_wall_s']:.1f} | {r['cpu_s']:.1f} "
            f"| {PROBE_TIME_S / r['cpu_s']:.1f} | {r['maxrss_mib']:.0f} "
            f"| {c.get('frames', 0)} | {c.get('force_samples', 0)} | {c.get('events', 0)} "
            f"| `{r['rows_sha256'][:12]}` | `{r['summary_sha256'][:12]}` | {r['exit']} |"
        )
    same = all(
        r["rows_sha256"] == first["rows_sha256"] and r["summary_sha256"] == first["summary_sha256"]
        for r in runs.values()
    )
    res = first["summary"].get("results") or {}
    pit = res.get("pitting") or {}
    lines += [
        "",
        f"**Identical rows and summary.json in every run: {'yes' if same else 'NO'}.** "
        f"Verdict {first['summary']['verdict']['status']}; D_p {pit.get('depth_mm', 0):.4f} "
        f"mm, F_r {pit.get('rebound_force_n', 0):.4f} N, T_r "
        f"{pit.get('recovery_time_s', 0):.3f} s.",
        "",
        *NOTES,
        "",
    ]
    return "\n".join(lines)


#: How the demo gives the same answer (fixed text; the figures above are measured).
NOTES = (
    "Every device of the demo is simulated in the daemon's process, so its session clock is "
    "a `stipi_daemon.clock.VirtualClock`: session time moves from one waiter's deadline to "
    "the next (a frame's capture time, the emulated probe's next sample batch or heartbeat, "
    "a timeout) only when the event loop has nothing ready, the camera's capture thread is "
    "waiting for its next frame time, no bytes are on their way across the probe's pty and "
    "nothing is held (a device opening, the live fit the loop waits for). Every time the "
    "daemon stamps is therefore the same on any machine; a busy machine makes the run take "
    "longer, never different, and `run.speed` only caps how far ahead of real time it may "
    "run. The simulated camera waits for the video's encoders without a bound, so no frame "
    "is left out of the video either. Real devices keep wall time (`ScaledClock`) and the "
    "lag handling (`run.max_lag_s`, `processing_behind` gaps); the scene effect "
    "`processing_stall` exercises that path on purpose (configs/scenes/processing_stall.yaml, "
    "tests/daemon/test_processing_stall.py). `tests/daemon/test_speed_identity.py` checks "
    "the same identity on a short scene at speed 1, at 50 and at 50 beside two busy "
    "processes, in every run of the suite.",
    "",
    "The wall time of a run is kept in its session's `meta` table (`wall_s`, `pace`, "
    "`clock_steps`), not in `summary.json`, which holds only what the run measured.",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--short", action="store_true", help="two runs, no document")
    args = parser.parse_args()
    speed = float(yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())["run"]["speed"])
    own = f"speed {speed:g}" + (" (unpaced)" if speed == 0 else "")
    plan: list[tuple[str, bool, float | None, int]] = [
        (own, False, None, 0),
        ("speed 20", False, 20.0, 0),
        (f"{own}, 2 busy loops", False, None, 2),
        ("speed 1 (`--realtime`)", True, None, 0),
    ]
    if args.short:
        plan = plan[:2]
    with tempfile.TemporaryDirectory(prefix="stipi-demo-speed-") as tmp_name:
        tmp = Path(tmp_name)
        runs = {}
        for i, (label, realtime, pace, loops) in enumerate(plan):
            print(f"demo, {label} ...", flush=True)
            with busy(loops):
                runs[label] = run_demo(tmp, str(i), realtime, pace)
    text = render(runs)
    print(text)
    first = next(iter(runs.values()))
    if any(r["rows_sha256"] != first["rows_sha256"] for r in runs.values()):
        sys.exit("the runs stored different rows")
    if not (args.no_write or args.short):
        write_section(DOC, SECTION, text, after="## Live daemon latency")


if __name__ == "__main__":
    main()
