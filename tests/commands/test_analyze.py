"""``stipi-daemon analyze``: sessions reproduce their summary, simulator files their truth."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.analysis.imaging import RectROI, whole_frame_roi
from stipi_daemon.app.offline_io import SessionData, read_session
from stipi_daemon.cli import main
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.storage import SessionWriter, StorageOptions
from stipi_daemon.storage.reader import SessionReader
from tests._offline import SCENES, interrupted_copy, record_session, short_scene
from tests.commands.test_analyze_video import assert_untouched, digest, oracle_s_k


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_session(tmp_path_factory.mktemp("analyze-session"))


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``stipi-daemon simulate`` output of grade I at 640x480, 60 fps, 14 s of recovery."""
    base = tmp_path_factory.mktemp("analyze-sim")
    out = base / "out"
    assert main(["simulate", str(short_scene(base)), "--out", str(out), "--quiet"]) == 0
    return out


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("stipi-daemon: error: ")
    return err.strip()


def test_session_replay_reproduces_the_recorded_summary(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = digest(session_dir)  # every file, frames/ and report/ too
    out = tmp_path / "a.json"
    assert main(["analyze", str(session_dir), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "recorded summary: identical results" in text
    assert "D_p =" in text and "ground truth (simulator)" in text
    doc = json.loads(out.read_text())
    assert doc["format"] == "stipi-offline-analysis" and doc["version"] == 1
    assert doc["comparison"]["stored_summary"] == {"identical": True, "differences": []}
    stored = json.loads((session_dir / "summary.json").read_text())
    assert doc["summary"]["results"] == stored["results"]
    assert doc["input"]["status"] == "complete"
    # Nothing recorded was changed.
    assert_untouched(session_dir, before)


def test_default_output_goes_next_to_the_session_never_over_it(
    session_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    summary = (session_dir / "summary.json").read_bytes()
    assert main(["analyze", str(session_dir), "--quiet"]) == 0
    written = Path(capsys.readouterr().out.strip())
    assert written.parent == session_dir and written.name.startswith("analysis-")
    assert json.loads(written.read_text())["summary"]["phase"] == "done"
    assert (session_dir / "summary.json").read_bytes() == summary
    summary_path = str(session_dir / "summary.json")
    err = _error(capsys, ["analyze", str(session_dir), "--out", summary_path, "--overwrite"])
    assert f"inside the session directory {session_dir}" in err
    written.unlink()


def test_session_by_id_under_root(session_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = session_dir.parent.parent / "by-id.json"
    argv = ["analyze", session_dir.name, "--root", str(session_dir.parent), "--out", str(out)]
    assert main(argv) == 0
    assert json.loads(out.read_text())["input"]["session_id"] == session_dir.name


def _check_truth(doc: dict[str, object]) -> None:
    rows = {r["name"]: r for r in doc["comparison"]["ground_truth"]}  # type: ignore[index]
    tolerances = {"depth_mm": 1.0, "rebound_force_n": 1.0, "time_constant_s": 2.0}
    tolerances["elasticity_kpa"] = 1.0
    for name, tol in tolerances.items():
        assert rows[name]["tolerance_percent"] == tol
        assert abs(rows[name]["error_percent"]) <= tol, rows[name]
        assert rows[name]["within_tolerance"] is True


def test_simulator_files_match_ground_truth(
    sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    assert truth["scene"] == "grade1_short"
    out = tmp_path / "sim.json"
    argv = ["analyze", "--video", str(sim_dir / "video.mkv"), "--force", str(sim_dir / "force.csv")]
    assert main([*argv, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(ok, tolerance 1 %)" in text and "OUTSIDE" not in text
    doc = json.loads(out.read_text())
    _check_truth(doc)
    assert doc["summary"]["status"] == "complete"
    assert doc["settings"]["imaging"]["threshold_p"] == 128
    assert doc["input"]["frame_times"] == str(sim_dir / "frames.csv")
    assert any("calibration: the scene's" in n for n in doc["notes"])


def test_simulator_files_with_explicit_calibration_and_options(
    sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = short_scene(tmp_path)
    cal, _ = scaled_calibration(load_scene(base))
    cal_path = save_calibration(tmp_path / "cal.json", cal)
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    roi = truth["roi"]
    out = tmp_path / "x.json"
    argv = [
        "analyze",
        "--video",
        str(sim_dir / "video.mkv"),
        "--force",
        str(sim_dir / "force.csv"),
        "--frame-times",
        str(sim_dir / "frames.csv"),
        "--calibration",
        str(cal_path),
        "--threshold",
        "128",
        "--roi",
        f"circle:{roi['cx_px']},{roi['cy_px']},{roi['radius_px']}",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    doc = json.loads(out.read_text())
    _check_truth(doc)
    assert doc["settings"]["calibration"]["source"] == str(cal_path)
    assert doc["settings"]["imaging"]["threshold_source"] == "--threshold"
    capsys.readouterr()


def test_interrupted_session_is_analysed_with_a_note(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stored = json.loads((session_dir / "summary.json").read_text())
    t0 = stored["measurement"]["t0_refined_s"]
    cut = interrupted_copy(session_dir, tmp_path / "sessions", "cut", t0 + 8.0)
    out = tmp_path / "cut.json"
    assert main(["analyze", str(cut), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "session cut (interrupted)" in text
    assert "note: session interrupted" in text
    doc = json.loads(out.read_text())
    assert doc["input"]["status"] == "interrupted"
    assert doc["summary"]["status"] == "partial" and doc["replay"]["partial_recovery"]
    assert doc["comparison"]["stored_summary"] is None  # no summary.json was written
    got = doc["summary"]["results"]["pitting"]
    assert got["depth_mm"] == stored["results"]["pitting"]["depth_mm"]
    assert got["recovery_time_s"] == stored["results"]["pitting"]["recovery_time_s"]

    with SessionReader(session_dir) as reader:
        first_frame_s = float(reader.frames()["t_capture_host_s"][0])
    # 5 s into the scene: during the pitting.
    early = interrupted_copy(session_dir, tmp_path / "sessions", "early", first_frame_s + 5.0)
    assert main(["analyze", str(early), "--out", str(tmp_path / "early.json")]) == 1
    text = capsys.readouterr().out
    assert "no results: no recovery recorded (recording ends in phase pitting)" in text


def test_complete_session_ended_early_by_an_older_rule_is_analysed_with_a_note(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Sessions recorded before docs/settling.md's rule stopped the recovery sooner than
    # the current one does; a longer hold than the recorder's reproduces that here.
    stored = json.loads((session_dir / "summary.json").read_text())
    cfg = tmp_path / "longer-hold.yaml"
    cfg.write_text(
        json.dumps(
            {
                "probe": {"transport": {"kind": "emulated", "scene": "x.yaml"}},
                "camera": {"kind": "simulator", "scene": "x.yaml"},
                "measurement": {"settle_hold_s": 20.0},
            }
        )
    )
    out = tmp_path / "older.json"
    assert main(["analyze", str(session_dir), "--config", str(cfg), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "note: the recorder ended the recovery before these settings would have" in text
    doc = json.loads(out.read_text())
    assert doc["input"]["status"] == "complete" and doc["replay"]["partial_recovery"]
    got = doc["summary"]["results"]["pitting"]
    assert got["depth_mm"] == stored["results"]["pitting"]["depth_mm"]
    assert got["recovery_time_s"] == stored["results"]["pitting"]["recovery_time_s"]


def _session_with_video(sim_dir: Path, root: Path) -> Path:
    """A session whose stored S_k were lost (all 0) but whose video was kept."""
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    with (sim_dir / "frames.csv").open() as f:
        frames = [(int(r["index"]), float(r["t_s"])) for r in csv.DictReader(f)]
    with (sim_dir / "force.csv").open() as f:
        force = [
            (int(r["index"]), int(r["adc_counts"]), int(r["t_mcu_us"]) % 2**32, int(r["t_mcu_us"]),
             float(r["t_true_s"]), float(r["force_n"]))
            for r in csv.DictReader(f)
        ]  # fmt: skip
    config = {"measurement": {}, "analysis": {}, "imaging": {"threshold_p": None, "roi": None}}
    calibration = {k: truth["calibration"][k] for k in ("alpha1_mm_per_px2", "alpha2_mm_per_px")}
    calibration |= {k: truth["calibration"][k] for k in ("c1_px", "c2_px_per_n", "threshold_p")}
    with SessionWriter.create(
        root,
        config,
        calibration,
        None,
        session_id="with-video",
        video=True,
        options=StorageOptions(min_free_bytes=0),
    ) as writer:
        writer.add_force_samples(force)
        writer.add_frames([(i, t, t, 0, "") for i, t in frames])
        writer.add_transition(0.0, "idle", "armed", "armed by the operator")
        (root / "with-video" / "video.mkv").write_bytes((sim_dir / "video.mkv").read_bytes())
        writer.finish("complete", {"ground_truth": truth})
    return root / "with-video"


def test_recompute_sk_from_the_session_video(
    sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    directory = _session_with_video(sim_dir, tmp_path / "sessions")
    data: SessionData = read_session(directory)
    assert data.video_path is not None and not data.s_k_px.any()
    assert main(["analyze", str(directory), "--out", str(tmp_path / "stored.json")]) == 0
    stored = json.loads((tmp_path / "stored.json").read_text())["summary"]["results"]
    assert "no_recovery" in stored["flags"]  # S_k all 0: nothing to see
    out = tmp_path / "re.json"
    argv = ["analyze", str(directory), "--recompute-sk", "--out", str(out)]
    capsys.readouterr()
    # The recount does not reproduce the stored (lost) S_k: reported, results flagged, exit 3.
    assert main(argv) == 3
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    oracle = oracle_s_k(sim_dir / "video.mkv", 128, {"kind": "circle", **truth["roi"]})
    n, differ = len(oracle), sum(1 for v in oracle if v != 0)
    assert n == data.s_k_px.size and differ > 0
    text = capsys.readouterr().out
    assert f"S_k recounted from the video: {n} of {n} stored frames: {differ} differ" in text
    doc = json.loads(out.read_text())
    assert doc["settings"]["imaging"]["threshold_p"] == 128
    assert doc["settings"]["imaging"]["threshold_source"] == "session manifest calibration"
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["differing"] == differ
    assert "ROI: the simulator's waveguide disc (ground truth)" in doc["notes"]
    # No video_frames rows: paired by position, as many frames in the video as rows.
    assert f"no video_frames rows: the {n} stored frames are paired with the video's {n} " in (
        " ".join(doc["notes"])
    )
    assert doc["summary"]["verdict"]["status"] != "complete"
    assert "s_k_not_reproduced" in doc["summary"]["validity"]["depth_mm"]["flags"]
    _check_truth(doc)


def test_refusals_are_one_line(
    session_dir: Path, sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    video, force = str(sim_dir / "video.mkv"), str(sim_dir / "force.csv")
    gt = str(sim_dir / "ground_truth.json")
    bad_force = tmp_path / "force.csv"
    bad_force.write_text("t_s,newtons\n0,1\n")
    err = _error(capsys, ["analyze", "--video", video, "--force", str(bad_force)])
    assert f"{bad_force}: line 1: missing column 'force_n' (header has: t_s, newtons)" in err
    bad_force.write_text("t_s,force_n\n0,1\n0.01,x\n")
    err = _error(capsys, ["analyze", "--video", video, "--force", str(bad_force)])
    assert "line 3: column 'force_n': 'x' is not a number" in err
    bad_video = tmp_path / "v.avi"
    bad_video.write_bytes(b"\x00garbage" * 500)
    err = _error(
        capsys,
        ["analyze", "--video", str(bad_video), "--force", force, "--ground-truth", gt],
    )
    assert str(bad_video) in err
    err = _error(capsys, ["analyze", "--video", str(tmp_path / "no.avi"), "--force", force])
    assert f"{tmp_path / 'no.avi'}: no such video file" in err
    assert "not both" in _error(capsys, ["analyze", str(session_dir), "--video", video])
    assert "nothing to analyse" in _error(capsys, ["analyze"])
    assert "--video needs --force" in _error(capsys, ["analyze", "--video", video])
    no_video = tmp_path / "sessions" / "no-video"  # a session recorded with storage.video off
    shutil.copytree(session_dir, no_video)
    (no_video / "video.mkv").unlink(missing_ok=True)
    err = _error(capsys, ["analyze", str(no_video), "--recompute-sk"])
    assert "the session has no video file" in err
    err = _error(capsys, ["analyze", "--video", video, "--force", force, "--roi", "oval:1"])
    assert "--roi 'oval:1': expected circle:CX,CY,R" in err
    # Issue 14 case 6: an ROI off the frame is refused before anything is counted.
    out = tmp_path / "never.json"
    argv = ["analyze", "--video", video, "--force", force, "--out", str(out)]
    err = _error(capsys, [*argv, "--roi", "circle:900,100,200"])
    assert "--roi: circle centre (900, 100) r 200 px lies outside the 640x480 frame" in err
    err = _error(capsys, [*argv, "--roi", "rect:620,10,40,20"])
    assert "--roi: rect at (620, 10) size 40x20 px lies partly outside the 640x480 frame" in err
    assert not out.exists()
    # A stored session's S_k was counted live: --roi without --recompute-sk is refused.
    err = _error(capsys, ["analyze", str(session_dir), "--roi", "circle:900,100,200"])
    assert "--roi applies where S_k is counted" in err
    err = _error(capsys, ["analyze", "nope", "--root", str(tmp_path)])
    assert "no such session" in err
    # No ground truth, no calibration: the user must give one.
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "video.mkv").write_bytes((sim_dir / "video.mkv").read_bytes())
    err = _error(capsys, ["analyze", "--video", str(lone / "video.mkv"), "--force", force])
    assert "no calibration: give --calibration CAL.json" in err


def test_a_calibration_made_at_another_frame_size_is_refused(
    session_dir: Path, sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session records the size its S_k were counted at (the manifest's calibration
    record); a video has its own. ``--calibration`` made at another size is refused in one
    line naming the calibration and both sizes, before anything is written."""
    manifest = json.loads((session_dir / "manifest.json").read_text())
    assert manifest["calibration"]["frame_size_px"] == [640, 480]
    cal, _ = scaled_calibration(load_scene(short_scene(tmp_path)))
    cal_path = save_calibration(
        tmp_path / "cal.json", dataclasses.replace(cal, frame_size_px=(1280, 720))
    )
    out = tmp_path / "never.json"
    err = _error(
        capsys,
        ["analyze", str(session_dir), "--calibration", str(cal_path), "--out", str(out)],
    )
    session_id = manifest["session_id"]
    assert (
        f"calibration ({cal_path}): session {session_id} has 640x480 px frames, but the "
        "calibration was made at 1280x720 px"
    ) in err
    assert err.endswith("give one made at 640x480 px")
    video = sim_dir / "video.mkv"
    argv = ["analyze", "--video", str(video), "--force", str(sim_dir / "force.csv")]
    err = _error(capsys, [*argv, "--calibration", str(cal_path), "--out", str(out)])
    assert f"calibration ({cal_path}): video {video} has 640x480 px frames" in err
    assert not out.exists()
    # Made at the session's size, or recording none: analysed.
    for size in ((640, 480), None):
        save_calibration(cal_path, dataclasses.replace(cal, frame_size_px=size))
        argv = ["analyze", str(session_dir), "--calibration", str(cal_path)]
        assert main([*argv, "--out", str(out), "--overwrite"]) == 0
        recorded = json.loads(out.read_text())["settings"]["calibration"]["frame_size_px"]
        assert recorded == (None if size is None else [640, 480])
    capsys.readouterr()


def _uncalibrated(doc: dict[str, Any], flag: str = "threshold_not_calibrated") -> list[str]:
    """The quantities an analysis flags ``flag``."""
    validity = doc["summary"]["validity"]
    return sorted(q for q, v in validity.items() if flag in v["flags"])


def _video_argv(sim_dir: Path) -> list[str]:
    """``analyze`` of the simulator's video and force CSV."""
    return ["analyze", "--video", str(sim_dir / "video.mkv"), "--force", str(sim_dir / "force.csv")]


#: Every quantity computed from S_k (F_a, from the force alone, is not among them).
_CALIBRATED = sorted(
    [
        "depth_mm",
        "elasticity_kpa",
        "rebound_force_n",
        "recovery_time_s",
        "severity",
        "tau_s",
        "viscosity_n_s_per_mm2",
        "viscosity_fit_n_s_per_mm2",
        "severity_fit",
    ]
)


def test_s_k_counted_with_another_threshold_than_the_calibrations_flags_what_it_calibrates(
    session_dir: Path, sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """S_k depends on p (Eq. 1) and Eqs. 4-5 were fitted on S counted with the
    calibration's p. Exploring another p (``--threshold``) or bringing a calibration made
    with another p is allowed offline, but D_p, F_r, T_r (its settling level is a fraction
    of S_max), tau and what follows from them (E, eta, the severity) are flagged, with the
    reason, and the verdict is not ``complete``; F_a (force only) is not."""
    video = _video_argv(sim_dir)
    out = tmp_path / "a.json"
    assert main([*video, "--out", str(out)]) == 0  # the scene's calibration and p
    assert _uncalibrated(json.loads(out.read_text())) == []
    assert main([*video, "--threshold", "110", "--out", str(out), "--overwrite"]) == 0
    doc = json.loads(out.read_text())
    assert _uncalibrated(doc) == _CALIBRATED
    reason = doc["summary"]["validity"]["depth_mm"]["reason"]
    assert "S_k counted with threshold p 110, the calibration (" in reason
    assert (
        "made with p 128: S_k are not the calibration's S, so D_p, F_r, T_r, tau and what "
        "follows from them do not hold"
    ) in reason
    assert doc["summary"]["verdict"]["status"] != "complete"
    assert any("threshold p 110" in n for n in doc["notes"])
    # A session's stored S_k (p 128) against a calibration made with p 100.
    cal, _ = scaled_calibration(load_scene(short_scene(tmp_path)))
    cal_path = save_calibration(tmp_path / "p100.json", dataclasses.replace(cal, threshold_p=100))
    argv = ["analyze", str(session_dir), "--calibration", str(cal_path)]
    assert main([*argv, "--out", str(out), "--overwrite"]) == 0
    doc = json.loads(out.read_text())
    assert _uncalibrated(doc) == _CALIBRATED
    assert (
        f"S_k counted with threshold p 128, the calibration ({cal_path}) made with p 100"
        in (doc["summary"]["validity"]["rebound_force_n"]["reason"])
    )
    capsys.readouterr()


def test_s_k_counted_in_another_roi_than_the_calibrations_flags_what_it_calibrates(
    session_dir: Path, sim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """S counts the occluded pixels within the ROI, and Eqs. 4-5 were fitted on S counted
    in the calibration's ROI (the scene's: its waveguide disc). Counting in another ROI
    (``--roi``: on a video, or again on a session's video) or bringing a calibration made
    in another ROI than the session counted in is allowed offline, but every quantity from
    S_k is flagged ``roi_not_calibrated`` with the reason."""
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    disc = truth["roi"]
    assert truth["calibration"]["roi"] == {"kind": "circle", **disc}
    same = f"circle:{disc['cx_px']:g},{disc['cy_px']:g},{disc['radius_px']:g}"
    smaller = f"circle:{disc['cx_px']:g},{disc['cy_px']:g},{disc['radius_px'] - 20:g}"
    video = _video_argv(sim_dir)
    out = tmp_path / "a.json"
    flag = "roi_not_calibrated"
    assert main([*video, "--roi", same, "--out", str(out)]) == 0
    assert _uncalibrated(json.loads(out.read_text()), flag) == []
    assert main([*video, "--roi", smaller, "--out", str(out), "--overwrite"]) == 0
    doc = json.loads(out.read_text())
    assert _uncalibrated(doc, flag) == _CALIBRATED
    reason = doc["summary"]["validity"]["depth_mm"]["reason"]
    assert f"S_k counted in circle centre ({disc['cx_px']:g}, {disc['cy_px']:g}) r " in reason
    assert "so D_p, F_r, T_r, tau and what follows from them do not hold" in reason
    assert doc["summary"]["verdict"]["status"] != "complete"
    assert _uncalibrated(doc) == []  # the threshold is the calibration's
    # A disc 20 px wider than the lit one adds its dark ring to every S_k: D_p and T_r (its
    # settling level is a fraction of S_max) move far from the scene's truth, and are flagged.
    wider = f"circle:{disc['cx_px']:g},{disc['cy_px']:g},{disc['radius_px'] + 20:g}"
    assert main([*video, "--roi", wider, "--out", str(out), "--overwrite"]) == 0
    doc = json.loads(out.read_text())
    pitting = doc["summary"]["results"]["pitting"]
    assert abs(pitting["depth_mm"] / truth["depth_mm"] - 1) > 0.5
    assert abs(pitting["recovery_time_s"] / truth["recovery_time_s"] - 1) > 0.1
    assert _uncalibrated(doc, flag) == _CALIBRATED
    # A session's stored S_k (the scene's disc) against a calibration made in a rectangle.
    manifest = json.loads((session_dir / "manifest.json").read_text())
    assert manifest["calibration"]["roi"]["kind"] == "circle"
    cal, _ = scaled_calibration(load_scene(short_scene(tmp_path)))
    rect = RectROI(kind="rect", x_px=0, y_px=0, width_px=64, height_px=48)
    cal_path = save_calibration(tmp_path / "rect.json", dataclasses.replace(cal, roi=rect))
    argv = ["analyze", str(session_dir), "--calibration", str(cal_path)]
    assert main([*argv, "--out", str(out), "--overwrite"]) == 0
    doc = json.loads(out.read_text())
    assert _uncalibrated(doc, flag) == _CALIBRATED
    assert (
        f"the calibration ({cal_path}) made in rect at (0, 0) size 64x48 px"
        in (doc["summary"]["validity"]["rebound_force_n"]["reason"])
    )
    assert doc["settings"]["calibration"]["roi"] == rect.model_dump(mode="json")
    # The session's own calibration (the manifest's) and its ROI: nothing flagged.
    assert main(["analyze", str(session_dir), "--out", str(out), "--overwrite"]) == 0
    assert _uncalibrated(json.loads(out.read_text()), flag) == []
    # A calibration made in the whole frame (calibrate --roi full --frame-size WxH): S
    # counted in the whole frame is its S, S counted in the disc is not.
    size = (truth["frame"]["width_px"], truth["frame"]["height_px"])
    full = dataclasses.replace(cal, frame_size_px=size, roi=whole_frame_roi(size))
    cal_path = save_calibration(tmp_path / "full.json", full)
    argv = [*video, "--calibration", str(cal_path), "--out", str(out), "--overwrite"]
    assert main([*argv, "--roi", "full"]) == 0
    assert _uncalibrated(json.loads(out.read_text()), flag) == []
    assert main([*argv, "--roi", same]) == 0
    assert _uncalibrated(json.loads(out.read_text()), flag) == _CALIBRATED
    capsys.readouterr()


def test_session_keeps_the_calibration_extrapolated_flag_the_live_run_set(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The manifest records the calibration's valid ranges, so the replay flags as live did."""
    scene_cal, _ = scaled_calibration(load_scene(SCENES / "grade1.yaml"))
    # Valid ranges the measurement falls outside of: the live run flags its results.
    narrow = dataclasses.replace(
        scene_cal, s0_valid_range_px=(0.0, 1.0), force_valid_range_n=(0.0, 1e-3)
    )
    cal_path = save_calibration(tmp_path / "narrow.json", narrow)
    session = record_session(tmp_path, calibration=cal_path)
    stored = json.loads((session / "summary.json").read_text())
    assert "calibration_extrapolated" in stored["results"]["pitting"]["flags"]
    manifest = json.loads((session / "manifest.json").read_text())
    assert manifest["calibration"]["s0_valid_range_px"] == [0.0, 1.0]
    assert manifest["calibration"]["force_valid_range_n"] == [0.0, 1e-3]
    out = tmp_path / "a.json"
    assert main(["analyze", str(session), "--out", str(out)]) == 0
    capsys.readouterr()
    doc = json.loads(out.read_text())
    assert "calibration_extrapolated" in doc["summary"]["results"]["pitting"]["flags"]
    assert doc["settings"]["calibration"]["s0_valid_range_px"] == [0.0, 1.0]
    assert doc["comparison"]["stored_summary"] == {"identical": True, "differences": []}


def _ended_early(
    source: Path, root: Path, until_s: float, status: str, why: str, link_down_s: float | None
) -> Path:
    """A copy of ``source``'s rows up to ``until_s``, finished as ``status`` without results,
    as the daemon leaves a session that ended early (optionally a ``link_down`` event)."""
    from stipi_daemon.storage import SessionWriter, StorageOptions

    with SessionReader(source) as reader:
        manifest = reader.manifest
        force, frames, transitions = reader.force_samples(), reader.frames(), reader.transitions()
    writer = SessionWriter.create(
        root,
        manifest["config"],
        manifest["calibration"],
        manifest["firmware"],
        session_id=status,
        options=StorageOptions(min_free_bytes=0),
    )
    writer.add_force_samples([r for r in force.tolist() if r[4] <= until_s])
    writer.add_frames(
        [
            (seq, tc, th, sk, [f for f in flags.split(",") if f])
            for seq, tc, th, sk, flags in frames.tolist()
            if tc <= until_s
        ]
    )
    for t in transitions:
        if t.t_host_s <= until_s:
            writer.add_transition(t.t_host_s, t.old_state, t.new_state, t.reason)
    if link_down_s is not None:
        writer.add_event(link_down_s, "camera_stalled", {"detail": "test"})
    writer.finish(status, {"status": status, "end_reason": why, "results": None})
    writer.close()
    return root / status


@pytest.mark.parametrize(
    ("status", "why", "link_down_after_s"),
    [
        ("aborted", "aborted by the operator in recovery", None),
        ("fault", "camera stalled in recovery", 6.0),
    ],
)
def test_a_session_that_ended_early_is_rescued_beside_it(
    session_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    status: str,
    why: str,
    link_down_after_s: float | None,
) -> None:
    """Issue 14 case 9: what the recording allows, computed; why it is incomplete, said."""
    stored = json.loads((session_dir / "summary.json").read_text())
    t0 = stored["measurement"]["t0_refined_s"]
    root = tmp_path / "sessions"
    # With a link_down that never recovers, the replay re-enacts the fault (the watchdog's
    # timeout): the recording before it is analysed.
    link_down_s = None if link_down_after_s is None else t0 + link_down_after_s
    cut = _ended_early(session_dir, root, t0 + 10.0, status, why, link_down_s)
    before = digest(cut)
    assert main(["analyze", str(cut)]) == 0
    text = capsys.readouterr().out
    written = sorted(cut.glob("analysis-*.json"))
    assert len(written) == 1  # beside the session, never over what was recorded
    assert_untouched(cut, before)
    doc = json.loads(written[0].read_text())
    summary = doc["summary"]
    assert summary["results"] is not None
    assert summary["verdict"]["status"] == "incomplete"
    assert summary["verdict"]["line"].startswith(f"Session {status} ({why}): ")
    assert f"verdict: INCOMPLETE: Session {status} ({why})" in text
    got = summary["results"]["pitting"]["depth_mm"]
    assert got == pytest.approx(stored["results"]["pitting"]["depth_mm"], rel=0.02)
    if link_down_after_s is not None:  # the replay faulted as the session did: cut before it
        assert "the replay ends as the session did" in text
        assert "results rescued from the recording before" in summary["verdict"]["line"]
