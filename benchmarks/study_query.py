"""Study query benchmark: a DuckDB aggregate over >= 10^8 force-sample rows of a study dataset.

Writes a synthetic study dataset into a temporary directory: ``force_samples`` files laid
out exactly as ``stipi-daemon study index`` lays them out (one Parquet file per session,
``site=/probe=/date=`` partitions, the dataset's schema and zstd compression), 1,000
sessions of 100,000 samples (a 1 kHz probe for 100 s; force from 10-bit ADC counts, a
pitting-shaped profile plus noise), 3 sites x 4 probes x 5 days. Then times, side by side
in the same run, the same aggregate (mean and max force and the sample count per site and
probe)::

    study query   run_query(): the study's DuckDB views (hive partitioning, union_by_name)
    duckdb glob   DuckDB on the same files directly (hive partitioning, no union_by_name)
    pyarrow       pyarrow.dataset (hive partitioning) + Table.group_by, another engine

each run 3 times, interleaved, each on a fresh connection. The files were just written
and sit in the page cache (as they do for a lab's repeated queries on a machine with the
memory): the times are of a warm cache, not of a cold disk. The results of the three
engines are checked to agree.
Writes the section "## Query benchmark" of docs/study.md (other sections are kept)::

    .venv/bin/python benchmarks/study_query.py            # 10^8 rows (~2 GB, minutes)
    .venv/bin/python benchmarks/study_query.py --quick    # 10^6 rows, smoke run
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks._machine import cpu_model  # noqa: E402
from stipi_daemon import __version__  # noqa: E402
from stipi_daemon.study.dataset import (  # noqa: E402
    arrow_schema,
    new_state,
    partition_dir,
    save_state,
)
from stipi_daemon.study.query import run_query  # noqa: E402

SECTION = "## Query benchmark"
GOAL_S = 5.0
SITES = ("Lab A", "Clinic B", "Hospital C")
PROBES = ("usb:FTX-001", "usb:FTX-002", "ble:AA:BB:CC:DD:EE:01", "ble:AA:BB:CC:DD:EE:02")
SQL = (
    "SELECT site, probe, avg(force_n) AS mean_force_n, max(force_n) AS max_force_n, "
    "count(*) AS n FROM force_samples GROUP BY site, probe ORDER BY site, probe"
)
ZERO_COUNTS = 102
SPAN_N_PER_COUNT = 0.054297


def write_dataset(dataset: Path, sessions: int, rows: int) -> float:
    """The synthetic dataset; returns its size [B]."""
    dataset.mkdir(parents=True, exist_ok=True)
    save_state(dataset, new_state(__version__))
    schema = arrow_schema("force_samples")
    rng = np.random.default_rng(19)
    k = np.arange(rows, dtype=np.int64)
    t_s = k * 1e-3 + 0.5
    profile = (200 * np.exp(-(((k - 0.3 * rows) / (0.15 * rows)) ** 2))).astype(np.int64)
    shared = [pa.array(k), pa.array(t_s)]
    size = 0
    for i in range(sessions):
        site, probe = SITES[i % len(SITES)], PROBES[(i // len(SITES)) % len(PROBES)]
        date = f"2026-0{1 + i % 5}-15"
        uid = f"2026{i:06d}-bench"
        adc = ZERO_COUNTS + profile + rng.integers(-2, 3, rows)
        uids = pa.DictionaryArray.from_arrays(
            pa.array(np.zeros(rows, np.int32)), pa.array([uid])
        ).cast(pa.string())
        columns = [
            uids,
            *shared,
            pa.array((adc - ZERO_COUNTS) * SPAN_N_PER_COUNT),
            shared[0],
            pa.array(adc),
            pa.array(k * 1000 % 2**32),
            pa.array(k * 1000),
            pa.array(t_s + 1000.0 * i),
        ]
        path = dataset / partition_dir("force_samples", site, probe, date) / f"{uid}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_arrays(columns, schema=schema), path, compression="zstd")
        size += path.stat().st_size
    return float(size)


def study_query(dataset: Path) -> list[tuple[Any, ...]]:
    result = run_query(dataset, SQL)
    return [tuple(r.values()) for r in result.to_pylist()]


def duckdb_glob(dataset: Path) -> list[tuple[Any, ...]]:
    import duckdb

    pattern = str(dataset / "force_samples" / "**" / "*.parquet")
    sql = SQL.replace(
        "FROM force_samples",
        f"FROM read_parquet('{pattern}', hive_partitioning = true, "
        "hive_types = {'site': 'VARCHAR', 'probe': 'VARCHAR', 'date': 'VARCHAR'})",
    )
    with duckdb.connect() as con:
        return [tuple(r) for r in con.sql(sql).fetchall()]


def pyarrow_engine(dataset: Path) -> list[tuple[Any, ...]]:
    import pyarrow.dataset as ds

    part = ds.partitioning(
        pa.schema([("site", pa.string()), ("probe", pa.string()), ("date", pa.string())]),
        flavor="hive",
    )
    data = ds.dataset(dataset / "force_samples", format="parquet", partitioning=part)
    table = data.to_table(columns=["site", "probe", "force_n"])
    agg = table.group_by(["site", "probe"]).aggregate(
        [("force_n", "mean"), ("force_n", "max"), ([], "count_all")]
    )
    rows = agg.to_pylist()
    out = [
        (r["site"], r["probe"], r["force_n_mean"], r["force_n_max"], r["count_all"]) for r in rows
    ]
    return sorted(out)


ENGINES: dict[str, Callable[[Path], list[tuple[Any, ...]]]] = {
    "study query": study_query,
    "duckdb glob": duckdb_glob,
    "pyarrow": pyarrow_engine,
}


def _agree(a: list[tuple[Any, ...]], b: list[tuple[Any, ...]]) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if x[:2] != y[:2] or x[4] != y[4] or x[3] != y[3]:
            return False
        if abs(x[2] - y[2]) > 1e-9 * max(1.0, abs(x[2])):
            return False
    return True


def measure(dataset: Path, passes: int) -> tuple[dict[str, list[float]], list[tuple[Any, ...]]]:
    """Seconds per run of every engine, interleaved pass by pass; the study's result."""
    times: dict[str, list[float]] = {name: [] for name in ENGINES}
    reference: list[tuple[Any, ...]] | None = None
    for _ in range(passes):
        for name, engine in ENGINES.items():
            t0 = time.perf_counter()
            rows = engine(dataset)
            times[name].append(time.perf_counter() - t0)
            if reference is None:
                reference = rows
            elif not _agree(reference, rows):
                raise SystemExit(f"{name}: result differs from study query's")
    assert reference is not None
    return times, reference


