"""The bad-input campaign, kept in the suite: careless and hostile input to every command.

One table: each case makes its bad input in a copy of a tree of good data (config,
calibration, scene, study settings, a finished session, a sessions directory and a study
dataset indexed from it), runs the CLI entry point (:func:`stipi_daemon.cli.main`, as
``stipi-daemon`` does) and checks what must hold for every one of them: the exit status
(2, bad input), exactly one line on stderr naming the problem (the fragments given), no
traceback, and every file of the tree byte-identical afterwards (SHA-256), with no file
or directory created: a command refused writes nothing. Cases of closed or full standard
output and of SIGHUP need a real process and are in ``tests/daemon/test_cli_streams.py``.
"""

from __future__ import annotations

import hashlib
import json
import random
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.cli import main
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.study.index import index_sessions

from ..study._synthetic import write_session
from .conftest import REPO_ROOT, SCENES
from .test_bad_inputs import _good_config

LATIN1 = "caf\xe9".encode("latin-1")  # one Latin-1 character: not UTF-8


@dataclass(frozen=True)
class Case:
    """One bad input: how to make it, what the one line must say, the exit status."""

    id: str
    make: Callable[[Path], list[str]]
    """Writes the bad input under the work dir (before the snapshot); returns argv."""
    expect: tuple[str, ...]
    """Fragments the one error line must contain."""
    code: int = 2


def _with(name: str, data: bytes, argv: Callable[[Path], list[str]]) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        (w / name).write_bytes(data)
        return argv(w)

    return make


def _yaml_bytes(doc: object, extra: bytes = b"") -> bytes:
    return yaml.safe_dump(doc).encode() + extra


def _latin1_config(w: Path) -> bytes:
    return _yaml_bytes(_good_config(w), b"session: {note: " + LATIN1 + b"}\n")


def _latin1_scene(w: Path) -> bytes:
    return (w / "scene.yaml").read_bytes() + b"description: " + LATIN1 + b"\n"


def _session(w: Path) -> Path:
    return next((w / "sessions").iterdir())


def _query(sql: Callable[[Path], str], *more: str) -> Callable[[Path], list[str]]:
    """``study query`` of ``sql``; ``more`` may name {w}, {dataset_file} and {session}."""

    def make(w: Path) -> list[str]:
        names = {"w": w, "dataset_file": _dataset_file(w), "session": _session(w)}
        return ["study", "query", str(w / "ds"), sql(w), *(m.format(**names) for m in more)]

    return make


def _calibrate(*more: str) -> list[str]:
    """``calibrate`` of the example pairs (configs/calibration) and ``more`` options."""
    examples = REPO_ROOT / "configs" / "calibration"
    depth, force = examples / "example_depth_pairs.csv", examples / "example_force_pairs.csv"
    return ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(force), *more]


def _dataset_file(w: Path) -> Path:
    return next((w / "ds" / "results").rglob("*.parquet"))


def _make_latin1(
    name: str, content: Callable[[Path], bytes], argv: Callable[[Path], list[str]]
) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        (w / name).write_bytes(content(w))
        return argv(w)

    return make


