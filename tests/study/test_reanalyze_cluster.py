"""``study reanalyze`` on Dask distributed: the same rows as the serial path, a worker
killed mid-run, a client killed mid-run and the rerun (docs/study.md, "Re-analysis on one
PC and on a cluster").

The sessions are clones of one daemon recording with video (``_reanalyze_sessions``);
the re-analysis counts S_k again from each video (``--recompute-sk``), so a task lasts
long enough (about a second) for a kill to land while it runs. The analysis's own oracle
is the daemon's recorded summary: the clones hold the live pipeline's S_k, and the
recount of the stored video (the camera's JPEGs, decoded as the daemon decoded them) must
give the same results. No timing is asserted.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from stipi_daemon.study.diff import diff_versions
from stipi_daemon.study.query import run_query
from stipi_daemon.study.reanalyze import ReanalysisReport, reanalyze
from tests.study._reanalyze_sessions import make_study

pytestmark = [pytest.mark.timeout(600), pytest.mark.xdist_group("realtime")]

SETTINGS = "analysis: {bootstrap_replicates: 0}\nimaging: {saturation_limit_fraction: 0.02}\n"


def _settings(directory: Path) -> Path:
    path = directory / "S.yaml"
    path.write_text(SETTINGS)
    return path


def _rows(dataset: Path, version: str) -> dict[str, dict[str, Any]]:
    table = run_query(
        dataset, f"SELECT * FROM results WHERE analysis = '{version}' ORDER BY session_uid"
    )
    return {r["session_uid"]: r for r in table.to_pylist()}


def _without_run(row: dict[str, Any]) -> dict[str, Any]:
    """A row without what names the run (version, time)."""
    return {
        k: v for k, v in row.items() if k not in ("analysis_version", "analysis", "analysed_utc")
    }


def test_two_workers_give_the_serial_rows_and_collect_a_corrupt_session(
    tmp_path_factory: pytest.TempPathFactory, tmp_path: Path
) -> None:
    dataset = make_study(tmp_path_factory, tmp_path, 5, corrupt=(2,))
    settings = _settings(tmp_path)
    serial = reanalyze(dataset, settings, recompute_sk=True, scheduler="synchronous", name="serial")
    cluster = reanalyze(dataset, settings, recompute_sk=True, workers=2, name="cluster")
    for report in (serial, cluster):
        assert (report.sessions, report.computed, report.skipped) == (5, 5, 0)
        assert not report.failed and report.exit_code == 0
        assert [uid for uid, _ in report.errors] == ["R002"]
        assert "R002/video.mkv: not a readable video" in report.errors[0][1]
    assert "LocalCluster, 2 worker" in cluster.where
    a, b = _rows(dataset, "serial"), _rows(dataset, "cluster")
    assert sorted(a) == sorted(b) == [f"R{i:03d}" for i in range(5)]
    for uid in a:
        assert _without_run(a[uid]) == _without_run(b[uid]), uid
    # The corrupt session is a row with its error and no values.
    bad = a["R002"]
    assert bad["verdict"] == "unknown" and bad["depth_mm"] is None and "video" in bad["error"]
    # Each good session reproduces what the daemon recorded live (the recount of the
    # stored JPEGs is the stored S_k).
    recorded = _rows(dataset, "recorded")
    for uid in ("R000", "R001", "R003", "R004"):
        assert a[uid]["error"] is None and a[uid]["verdict"] == recorded[uid]["verdict"]
        for q in ("depth_mm", "rebound_force_n", "elasticity_kpa", "viscosity_n_s_per_mm2"):
            assert a[uid][q] == pytest.approx(recorded[uid][q], rel=1e-9), (uid, q)
    diff = diff_versions(dataset, "serial", "cluster")
    assert not diff.changed()
    assert all(q.max_abs in (None, 0.0) and q.status_changed == 0 for q in diff.quantities)
    record = json.loads((dataset / "analyses" / "cluster.json").read_text())
    assert record["status"] == "finished" and record["recompute_sk"] is True
    assert record["counts"] == {"sessions": 5, "done": 5, "errors": 1, "failed": 0}
    assert record["settings_hash"] == a["R000"]["settings_hash"] == b["R000"]["settings_hash"]


def _kill_a_busy_worker(client: Any, stop: threading.Event) -> dict[str, Any]:
    """Wait until a worker runs a task, SIGKILL its process; what was killed."""
    while not stop.is_set():
        processing = {w: keys for w, keys in client.processing().items() if keys}
        if processing:
            worker, keys = next(iter(processing.items()))
            pids = client.run(os.getpid, workers=[worker])
            time.sleep(0.3)  # into the task (decoding the video), not at its start
            os.kill(pids[worker], signal.SIGKILL)
            return {"worker": worker, "pid": pids[worker], "keys": list(keys)}
        time.sleep(0.05)
    return {}


def test_a_worker_killed_mid_run_loses_no_session(
    tmp_path_factory: pytest.TempPathFactory, tmp_path: Path
) -> None:
    from distributed import Client, LocalCluster

    dataset = make_study(tmp_path_factory, tmp_path, 4)
    settings = _settings(tmp_path)
    with (
        LocalCluster(  # type: ignore[no-untyped-call]
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as watcher,  # type: ignore[no-untyped-call]
    ):
        result: dict[str, ReanalysisReport] = {}

        def run() -> None:
            result["report"] = reanalyze(
                dataset, settings, recompute_sk=True, scheduler=cluster.scheduler_address
            )

        thread = threading.Thread(target=run)
        thread.start()
        stop = threading.Event()
        try:
            killed = _kill_a_busy_worker(watcher, stop)
        finally:
            thread.join(timeout=500)
            stop.set()
        assert not thread.is_alive()
        assert killed, "no task was seen running"
        # The task the killed worker ran was given to a worker again (the scheduler's log).
        runs = [
            sum(1 for entry in cluster.scheduler.story(key) if entry[2] == "processing")
            for key in killed["keys"]
        ]
        assert max(runs) >= 2, (killed, runs)
    report = result["report"]
    assert (report.computed, report.errors, report.failed) == (4, [], [])
    rows = _rows(dataset, report.version)
    assert sorted(rows) == ["R000", "R001", "R002", "R003"]
    assert all(r["error"] is None and r["verdict"] == "complete" for r in rows.values())


def _results_files(dataset: Path, version: str) -> dict[str, int]:
    root = dataset / "results" / f"analysis={version}"
    return {p.stem: p.stat().st_mtime_ns for p in root.rglob("*.parquet")}


def test_a_rerun_after_the_client_was_killed_does_only_what_was_missing(
    tmp_path_factory: pytest.TempPathFactory, tmp_path: Path
) -> None:
    n = 6
    dataset = make_study(tmp_path_factory, tmp_path, n)
    settings = _settings(tmp_path)
    argv = [sys.executable, "-m", "stipi_daemon", "study", "reanalyze", str(dataset)]
    argv += ["--settings", str(settings), "--recompute-sk", "--workers", "1", "--name", "v"]
    # Its own process group: the client and its cluster's processes die together.
    proc = subprocess.Popen(
        argv, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 400
        while not _results_files(dataset, "v") and proc.poll() is None:
            assert time.monotonic() < deadline, "no session finished"
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
        assert proc.stderr is not None
        stderr = proc.stderr.read().decode()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL, stderr
    before = _results_files(dataset, "v")
    assert 1 <= len(before) < n, f"killed after {len(before)} of {n}"
    record = json.loads((dataset / "analyses" / "v.json").read_text())
    assert record["status"] == "running" and "finished_utc" not in record["runs"][-1]

    report = reanalyze(dataset, settings, recompute_sk=True, scheduler="synchronous", name="v")
    assert (report.skipped, report.computed) == (len(before), n - len(before))
    after = _results_files(dataset, "v")
    assert sorted(after) == [f"R{i:03d}" for i in range(n)]
    assert {uid: after[uid] for uid in before} == before  # not written again
    record = json.loads((dataset / "analyses" / "v.json").read_text())
    assert record["status"] == "finished"
    assert record["runs"][-1]["analysed"] == n - len(before)
    assert record["runs"][-1]["skipped"] == len(before)
    assert record["counts"]["done"] == n
    # A third run finds everything done.
    again = reanalyze(dataset, settings, recompute_sk=True, scheduler="synchronous", name="v")
    assert (again.skipped, again.computed, again.where) == (n, 0, "nothing to do")
    for uid, mtime in _results_files(dataset, "v").items():
        assert mtime == after[uid]
        row = pq.read_table(
            next((dataset / "results" / "analysis=v").rglob(f"{uid}.parquet"))
        ).to_pylist()[0]
        assert row["error"] is None and row["analysis_version"] == "v"
