"""``analyze SESSION --recompute-sk`` on a video that stores only the ROI's gray box: the ROI
in camera-frame coordinates, refusals, a recount that does not reproduce the stored S_k,
pairing by ``frame_index``, and ``--out`` never inside a session.

One session is recorded (the short grade-I scene, 160x120 frames, lossless video of the
ROI's bounding box); each test works on a copy. Oracles: PyAV's own demuxing and decoding
and a numpy count (:func:`tests.commands.test_analyze_video.oracle_s_k`), SQLite for the
stored rows.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import av
import pytest

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.imaging import recorded_source
from stipi_daemon.app.offline_io import count_session_video, count_video
from stipi_daemon.cli import main
from stipi_daemon.errors import ConfigError
from stipi_daemon.storage.video_readback import probe_video
from tests.commands.test_analyze_video import (
    decoded_gray,
    digest,
    oracle_s_k,
    record,
    stored_rows,
)

#: The recorded camera frame [px] (tests.daemon._support.short_scene at 160x120).
FRAME = (160, 120)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("recount")
    return record(base, {}, {"video": "lossless", "video_roi_only": True})


def _copy(session: Path, root: Path, name: str = "") -> Path:
    target = root / "sessions" / (name or session.name)
    shutil.copytree(session, target)
    return target


def _crop(video: Path) -> tuple[int, int, int, int]:
    """The stored box, read from the file's tag with PyAV."""
    with av.open(str(video)) as container:
        x0, y0, x1, y1 = (int(v) for v in str(container.metadata["STIPI_CROP"]).split(","))
    return x0, y0, x1, y1


def _roi(session: Path) -> dict[str, Any]:
    roi: dict[str, Any] = json.loads((session / "manifest.json").read_text())["calibration"]["roi"]
    return roi


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip().removeprefix("stipi-daemon: error: ")


def _recount(
    capsys: pytest.CaptureFixture[str], session: Path, out: Path, *extra: str
) -> tuple[int, str, dict[str, Any]]:
    capsys.readouterr()
    rc = main(["analyze", str(session), "--recompute-sk", "--out", str(out), *extra])
    text = capsys.readouterr().out
    doc: dict[str, Any] = json.loads(out.read_text())
    return rc, text, doc


# --------------------------------------------------------------------------------------------
# --out
# --------------------------------------------------------------------------------------------