CASES = [
    # ---- every text input is UTF-8; one line naming file and byte offset when it is not
    Case(
        "utf8-config",
        _make_latin1("bad.yaml", _latin1_config, lambda w: ["--config", str(w / "bad.yaml")]),
        ("bad.yaml", "not UTF-8", "byte offset"),
    ),
    Case(
        "utf8-scene-simulate",
        _make_latin1(
            "bad-scene.yaml",
            _latin1_scene,
            lambda w: ["simulate", str(w / "bad-scene.yaml"), "--out", str(w / "simout")],
        ),
        ("bad-scene.yaml", "not UTF-8", "byte offset"),
    ),
    Case(
        "utf8-scene-option",
        _make_latin1(
            "bad-scene.yaml",
            _latin1_scene,
            lambda w: ["--config", str(w / "config.yaml"), "--scene", str(w / "bad-scene.yaml")],
        ),
        ("bad-scene.yaml", "not UTF-8", "byte offset"),
    ),
    Case(
        "utf8-calibration",
        _make_latin1(
            "bad.yaml",
            lambda w: _yaml_bytes(_good_config(w) | {"calibration": str(w / "badcal.json")}),
            lambda w: (
                (w / "badcal.json").write_bytes(b'{"format": "' + LATIN1 + b'"}'),
                ["--config", str(w / "bad.yaml")],
            )[1],
        ),
        ("badcal.json", "not UTF-8", "byte offset 15"),
    ),
    Case(
        "utf8-study-settings",
        _with(
            "settings.yaml",
            b"format: stipi-study-settings\nversion: 1\n# " + LATIN1 + b"\n",
            lambda w: ["study", "reanalyze", str(w / "ds"), "--settings", str(w / "settings.yaml")],
        ),
        ("settings.yaml", "not UTF-8", "byte offset 45"),
    ),
    Case(
        "utf8-depth-pairs",
        _with(
            "depth.csv",
            b"s0_px,depth_change_mm\n" + LATIN1 + b",1\n",
            lambda w: [
                "calibrate",
                "--depth-pairs",
                str(w / "depth.csv"),
                "--force-pairs",
                str(w / "depth.csv"),
                "--out",
                str(w / "newcal.json"),
            ],
        ),
        ("depth.csv", "not UTF-8", "byte offset 25"),
    ),
    Case(
        "scene-option-given-a-config",
        lambda w: ["--config", str(w / "config.yaml"), "--scene", str(w / "config.yaml")],
        ("config.yaml", "is a daemon config", "not a scene"),
    ),
    Case(
        "simulate-given-a-config",
        lambda w: ["simulate", str(w / "config.yaml"), "--out", str(w / "simout")],
        ("config.yaml", "is a daemon config", "not a scene"),
    ),
    # ---- a study query changes nothing and reads only the dataset
    Case(
        "query-explain-analyze-copy-study-json",
        _query(lambda w: f"EXPLAIN ANALYZE COPY (SELECT 1) TO '{w}/ds/study.json' (FORMAT csv)"),
        ("SQL: EXPLAIN", "not of COPY"),
    ),
    Case(
        "query-explain-analyze-copy-over-a-dataset-file",
        _query(lambda w: f"EXPLAIN ANALYZE COPY sessions TO '{_dataset_file(w)}' (FORMAT parquet)"),
        ("SQL: EXPLAIN", "not of COPY"),
    ),
    Case(
        "query-copy-user-file",
        _query(lambda w: f"COPY sessions TO '{w}/config.yaml' (FORMAT csv)"),
        ("SQL: only queries", "not COPY"),
    ),
    Case("query-attach", _query(lambda w: f"ATTACH '{w}/x.duckdb'"), ("SQL: only queries",)),
    Case(
        "query-read-csv-passwd",
        _query(lambda w: "SELECT * FROM read_csv('/etc/passwd')"),
        ("SQL: Permission Error", "/etc/passwd", "dataset's own files"),
    ),
    # ---- no command writes into a session, a dataset, or over a file without --overwrite
    Case(
        "query-out-over-a-dataset-file",
        _query(lambda w: "SELECT 1 AS a", "--overwrite", "--out", "{dataset_file}"),
        ("--out", "inside the dataset"),
    ),
    Case(
        "query-out-into-the-dataset",
        _query(lambda w: "SELECT 1 AS a", "--out", "{w}/ds/mine.csv"),
        ("--out", "inside the dataset"),
    ),
    Case(
        "query-out-over-a-file",
        _query(lambda w: "SELECT 1 AS a", "--out", "{w}/old.csv"),
        ("--out", "old.csv", "exists already", "--overwrite"),
    ),
    Case(
        "query-out-into-a-session",
        _query(lambda w: "SELECT 1 AS a", "--out", "{session}/result.csv"),
        ("--out", "inside the session directory"),
    ),
    Case(
        "diff-out-over-a-file",
        lambda w: ["study", "diff", str(w / "ds"), "recorded", "recorded", "--out", "old.csv"],
        ("--out", "old.csv", "exists already"),
    ),
    Case(
        "export-out-empty",
        lambda w: ["sessions", "export", str(_session(w)), "--out", ""],
        ("--out ''", "empty"),
    ),
    Case(
        "export-out-into-a-session",
        lambda w: ["sessions", "export", str(_session(w)), "--out", str(_session(w) / "x")],
        ("--out", "inside the session directory"),
    ),
    Case(
        "export-out-over-a-file",
        lambda w: ["sessions", "export", str(_session(w)), "--out", str(w / "export")],
        ("frames.csv", "exists already", "--overwrite"),
    ),
    Case(
        "table-out-empty",
        lambda w: ["sessions", "table", "--root", str(w / "sessions"), "--out", ""],
        ("--out ''", "empty"),
    ),
    Case(
        "simulate-out-empty",
        lambda w: ["simulate", str(w / "scene.yaml"), "--out", ""],
        ("--out ''", "empty"),
    ),
    Case(
        "simulate-out-into-a-session",
        lambda w: ["simulate", str(w / "scene.yaml"), "--out", str(_session(w) / "sim")],
        ("--out", "inside the session directory"),
    ),
    Case(
        "index-out-empty",
        lambda w: ["study", "index", str(w / "sessions"), "--out", ""],
        ("--out ''", "empty"),
    ),
    Case(
        "calibrate-out-over-a-session-summary",
        lambda w: [*_calibrate(), "--out", str(_session(w) / "summary.json"), "--overwrite"],
        ("--out", "summary.json", "inside the session directory"),
    ),
    Case(
        "calibrate-out-into-a-session",
        lambda w: [*_calibrate(), "--out", str(_session(w) / "cal.json")],
        ("--out", "inside the session directory"),
    ),
    Case(
        "calibrate-roi-outside-its-frame",
        lambda w: [
            *_calibrate(),
            "--out",
            str(w / "new.json"),
            "--frame-size",
            "640x480",
            "--roi",
            "circle:900,100,50",
        ],
        ("--roi", "outside the 640x480 frame"),
    ),
    Case(
        "calibrate-roi-partly-outside-its-frame",
        lambda w: [
            *_calibrate(),
            "--out",
            str(w / "new.json"),
            "--frame-size",
            "640x480",
            "--roi",
            "rect:600,400,100,100",
        ],
        ("--roi", "partly outside the 640x480 frame"),
    ),
    Case(
        "calibrate-out-empty",
        lambda w: _calibrate("--out", "", "--overwrite"),
        ("--out ''", "empty"),
    ),
    Case(
        "calibrate-out-a-directory",
        lambda w: _calibrate("--out", str(w / "export"), "--overwrite"),
        ("--out", "is a directory"),
    ),
    Case(
        "analyze-out-empty",
        lambda w: ["analyze", str(_session(w)), "--out", ""],
        ("--out", "is a directory"),
    ),
    Case(
        "diff-with-a-damaged-dataset-file",
        lambda w: (
            _dataset_file(w).write_bytes(b"a,b\n1,2\n"),
            ["study", "diff", str(w / "ds"), "recorded", "recorded"],
        )[1],
        ("a dataset file is unreadable", "study index"),
    ),
    Case(
        "query-with-a-truncated-dataset-file",
        lambda w: (
            _dataset_file(w).write_bytes(_dataset_file(w).read_bytes()[:64]),
            ["study", "query", str(w / "ds"), "SELECT count(*) FROM results"],
        )[1],
        ("a dataset file is unreadable", "study index"),
    ),
    Case(
        "query-read-text-user-file",
        _query(lambda w: f"SELECT * FROM read_text('{w}/config.yaml')"),
        ("SQL: Permission Error", "config.yaml"),
    ),
]


