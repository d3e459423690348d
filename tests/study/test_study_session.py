"""A session recorded by the daemon, indexed and queried; incremental re-indexing; bad input.

One session is recorded once per module by the real daemon (``stipi-daemon --config``,
emulated Feather on a pty, simulator camera, a grade-I scene with a short recovery,
``--site``/``--subject`` on the command line). The dataset's rows are checked against the
session read back by the storage reader and against its ``summary.json``; the provenance
hashes are recomputed here with hashlib from the manifest as docs/study.md defines them.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import shutil
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest
import yaml

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.study.hashing import data_hash
from stipi_daemon.study.index import index_sessions
from stipi_daemon.study.query import run_query
from tests._offline import SCENES


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One complete daemon session (slower again while it does not complete: a loaded
    machine slows the test instead of failing it)."""
    base = tmp_path_factory.mktemp("study_session")
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["force_profile"]["hold_s"] = 16.0
    doc["force_profile"]["recovery_s"] = 14.0
    doc["name"] = "grade1_study"
    (base / "grade1_study.yaml").write_text(yaml.safe_dump(doc))
    for speed in (8.0, 4.0, 2.0, 1.0):
        cfg = {
            "probe": {"transport": {"kind": "emulated", "scene": "grade1_study.yaml"}},
            "camera": {"kind": "simulator", "scene": "grade1_study.yaml"},
            "storage": {"root": "sessions", "min_free_mb": 0, "video": "off"},
            "run": {"speed": speed},
        }
        (base / "config.yaml").write_text(yaml.safe_dump(cfg))
        argv = ["--config", str(base / "config.yaml"), "--quiet", "--site", "Lab A"]
        _, out, _ = _run([*argv, "--subject", "P-019"])
        session = Path(out.strip().splitlines()[-1])
        if json.loads((session / "summary.json").read_text())["status"] == "complete":
            return session
        shutil.rmtree(session)
    raise AssertionError("no complete recording")


