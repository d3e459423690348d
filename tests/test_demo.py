"""The README's first command: the demo config, end to end, through the real CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from stipi_daemon.storage.reader import SessionReader
from tests.conftest import REPO_ROOT


def _run_cli(config: Path, timeout_s: float = 60) -> subprocess.CompletedProcess[str]:
    """Run ``stipi-daemon --config CONFIG`` in a child interpreter."""
    return subprocess.run(
        [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


#: Wall time the whole demo may take here [s]: its CPU (20-45 s) on a loaded machine.
DEMO_WALL_LIMIT_S = 900


@pytest.mark.timeout(DEMO_WALL_LIMIT_S + 60)
def test_demo_config_runs_a_whole_measurement(tmp_path: Path) -> None:
    cfg = yaml.safe_load((REPO_ROOT / "configs" / "demo.yaml").read_text())
    scene = str(REPO_ROOT / "configs" / "scenes" / "demo_grade3.yaml")
    cfg["probe"]["transport"]["scene"] = scene
    cfg["camera"]["scene"] = scene
    cfg["storage"]["root"] = str(tmp_path / "sessions")
    # The demo's own config: unpaced (run.speed 0) on the clock that waits for the daemon,
    # so its rows are the same at any load (tests/daemon/test_speed_identity.py); beside the
    # suite's other worker and two busy loops it took 180-350 s of wall time.
    assert cfg["run"]["speed"] == 0
    path = tmp_path / "demo.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = _run_cli(path, timeout_s=DEMO_WALL_LIMIT_S)
    assert proc.returncode == 0, proc.stderr + proc.stdout[-2000:]
    out = proc.stdout
    for needle in (
        "D_p =",
        "F_r =",
        "T_r =",
        "E   =",
        "tau =",
        "severity (paper estimator): SEVERE",
    ):
        assert needle in out
    sessions = list((tmp_path / "sessions").iterdir())
    assert len(sessions) == 1
    with SessionReader(sessions[0]) as reader:
        assert reader.integrity_check().ok
        assert str(reader.status) == "complete"
        counts = reader.counts()
        assert counts["frames"] > 3000 and counts["force_samples"] > 5000
        assert counts["transitions"] >= 6
        assert counts["live_parameters"] > 10
        stored = reader.video_frames()["seq"].size
    summary = json.loads((sessions[0] / "summary.json").read_text())
    # the session holds its video, every frame: the simulated camera waits for the encoders
    video = summary["run"]["video"]
    assert video["codec"] == "ffv1" and video["frames"] == stored > 0
    assert video["left_out"] == 0 and stored == counts["frames"]
    _assert_documented(summary)
    res, gt = summary["results"], summary["ground_truth"]
    assert res["pitting"]["depth_mm"] == pytest.approx(gt["depth_mm"], rel=0.01)
    assert res["pitting"]["rebound_force_n"] == pytest.approx(gt["rebound_force_n"], rel=0.01)
    assert res["fitted_recovery"]["tau_s"] == pytest.approx(gt["time_constant_s"], rel=0.02)
    assert res["paper_estimator"]["elasticity_kpa"] == pytest.approx(gt["elasticity_kpa"], rel=0.01)


def _assert_documented(summary: dict[str, object]) -> None:
    """Every field of the summary and of its ``run`` (with its camera, probe and video) is
    named in docs/storage.md's ``summary.json`` section."""
    doc = (REPO_ROOT / "docs" / "storage.md").read_text()
    section = doc.split("### `summary.json`", 1)[1].split("\n## ", 1)[0]
    run = summary["run"]
    assert isinstance(run, dict)
    keys = set(summary) | set(run)
    for part in ("camera", "probe", "video"):
        keys |= set(run[part])
    missing = sorted(k for k in keys if f"`{k}`" not in section)
    assert not missing, f"summary.json fields not described in docs/storage.md: {missing}"


def test_bad_config_is_one_line_and_nonzero(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(
        "probe: {transport: {kind: emulated, scene: x.yaml}}\n"
        "camera: {kind: simulator, scene: x.yaml}\nmeasurment: {}\n"
    )
    proc = _run_cli(path)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1
    assert "field 'measurment': unknown key" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_missing_scene_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(
        "probe: {transport: {kind: emulated, scene: nope.yaml}}\n"
        f"camera: {{kind: simulator, scene: nope.yaml}}\nstorage: {{root: {tmp_path}}}\n"
    )
    proc = _run_cli(path)
    assert proc.returncode == 2
    assert "nope.yaml" in proc.stderr and "Traceback" not in proc.stderr
    assert not any(tmp_path.glob("*/session.sqlite"))
