"""The report's representative frames come from the session's video (issue 16).

A daemon run with ``storage.video_roi_only`` stores only the ROI's gray bounding box in an
FFV1 ``video.mkv``. The frames figure must show that crop at its place in the camera frame,
read from the video (checked against PyAV's own decode of the frame the ``video_frames``
row names, read with SQLite), with the rest marked as not stored, the recount equal to the
recorded S_k, and a caption saying so; a frame the video cannot give falls back to the PNG
(checked against OpenCV's reading of it) with a note saying why.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.image import AxesImage

from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.panels import frame_panels
from stipi_daemon.report.render import draw_frames
from tests.daemon._support import short_session

KINDS = ("pitting", "recovery_start", "recovered")


@pytest.fixture(scope="module")
def cropped_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A daemon session whose video holds only the ROI's gray bounding box (FFV1)."""
    directory = tmp_path_factory.mktemp("cropped")
    return short_session(directory, {"video": "lossless", "video_roi_only": True}, speed=0.0)


def _figure(session: Path) -> tuple[Figure, dict[str, AxesImage]]:
    fig = draw_frames(frame_panels(load_report_input(session)))
    images = {str(im.get_gid()): im for ax in fig.axes for im in ax.get_images() if im.get_gid()}
    return fig, images


def _title(fig: Figure, gid: str) -> str:
    for ax in fig.axes:
        if any(im.get_gid() == gid for im in ax.get_images()):
            return " ".join(str(ax.get_title()).split())  # the lines wrapped, joined
    raise AssertionError(gid)


def _rows(session: Path) -> tuple[dict[int, int], dict[int, float]]:
    """seq -> video frame index, and seq -> recorded S_k [px], read with SQLite."""
    with sqlite3.connect(f"file:{session / 'session.sqlite'}?mode=ro", uri=True) as db:
        index = dict(db.execute("SELECT seq, frame_index FROM video_frames").fetchall())
        s_k = dict(db.execute("SELECT seq, s_k FROM frames").fetchall())
    return index, s_k


def _pyav_gray_frames(video: Path, wanted: set[int]) -> tuple[dict[int, np.ndarray], str]:
    """The frames at ``wanted`` indices as PyAV decodes them (gray), and the crop tag."""
    out: dict[int, np.ndarray] = {}
    with av.open(str(video)) as container:
        crop = str(container.metadata.get("STIPI_CROP", ""))
        for k, frame in enumerate(container.decode(video=0)):
            if k in wanted:
                out[k] = frame.to_ndarray(format="gray")
            if len(out) == len(wanted):
                break
    return out, crop


def test_cropped_video_frames_are_shown_from_the_video_in_camera_coordinates(
    cropped_session: Path,
) -> None:
    index, s_k = _rows(cropped_session)
    fig, images = _figure(cropped_session)
    panels = frame_panels(load_report_input(cropped_session))
    assert [p.kind for p in panels] == list(KINDS)
    wanted = {index[p.seq] for p in panels}
    decoded, crop = _pyav_gray_frames(cropped_session / "video.mkv", wanted)
    assert crop, "the daemon did not record a cropped video"
    x0, y0, x1, y1 = (int(v) for v in crop.split(","))
    for p in panels:
        shown = np.asarray(images[f"raw_{p.kind}"].get_array())
        h, w = shown.shape[:2]
        assert (x1 - x0, y1 - y0) < (w, h)  # a crop of the camera frame, drawn at full size
        gray = decoded[index[p.seq]]
        for channel in range(3):  # the stored pixels, at their place in the camera frame
            np.testing.assert_array_equal(shown[y0:y1, x0:x1, channel], gray)
        # Outside the crop: the two colours of the not-stored stripes, not camera data.
        outside = np.ones((h, w), bool)
        outside[y0:y1, x0:x1] = False
        colours = {tuple(c) for c in shown[outside][:, :3].tolist()}
        assert colours == {(205, 205, 220), (150, 150, 170)}
        binary = np.asarray(images[f"binary_{p.kind}"].get_array())
        assert {tuple(c) for c in binary[outside][:, :3].tolist()} == colours
        # The recount on the video's pixels is the recorded S_k.
        assert p.s_k_recount_px == p.s_k_live_px == s_k[p.seq]
        title = _title(fig, f"raw_{p.kind}")
        assert f"from video.mkv, its stored frame {index[p.seq]}" in title
    caption = fig.get_suptitle()  # type: ignore[attr-defined]
    assert f"only the ROI's bounding box (x {x0}-{x1}, y {y0}-{y1} px" in caption
    assert "not stored" in caption


def test_frames_the_video_cannot_give_come_from_the_png_and_say_why(
    cropped_session: Path, tmp_path: Path
) -> None:
    session = tmp_path / cropped_session.name
    shutil.copytree(cropped_session, session)
    index, _ = _rows(session)
    video = session / "video.mkv"
    # Cut the video before the recovered frame: that frame does not decode any more.
    panels = frame_panels(load_report_input(session))
    seq = {p.kind: p.seq for p in panels}
    assert index[seq["pitting"]] < index[seq["recovered"]] - 2
    with av.open(str(video)) as container:
        positions = [pk.pos for pk in container.demux(video=0) if pk.size]
    cut = positions[index[seq["recovered"]] - 1]
    with open(video, "r+b") as f:
        f.truncate(cut)
    fig, images = _figure(session)
    title = _title(fig, "raw_recovered")
    assert "from frames/representative_recovered.png: not from the video" in title
    assert f"video.mkv frame {index[seq['recovered']]}" in title
    png = cv2.imread(str(session / "frames" / "representative_recovered.png"))
    np.testing.assert_array_equal(images["raw_recovered"].get_array()[:, :, :3], png[:, :, ::-1])
    assert "from video.mkv" in _title(fig, "raw_pitting")  # still read from the video
    # No video at all: every frame from its PNG, and each says so.
    video.unlink()
    fig, images = _figure(session)
    for kind in KINDS:
        assert "not from the video, as video.mkv is missing" in _title(fig, f"raw_{kind}")
    assert "bounding box" not in fig.get_suptitle()  # type: ignore[attr-defined]