def _copy(session: Path, root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    return Path(shutil.copytree(session, root / session.name))


def _canonical_sha256(value: Any) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def test_index_and_query_a_recorded_session(recorded: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "ds"
    status, out, err = _run(["study", "index", str(recorded.parent), "--out", str(dataset)])
    assert (status, err) == (0, "")
    assert "1 added, 0 replaced, 0 unchanged, 0 unreadable" in out
    with SessionReader(recorded) as reader:
        manifest, summary = reader.manifest, reader.summary
        force, frames = reader.force_samples(), reader.frames()
        t0 = manifest["clock_reference"]["monotonic_s"]
    assert summary is not None
    assert manifest["firmware"]["probe_id"] == "emulated"
    day = manifest["created_utc"][:10]
    part = f"site=Lab%20A/probe=emulated/date={day}/{recorded.name}.parquet"
    for table in ("sessions", "force_samples", "frames"):
        assert (dataset / table / part).is_file()
    results_file = dataset / "results" / "analysis=recorded" / part
    units = json.loads(pq.read_schema(results_file).metadata[b"units"])
    assert units["viscosity_n_s_per_mm2"] == "N*s/mm^2" and units["depth_mm"] == "mm"

    row = run_query(dataset, "SELECT * FROM sessions").to_pylist()
    assert len(row) == 1
    s = row[0]
    assert (s["site"], s["subject"], s["probe"], s["probe_id"]) == (
        "Lab A",
        "P-019",
        "emulated",
        "emulated",
    )
    assert (s["n_force_samples"], s["n_frames"]) == (len(force), len(frames))
    assert s["path"] == str(recorded.resolve()) and s["status"] == "complete"

    got = run_query(dataset, "SELECT seq, t_s, force_n FROM force_samples ORDER BY seq")
    assert got["seq"].to_pylist() == list(range(len(force)))
    want_force = [None if math.isnan(v) else v for v in force["force_n"].tolist()]
    assert got["force_n"].to_pylist() == want_force
    assert got["t_s"].to_pylist() == pytest.approx((force["t_host_s"] - t0).tolist(), abs=1e-9)
    sk = run_query(dataset, "SELECT seq, s_k_px FROM frames ORDER BY seq").to_pylist()
    assert [(r["seq"], r["s_k_px"]) for r in sk] == [
        (q, k) for q, k in frames[["seq", "s_k"]].tolist()
    ]

    r = run_query(dataset, "SELECT * FROM results").to_pylist()[0]
    assert r["analysis"] == r["analysis_version"] == "recorded"
    assert r["data_hash"] == s["data_hash"] and r["data_hash"].startswith("sha256:")
    config = manifest["config"]
    settings = {k: config[k] for k in ("analysis", "imaging", "measurement")}
    assert r["settings_hash"] == _canonical_sha256(
        settings | {"calibration": manifest["calibration"]}
    )
    assert r["package_version"] == manifest["software"]["stipi_daemon"]
    assert r["verdict"] == summary["verdict"]["status"] and r["error"] is None
    eta = summary["results"]["paper_estimator"]["viscosity_n_s_per_mm2"]
    eta_status = summary["validity"]["viscosity_n_s_per_mm2"]["status"]
    assert r["viscosity_n_s_per_mm2_status"] == eta_status
    assert r["viscosity_n_s_per_mm2"] == (None if eta_status == "invalid" else eta)
    assert r["severity_class"] == summary["results"]["severity"]["paper_estimator"]["severity"]
    summary_hash = "sha256:" + hashlib.sha256((recorded / "summary.json").read_bytes()).hexdigest()
    assert s["summary_hash"] == summary_hash


def _mtimes(directory: Path) -> dict[str, int]:
    return {
        str(p.relative_to(directory)): p.stat().st_mtime_ns for p in directory.rglob("*.parquet")
    }


def test_reindex_adds_changed_sessions_only(recorded: Path, tmp_path: Path) -> None:
    session = _copy(recorded, tmp_path / "root")
    dataset = tmp_path / "ds"
    first = index_sessions([session.parent], dataset)
    assert len(first.added) == 1
    first_hash = json.loads((dataset / "study.json").read_text())["sessions"][session.name][
        "data_hash"
    ]
    with SessionReader(recorded) as reader:  # the data hash is the same for a copy
        assert data_hash(reader) == first_hash
    foreign = dataset / "sessions" / "notes.txt"  # the user's own file: never removed
    foreign.write_text("mine\n")
    before = _mtimes(dataset)

    again = index_sessions([session.parent], dataset)
    assert (again.added, again.replaced, again.unchanged) == ([], [], 1)
    assert _mtimes(dataset) == before

    # The same session found under a second root is a copy: not indexed twice.
    copy = _copy(recorded, tmp_path / "backup")
    twice = index_sessions([session.parent, copy.parent], dataset)
    assert twice.unchanged == 1 and len(twice.notes) == 1 and "a copy of" in twice.notes[0]
    assert _mtimes(dataset) == before

    # A changed session (its site corrected in the manifest) is replaced, and moves.
    manifest = json.loads((session / "manifest.json").read_text())
    manifest["metadata"]["site"] = "Lab B"
    (session / "manifest.json").write_text(json.dumps(manifest, indent=2))
    changed = index_sessions([session.parent], dataset)
    assert (changed.added, changed.replaced) == ([], [session.name])
    after = _mtimes(dataset)
    assert not [f for f in after if "site=Lab%20A" in f]
    assert len([f for f in after if "site=Lab%20B" in f]) == 4
    assert foreign.read_text() == "mine\n"
    rows = run_query(dataset, "SELECT site, data_hash FROM sessions").to_pylist()
    assert [r["site"] for r in rows] == ["Lab B"]
    state = json.loads((dataset / "study.json").read_text())["sessions"][session.name]
    assert rows[0]["data_hash"] == state["data_hash"] != first_hash


def test_unreadable_and_recording_sessions_are_skipped(recorded: Path, tmp_path: Path) -> None:
    root = tmp_path / "root"
    _copy(recorded, root)
    broken = root / "broken"
    broken.mkdir()
    shutil.copy(recorded / "manifest.json", broken / "manifest.json")
    (broken / "session.sqlite").write_bytes(b"not a database" * 100)
    live = SessionWriter.create(
        root, {}, {}, None, session_id="live", options=StorageOptions(min_free_bytes=0)
    )
    try:
        status, out, err = _run(["study", "index", str(root), "--out", str(tmp_path / "ds")])
    finally:
        live.close()
    assert status == 0
    assert "1 added, 0 replaced, 0 unchanged, 1 unreadable, 1 passed over" in out
    lines = err.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith(f"stipi-daemon: skipped {broken}")
    assert "not a readable SQLite database" in lines[0]
    assert lines[1] == f"stipi-daemon: note: {root / 'live'}: skipped, a writer is recording it"


def test_query_output_and_errors(recorded: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "ds"
    index_sessions([recorded.parent], dataset)
    status, out, _ = _run(["study", "query", str(dataset), "SELECT site, verdict FROM sessions"])
    assert status == 0 and out.splitlines()[0].split() == ["site", "verdict"]
    assert out.splitlines()[1].startswith("Lab A")
    sql = "SELECT seq, force_n FROM force_samples ORDER BY seq"
    assert _run(["study", "query", str(dataset), sql, "--out", str(tmp_path / "f.csv")])[0] == 0
    assert _run(["study", "query", str(dataset), sql, "--out", str(tmp_path / "f.parquet")])[0] == 0
    with open(tmp_path / "f.csv", newline="") as f:
        csv_rows = list(csv.DictReader(f))
    table = pq.read_table(tmp_path / "f.parquet")
    assert len(csv_rows) == table.num_rows > 100
    assert [int(r["seq"]) for r in csv_rows] == table["seq"].to_pylist()

    for argv, expected in (
        ([str(dataset), "SELEC 1"], "stipi-daemon: error: SQL: Parser Error: syntax error"),
        ([str(dataset), "SELECT nope FROM sessions"], "stipi-daemon: error: SQL: Binder Error"),
        ([str(dataset), "DROP VIEW sessions"], "stipi-daemon: error: SQL: only queries"),
        ([str(dataset), "SELECT 1; SELECT 2"], "stipi-daemon: error: SQL: give exactly one"),
        ([str(tmp_path), "SELECT 1"], f"stipi-daemon: error: {tmp_path}: not a study dataset"),
        (
            [str(dataset), "SELECT 1", "--out", str(tmp_path / "x.txt")],
            "stipi-daemon: error: --out",
        ),
    ):
        status, out, err = _run(["study", "query", *argv])
        assert status == 2 and out == "", argv
        assert len(err.strip().splitlines()) == 1 and err.startswith(expected), err
    assert not (tmp_path / "x.txt").exists()
