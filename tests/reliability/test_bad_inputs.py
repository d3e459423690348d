"""Bad configuration and bad files, table-driven, through the command line.

Every case writes one malformed input next to a tree of good data (a valid config,
calibration and scene, and a finished session), runs the CLI entry point
(:func:`stipi_daemon.cli.main`, as ``stipi-daemon`` does; a few cases also as a real
subprocess), and checks: a non-zero exit, exactly one line on stderr, naming the file and
the field (or the problem) - and that every pre-existing file is byte-identical afterwards
and no session was created.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.cli import main
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.storage import SessionWriter, StorageOptions

from .conftest import PYTHON, REPO_ROOT, SCENES


@dataclass(frozen=True)
class Case:
    """One malformed input: how to make it, what to run, what the line must name."""

    id: str
    make: Callable[[Path], list[str]]
    """Writes the bad input under the work dir; returns the CLI arguments."""
    expect: tuple[str, ...]
    """Substrings the one error line must contain (file name, field)."""


def _good_config(w: Path) -> dict[str, Any]:
    return {
        "format": "stipi-daemon-config",
        "version": 1,
        "probe": {"transport": {"kind": "emulated", "scene": str(w / "scene.yaml")}},
        "camera": {"kind": "simulator", "scene": str(w / "scene.yaml")},
        "calibration": str(w / "cal.json"),
        "storage": {"root": str(w / "sessions"), "min_free_mb": 0},
    }


def _config(mutate: Callable[[dict[str, Any]], object]) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        doc = _good_config(w)
        mutate(doc)
        (w / "bad.yaml").write_text(yaml.safe_dump(doc))
        return ["--config", str(w / "bad.yaml")]

    return make


def _config_text(text: str) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        (w / "bad.yaml").write_text(text)
        return ["--config", str(w / "bad.yaml")]

    return make


def _calibration(mutate: Callable[[dict[str, Any]], object]) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        doc = json.loads((w / "cal.json").read_text())
        mutate(doc)
        (w / "badcal.json").write_text(json.dumps(doc))
        cfg = _good_config(w) | {"calibration": str(w / "badcal.json")}
        (w / "bad.yaml").write_text(yaml.safe_dump(cfg))
        return ["--config", str(w / "bad.yaml")]

    return make


def _calibration_text(text: str) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        (w / "badcal.json").write_text(text)
        cfg = _good_config(w) | {"calibration": str(w / "badcal.json")}
        (w / "bad.yaml").write_text(yaml.safe_dump(cfg))
        return ["--config", str(w / "bad.yaml")]

    return make


def _scene(mutate: Callable[[dict[str, Any]], object]) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        doc = yaml.safe_load((w / "scene.yaml").read_text())
        mutate(doc)
        (w / "badscene.yaml").write_text(yaml.safe_dump(doc))
        return ["simulate", str(w / "badscene.yaml"), "--out", str(w / "simout")]

    return make


def _session(
    damage: Callable[[Path], object], command: str = "show"
) -> Callable[[Path], list[str]]:
    def make(w: Path) -> list[str]:
        bad = w / "badsession"
        shutil.copytree(w / "sessions" / "good", bad)
        damage(bad)
        if command == "analyze":
            return ["analyze", str(bad), "--out", str(w / "out.json")]
        return ["sessions", "show", str(bad)]

    return make


def _set(path: str, value: object) -> Callable[[dict[str, Any]], None]:
    def mutate(doc: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        d = doc
        for p in parents:
            d = d.setdefault(p, {})
        d[last] = value

    return mutate


def _drop(path: str) -> Callable[[dict[str, Any]], None]:
    def mutate(doc: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        d = doc
        for p in parents:
            d = d[p]
        del d[last]

    return mutate


def _truncate(name: str, keep: float) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        f = d / name
        data = f.read_bytes()
        f.write_bytes(data[: int(len(data) * keep)])

    return damage


def _manifest(mutate: Callable[[dict[str, Any]], object]) -> Callable[[Path], None]:
    def damage(d: Path) -> None:
        doc = json.loads((d / "manifest.json").read_text())
        mutate(doc)
        (d / "manifest.json").write_text(json.dumps(doc))

    return damage


def _user_version(d: Path) -> None:
    con = sqlite3.connect(d / "session.sqlite")
    con.execute("PRAGMA user_version=7")
    con.commit()
    con.close()


CASES = [
    # ---- daemon configs
    Case("config-missing-probe", _config(_drop("probe")), ("bad.yaml", "probe", "required")),
    Case(
        "config-unknown-key",
        _config(_set("probe.colour", "red")),
        ("bad.yaml", "probe.colour", "unknown key"),
    ),
    Case("config-unknown-top-key", _config(_set("extra", 1)), ("bad.yaml", "extra", "unknown key")),
    Case("config-rate-type", _config(_set("probe.rate_hz", "fast")), ("bad.yaml", "probe.rate_hz")),
    Case("config-rate-range", _config(_set("probe.rate_hz", 5000)), ("bad.yaml", "probe.rate_hz")),
    Case(
        "config-led-negative", _config(_set("probe.led_level", -1)), ("bad.yaml", "probe.led_level")
    ),
    Case(
        "config-transport-kind",
        _config(_set("probe.transport.kind", "usb3")),
        ("bad.yaml", "probe.transport"),
    ),
    Case(
        "config-camera-missing-scene", _config(_drop("camera.scene")), ("bad.yaml", "camera.scene")
    ),
    Case("config-speed-negative", _config(_set("run.speed", -1)), ("bad.yaml", "run.speed")),
    Case(
        "config-commit-interval",
        _config(_set("storage.commit_interval_s", 1.0)),
        ("bad.yaml", "storage.commit_interval_s"),
    ),
    Case(
        "config-measurement-nan",
        _config(_set("measurement.target_force_n", float("nan"))),
        ("bad.yaml", "measurement.target_force_n"),
    ),
    Case(
        "config-measurement-inconsistent",
        _config(_set("measurement.release_force_n", 15.0)),
        ("bad.yaml", "measurement", "release_force_n"),
    ),
    Case(
        "config-threshold-range",
        _config(_set("imaging.threshold_p", 300)),
        ("bad.yaml", "imaging.threshold_p"),
    ),
    Case("config-wrong-version", _config(_set("version", 2)), ("bad.yaml", "version")),
    Case("config-wrong-format", _config(_set("format", "other")), ("bad.yaml", "format")),
    Case(
        "config-truncated-yaml",
        _config_text("probe:\n  transport: {kind: emulated, scene: [x\n"),
        ("bad.yaml", "not valid YAML", "line"),
    ),
    Case("config-not-a-mapping", _config_text("- 1\n- 2\n"), ("bad.yaml", "mapping")),
    Case("config-empty", _config_text(""), ("bad.yaml",)),
    Case(
        "config-missing-file",
        lambda w: ["--config", str(w / "nope.yaml")],
        ("nope.yaml", "cannot read"),
    ),
    # ---- calibration files (referenced by the config, loaded before any device)
    Case("cal-wrong-version", _calibration(_set("version", 9)), ("badcal.json", "version")),
    Case("cal-wrong-format", _calibration(_set("format", "other")), ("badcal.json", "format")),
    Case(
        "cal-missing-alpha1",
        _calibration(_drop("alpha1_mm_per_px2")),
        ("badcal.json", "alpha1_mm_per_px2"),
    ),
    Case("cal-wrong-type", _calibration(_set("c1_px", "many")), ("badcal.json", "c1_px")),
    Case("cal-unknown-key", _calibration(_set("colour", 1)), ("badcal.json", "colour")),
    Case(
        "cal-truncated",
        _calibration_text('{"format": "stipi-calibration", "vers'),
        ("badcal.json",),
    ),
    Case(
        "cal-threshold-range",
        _calibration(_set("threshold_p", 256)),
        ("badcal.json", "threshold_p"),
    ),
    # ---- scene files
    Case("scene-negative-fps", _scene(_set("camera.fps", -5)), ("badscene.yaml", "camera.fps")),
    Case(
        "scene-unknown-key",
        _scene(_set("tissue.colour", "red")),
        ("badscene.yaml", "tissue.colour"),
    ),
    Case("scene-missing-tissue", _scene(_drop("tissue")), ("badscene.yaml", "tissue")),
    Case(
        "scene-wrong-type",
        _scene(_set("force_profile.hold_s", "long")),
        ("badscene.yaml", "force_profile.hold_s"),
    ),
    Case(
        "scene-unknown-effect",
        _scene(_set("effects", [{"kind": "gremlins"}])),
        ("badscene.yaml", "effects"),
    ),
    # ---- session directories
    Case("session-db-truncated", _session(_truncate("session.sqlite", 0.3)), ("session.sqlite",)),
    Case(
        "session-db-empty", _session(_truncate("session.sqlite", 0.0)), ("session.sqlite", "empty")
    ),
    Case(
        "session-db-missing",
        _session(lambda d: (d / "session.sqlite").unlink()),
        ("session.sqlite", "missing"),
    ),
    Case(
        "session-manifest-missing",
        _session(lambda d: (d / "manifest.json").unlink()),
        ("manifest.json",),
    ),
    Case(
        "session-manifest-truncated", _session(_truncate("manifest.json", 0.5)), ("manifest.json",)
    ),
    Case(
        "session-manifest-version",
        _session(_manifest(_set("format_version", 3))),
        ("manifest.json", "format_version"),
    ),
    Case("session-schema-version", _session(_user_version), ("session.sqlite", "schema version 7")),
    Case(
        "session-summary-truncated",
        _session(_truncate("summary.json", 0.5), "analyze"),
        ("summary.json",),
    ),
    Case(
        "session-analyze-no-manifest",
        _session(lambda d: (d / "manifest.json").unlink(), "analyze"),
        ("manifest.json",),
    ),
]


def _snapshot(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def good_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    w = tmp_path_factory.mktemp("good")
    shutil.copy(SCENES / "grade1.yaml", w / "scene.yaml")
    cal, _ = scaled_calibration(load_scene(w / "scene.yaml"))
    save_calibration(w / "cal.json", cal)
    (w / "config.yaml").write_text(yaml.safe_dump(_good_config(w)))
    with SessionWriter.create(
        w / "sessions",
        _good_config(w),
        json.loads((w / "cal.json").read_text()),
        None,
        session_id="good",
        options=StorageOptions(min_free_bytes=0),
    ) as writer:
        writer.add_force_samples(
            [(i, 500, i * 10_000, i * 10_000, i * 0.01, 1.0) for i in range(50)]
        )
        writer.add_frames([(i, i / 60, i / 60, 100, "") for i in range(30)])
        writer.finish("complete", {"status": "complete"})
    return w


def test_at_least_30_cases() -> None:
    assert len(CASES) >= 30 and len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_gives_one_clear_line_and_touches_nothing(
    case: Case, good_tree: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    w = tmp_path / "w"
    shutil.copytree(good_tree, w)
    # The cases refer to the work dir's own good files.
    (w / "config.yaml").write_text(yaml.safe_dump(_good_config(w)))
    argv = case.make(w)
    before = _snapshot(w)
    code = main(argv)
    captured = capsys.readouterr()
    assert code != 0
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    line = lines[0]
    assert line.startswith("stipi-daemon: error: ")
    for part in case.expect:
        assert part in line, f"{part!r} not in {line!r}"
    assert _snapshot(w) == before  # no existing file changed, nothing written
    assert sorted(p.name for p in (w / "sessions").iterdir()) == ["good"]


@pytest.mark.parametrize("case_id", ["config-unknown-key", "session-db-truncated"])
def test_as_a_real_process(case_id: str, good_tree: Path, tmp_path: Path) -> None:
    case = next(c for c in CASES if c.id == case_id)
    w = tmp_path / "w"
    shutil.copytree(good_tree, w)
    argv = case.make(w)
    before = _snapshot(w)
    proc = subprocess.run(
        [PYTHON, "-m", "stipi_daemon", *argv], capture_output=True, text=True, cwd=REPO_ROOT
    )
    # a damaged session is exit 4, bad input 2 (stipi_daemon.errors)
    assert proc.returncode == (4 if case_id == "session-db-truncated" else 2)
    (line,) = proc.stderr.strip().splitlines()
    assert all(part in line for part in case.expect), line
    assert _snapshot(w) == before
