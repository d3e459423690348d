"""Reading offline inputs: CSV errors name file, line and column; videos; ROI syntax."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.offline_io import (
    count_video,
    match_frame_times,
    parse_roi,
    read_csv_table,
    read_force_csv,
    read_frame_times_csv,
    read_session,
)
from stipi_daemon.errors import DataFileError
from stipi_daemon.measurement.state_machine import (
    CameraRecovered,
    CameraStalled,
    LinkLost,
    LinkRestored,
)
from stipi_daemon.storage import SessionState, SessionWriter, StorageOptions


def _write(tmp_path: Path, text: str, name: str = "f.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_csv_comments_alternatives_extra_columns(tmp_path: Path) -> None:
    p = _write(tmp_path, "# a comment\n\nt_true_s,force_n,extra\n0,1.5,x\n0.01,,y\n# end\n")
    t, f, col = read_force_csv(p)
    assert col == "t_true_s"
    assert t.tolist() == [0.0, 0.01]
    assert f[0] == 1.5 and np.isnan(f[1])
    table = read_csv_table(p, ["force_n"], optional=["t_true_s", "nope"], nullable=["force_n"])
    assert set(table.columns) == {"force_n", "t_true_s"}
    assert table.lines.tolist() == [4, 5]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("t_s,f\n0,1\n", r"f.csv: line 1: missing column 'force_n' \(header has: t_s, f\)"),
        ("x,force_n\n0,1\n", r"line 1: missing column 't_s' or 't_true_s' or 't_host_s'"),
        ("t_s,force_n\n0,1\n0.1,abc\n", r"f.csv: line 3: column 'force_n': 'abc' is not a number"),
        ("t_s,force_n\n0,1\n0.1\n", r"line 3: 1 fields, column 'force_n' \(field 2\) missing"),
        ("t_s,force_n\n0,1\n0,2\n", r"line 3: column 't_s': time 0.0 does not increase"),
        ("t_s,force_n\n", r"no data rows after the header \(line 1\)"),
        ("", r"empty file"),
        ("t_s,force_n\n0,inf\n", r"line 2: column 'force_n': 'inf' is not finite"),
    ],
)
def test_force_csv_errors(tmp_path: Path, text: str, message: str) -> None:
    p = _write(tmp_path, text)
    with pytest.raises(DataFileError, match=message):
        read_force_csv(p)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DataFileError, match=r"nope\.csv: no such file"):
        read_frame_times_csv(tmp_path / "nope.csv")


def test_frame_times_prefers_capture_time(tmp_path: Path) -> None:
    p = _write(tmp_path, "seq,t_capture_host_s,t_host_s,s_k,flags\n0,1.0,1.1,5,\n1,2.0,2.1,6,x\n")
    t, col = read_frame_times_csv(p)
    assert col == "t_capture_host_s" and t.tolist() == [1.0, 2.0]


def test_parse_roi() -> None:
    assert parse_roi("circle:319.5, 239.5,209.68") == CircleROI(
        kind="circle", cx_px=319.5, cy_px=239.5, radius_px=209.68
    )
    assert parse_roi("rect:1,2,30,40") == RectROI(
        kind="rect", x_px=1, y_px=2, width_px=30, height_px=40
    )
    assert parse_roi("full") is None
    for bad in ("circle:1,2", "square:1,2,3", "rect:1,2,3,x", "circle:1,2,-3"):
        with pytest.raises(DataFileError, match="--roi"):
            parse_roi(bad)


def _video(path: Path, frames: list[np.ndarray], fps: float = 30.0) -> Path:
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h), True)
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()
    return path


def test_count_video_and_frame_times(tmp_path: Path) -> None:
    frames = []
    for k in range(4):
        img = np.full((48, 64, 3), 220, np.uint8)
        img[:, : 8 * (k + 1)] = 20  # dark columns: 48 * 8 (k + 1) occluded pixels
        frames.append(img)
    video = count_video(_video(tmp_path / "v.avi", frames), 128, None)
    assert video.s_k_px.tolist() == [48 * 8 * (k + 1) for k in range(4)]
    assert video.fps == pytest.approx(30.0) and video.frame_shape == (48, 64, 3)
    roi = RectROI(kind="rect", x_px=0, y_px=0, width_px=4, height_px=48)
    assert count_video(tmp_path / "v.avi", 128, roi).s_k_px.tolist() == [192.0] * 4

    t, _, notes = match_frame_times(video, None, "-")
    assert t.tolist() == pytest.approx([0, 1 / 30, 2 / 30, 3 / 30]) and "frame rate" in notes[0]
    t, _, notes = match_frame_times(video, np.arange(6.0), "times.csv")
    assert t.tolist() == [0, 1, 2, 3] and "the last 2 frame(s) are missing" in notes[0]
    with pytest.raises(
        DataFileError, match=r"times\.csv: 3 frame times but the video v\.avi has 4"
    ):
        match_frame_times(video, np.arange(3.0), "times.csv")


def test_unreadable_video(tmp_path: Path) -> None:
    with pytest.raises(DataFileError, match="no such video file"):
        count_video(tmp_path / "none.avi", 128, None)
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video at all" * 100)
    with pytest.raises(DataFileError, match=r"bad\.avi: (OpenCV cannot open|the video holds no)"):
        count_video(bad, 128, None)


def test_read_session_maps_watchdog_events_and_arm_time(tmp_path: Path) -> None:
    with SessionWriter.create(
        tmp_path, {}, {}, None, session_id="s", options=StorageOptions(min_free_bytes=0)
    ) as w:
        w.add_force_samples([(0, 1, 0, 0, 0.5, 1.0), (1, 1, 10, 10, 0.6, None)])
        w.add_frames([(0, 0.52, 0.53, 7, "")])
        w.add_transition(0.25, "idle", "armed", "armed by the operator")
        w.add_event(1.0, "link_down", {"reason": "timeout"})
        w.add_event(1.5, "prompt", {"text": "x"})
        w.add_event(2.0, "link_up", {})
        w.add_event(3.0, "camera_stalled", {"detail": ""})
        w.add_event(4.0, "camera_recovered", {"detail": ""})
    data = read_session(tmp_path / "s")
    assert data.status is SessionState.INTERRUPTED
    assert data.t_arm_s == 0.25
    assert data.frame_times_s.tolist() == [0.52]  # capture time, not processing time
    assert data.force_n[0] == 1.0 and np.isnan(data.force_n[1])
    assert data.link_events == (
        LinkLost(1.0),
        LinkRestored(2.0),
        CameraStalled(3.0),
        CameraRecovered(4.0),
    )
    assert data.video_path is None and data.summary is None
