"""Sessions recorded by the daemon with metadata: list, show, search, analyze, table, export.

Two sessions are recorded once per module by the real daemon (``stipi-daemon --config``,
emulated Feather on a pty, simulator camera, a grade-I scene with a short recovery): one
with its metadata from the config's ``session`` section and replaced in part by the
command line, one with metadata from the command line only. Nothing here writes a
summary by hand: the severity, verdict and validity the commands show are the daemon's.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.io
import yaml

from stipi_daemon.cli import main
from stipi_daemon.storage import SessionReader
from tests._offline import SCENES


@dataclass(frozen=True)
class Recorded:
    root: Path
    config: Path
    first: Path  # subject P-001 (config) ... replaced by the command line
    second: Path  # subject P-002, command line only


def _scene(directory: Path) -> Path:
    # Grade I with an operator who holds until the release prompt (hold 16 s), short
    # recovery: ~31 s of session time.
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["force_profile"]["hold_s"] = 16.0
    doc["force_profile"]["recovery_s"] = 14.0
    doc["name"] = "grade1_meta"
    path = directory / "grade1_meta.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _main_out(argv: list[str]) -> tuple[int, str]:
    """Exit status and stdout of ``stipi-daemon argv`` (also in module-scoped fixtures)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(argv)
    return status, out.getvalue()


def _record(directory: Path, session: dict[str, str], options: list[str]) -> tuple[Path, Path]:
    """Record one session through the command line; slower again while it does not
    complete (a loaded machine slows the test instead of failing it)."""
    scene = _scene(directory)
    for speed in (8.0, 4.0, 2.0, 1.0):
        cfg = {
            "probe": {"transport": {"kind": "emulated", "scene": scene.name}},
            "camera": {"kind": "simulator", "scene": scene.name},
            "storage": {"root": "sessions", "min_free_mb": 0, "video": "off"},
            "run": {"speed": speed},
            "session": session,
        }
        config = directory / "config.yaml"
        config.write_text(yaml.safe_dump(cfg))
        _, out = _main_out(["--config", str(config), "--quiet", *options])
        session_dir = Path(out.strip().splitlines()[-1])
        summary = json.loads((session_dir / "summary.json").read_text())
        if summary["status"] == "complete":
            return config, session_dir
        shutil.rmtree(session_dir)  # only the complete recording stays in the root
    raise AssertionError(f"no complete recording: {summary['end_reason']}")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    base = tmp_path_factory.mktemp("metadata")
    config, first = _record(
        base,
        {"subject": "P-001", "site": "Lab A", "operator": "config operator"},
        ["--operator", "Dr. X", "--note", "left ankle, day 3\nafter 10 min rest"],
    )
    _, second = _record(base, {}, ["--subject", "P-002", "--site", "Lab B"])
    return Recorded(base / "sessions", config, first, second)


def _summary(directory: Path) -> dict[str, Any]:
    summary: dict[str, Any] = json.loads((directory / "summary.json").read_text())
    return summary


def _table(out: str) -> list[dict[str, str]]:
    """The rows of a ``format_table`` text by the header's column positions (cells may
    hold spaces)."""
    lines = out.splitlines()
    header = lines[0]
    names = [n for n in header.split("  ") if n.strip()]
    starts = [header.index(n.strip()) for n in names]
    ends = [*starts[1:], None]
    return [
        {n.strip(): line[s:e].strip() for n, s, e in zip(names, starts, ends, strict=True)}
        for line in lines[1:]
        if line.strip()
    ]


