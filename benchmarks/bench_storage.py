"""Insert throughput of :class:`SessionWriter` against the real acquisition load.

Run: ``./dev python benchmarks/bench_storage.py`` (or ``./dev bench``). Prints a Markdown
table and writes it to ``docs/bench_storage.md``. A measurement streams ~1000 force
samples/s (batches of 10, as SAMPLES frames bring them), 60 frames/s (one call each) and a
few live parameters/s; here a 120 s session of that load is written as fast as the writer
takes it, with the default 0.2 s commit interval, with ``synchronous`` NORMAL and FULL.
The real-time factor is session seconds written per wall second: the margin over the
real load. Per-call costs come from ``timeit``.
"""

from __future__ import annotations

import os
import platform
import sqlite3
import tempfile
import time
import timeit
from pathlib import Path

from stipi_daemon.storage import SessionWriter, StorageOptions
from stipi_daemon.storage.writer import Synchronous

SESSION_S = 120.0
FORCE_HZ = 1000
BATCH = 10
FPS = 60


def stream(options: StorageOptions) -> dict[str, float]:
    """Write a SESSION_S-long session as fast as possible; return rates and sizes."""
    with tempfile.TemporaryDirectory() as tmp:
        writer = SessionWriter.create(tmp, {}, {}, session_id="b", options=options)
        n_batches = int(SESSION_S * FORCE_HZ / BATCH)
        frame_every = FORCE_HZ / BATCH / FPS  # batches per frame
        next_frame = 0.0
        seq = 0
        rows = 0
        t0 = time.perf_counter()
        for b in range(n_batches):
            t = b * BATCH / FORCE_HZ
            i0 = b * BATCH
            writer.add_force_samples(
                [
                    (i, 512, (1000 * i) % 2**32, 1000 * i, t + k / FORCE_HZ, 1.234)
                    for k, i in enumerate(range(i0, i0 + BATCH))
                ]
            )
            rows += BATCH
            while next_frame <= b:
                writer.add_frames([(seq, t, t + 0.004, 40_000 + seq % 100, "")])
                seq += 1
                rows += 1
                next_frame += frame_every
            if b % 20 == 0:  # 5 Hz live parameters
                rows += writer.add_live_parameters(t, {"d_p_mm": 4.2, "f_r_n": 1.1, "t_r_s": 30.0})
        writer.finish("complete", {"ok": True})
        elapsed = time.perf_counter() - t0
        commits, max_commit_s = writer.stats.commits, writer.stats.max_commit_s
        writer.close()
        size = (Path(tmp) / "b" / "session.sqlite").stat().st_size
    return {
        "rows": rows,
        "rows_per_s": rows / elapsed,
        "realtime_factor": SESSION_S / elapsed,
        "commits": commits,
        "max_commit_ms": max_commit_s * 1e3,
        "mib": size / 2**20,
    }


def per_call_us() -> dict[str, float]:
    """Cost of one add_* call [us], commits included (background thread, 0.2 s)."""
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        options = StorageOptions(min_free_bytes=0)
        with SessionWriter.create(tmp, {}, {}, session_id="c", options=options) as w:
            batch = [(i, 512, i, i, float(i), 1.0) for i in range(BATCH)]
            frame = [(1, 1.0, 1.0, 40_000, "")]
            n = 20_000
            out["add_force_samples (10 rows)"] = (
                min(timeit.repeat(lambda: w.add_force_samples(batch), number=n, repeat=3)) / n * 1e6
            )
            out["add_frames (1 row)"] = (
                min(timeit.repeat(lambda: w.add_frames(frame), number=n, repeat=3)) / n * 1e6
            )
            out["add_event"] = (
                min(timeit.repeat(lambda: w.add_event(1.0, "k", {"a": 1}), number=n, repeat=3))
                / n
                * 1e6
            )
            w.finish("complete")
    return out


def interval_commit_ms(sync: Synchronous) -> float:
    """Median cost of committing one 0.2 s interval of the real load [ms] (200 samples,
    12 frames, 3 live parameters), adding the rows included."""
    with tempfile.TemporaryDirectory() as tmp:
        options = StorageOptions(
            synchronous=sync,
            min_free_bytes=0,
            background_commit=False,
            commit_interval_s=60.0,
        )
        with SessionWriter.create(tmp, {}, {}, session_id="i", options=options) as w:
            force = [(i, 512, i, i, float(i), 1.0) for i in range(200)]
            frames = [(i, 1.0, 1.0, 40_000, "") for i in range(12)]

            def one_interval() -> None:
                w.add_force_samples(force)
                w.add_frames(frames)
                w.add_live_parameters(1.0, {"d_p_mm": 4.2, "f_r_n": 1.1, "t_r_s": 30.0})
                w.commit()

            times = timeit.repeat(one_interval, number=1, repeat=50)
            w.finish("complete")
    times.sort()
    return times[len(times) // 2] * 1e3


def main() -> None:
    lines = [
        "# SessionWriter throughput",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, SQLite {sqlite3.sqlite_version}; session files in "
        f"{tempfile.gettempdir()}. Load: {FORCE_HZ} force samples/s in batches of {BATCH}, "
        f"{FPS} frames/s one per call, 3 live parameters at 5 Hz; {SESSION_S:.0f} s of session "
        "written as fast as possible, commit interval 0.2 s. Command: "
        "`./dev python benchmarks/bench_storage.py`.",
        "",
        "| synchronous | rows | rows/s | real-time factor | commits | longest commit [ms] "
        "| file [MiB] |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for sync in ("NORMAL", "FULL"):
        r = stream(StorageOptions(synchronous=sync, min_free_bytes=0))
        lines.append(
            f"| {sync} | {r['rows']:.0f} | {r['rows_per_s']:,.0f} | {r['realtime_factor']:.0f}x "
            f"| {r['commits']:.0f} | {r['max_commit_ms']:.1f} | {r['mib']:.1f} |"
        )
    lines += [
        "",
        "| synchronous | one 0.2 s interval of real load, added and committed [ms] |",
        "|---|---:|",
    ]
    modes: tuple[Synchronous, ...] = ("NORMAL", "FULL")
    for mode in modes:
        lines.append(f"| {mode} | {interval_commit_ms(mode):.2f} |")
    lines += ["", "| call | cost [us] |", "|---|---:|"]
    for name, us in per_call_us().items():
        lines.append(f"| `{name}` | {us:.1f} |")
    load = os.getloadavg()[0]
    lines += ["", f"1-min load average at the end: {load:.1f}."]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(__file__).resolve().parent.parent / "docs" / "bench_storage.md"
    out.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
