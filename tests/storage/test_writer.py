from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stipi_daemon.errors import ConfigError, SessionError
from stipi_daemon.storage import (
    DEFAULT_COMMIT_INTERVAL_S,
    SessionReader,
    SessionState,
    SessionWriter,
    StorageOptions,
)
from stipi_daemon.storage.writer import COMMIT_LEAD_FRACTION, IDLE_POLL_MIN_S
from tests.storage.conftest import (
    CALIBRATION,
    CONFIG,
    FIRMWARE,
    OPTIONS,
    SOFTWARE,
    SUMMARY,
    Recorded,
)
from tests.storage.writer_child import PROGRESS

CHILD = Path(__file__).with_name("writer_child.py")
REPO_ROOT = Path(__file__).resolve().parents[2]


def _as_float(v: Any) -> float:
    return math.nan if v is None else float(v)


def _assert_rows_equal(array: np.ndarray, expected: list[tuple[Any, ...]]) -> None:
    assert len(array) == len(expected)
    for got, want in zip(array.tolist(), expected, strict=True):
        for g, w in zip(got, want, strict=True):
            if isinstance(w, float) or w is None:
                np.testing.assert_equal(g, _as_float(w))  # NaN == NaN here
            else:
                assert g == w


def test_round_trip_of_every_table(recorded: Recorded) -> None:
    with SessionReader(recorded.directory) as reader:
        rows = recorded.rows
        _assert_rows_equal(reader.force_samples(), rows["force_samples"])
        _assert_rows_equal(reader.frames(), rows["frames"])
        _assert_rows_equal(reader.gaps(), rows["gaps"])
        _assert_rows_equal(reader.clock_probes(), rows["clock_probes"])
        _assert_rows_equal(reader.live_parameters(), rows["live_parameters"])
        assert [tuple(e) for e in reader.events()] == rows["events"]
        assert [tuple(t) for t in reader.transitions()] == rows["transitions"]
        assert reader.counts() == {name: len(r) for name, r in rows.items()}
        # MCU times above 2^32 survive (64-bit integers), raw times stay below 2^32.
        force = reader.force_samples()
        assert force["t_mcu_us"].max() > 2**32
        assert force["t_mcu_raw_us"].max() < 2**32
        assert reader.status is SessionState.COMPLETE
        assert reader.summary == SUMMARY


def test_manifest_contents(recorded: Recorded) -> None:
    manifest = json.loads((recorded.directory / "manifest.json").read_text())
    assert manifest["format"] == "stipi-session"
    assert manifest["format_version"] == 1
    assert manifest["session_id"] == recorded.session_id
    assert manifest["created_utc"].endswith("Z")
    assert manifest["config"] == CONFIG
    assert manifest["calibration"] == CALIBRATION
    assert manifest["firmware"] == FIRMWARE
    assert manifest["files"] == {
        "database": "session.sqlite",
        "summary": "summary.json",
        "video": "video.mkv",
    }
    assert set(manifest["software"]) == {
        "stipi_daemon",
        "python",
        "numpy",
        "opencv",
        "sqlite",
        "sk_kernel",
    }
    assert manifest["software"]["sk_kernel"] == SOFTWARE["sk_kernel"]
    assert manifest["software"]["sqlite"] == sqlite3.sqlite_version
    assert manifest["storage"]["commit_interval_s"] == DEFAULT_COMMIT_INTERVAL_S


def test_finished_session_is_one_file_and_lock_is_gone(recorded: Recorded) -> None:
    names = sorted(p.name for p in recorded.directory.iterdir())
    assert names == ["manifest.json", "session.sqlite", "summary.json", "video.mkv"]
    conn = sqlite3.connect(recorded.directory / "session.sqlite")
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
        assert conn.execute("PRAGMA user_version").fetchone()[0] == 2
    finally:
        conn.close()


@pytest.mark.parametrize("status", ["complete", "aborted", "fault"])
def test_finish_states(tmp_path: Path, status: str) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        writer.finish(status)
    with SessionReader(tmp_path / "s") as reader:
        assert reader.status.value == status
        assert reader.summary is None
        assert "finished_utc" in reader.meta()