def _snapshot(root: Path) -> dict[str, str]:
    files = {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }
    dirs = {str(p.relative_to(root)) + "/": "" for p in root.rglob("*") if p.is_dir()}
    return files | dirs


@pytest.fixture(scope="module")
def good_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    w = tmp_path_factory.mktemp("campaign")
    shutil.copy(SCENES / "grade1.yaml", w / "scene.yaml")
    cal, _ = scaled_calibration(load_scene(w / "scene.yaml"))
    save_calibration(w / "cal.json", cal)
    (w / "config.yaml").write_text(yaml.safe_dump(_good_config(w)))
    rng = random.Random(40)
    for i in range(2):
        write_session(w / "sessions", i, rng)
    index_sessions([w / "sessions"], w / "ds")
    (w / "old.csv").write_text("a\n1\n")
    (w / "export").mkdir()
    (w / "export" / "frames.csv").write_text("mine\n")
    return w


def test_cases_are_unique() -> None:
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(
    case: Case,
    good_tree: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    w = tmp_path / "w"
    shutil.copytree(good_tree, w)
    monkeypatch.chdir(w)  # a relative or empty output would land in the tree and be seen
    (w / "config.yaml").write_text(yaml.safe_dump(_good_config(w)))
    state = json.loads((w / "ds" / "study.json").read_text())
    argv = case.make(w)
    before = _snapshot(w)
    code = main(argv)
    captured = capsys.readouterr()
    assert code == case.code, captured.err
    assert "Traceback" not in captured.err + captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("stipi-daemon: error: ")
    for part in case.expect:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    assert _snapshot(w) == before
    assert json.loads((w / "ds" / "study.json").read_text()) == state