def _files(directory: Path) -> dict[str, tuple[bytes, int]]:
    """Every file below ``directory``: bytes and modification time [ns]."""
    return {
        str(p.relative_to(directory)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def test_manifest_metadata_from_config_and_command_line(recorded: Recorded) -> None:
    first = json.loads((recorded.first / "manifest.json").read_text())
    assert first["metadata"] == {
        "subject": "P-001",  # config
        "site": "Lab A",  # config
        "operator": "Dr. X",  # --operator replaces the config's
        "note": "left ankle, day 3\nafter 10 min rest",  # --note
    }
    # The recorded config agrees with the metadata the session was recorded with.
    assert first["config"]["session"] == first["metadata"]
    second = json.loads((recorded.second / "manifest.json").read_text())
    assert second["metadata"] == {
        "subject": "P-002",
        "site": "Lab B",
        "operator": None,
        "note": None,
    }


def test_list_shows_the_daemons_severity_verdict_and_metadata(recorded: Recorded) -> None:
    status, out = _main_out(["sessions", "list", "--root", str(recorded.root)])
    assert status == 0
    rows = {r["ID"]: r for r in _table(out)}
    assert set(rows) == {recorded.first.name, recorded.second.name}
    for directory in (recorded.first, recorded.second):
        summary, row = _summary(directory), rows[directory.name]
        paper = summary["results"]["severity"]["paper_estimator"]
        # The scene is a grade-I phantom: its curve is nearest the grade-I reference.
        assert paper["nearest_grade"] == "I"
        if summary["validity"]["severity"]["status"] == "invalid":
            assert row["SEVERITY"] == "invalid"
        else:
            assert row["SEVERITY"] == f"{paper['severity']} (I)"
        assert row["VALIDITY"] == summary["verdict"]["status"] != "unknown"
        assert row["STATUS"] == "complete"
    first, second = rows[recorded.first.name], rows[recorded.second.name]
    assert (first["SUBJECT"], first["SITE"], first["OPERATOR"]) == ("P-001", "Lab A", "Dr. X")
    assert first["LABEL"] == "left ankle, day 3"  # the note's first line
    assert (second["SUBJECT"], second["SITE"], second["OPERATOR"]) == ("P-002", "Lab B", "-")
    assert second["LABEL"] == "scene:grade1_meta"  # no note: the simulated scene


@pytest.mark.parametrize(
    ("option", "value", "which"),
    [
        ("--subject", "P-001", "first"),
        ("--subject", "P-002", "second"),
        ("--site", "Lab B", "second"),
        ("--operator", "Dr. X", "first"),
        ("--subject", "P-00", None),  # exact match, no prefix
        ("--subject", "p-001", None),  # exact match, case counts
    ],
)
def test_list_selects_by_metadata(
    recorded: Recorded, option: str, value: str, which: str | None
) -> None:
    status, out = _main_out(["sessions", "list", "--root", str(recorded.root), option, value])
    assert status == 0
    if which is None:
        assert out.strip() == f"no sessions with {option[2:]} {value!r} in {recorded.root}"
    else:
        assert [r["ID"] for r in _table(out)] == [getattr(recorded, which).name]


def test_show_prints_the_metadata(recorded: Recorded) -> None:
    status, out = _main_out(["sessions", "show", str(recorded.first)])
    assert status == 0
    assert "\nsubject    P-001\n" in out
    assert "\nsite       Lab A\n" in out
    assert "\noperator   Dr. X\n" in out
    assert "\nnote       left ankle, day 3\n           after 10 min rest\n" in out
    assert "\nlabel      left ankle, day 3\n" in out


def test_bad_metadata_is_one_line_and_records_nothing(
    recorded: Recorded, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = sorted(p.name for p in recorded.root.iterdir())
    config = str(recorded.config)
    assert main(["--config", config, "--subject", "P-1\nP-2"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "stipi-daemon: error: --subject: contains a line break (one line of at most 64 "
        "characters)\n"
    )
    assert main(["--config", config, "--site", "s" * 65]) == 2
    assert "--site: is 65 characters long" in capsys.readouterr().err
    # In the config: the error names the file and the field.
    doc = yaml.safe_load(recorded.config.read_text())
    doc["session"] = {"operator": "x" * 100}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    assert main(["--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad}: field 'session.operator'" in err
    assert "is 100 characters long" in err
    # Metadata describes a measurement: not accepted with another command.
    assert main(["--subject", "P-1", "sessions", "list", "--root", str(recorded.root)]) == 2
    assert "give them with --config FILE and no command" in capsys.readouterr().err
    assert sorted(p.name for p in recorded.root.iterdir()) == before


def test_analyze_keeps_the_metadata(recorded: Recorded, tmp_path: Path) -> None:
    out = tmp_path / "analysis.json"
    status, _ = _main_out(["analyze", str(recorded.first), "--out", str(out)])
    assert status == 0
    doc = json.loads(out.read_text())
    manifest = json.loads((recorded.first / "manifest.json").read_text())
    assert doc["metadata"] == manifest["metadata"]
    assert doc["metadata"]["subject"] == "P-001"


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_results_table_csv_and_parquet(recorded: Recorded, tmp_path: Path) -> None:
    root = str(recorded.root)
    status, out = _main_out(["sessions", "table", "--root", root, "--out", str(tmp_path / "r.csv")])
    assert status == 0 and out.strip() == f"{tmp_path / 'r.csv'} (2 sessions)"
    status, _ = _main_out(
        ["sessions", "table", "--root", root, "--out", str(tmp_path / "r.parquet")]
    )
    assert status == 0
    rows = {r["session_id"]: r for r in _read_csv(tmp_path / "r.csv")}
    parquet = pq.read_table(tmp_path / "r.parquet")
    prow = {r["session_id"]: r for r in parquet.to_pylist()}
    assert list(rows) == list(prow) == [recorded.first.name, recorded.second.name]
    for directory in (recorded.first, recorded.second):
        summary, row, pr = _summary(directory), rows[directory.name], prow[directory.name]
        results, validity = summary["results"], summary["validity"]
        expected = {
            "depth_mm": results["pitting"]["depth_mm"],
            "rebound_force_n": results["pitting"]["rebound_force_n"],
            "recovery_time_s": results["pitting"]["recovery_time_s"],
            "elasticity_kpa": results["paper_estimator"]["elasticity_kpa"],
            "viscosity_n_s_per_mm2": results["paper_estimator"]["viscosity_n_s_per_mm2"],
            "tau_s": results["fitted_recovery"]["tau_s"],
            "applied_force_n": results["applied_force_n"],
        }
        for name, value in expected.items():
            assert row[f"{name}_status"] == pr[f"{name}_status"] == validity[name]["status"]
            if validity[name]["status"] == "invalid":
                assert row[name] == "" and pr[name] is None
            else:
                assert float(row[name]) == pr[name] == value  # exact round trip
        assert row["severity"] == summary["results"]["severity"]["paper_estimator"]["severity"]
        assert row["severity_grade"] == "I"
        assert row["verdict"] == pr["verdict"] == summary["verdict"]["status"]
        assert row["verdict_line"] == summary["verdict"]["line"]
        assert int(row["n_frames"]) == pr["n_frames"] > 0
        # The recovery models the daemon compared, exactly as summary.json has them.
        models = results["recovery_models"]
        assert row["recovery_models_best"] == pr["recovery_models_best"] == models["best_model"]
        assert pr["kelvin_voigt_rejected"] is models["kelvin_voigt_rejected"]
        assert row["kelvin_voigt_rejected"] == str(models["kelvin_voigt_rejected"])
        for name, fit in models["models"].items():
            assert pr[f"{name}_aicc"] == fit["aicc"]
            assert pr[f"{name}_aicc_weight"] == fit["akaike_weight"]
            for q in ("tau_s", "recovery_time_s", "rebound_force_n", "viscosity_n_s_per_mm2"):
                if (
                    q == "viscosity_n_s_per_mm2"
                    and validity["elasticity_kpa"]["status"] == "invalid"
                ):
                    assert pr[f"{name}_{q}"] is None
                    continue
                assert pr[f"{name}_{q}"] == fit[q]
                bounds = fit["ci95"].get(q) or [None, None]
                assert [pr[f"{name}_{q}_ci95_low"], pr[f"{name}_{q}_ci95_high"]] == bounds
                got = row[f"{name}_{q}_ci95_low"]
                assert (float(got) if got else None) == bounds[0]
    first = rows[recorded.first.name]
    assert (first["subject"], first["site"], first["operator"]) == ("P-001", "Lab A", "Dr. X")
    assert first["note"] == "left ankle, day 3\nafter 10 min rest"
    assert rows[recorded.second.name]["operator"] == ""
    # Units: in the column names, in each Parquet field and in the schema metadata.
    schema = parquet.schema
    assert schema.field("depth_mm").metadata[b"unit"] == b"mm"
    assert schema.field("elasticity_kpa").metadata[b"unit"] == b"kPa"
    units = json.loads(schema.metadata[b"units"])
    assert units["viscosity_n_s_per_mm2"] == "N*s/mm^2" and units["duration_s"] == "s"
    assert units["two_exponential_tau_s_ci95_low"] == "s"
    assert schema.field("power_law_viscosity_n_s_per_mm2_ci95_high").metadata[b"unit"] == (
        b"N*s/mm^2"
    )


def test_results_table_selects_and_has_a_default_place(recorded: Recorded) -> None:
    root = str(recorded.root)
    default = recorded.root.parent / "exports" / "results.csv"
    status, out = _main_out(["sessions", "table", "--root", root, "--subject", "P-002"])
    assert status == 0 and out.strip() == f"{default} (1 session)"
    assert [r["subject"] for r in _read_csv(default)] == ["P-002"]
    # An existing file is kept unless --overwrite.
    status, _ = _main_out(["sessions", "table", "--root", root])
    assert status == 2
    status, _ = _main_out(["sessions", "table", "--root", root, "--overwrite"])
    assert status == 0 and len(_read_csv(default)) == 2
    default.unlink()


def test_export_default_place_carries_the_metadata(recorded: Recorded) -> None:
    session = recorded.first.name
    args = ["sessions", "export", session, "--root", str(recorded.root)]
    status, out = _main_out(args)
    target = recorded.root.parent / "exports" / session
    assert status == 0 and out.splitlines()[0] == str(target / "force_samples.csv")
    row = _read_csv(target / "session.csv")
    assert [(r["session_id"], r["subject"], r["operator"]) for r in row] == [
        (session, "P-001", "Dr. X")
    ]
    manifest = json.loads((target / "manifest.json").read_text())
    assert manifest["metadata"]["site"] == "Lab A"
    # The other format beside it: the copies it shares with the CSV export are identical.
    status, _ = _main_out([*args, "--format", "parquet"])
    assert status == 0
    assert pq.read_table(target / "session.parquet").column("subject").to_pylist() == ["P-001"]
    shutil.rmtree(target)


def test_mat_export_reads_back(recorded: Recorded, tmp_path: Path) -> None:
    session = recorded.first
    status, out = _main_out(
        ["sessions", "export", str(session), "--format", "mat", "--out", str(tmp_path)]
    )
    assert status == 0 and out.strip() == str(tmp_path / f"{session.name}.mat")
    mat = scipy.io.loadmat(tmp_path / f"{session.name}.mat", simplify_cells=True)
    with SessionReader(session) as reader:
        force = reader.force_samples()
        frames = reader.frames()
        summary = reader.summary
        assert summary is not None
    np.testing.assert_array_equal(mat["force_samples"]["force_n"], force["force_n"])
    np.testing.assert_array_equal(mat["force_samples"]["t_host_s"], force["t_host_s"])
    np.testing.assert_array_equal(mat["force_samples"]["sample_index"], force["sample_index"])
    np.testing.assert_array_equal(mat["frames"]["s_k"], frames["s_k"])
    np.testing.assert_array_equal(mat["frames"]["t_capture_host_s"], frames["t_capture_host_s"])
    # An empty text is MATLAB's '' (loadmat gives an empty array for it).
    flags = [f if isinstance(f, str) else "" for f in mat["frames"]["flags"]]
    assert flags == list(frames["flags"])
    assert mat["units"]["frames"]["s_k"] == "px" and mat["units"]["force_samples"]["force_n"] == "N"
    assert mat["metadata"]["subject"] == "P-001"
    assert mat["metadata"]["note"] == "left ankle, day 3\nafter 10 min rest"
    depth = mat["results"]["depth_mm"]
    assert depth["status"] == summary["validity"]["depth_mm"]["status"]
    if depth["status"] != "invalid":
        assert depth["value"] == summary["results"]["pitting"]["depth_mm"]
    assert depth["unit"] == "mm"
    assert mat["results"]["verdict"]["status"] == summary["verdict"]["status"]
    assert json.loads(mat["summary_json"]) == summary
    assert mat["session_id"] == session.name and mat["format"] == "stipi-session-mat"


@pytest.mark.parametrize(
    "where",
    [
        "{root}/{other}",  # the other session's directory
        "{root}/{other}/sub",  # inside it
        "{root}/{session}",  # the exported session itself
        "{root}",  # the sessions directory
        "{root}/new",  # a new directory in it would be listed as a session
    ],
)
@pytest.mark.parametrize("fmt", ["csv", "mat"])
def test_export_never_writes_into_a_session(
    recorded: Recorded, capsys: pytest.CaptureFixture[str], where: str, fmt: str
) -> None:
    before = _files(recorded.root)
    out = where.format(root=recorded.root, other=recorded.second.name, session=recorded.first.name)
    args = ["sessions", "export", recorded.first.name, "--root", str(recorded.root)]
    for overwrite in ("--overwrite", "--force"):
        assert main([*args, "--format", fmt, "--out", out, overwrite]) == 2
        err = capsys.readouterr().err.splitlines()
        lines = [line for line in err if not line.startswith("stipi-daemon: note:")]
        assert len(lines) == 1 and lines[0].startswith(f"stipi-daemon: error: --out {out}: ")
    assert _files(recorded.root) == before  # nothing touched, nothing created


def test_results_table_never_writes_into_a_session(
    recorded: Recorded, capsys: pytest.CaptureFixture[str]
) -> None:
    before = _files(recorded.root)
    out = recorded.second / "results.csv"
    args = ["sessions", "table", "--root", str(recorded.root), "--out", str(out), "--overwrite"]
    assert main(args) == 2
    assert "inside the session directory" in capsys.readouterr().err
    assert _files(recorded.root) == before