def render(
    times: dict[str, list[float]],
    result: list[tuple[Any, ...]],
    meta: dict[str, Any],
) -> str:
    study = times["study query"]
    best = min(study)
    out = [SECTION, ""]
    out.append(
        "Generated by `.venv/bin/python benchmarks/study_query.py"
        f"{' --quick' if meta['quick'] else ''}` (do not edit this section by hand). "
        f"Machine: {platform.machine()} ({cpu_model()}), {os.cpu_count()} CPUs shared with "
        f"other work; 1-min load average {meta['load_before']:.1f} before and "
        f"{meta['load_after']:.1f} after; Python {platform.python_version()}, DuckDB "
        f"{meta['duckdb']}, pyarrow {pa.__version__}. Dataset: {meta['rows']:,} force-sample "
        f"rows in {meta['sessions']:,} session files ({meta['size_b'] / 1e9:.2f} GB, zstd), "
        f"{len(SITES)} sites x {len(PROBES)} probes x 5 days, written in "
        f"{meta['write_s']:.0f} s. Query: `{SQL}`. Each engine ran {len(study)} times, "
        "interleaved; all three gave the same groups, counts, maxima and means.\n"
    )
    out.append("| engine | first [s] | best [s] | median [s] | x study query (best) |")
    out.append("|---|---:|---:|---:|---:|")
    for name, ts in times.items():
        out.append(
            f"| {name} | {ts[0]:.2f} | {min(ts):.2f} | {statistics.median(ts):.2f} | "
            f"{min(ts) / best:.2f} |"
        )
    out.append("")
    verdict = "met" if max(study) < GOAL_S else "missed"
    out.append(
        f"Goal: the aggregate over >= 10^8 rows in under {GOAL_S:g} s: **{verdict}** "
        f"(slowest of {len(study)} study-query runs {max(study):.2f} s"
        f"{'; a --quick run has 10^6 rows and does not test the goal' if meta['quick'] else ''}"
        f"). Throughput {meta['rows'] / best / 1e6:.0f} million rows/s at best.\n"
    )
    out.append("| site | probe | mean force [N] | max force [N] | samples |")
    out.append("|---|---|---:|---:|---:|")
    for site, probe, mean, peak, n in result:
        out.append(f"| {site} | {probe} | {mean:.4f} | {peak:.3f} | {n:,} |")
    return "\n".join(out) + "\n"


def splice(path: Path, section: str) -> str:
    """The file's text with our section replaced (or appended); other sections kept."""
    text = path.read_text() if path.exists() else "# Studies\n"
    start = text.find(SECTION)
    if start < 0:
        return text.rstrip("\n") + "\n\n" + section
    nxt = text.find("\n## ", start + len(SECTION))
    end = len(text) if nxt < 0 else nxt + 1
    return text[:start] + section + ("\n" if nxt >= 0 else "") + text[end:]


def main(argv: Sequence[str] | None = None) -> int:
    import duckdb

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10^6 rows: a smoke run")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "study.md")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--keep", type=Path, help="write the dataset here and keep it")
    args = ap.parse_args(argv)
    sessions, rows = (100, 10_000) if args.quick else (1000, 100_000)
    meta: dict[str, Any] = {"quick": args.quick, "sessions": sessions, "rows": sessions * rows}
    meta["duckdb"] = duckdb.__version__
    meta["load_before"] = os.getloadavg()[0]
    work = args.keep or Path(tempfile.mkdtemp(prefix="stipi-study-bench-"))
    try:
        t0 = time.perf_counter()
        meta["size_b"] = write_dataset(work, sessions, rows)
        meta["write_s"] = time.perf_counter() - t0
        times, result = measure(work, max(1, args.passes))
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    meta["load_after"] = os.getloadavg()[0]
    section = render(times, result, meta)
    print(section)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(splice(args.out, section))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
