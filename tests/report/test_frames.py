"""Representative frames: the choice while recording (pure) and their storage."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.analysis.imaging import CircleROI, occluded_pixel_count
from stipi_daemon.errors import SessionError
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase
from stipi_daemon.report.frames import (
    FRAMES_DIR,
    FRAMES_INDEX,
    RepresentativeFrame,
    read_representative_frames,
    write_representative_frames,
)
from stipi_daemon.report.panels import roi_from_mapping
from stipi_daemon.storage import SessionReader


def _img(v: int) -> np.ndarray:
    return np.full((4, 5, 3), v, dtype=np.uint8)


def test_choice_follows_phases_and_s_k() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=10.0)
    # Before the hold: nothing is kept, even a tiny S_k (no contact yet).
    keeper.offer(0, 1.0, _img(0), 0, Phase.ARMED, None, None)
    assert keeper.selected() == ()
    # Hold from t = 2 s: the frame nearest t = 7 s is the pitting frame.
    for i, t in enumerate(np.arange(2.0, 12.0, 0.5)):
        keeper.offer(10 + i, float(t), _img(i), 900, Phase.PITTING, 2.0, None)
    # Lift: S_k drops to S_0 = 200 (offered while the machine still says release), then rises.
    keeper.offer(50, 12.2, _img(50), 200, Phase.RELEASE, 2.0, None)
    for i, (t, s) in enumerate([(12.4, 250), (13.0, 400), (14.0, 600), (15.0, 590)]):
        keeper.offer(60 + i, t, _img(60 + i), s, Phase.RECOVERY, 2.0, 12.1)
    # Frames after the end (no longer recording a recovery) are ignored.
    keeper.offer(99, 20.0, _img(99), 5000, Phase.DONE, 2.0, 12.1)
    chosen = {f.kind: f for f in keeper.selected()}
    assert list(chosen) == ["pitting", "recovery_start", "recovered"]
    assert chosen["pitting"].t_s == 7.0 and chosen["pitting"].seq == 20
    assert (chosen["recovery_start"].seq, chosen["recovery_start"].s_k_px) == (50, 200)
    assert (chosen["recovered"].seq, chosen["recovered"].s_k_px) == (62, 600)
    assert chosen["recovered"].image is not None and int(chosen["recovered"].image[0, 0, 0]) == 62


def test_recovery_frames_before_the_release_time_are_not_recovered() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=15.0)
    keeper.offer(1, 9.9, _img(1), 800, Phase.RECOVERY, 0.0, 10.0)
    assert [f.kind for f in keeper.selected()] == ["recovery_start"]


def test_pitting_duration_must_be_positive() -> None:
    with pytest.raises(ValueError, match="pitting_duration_s"):
        RepresentativeFrames(0.0)


def test_write_read_roundtrip_is_lossless(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    frames = (
        RepresentativeFrame("pitting", 3, 1.5, 17, rng.integers(0, 256, (6, 7, 3), np.uint8)),
        RepresentativeFrame("recovered", 9, 4.25, 2, rng.integers(0, 256, (6, 7), np.uint8)),
    )
    written = write_representative_frames(tmp_path, frames)
    assert [p.name for p in written] == [
        "representative_pitting.png",
        "representative_recovered.png",
        FRAMES_INDEX,
    ]
    back = read_representative_frames(tmp_path)
    assert [f.kind for f in back] == ["pitting", "recovered"]
    for a, b in zip(frames, back, strict=True):
        assert (a.seq, a.t_s, a.s_k_px) == (b.seq, b.t_s, b.s_k_px)
        np.testing.assert_array_equal(a.image, b.image)


def test_nothing_to_write_and_nothing_stored(tmp_path: Path) -> None:
    assert write_representative_frames(tmp_path, ()) == []
    assert read_representative_frames(tmp_path) == ()


def test_damaged_storage_is_named(tmp_path: Path) -> None:
    frames = (RepresentativeFrame("pitting", 3, 1.5, 17, _img(3)),)
    write_representative_frames(tmp_path, frames)
    png = tmp_path / FRAMES_DIR / "representative_pitting.png"
    png.unlink()
    with pytest.raises(SessionError, match=r"representative_pitting\.png: representative frame"):
        read_representative_frames(tmp_path)
    cv2.imwrite(str(png), np.zeros((2, 2), np.uint8))
    with pytest.raises(SessionError, match="index says"):
        read_representative_frames(tmp_path)
    (tmp_path / FRAMES_DIR / FRAMES_INDEX).write_text("{not json")
    with pytest.raises(SessionError, match="not readable JSON"):
        read_representative_frames(tmp_path)
    (tmp_path / FRAMES_DIR / FRAMES_INDEX).write_text(json.dumps({"pitting": {"file": "x"}}))
    with pytest.raises(SessionError, match="entry 'pitting' is malformed"):
        read_representative_frames(tmp_path)


def test_daemon_stores_frames_that_reproduce_the_recorded_s_k(demo_session: Path) -> None:
    """The stored PNGs are the camera's pixels: Eq. (1)-(2) on them gives the session's S_k."""
    frames = read_representative_frames(demo_session)
    assert [f.kind for f in frames] == ["pitting", "recovery_start", "recovered"]
    with SessionReader(demo_session) as reader:
        rows = reader.frames()
        cal = reader.manifest["calibration"]
        summary = reader.summary
        transitions = reader.transitions()
    assert summary is not None
    assert summary["run"]["representative_frames"][-1] == FRAMES_INDEX
    by_seq = dict(zip(rows["seq"].tolist(), rows["s_k"].tolist(), strict=True))
    roi = roi_from_mapping(cal["roi"], "calibration.roi")
    assert isinstance(roi, CircleROI)
    for f in frames:
        assert occluded_pixel_count(f.image, cal["threshold_p"], roi) == f.s_k_px
        assert by_seq[f.seq] == f.s_k_px
    chosen = {f.kind: f for f in frames}
    pit = summary["results"]["pitting"]
    hold = [t.t_host_s for t in transitions if t.new_state in ("pitting", "release")]
    t, s_k = rows["t_capture_host_s"], rows["s_k"]
    # Pitting frame inside the hold; the S_0 frame is the smallest S_k from the hold on,
    # within a few frames of T_0; the recovered frame the largest S_k stored after T_0.
    assert hold[0] <= chosen["pitting"].t_s <= hold[1]
    assert chosen["recovery_start"].s_k_px == s_k[t >= hold[0]].min()
    assert abs(chosen["recovery_start"].t_s - pit["t0_s"]) < 0.1
    assert chosen["recovered"].s_k_px == s_k[t >= pit["t0_s"]].max() >= pit["s_max_px"]


def test_frames_drawn_as_8_bit_rgba_look_as_through_the_gray_colour_map() -> None:
    """The frames figure draws gray and BGR frames as 8-bit RGBA (matplotlib then resamples
    in float32, not float64): a BGR frame's pixels are those of its RGB drawing, a gray
    frame's within one level of the gray colour map's (vmin 0, vmax 255: the float32
    rounding of the resampling; the recount is made on the frame, not on the picture)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from stipi_daemon.report.render import _rgba

    rng = np.random.default_rng(4)
    gray = rng.integers(0, 256, (61, 83), dtype=np.uint8)
    bgr = rng.integers(0, 256, (61, 83, 3), dtype=np.uint8)

    def drawn(image: np.ndarray, **kwargs: object) -> np.ndarray:
        fig = Figure(figsize=(3.1, 2.3), dpi=100)
        canvas = FigureCanvasAgg(fig)
        fig.add_axes((0, 0, 1, 1)).imshow(image, interpolation="nearest", **kwargs)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba()).astype(np.int16)

    mapped = drawn(gray, cmap="gray", vmin=0, vmax=255)
    assert np.abs(drawn(_rgba(gray)) - mapped).max() <= 1
    assert np.array_equal(drawn(_rgba(bgr)), drawn(bgr[:, :, ::-1]))
    assert _rgba(gray).dtype == np.uint8 and (_rgba(gray)[:, :, 3] == 255).all()
