"""The daemon and a calibration file that does not record its frame size or its ROI.

A calibration made at another frame size than the camera's, or in another ROI than the
config's, is refused before anything is recorded (``tests/daemon/test_cli_errors.py``).
One that records no size or no ROI (fitted from pairs without ``--frame-size`` or
``--roi``, or written before the fields existed) cannot be checked: the run goes on, and
says so on stderr and in the session, whose manifest records the size and the ROI its S_k
were counted at. One that records its ROI is counted in when the config gives none.
"""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from pathlib import Path

import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.analysis.imaging import (
    CircleROI,
    RectROI,
    describe_roi,
    roi_from_record,
    whole_frame_roi,
)
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from tests.daemon._support import short_config


def test_a_calibration_without_a_frame_size_is_used_with_a_warning_and_an_event(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = short_config(tmp_path, {}, speed=0.0)
    doc = yaml.safe_load(path.read_text())
    scene = doc["camera"]["scene"]
    cal, _ = scaled_calibration(load_scene(scene))
    assert cal.frame_size_px == (160, 120)
    cal_path = save_calibration(tmp_path / "cal.json", dataclasses.replace(cal, frame_size_px=None))
    doc["calibration"] = str(cal_path)
    path.write_text(yaml.safe_dump(doc))
    session = run_measurement(load_config(path), quiet=True).session_dir
    assert session is not None
    err = capfd.readouterr().err
    warning = (
        f"stipi-daemon: warning: the calibration {cal_path} does not record the frame size it "
        "was made at (field 'frame_size_px'): D_p and F_r are right only if that was 160x120 px"
    )
    assert warning in err, err
    manifest = json.loads((Path(session) / "manifest.json").read_text())
    assert manifest["calibration"]["frame_size_px"] == [160, 120]  # the camera's
    assert manifest["calibration"]["source"] == str(cal_path)
    with sqlite3.connect(Path(session) / "session.sqlite") as db:
        rows = db.execute(
            "SELECT detail_json FROM events WHERE kind = 'calibration_frame_size_unknown'"
        ).fetchall()
    assert len(rows) == 1
    assert json.loads(rows[0][0])["camera"] == [160, 120]
    # No ROI recorded either: the scene's disc is counted in, and the run says so.
    disc = manifest["calibration"]["roi"]
    assert disc is not None and disc["kind"] == "circle"
    assert (
        f"stipi-daemon: warning: the calibration {cal_path} does not record the ROI it was "
        f"made in (field 'roi'): D_p and F_r are right only if that was "
        f"{describe_roi(CircleROI(**disc))}, the one counted in"
    ) in err, err
    with sqlite3.connect(Path(session) / "session.sqlite") as db:
        rows = db.execute(
            "SELECT detail_json FROM events WHERE kind = 'calibration_roi_unknown'"
        ).fetchall()
    assert len(rows) == 1 and json.loads(rows[0][0])["roi"] == disc
    summary = json.loads((Path(session) / "summary.json").read_text())
    assert summary["verdict"]["status"] == "complete", summary["verdict"]


@pytest.mark.parametrize(
    "own",
    [
        CircleROI(kind="circle", cx_px=80.0, cy_px=60.0, radius_px=50.0),
        whole_frame_roi((160, 120)),  # calibrate --roi full --frame-size 160x120
    ],
    ids=["disc", "whole-frame"],
)
def test_a_calibrations_own_roi_is_counted_in_when_the_config_gives_none(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], own: CircleROI | RectROI
) -> None:
    """``imaging.roi`` left out: S_k are counted in the ROI the calibration was made in
    (not the scene's disc; the whole frame too), as the manifest records, with no warning
    about the ROI."""
    path = short_config(tmp_path, {}, speed=0.0)
    doc = yaml.safe_load(path.read_text())
    cal, _ = scaled_calibration(load_scene(doc["camera"]["scene"]))
    cal_path = save_calibration(tmp_path / "cal.json", dataclasses.replace(cal, roi=own))
    doc["calibration"] = str(cal_path)
    path.write_text(yaml.safe_dump(doc))
    session = run_measurement(load_config(path), quiet=True).session_dir
    assert session is not None
    assert "does not record the ROI" not in capfd.readouterr().err
    manifest = json.loads((Path(session) / "manifest.json").read_text())
    assert roi_from_record(manifest["calibration"]["roi"]) == own