def test_out_inside_any_session_is_refused(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b = _copy(recorded, tmp_path, "a"), _copy(recorded, tmp_path, "b")
    assert (a / "frames" / "representative.json").is_file()
    before = {a: digest(a), b: digest(b)}
    targets = [
        (a / "frames" / "representative.json", True),  # a recorded file below the top level
        (b / "summary.json", True),  # another session's file
        (a / "session.sqlite", True),
        (a / "analysis-mine.json", False),  # a new file in the session
        (b / "report" / "new.json", False),
    ]
    for target, exists in targets:
        argv = ["analyze", str(a), "--out", str(target)] + (["--overwrite"] if exists else [])
        err = _error(capsys, argv)
        session = a if a in target.parents else b
        assert err.startswith(f"--out {target}: inside the session directory {session}"), err
        assert "never writes into a session" in err
    assert {a: digest(a), b: digest(b)} == before  # every file, frames/ and report/ too
    out = tmp_path / "outside.json"
    assert main(["analyze", str(a), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["input"]["session_dir"] == str(a)


# --------------------------------------------------------------------------------------------
# the ROI: camera-frame coordinates, within the frame and the stored box
# --------------------------------------------------------------------------------------------


def test_roi_off_the_frame_or_the_stored_box_is_refused(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    video = session / "video.mkv"
    x0, y0, x1, y1 = _crop(video)
    assert (x1 - x0, y1 - y0) != FRAME
    box = f"the box {x0},{y0},{x1},{y1} [px] of the {FRAME[0]}x{FRAME[1]} camera frame"
    before = digest(session)
    frame = f"the {FRAME[0]}x{FRAME[1]} frame"
    cases = {
        "circle:1000,1000,10": f"--roi: circle centre (1000, 1000) r 10 px lies outside {frame}",
        "circle:150,60,30": f"--roi: circle centre (150, 60) r 30 px lies partly outside {frame}",
        # inside the camera frame, not inside the stored box
        "circle:79.5,59.5,55": f"--roi: circle centre (79.5, 59.5) r 55 px lies partly outside "
        f"{box}, all the video {video} holds",
        "rect:0,0,20,8": f"--roi: rect at (0, 0) size 20x8 px lies outside {box}",
        "full": f"--roi full: the whole frame cannot be counted: the video {video} holds only "
        f"{box}",
    }
    for roi, expected in cases.items():
        err = _error(capsys, ["analyze", str(session), "--recompute-sk", "--roi", roi])
        assert err.startswith(expected), (roi, err)
    assert digest(session) == before  # nothing written
    # The camera frame's size is the video's own record (a tag beside the box; PyAV reads
    # it), so a session without a simulator's ground truth names the frame too.
    with av.open(str(video)) as container:
        assert container.metadata["STIPI_FRAME_SIZE"] == f"{FRAME[0]}x{FRAME[1]}"
    assert probe_video(video).frame_size == FRAME
    assert main(["sessions", "show", str(session)]) == 0
    assert f"crop {x0},{y0},{x1},{y1} of {FRAME[0]}x{FRAME[1]}, " in capsys.readouterr().out
    off = CircleROI(kind="circle", cx_px=1000.0, cy_px=1000.0, radius_px=10.0)
    with pytest.raises(ConfigError) as raised:  # no frame size given by the caller
        count_session_video(video, 128, off, roi_field="--roi")
    assert str(raised.value).startswith(cases["circle:1000,1000,10"])


def test_roi_is_given_in_camera_coordinates(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    video = session / "video.mkv"
    for roi in (
        CircleROI(kind="circle", cx_px=79.5, cy_px=59.5, radius_px=15.0),
        RectROI(kind="rect", x_px=40, y_px=20, width_px=30, height_px=80),
    ):
        got = count_session_video(video, 128, roi, roi_field="--roi").s_k_px.tolist()
        assert got == oracle_s_k(video, 128, roi.model_dump())
    seqs, s_k, index = stored_rows(session)
    recorded_roi = _roi(session)
    text = f"circle:{recorded_roi['cx_px']:g},{recorded_roi['cy_px']:g},"
    text += f"{recorded_roi['radius_px']:g}"
    rc, out, doc = _recount(capsys, session, tmp_path / "same.json", "--roi", text)
    n = len(seqs)
    assert rc == 0 and f"S_k recounted from the video: {n} of {n} stored frames, all equal" in out
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["settings"] == "recorded"
    # A smaller disc: differences expected, reported, not an error.
    oracle = oracle_s_k(video, 128, {"kind": "circle", "cx_px": 79.5, "cy_px": 59.5,
                                     "radius_px": 15.0})  # fmt: skip
    differ = sum(oracle[index[q]] != v for q, v in zip(seqs, s_k, strict=True))
    rc, out, doc = _recount(
        capsys, session, tmp_path / "small.json", "--roi", "circle:79.5,59.5,15"
    )
    check = doc["settings"]["imaging"]["s_k_vs_stored"]
    assert rc == 0 and check["problem"] is None and check["differing"] == differ > 0
    assert check["settings"] == "ROI circle:79.5,59.5,15 from --roi"
    assert doc["settings"]["imaging"]["video_crop"] == list(_crop(video))


def test_exported_crop_video_is_counted_in_camera_coordinates(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    exported = tmp_path / "export"
    assert (
        main(["sessions", "export", str(session), "--format", "csv", "--out", str(exported)]) == 0
    )
    video = exported / "video.mkv"
    roi = _roi(session)
    seqs, s_k, index = stored_rows(session)
    by_file = {i: v for q, v in zip(seqs, s_k, strict=True) for i in [index[q]]}
    got = count_video(video, 128, CircleROI(**roi), roi_field="--roi").s_k_px.tolist()
    assert got == [by_file[i] for i in range(len(got))] == oracle_s_k(video, 128, roi)
    cal = recorded_source(json.loads((session / "manifest.json").read_text())["calibration"], "m")
    assert cal.calibration is not None
    cal_path = save_calibration(tmp_path / "cal.json", cal.calibration.value)
    argv = ["analyze", "--video", str(video), "--force", str(exported / "force_samples.csv")]
    argv += ["--frame-times", str(exported / "frames.csv"), "--calibration", str(cal_path)]
    config = tmp_path / "recorded.yaml"  # the session's settings (its short measurement)
    config.write_text(json.dumps(json.loads((session / "manifest.json").read_text())["config"]))
    argv += ["--config", str(config)]
    out = tmp_path / "files.json"
    roi_text = f"circle:{roi['cx_px']:g},{roi['cy_px']:g},{roi['radius_px']:g}"
    assert main([*argv, "--roi", roi_text, "--out", str(out)]) == 0
    imaging = json.loads(out.read_text())["settings"]["imaging"]
    assert imaging["video_crop"] == list(_crop(video))
    assert imaging["s_k_range_px"] == [min(s_k), max(s_k)]
    x0, y0, x1, y1 = _crop(video)
    err = _error(capsys, [*argv, "--roi", "full"])
    assert err.startswith("--roi: the whole frame cannot be counted: the video ")
    assert f"holds only the box {x0},{y0},{x1},{y1} [px]" in err
    err = _error(capsys, [*argv, "--roi", "circle:79.5,59.5,55"])
    assert err.startswith("--roi: circle centre (79.5, 59.5) r 55 px lies partly outside the box")


# --------------------------------------------------------------------------------------------
# a recount that does not reproduce the stored S_k
# --------------------------------------------------------------------------------------------


def test_truncated_video_flags_the_results(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    video = session / "video.mkv"
    with video.open("r+b") as f:
        f.truncate(video.stat().st_size // 2)
    seqs, _, index = stored_rows(session)
    n, decoded = len(seqs), len(decoded_gray(video)[0])  # PyAV's own count
    in_video = sum(1 for q in seqs if index[q] < decoded)
    assert 0 < in_video < n
    rc, text, doc = _recount(capsys, session, tmp_path / "cut.json")
    assert rc == 3
    assert (
        f"S_k recounted from the video: {in_video} of {n} stored frames: 0 differ, "
        f"{n - in_video} not in the video, 0 undecodable: the results are flagged"
    ) in text
    problem = (
        f"S_k recount from the video: of the {n} stored frames, {n - in_video} not in the video"
    )
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["problem"] == problem
    summary = doc["summary"]
    assert summary["verdict"]["status"] != "complete" and problem in summary["verdict"]["line"]
    for q in ("depth_mm", "rebound_force_n", "recovery_time_s", "elasticity_kpa"):
        assert summary["validity"][q]["status"] != "valid"
        assert "s_k_not_reproduced" in summary["validity"][q]["flags"]
    assert summary["validity"]["applied_force_n"]["status"] == "valid"  # from force only
    assert doc["replay"]["frames_fed"] <= in_video
    # Other settings expect differences, but frames missing from the video still flag.
    rc, text, doc = _recount(capsys, session, tmp_path / "cut90.json", "--threshold", "90")
    assert rc == 3 and f"{n - in_video} not in the video" in text
    assert doc["summary"]["verdict"]["status"] != "complete"


def test_a_stored_s_k_the_video_does_not_reproduce_is_reported(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    seqs, _, _ = stored_rows(session)
    with sqlite3.connect(session / "session.sqlite") as conn:
        conn.execute("UPDATE frames SET s_k = s_k + 7 WHERE seq = ?", (seqs[len(seqs) // 2],))
    conn.close()
    rc, text, doc = _recount(capsys, session, tmp_path / "one.json")
    n = len(seqs)
    assert rc == 3
    assert (
        f"S_k recounted from the video: {n} of {n} stored frames: 1 differ (up to 7 px), "
        "0 not in the video, 0 undecodable: the results are flagged"
    ) in text
    check = doc["settings"]["imaging"]["s_k_vs_stored"]
    assert (check["differing"], check["max_abs_difference_px"]) == (1, 7.0)
    assert doc["summary"]["verdict"]["status"] != "complete"
    assert "1 differ from the stored S_k" in doc["summary"]["verdict"]["line"]


# --------------------------------------------------------------------------------------------
# pairing stored frames with the video's frames
# --------------------------------------------------------------------------------------------


def _rewrite_video_frames(session: Path, order: str) -> None:
    """The ``video_frames`` rows again, inserted in ``order`` (SQL ORDER BY)."""
    with sqlite3.connect(session / "session.sqlite") as conn:
        rows = conn.execute(
            f"SELECT seq, frame_index, pts_ms, t_capture_host_s FROM video_frames ORDER BY {order}"
        ).fetchall()
        conn.execute("DELETE FROM video_frames")
        conn.executemany(
            "INSERT INTO video_frames (seq, frame_index, pts_ms, t_capture_host_s) "
            "VALUES (?, ?, ?, ?)",
            rows,
        )
    conn.close()


def test_frames_are_paired_by_frame_index_not_row_order(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    _rewrite_video_frames(session, "frame_index DESC")
    n = len(stored_rows(session)[0])
    rc, text, doc = _recount(capsys, session, tmp_path / "rev.json")
    assert rc == 0 and f"{n} of {n} stored frames, all equal" in text
    assert doc["settings"]["imaging"]["s_k_vs_stored"]["differing"] == 0


def test_a_pairing_that_is_not_one_to_one_is_refused(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    with sqlite3.connect(session / "session.sqlite") as conn:
        conn.execute("UPDATE video_frames SET frame_index = 0 WHERE frame_index = 1")
    conn.close()
    err = _error(capsys, ["analyze", str(session), "--recompute-sk"])
    assert err.startswith(
        f"{session / 'session.sqlite'}: table video_frames: frame_index 0 occurs more than once"
    )
    assert not list(session.glob("analysis-*.json"))


def test_without_video_frames_rows_frames_pair_by_position_only_one_to_one(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = _copy(recorded, tmp_path)
    with sqlite3.connect(session / "session.sqlite") as conn:
        conn.execute("DELETE FROM video_frames")
    conn.close()
    n = len(stored_rows(session)[0])
    rc, text, doc = _recount(capsys, session, tmp_path / "pos.json")
    assert rc == 0 and f"{n} of {n} stored frames, all equal" in text  # the crop honoured
    assert (
        f"no video_frames rows: the {n} stored frames are paired with the video's {n} frames "
        "by position"
    ) in doc["notes"]
    video = session / "video.mkv"
    with video.open("r+b") as f:
        f.truncate(video.stat().st_size // 2)
    err = _error(capsys, ["analyze", str(session), "--recompute-sk"])
    assert err.startswith(f"{video}: --recompute-sk: the video holds ")
    assert f"the session {n} frame rows, and no video_frames rows tie them together" in err