def test_finish_rejects_unknown_status_and_rows_after_finish(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        with pytest.raises(SessionError, match="'done' is not one of aborted, complete, fault"):
            writer.finish("done")
        with pytest.raises(SessionError, match="recording"):
            writer.finish("recording")
        writer.finish("aborted")
        with pytest.raises(SessionError, match=r"finished \(aborted\)"):
            writer.add_event(1.0, "late", {})
    with pytest.raises(SessionError, match="closed"):
        writer.commit()


def test_close_without_finish_is_interrupted(tmp_path: Path) -> None:
    writer = SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS)
    writer.add_event(1.0, "start", {})
    with SessionReader(tmp_path / "s") as reader:
        assert reader.status is SessionState.RECORDING
        writer.close()
        assert reader.status.value == "interrupted"
        assert reader.count("events") == 1  # close commits the buffered rows


def test_bad_rows_raise_and_buffer_nothing(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        good = (0, 500, 0, 0, 1.0, 0.1)
        with pytest.raises(SessionError, match=r"force_samples row 1, column t_host_s: nan"):
            writer.add_force_samples([good, (1, 500, 0, 0, math.nan, 0.1)])
        with pytest.raises(SessionError, match=r"row 0, column adc_counts: 1.5 is not an integer"):
            writer.add_force_samples([(0, 1.5, 0, 0, 1.0, None)])
        with pytest.raises(SessionError, match="expected 6 values"):
            writer.add_force_samples([(0, 1, 2)])
        with pytest.raises(SessionError, match="does not fit in a signed 64-bit"):
            writer.add_clock_probe(2**64, 0, 1.0)
        with pytest.raises(SessionError, match="column count: 0 must be >= 1"):
            writer.add_gap("force", 3, 0, 1.0, "link")
        with pytest.raises(SessionError, match=r"events row 0, column detail_json.x: object"):
            writer.add_event(1.0, "bad", {"x": object()})
        with pytest.raises(SessionError, match="contains a comma"):
            writer.add_frames([(0, 1.0, 1.0, 5, ["a,b"])])
        assert writer.pending_rows == 0
        writer.finish("aborted")
    with SessionReader(tmp_path / "s") as reader:
        assert sum(reader.counts().values()) == 0


def test_numpy_rows_and_structured_arrays(tmp_path: Path) -> None:
    dtype = [
        ("sample_index", "<i8"),
        ("adc_counts", "<u2"),
        ("t_mcu_raw_us", "<u4"),
        ("t_mcu_us", "<i8"),
        ("t_host_s", "<f8"),
        ("force_n", "<f4"),
    ]
    data = np.zeros(5, dtype=dtype)
    data["sample_index"] = np.arange(5)
    data["adc_counts"] = 1023
    data["t_mcu_raw_us"] = 2**32 - 1
    data["t_host_s"] = np.linspace(1.0, 2.0, 5)
    data["force_n"] = [0.5, np.nan, 1.0, 2.0, 3.0]
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        assert writer.add_force_samples(data) == 5
        writer.add_frames([(np.int64(7), np.float64(1.0), np.float32(1.5), np.uint32(9), "")])
        writer.finish("complete")
    with SessionReader(tmp_path / "s") as reader:
        got = reader.force_samples()
        np.testing.assert_array_equal(got["t_mcu_raw_us"], 2**32 - 1)
        np.testing.assert_array_equal(got["force_n"], [0.5, np.nan, 1.0, 2.0, 3.0])
        assert reader.frames().tolist() == [(7, 1.0, 1.5, 9, "")]


def test_background_thread_commits_without_further_calls(tmp_path: Path) -> None:
    options = StorageOptions(commit_interval_s=0.3, min_free_bytes=0)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        writer.add_event(1.0, "a", {})
        with SessionReader(tmp_path / "s") as reader:
            assert reader.count("events") == 0  # buffered, not committed yet
            deadline = time.monotonic() + 5.0
            while reader.count("events") == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert reader.count("events") == 1
        assert writer.pending_rows == 0
        assert writer.stats.commits >= 1
        writer.finish("complete")


def test_background_thread_commits_at_a_commit_interval_too_short_to_poll(
    tmp_path: Path,
) -> None:
    # 4 ms: a quarter interval is under IDLE_POLL_MIN_S, so the idle thread waits untimed and
    # the first row must wake it (it would never commit otherwise).
    options = StorageOptions(commit_interval_s=0.004, min_free_bytes=0)
    assert (1.0 - COMMIT_LEAD_FRACTION) * options.commit_interval_s < IDLE_POLL_MIN_S
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        time.sleep(0.05)  # the thread is idle
        writer.add_event(1.0, "a", {})
        with SessionReader(tmp_path / "s") as reader:
            deadline = time.monotonic() + 5.0
            while reader.count("events") == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert reader.count("events") == 1
        writer.finish("complete")


def test_without_background_thread_a_due_add_commits(tmp_path: Path) -> None:
    options = StorageOptions(commit_interval_s=0.05, min_free_bytes=0, background_commit=False)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        writer.add_event(1.0, "a", {})
        time.sleep(0.1)
        assert writer.pending_rows == 1  # nobody committed in between
        writer.add_event(2.0, "b", {})  # due: commits both
        assert writer.pending_rows == 0
        writer.finish("complete")


def test_concurrent_adders_lose_nothing(tmp_path: Path) -> None:
    options = StorageOptions(commit_interval_s=0.01, min_free_bytes=0)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:

        def add(k: int) -> None:
            for i in range(400):
                writer.add_force_samples([(k * 1000 + i, 1, i, i, float(i), None)])
                if i % 50 == 0:
                    writer.add_event(float(i), f"thread{k}", {"i": i})
                    time.sleep(0.002)  # adding spans several commit intervals

        threads = [threading.Thread(target=add, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        writer.finish("complete")
        assert writer.stats.commits > 1
    with SessionReader(tmp_path / "s") as reader:
        index = reader.force_samples()["sample_index"]
        assert sorted(index.tolist()) == [k * 1000 + i for k in range(4) for i in range(400)]
        for k in range(4):  # each thread's rows keep their order
            mine = index[(index >= k * 1000) & (index < (k + 1) * 1000)]
            assert (np.diff(mine) == 1).all()
        assert reader.count("events") == 32


def test_failed_commit_keeps_rows_and_reports_on_next_call(tmp_path: Path) -> None:
    options = StorageOptions(min_free_bytes=0, background_commit=False)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        writer.add_event(1.0, "kept", {})
        # Another connection takes the write lock: the commit cannot proceed (SQLITE_BUSY).
        blocker = sqlite3.connect(tmp_path / "s" / "session.sqlite", isolation_level=None)
        blocker.execute("PRAGMA busy_timeout=0")
        blocker.execute("BEGIN IMMEDIATE")
        writer._conn.execute("PRAGMA busy_timeout=0")
        with pytest.raises(SessionError, match="commit failed, 1 rows kept in memory"):
            writer.commit()
        assert writer.pending_rows == 1
        blocker.execute("ROLLBACK")
        blocker.close()
        writer.commit()
        writer.finish("complete")
    with SessionReader(tmp_path / "s") as reader:
        assert [e.kind for e in reader.events()] == ["kept"]


def test_existing_directory_and_bad_id(tmp_path: Path) -> None:
    SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS).close()
    with pytest.raises(SessionError, match="exists already"):
        SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS)
    with pytest.raises(SessionError, match="not allowed"):
        SessionWriter.create(tmp_path, {}, {}, session_id="../escape", options=OPTIONS)


def test_default_session_id_sorts_by_time(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, options=OPTIONS) as writer:
        sid = writer.session_id
        assert writer.video_path is None
        writer.finish("complete")
    assert len(sid) == len("20250114T093012Z-3fa9c1")
    assert sid[8] == "T" and sid[15] == "Z"


def test_unserialisable_config_creates_nothing(tmp_path: Path) -> None:
    with pytest.raises(SessionError, match=r"config.camera: bytes value"):
        SessionWriter.create(tmp_path, {"camera": b"x"}, {}, session_id="s", options=OPTIONS)
    assert not (tmp_path / "s").exists()


def test_options_validation() -> None:
    with pytest.raises(ConfigError, match="commit_interval_s"):
        StorageOptions(commit_interval_s=0.0)
    with pytest.raises(ConfigError, match="synchronous"):
        StorageOptions(synchronous="OFF")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="min_free_bytes"):
        StorageOptions(min_free_bytes=-1)


