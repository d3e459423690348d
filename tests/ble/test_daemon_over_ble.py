"""Issue 6: a whole simulated measurement over the BLE path equals the serial path's.

Both runs use the same scene and seed: once with the emulated Feather on a pty (read
through pyserial), once with the emulated probe as a BLE peripheral on a virtual radio,
reached through bleak's public API on the Bumble backend. The camera is the same
simulator in both, so the frames and S_k are identical. What depends only on S_k at T_0
(S_0, D_p) is identical. What also depends on the force samples' mapped times differs by
the links' timing: the release is detected from the force (BLE delivers in connection
events), which moves the end of the recovery window by a frame or two and so S_max and
F_r slightly, and F_a (the mean over the hold) and E by the clock-sync error. Those agree
within the simulator issue's 1 %.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from stipi_daemon.app.config import parse_config
from stipi_daemon.app.daemon import run_measurement
from tests.conftest import REPO_ROOT
from tests.daemon._support import kept_up

SCENE = REPO_ROOT / "configs" / "scenes" / "demo_grade3.yaml"


#: Clock speeds of the attempts at a run that keeps up with its clock (see :func:`_run`).
SPEEDS = (4.0, 2.0, 1.0)


def _run(tmp_path: Path, transport: dict[str, Any], name: str) -> dict[str, Any]:
    """One measurement that kept up with its clock (:func:`kept_up`). On a loaded machine the
    renderer can stall (its frames are then skipped, the release frame among them, and the
    results flagged: correct, but not the same frames as the other run), so a run that
    lost frames or fell behind is made again at a lower speed, at most ``len(SPEEDS)`` times.
    The video keeps the ROI's gray box, as the demo's does (configs/demo.yaml): whole
    640 x 480 BGR frames in FFV1 at speed 2, beside Bumble's radio in this process, fell
    behind in CI (docs/storage.md), and the video is not what this test compares."""
    lost: list[dict[str, Any]] = []
    for k, speed in enumerate(SPEEDS):
        cfg = parse_config(
            {
                "probe": {"transport": transport, "rate_hz": 100},
                "camera": {"kind": "simulator", "scene": str(SCENE)},
                "storage": {
                    "root": str(tmp_path / f"{name}-{k}"),
                    "min_free_mb": 0,
                    "video_roi_only": True,
                },
                "run": {"speed": speed},
            },
            "test",
        )
        outcome = run_measurement(cfg, quiet=True)
        if kept_up(outcome.summary):
            assert outcome.exit_code == 0, outcome.summary.get("end_reason")
            return outcome.summary
        run = outcome.summary["run"]
        lost.append({k: v for k, v in run["camera"].items() if k != "source"})
        lost[-1]["late_frames"] = run.get("late_frames", 0)
        lost[-1]["video_left_out"] = (run.get("video") or {}).get("left_out", 0)
        lost[-1]["end_reason"] = outcome.summary.get("end_reason")
    raise AssertionError(f"{name}: no run kept up (frames lost or fell behind): {lost}")


@pytest.mark.timeout(1800)  # wall time (BLE): runs made again, slower, on a loaded machine
def test_ble_measurement_equals_serial(tmp_path: Path) -> None:
    serial = _run(tmp_path, {"kind": "emulated", "scene": str(SCENE)}, "serial")
    ble = _run(
        tmp_path,
        {
            "kind": "ble",
            "name": "STIPI-01",
            "hci": "virtual:stipi-test",
            "emulate": {"scene": str(SCENE)},
        },
        "ble",
    )
    rs, rb = serial["results"], ble["results"]

    # From S_k at T_0 (same frames): identical. T_0 on each run's scene timeline (each run
    # has its own session-time origin).
    def t0_scene(summary: dict[str, Any]) -> float:
        return float(
            summary["results"]["pitting"]["t0_s"] - summary["run"]["camera"]["source"]["t0_s"]
        )

    assert t0_scene(ble) == pytest.approx(t0_scene(serial), abs=1e-6)
    for key in ("s0_px", "depth_mm", "depth_change_mm"):
        assert rb["pitting"][key] == pytest.approx(rs["pitting"][key], rel=1e-9), key
    # Depending on where the recovery window ends (release detected from the force).
    assert rb["pitting"]["rebound_force_n"] == pytest.approx(
        rs["pitting"]["rebound_force_n"], rel=0.01
    )
    assert rb["fitted_recovery"]["tau_s"] == pytest.approx(rs["fitted_recovery"]["tau_s"], rel=1e-3)
    assert (
        rb["severity"]["paper_estimator"]["severity"]
        == rs["severity"]["paper_estimator"]["severity"]
    )
    assert rb["severity"]["fitted_recovery"]["nearest_grade"] == "III"
    # From the force samples' mapped times: equal to the clock-sync error.
    assert rb["applied_force_n"] == pytest.approx(rs["applied_force_n"], rel=2e-3)
    assert rb["paper_estimator"]["elasticity_kpa"] == pytest.approx(
        rs["paper_estimator"]["elasticity_kpa"], rel=2e-3
    )
    # Every sample accounted for on both links (sent = received + lost; BLE may lose whole
    # frames when the module's transmit buffer is full, as the real one does).
    for run in (ble, serial):
        p = run["run"]["probe"]
        assert p["samples_sent"] == p["samples_received"] + p["samples_lost"]
    assert serial["run"]["probe"]["samples_lost"] == 0
    # And both match the scene's ground truth as the simulator issue requires.
    gt = ble["ground_truth"]
    assert rb["pitting"]["depth_mm"] == pytest.approx(gt["depth_mm"], rel=0.01)
    assert rb["fitted_recovery"]["tau_s"] == pytest.approx(gt["time_constant_s"], rel=0.02)
    assert rb["paper_estimator"]["elasticity_kpa"] == pytest.approx(gt["elasticity_kpa"], rel=0.01)