def test_synchronous_full_option(tmp_path: Path) -> None:
    options = StorageOptions(synchronous="FULL", min_free_bytes=0)
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options) as writer:
        assert writer._conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
        writer.add_event(1.0, "a", {})
        writer.finish("complete")
    with SessionReader(tmp_path / "s") as reader:
        assert reader.manifest["storage"]["synchronous"] == "FULL"


def test_free_space_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = shutil.disk_usage

    def tiny(path: Any) -> Any:
        usage = real(path)
        return type(usage)(usage.total, usage.total - 10 * 2**20, 10 * 2**20)

    monkeypatch.setattr(shutil, "disk_usage", tiny)
    options = StorageOptions(min_free_bytes=100 * 2**20)
    with pytest.raises(SessionError) as info:
        SessionWriter.create(tmp_path, {}, {}, session_id="s", options=options)
    message = str(info.value)
    assert "\n" not in message
    assert str(tmp_path) in message
    assert "10.0 MiB free, 100.0 MiB required" in message
    assert not (tmp_path / "s").exists()
    # Enough space with a lower minimum.
    SessionWriter.create(
        tmp_path, {}, {}, session_id="s", options=StorageOptions(min_free_bytes=2**20)
    ).close()


def test_summary_write_is_atomic_under_concurrent_readers(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        path = writer.write_summary({"i": -1})
        stop = threading.Event()
        seen: list[int] = []
        errors: list[str] = []

        def read_loop() -> None:
            while not stop.is_set():
                try:
                    value = json.loads(path.read_text())
                except json.JSONDecodeError as exc:  # a partial file would land here
                    errors.append(str(exc))
                    return
                seen.append(value["i"])
                assert len(value["payload"] if "payload" in value else "x" * 50_000) == 50_000

        thread = threading.Thread(target=read_loop)
        thread.start()
        try:
            for i in range(60):
                writer.write_summary({"i": i, "payload": "x" * 50_000})
        finally:
            stop.set()
            thread.join()
        assert errors == []
        assert seen == sorted(seen)
        assert not path.with_name("summary.json.tmp").exists()
        # A summary that cannot be serialised leaves the previous one intact.
        with pytest.raises(SessionError, match=r"summary\.bad"):
            writer.write_summary({"bad": b"x"})
        assert json.loads(path.read_text())["i"] == 59
        writer.finish("complete", {"i": 100})
    assert json.loads(path.read_text()) == {"i": 100}


def _start_child(root: Path, mode: str, interval: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(CHILD), str(root), "child", mode, str(interval)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
    )


@pytest.mark.parametrize("interval", [DEFAULT_COMMIT_INTERVAL_S, 0.05])
def test_kill_9_loses_at_most_one_commit_interval(tmp_path: Path, interval: float) -> None:
    proc = _start_child(tmp_path, "stream", interval)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.6)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:  # pragma: no cover - only if an assertion fired early
            proc.kill()
            proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()
        assert proc.stdin is not None
        proc.stdin.close()
    with SessionReader(tmp_path / "child") as reader:
        report = reader.integrity_check()
        assert report.ok, report.problems
        assert reader.status is SessionState.INTERRUPTED
        force = reader.force_samples()
        assert reader.count("frames") > 0
    # Every committed row is there, in order, without holes.
    np.testing.assert_array_equal(force["sample_index"], np.arange(len(force)))
    assert len(force) > 100  # ~0.6 s at up to ~1 kHz
    # The rows the writer had accepted when it died (written by the child after each add).
    last_index, last_t_s = PROGRESS.unpack((tmp_path / "progress.bin").read_bytes())
    assert last_index >= int(force["sample_index"][-1])
    assert last_t_s <= t_kill
    lost_s = last_t_s - float(force["t_host_s"][-1])
    # Loss bound: one commit interval, plus 50 ms for scheduling and the commit itself.
    assert lost_s <= interval + 0.05, f"lost {lost_s * 1e3:.0f} ms of accepted rows"


def test_manifest_software_without_caller_entries(tmp_path: Path) -> None:
    with SessionWriter.create(tmp_path, {}, {}, session_id="s", options=OPTIONS) as writer:
        software = writer.manifest["software"]
    assert set(software) == {"stipi_daemon", "python", "numpy", "opencv", "sqlite"}
