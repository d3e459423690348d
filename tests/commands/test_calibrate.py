"""``stipi-daemon calibrate``: pairs or recordings -> fitted, reported, written calibration."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.calibration import (
    Calibration,
    calibration_from_fits,
    fit_depth_calibration,
    fit_force_calibration,
    load_calibration,
    save_calibration,
)
from stipi_daemon.analysis.imaging import CircleROI, RectROI, whole_frame_roi
from stipi_daemon.cli import main
from stipi_daemon.storage import SessionWriter, StorageOptions
from tests.test_calibrate_procedure import staircase

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "configs" / "calibration"
#: The simulator scenes' probe at 640x480 (configs/scenes/*.yaml).
SCENE = Calibration(1.42e-7, 2.556e-3, 1500.0, 2500.0, threshold_p=128)


def _pairs(tmp_path: Path, cal: Calibration, noise: float = 0.0) -> tuple[Path, Path]:
    rng = np.random.default_rng(3)
    d = np.linspace(2.0, 10.0, 9)
    s0 = np.array([cal.s0_for_depth_change(x) for x in d])
    f = np.linspace(2.0, 20.0, 10)
    s = cal.c1_px + cal.c2_px_per_n * f + rng.normal(0.0, noise, f.size)
    depth = tmp_path / "depth.csv"
    depth.write_text(
        "# comment\ns0_px,depth_change_mm,note\n"
        + "".join(f"{float(a)!r},{float(b)!r},x\n" for a, b in zip(s0, d, strict=True))
    )
    force = tmp_path / "force.csv"
    force.write_text(
        "s_px,force_n\n"
        + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(s, f, strict=True))
    )
    return depth, force


def _same(a: Calibration, b: Calibration) -> None:
    assert dataclasses.replace(a, created_utc=None) == dataclasses.replace(b, created_utc=None)


def test_round_trip_from_pairs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    depth, force = _pairs(tmp_path, SCENE, noise=30.0)
    out = tmp_path / "cal.json"
    argv = ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(force)]
    argv += ["--out", str(out), "--threshold", "128", "--probe-id", "STIPI-7"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "Eq. (4): 9 pairs" in text and "Eq. (5): 10 pairs" in text
    assert "alpha2 = " in text and "+-" in text and "R^2 = " in text and "residuals [px]" in text
    assert f"calibration written to {out}" in text
    got = load_calibration(out)
    table = np.array(
        [[float(x) for x in r.split(",")[:2]] for r in depth.read_text().splitlines()[2:]]
    )
    ftable = np.array(
        [[float(x) for x in r.split(",")] for r in force.read_text().splitlines()[1:]]
    )
    expected = calibration_from_fits(
        # Contiguous columns: numpy's pairwise sums differ in the last bit on strided views.
        fit_depth_calibration(table[:, 0].copy(), table[:, 1].copy()),
        fit_force_calibration(ftable[:, 0].copy(), ftable[:, 1].copy()),
        threshold_p=128,
        probe_id="STIPI-7",
    )
    _same(got, expected)
    # Noise-free depth points: Eq. (4) is recovered to rounding.
    assert got.alpha1_mm_per_px2 == pytest.approx(SCENE.alpha1_mm_per_px2, rel=1e-6)
    assert got.alpha2_mm_per_px == pytest.approx(SCENE.alpha2_mm_per_px, rel=1e-6)
    assert got.c2_px_per_n == pytest.approx(SCENE.c2_px_per_n, rel=0.01)
    # Refuses to overwrite unless asked.
    assert main(argv) == 2
    assert "exists already (give --overwrite" in capsys.readouterr().err
    assert main([*argv, "--overwrite"]) == 0


@settings(max_examples=25, deadline=None)
@given(
    a1=st.floats(0.0, 3e-7),
    a2=st.floats(1e-3, 5e-3),
    c1=st.floats(0.0, 5000.0),
    c2=st.floats(500.0, 5000.0),
)
def test_fit_save_load_round_trip(a1: float, a2: float, c1: float, c2: float) -> None:
    import tempfile

    cal = Calibration(a1, a2, c1, c2)
    d = np.linspace(0.5, min(10.0, 0.9 * cal.max_depth_change_mm), 8)
    s0 = np.array([cal.s0_for_depth_change(x) for x in d])
    f = np.linspace(1.0, 20.0, 6)
    fitted = calibration_from_fits(
        fit_depth_calibration(s0, d), fit_force_calibration(c1 + c2 * f, f), threshold_p=100
    )
    with tempfile.TemporaryDirectory() as tmp:
        _same(load_calibration(save_calibration(Path(tmp) / "c.json", fitted)), fitted)
    assert fitted.alpha2_mm_per_px == pytest.approx(a2, rel=1e-6)
    assert fitted.c2_px_per_n == pytest.approx(c2, rel=1e-6)


def test_example_files_agree_with_the_scene_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "example.json"
    argv = ["calibrate", "--depth-pairs", str(EXAMPLES / "example_depth_pairs.csv")]
    argv += ["--force-pairs", str(EXAMPLES / "example_force_pairs.csv"), "--threshold", "128"]
    assert main([*argv, "--out", str(out)]) == 0
    capsys.readouterr()
    cal = load_calibration(out)
    d, f = cal.depth_fit, cal.force_fit
    assert d is not None and f is not None
    assert abs(d.alpha1_mm_per_px2 - SCENE.alpha1_mm_per_px2) <= 3 * d.alpha1_se_mm_per_px2
    assert abs(d.alpha2_mm_per_px - SCENE.alpha2_mm_per_px) <= 3 * d.alpha2_se_mm_per_px
    assert abs(f.c1_px - SCENE.c1_px) <= 3 * f.c1_se_px
    assert abs(f.c2_px_per_n - SCENE.c2_px_per_n) <= 3 * f.c2_se_px_per_n
    assert d.r_squared > 0.999 and f.r_squared > 0.999


def _recording_session(root: Path, name: str, frames: list[tuple[float, float]],
                       force: list[tuple[float, float]],
                       size: list[int] | None = None,
                       summary_size: list[int] | None = None,
                       roi: dict[str, Any] | str | None = None) -> Path:  # fmt: skip
    """A session as the daemon records one; ``size``: the manifest's calibration record's
    ``frame_size_px`` (None: a session recorded before it was kept), ``summary_size``: its
    summary's camera size (``run.camera.source.size``), ``roi``: the record's ROI ("full":
    ``null``, S counted in the whole frame; None: no field, recorded before it was kept)."""
    record: dict[str, object] = {"threshold_p": 128}
    if roi is not None:
        record["roi"] = None if roi == "full" else roi
    if size is not None:
        record["frame_size_px"] = size
    with SessionWriter.create(
        root,
        {"imaging": {"threshold_p": 128}},
        record,
        None,
        session_id=name,
        options=StorageOptions(min_free_bytes=0),
    ) as w:
        w.add_force_samples([(i, 0, i, i, t, f) for i, (t, f) in enumerate(force)])
        w.add_frames([(i, t, t, round(s), "") for i, (t, s) in enumerate(frames)])
        camera = {"source": {"size": summary_size}} if summary_size is not None else {}
        w.finish("complete", {"run": {"camera": camera}})
    return root / name


def _recordings(
    tmp_path: Path,
    depth_size: list[int] | None,
    force_size: list[int] | None,
    force_summary_size: list[int] | None = None,
    rois: tuple[dict[str, Any] | str | None, dict[str, Any] | str | None] = (None, None),
) -> list[str]:
    """A depth run and a force run recorded as sessions; the calibrate arguments for them."""
    rng = np.random.default_rng(4)
    # Force run: plateaus at 4..20 N; S follows Eq. (5) with 60 px of noise per frame.
    t, f = staircase([4.0, 8.0, 12.0, 16.0, 20.0])
    fn = f + rng.normal(0.0, 0.05, f.size)
    ft = np.arange(0.0, t[-1], 1 / 30)
    s = SCENE.c1_px + SCENE.c2_px_per_n * np.interp(ft, t, f) + rng.normal(0, 60.0, ft.size)
    force_dir = _recording_session(
        tmp_path,
        "force-run",
        list(zip(ft, s, strict=True)),
        list(zip(t, fn, strict=True)),
        force_size,
        force_summary_size,
        rois[1],
    )
    # Depth run: the indenter held at 8 known displacements, 2 s each, 1 s moves between.
    d = np.linspace(3.0, 10.0, 8)
    rows, marks = [], ["t_start_s,t_end_s,depth_change_mm"]
    for k, dk in enumerate(d):
        a = 3.0 * k + 0.5
        marks.append(f"{a + 0.2},{a + 1.8},{dk}")
        for tt in np.arange(a, a + 2.0, 1 / 30):
            rows.append((tt, SCENE.s0_for_depth_change(dk) + rng.normal(0.0, 20.0)))
    depth_dir = _recording_session(
        tmp_path, "depth-run", rows, [(0.0, 0.0)], depth_size, roi=rois[0]
    )
    marks_csv = tmp_path / "displacements.csv"
    marks_csv.write_text("\n".join(marks) + "\n")
    argv = ["calibrate", "--depth-recording", str(depth_dir), "--displacements", str(marks_csv)]
    return [*argv, "--force-recording", str(force_dir)]


def test_calibration_from_recorded_sessions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rec.json"
    argv = [*_recordings(tmp_path, [640, 480], [640, 480]), "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "Eq. (4): 8 displacement(s) from session depth-run" in text
    assert "Eq. (5): 5 force plateau(s) found in session force-run" in text
    cal = load_calibration(out)
    assert cal.threshold_p == 128  # taken from the sessions
    assert cal.frame_size_px == (640, 480)  # likewise
    assert cal.alpha2_mm_per_px == pytest.approx(SCENE.alpha2_mm_per_px, rel=0.01)
    assert cal.c1_px == pytest.approx(SCENE.c1_px, abs=150.0)
    assert cal.c2_px_per_n == pytest.approx(SCENE.c2_px_per_n, rel=0.01)
    assert cal.force_valid_range_n is not None
    assert cal.force_valid_range_n == pytest.approx((4.0, 20.0), abs=0.05)


def test_the_frame_size_comes_from_the_option_or_the_recordings_and_must_agree(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """S is a pixel count, so a calibration belongs to one frame size: ``--frame-size`` or
    the recordings' (manifest, else the summary's camera) is written into the file, and
    sizes that disagree are refused in one line, nothing written."""
    depth, force = _pairs(tmp_path, SCENE)
    pairs = ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(force)]
    out = tmp_path / "c.json"
    assert main([*pairs, "--frame-size", "640x480", "--out", str(out)]) == 0
    assert "no frame size recorded" not in capsys.readouterr().out
    assert load_calibration(out).frame_size_px == (640, 480)
    assert main([*pairs, "--out", str(out), "--overwrite"]) == 0
    assert "warning: no frame size recorded (--frame-size WxH)" in capsys.readouterr().out
    assert load_calibration(out).frame_size_px is None
    with pytest.raises(SystemExit) as info:
        main([*pairs, "--frame-size", "640x0", "--out", str(tmp_path / "z.json")])
    assert info.value.code == 2
    assert "expected WIDTHxHEIGHT in px, both > 0" in capsys.readouterr().err

    out = tmp_path / "rec.json"
    mixed = _recordings(tmp_path / "mixed", [1280, 720], [640, 480])
    err = _err(capsys, [*mixed, "--out", str(out)])
    assert (
        "the recordings' frames differ in size (1280x720 px in session depth-run; 640x480 px "
        "in session force-run): S values are not comparable"
    ) in err
    same = _recordings(tmp_path / "same", [640, 480], None)  # force run: not recorded
    err = _err(capsys, [*same, "--frame-size", "320x240", "--out", str(out)])
    assert "--frame-size 320x240 px differs from 640x480 px in session depth-run" in err
    assert not out.exists()
    assert main([*same, "--out", str(out)]) == 0
    assert load_calibration(out).frame_size_px == (640, 480)
    # A session recorded before the manifest kept it: its summary's camera says.
    older = _recordings(tmp_path / "older", None, None, [320, 240])
    err = _err(capsys, [*older, "--frame-size", "640x480", "--out", str(tmp_path / "o.json")])
    assert "--frame-size 640x480 px differs from 320x240 px in session force-run" in err


def test_the_roi_comes_from_the_option_or_the_recordings_and_must_agree(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """S counts the occluded pixels within the ROI, so a calibration belongs to one ROI:
    ``--roi`` or the recordings' (the manifest's calibration record) is written into the
    file, and ROIs that disagree are refused in one line, nothing written."""
    depth, force = _pairs(tmp_path, SCENE)
    pairs = ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(force)]
    out = tmp_path / "c.json"
    assert main([*pairs, "--roi", "circle:320,240,180", "--out", str(out)]) == 0
    assert "no ROI recorded" not in capsys.readouterr().out
    assert load_calibration(out).roi == CircleROI(cx_px=320, cy_px=240, radius_px=180)
    assert main([*pairs, "--roi", "full", "--out", str(out), "--overwrite"]) == 0
    assert "no ROI recorded: S was counted in the whole frame, whose size" in (
        capsys.readouterr().out
    )
    assert load_calibration(out).roi is None
    full = ["--roi", "full", "--frame-size", "640x480", "--out", str(out), "--overwrite"]
    assert main([*pairs, *full]) == 0
    assert "no ROI recorded" not in capsys.readouterr().out
    assert load_calibration(out).roi == whole_frame_roi((640, 480))

    disc = {"kind": "circle", "cx_px": 320.0, "cy_px": 240.0, "radius_px": 180.0}
    rect = {"kind": "rect", "x_px": 140, "y_px": 60, "width_px": 360, "height_px": 360}
    out = tmp_path / "rec.json"
    mixed = _recordings(tmp_path / "mixed", None, None, rois=(disc, rect))
    err = _err(capsys, [*mixed, "--out", str(out)])
    assert (
        "the recordings' ROIs differ (circle centre (320, 240) r 180 px in session depth-run; "
        "rect at (140, 60) size 360x360 px in session force-run): S values are not comparable"
    ) in err
    same = _recordings(tmp_path / "same", None, None, rois=(disc, None))
    err = _err(capsys, [*same, "--roi", "circle:320,240,170", "--out", str(out)])
    assert (
        "--roi circle centre (320, 240) r 170 px differs from circle centre (320, 240) r 180 "
        "px in session depth-run"
    ) in err
    assert not out.exists()
    assert main([*same, "--out", str(out)]) == 0
    assert load_calibration(out).roi == CircleROI(**disc)


def test_recordings_counted_in_the_whole_frame_record_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session whose record has ``roi: null`` counted S in the whole frame: calibrating
    from it records the whole frame (the rect of its size), so that the daemon refuses a
    smaller ROI; ``--roi`` with another ROI is refused, as a rect holding the frame is
    not; a session from before the ROI was kept (no field) says nothing."""
    out = tmp_path / "c.json"
    whole = _recordings(tmp_path / "whole", [640, 480], [640, 480], rois=("full", "full"))
    assert main([*whole, "--out", str(out)]) == 0
    assert "no ROI recorded" not in capsys.readouterr().out
    assert load_calibration(out).roi == whole_frame_roi((640, 480))
    err = _err(capsys, [*whole, "--roi", "circle:320,240,180", "--out", str(tmp_path / "x")])
    assert (
        "--roi circle centre (320, 240) r 180 px differs from the whole frame in session "
        "depth-run; the whole frame in session force-run"
    ) in err
    rect = ["--roi", "rect:-2,0,650,480", "--out", str(out), "--overwrite"]
    assert main([*whole, *rect]) == 0
    assert load_calibration(out).roi == RectROI(
        kind="rect", x_px=-2, y_px=0, width_px=650, height_px=480
    )
    disc = {"kind": "circle", "cx_px": 320.0, "cy_px": 240.0, "radius_px": 180.0}
    mixed = _recordings(tmp_path / "mixed", [640, 480], [640, 480], rois=("full", disc))
    err = _err(capsys, [*mixed, "--out", str(tmp_path / "y")])
    assert "the recordings' ROIs differ (the whole frame in session depth-run; circle" in err
    # its size unknown, the whole frame cannot be recorded: a warning, no ROI
    unsized = _recordings(tmp_path / "unsized", None, None, rois=("full", None))
    assert main([*unsized, "--out", str(tmp_path / "z")]) == 0
    assert "no ROI recorded: S was counted in the whole frame" in capsys.readouterr().out
    assert load_calibration(tmp_path / "z").roi is None


def _err(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_refusals_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    depth, force = _pairs(tmp_path, SCENE)
    out = ["--out", str(tmp_path / "c.json")]
    two = tmp_path / "two.csv"
    two.write_text("s0_px,depth_change_mm\n100,0.2\n200,0.5\n")
    err = _err(capsys, ["calibrate", "--depth-pairs", str(two), "--force-pairs", str(force), *out])
    assert "Eq. (4) depth fit refused: " in err and "3" in err
    down = tmp_path / "down.csv"
    down.write_text("s_px,force_n\n5000,1\n4000,2\n3000,3\n2000,4\n")
    err = _err(capsys, ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(down), *out])
    assert "Eq. (5) force fit refused: non-positive slope C2" in err
    bad = tmp_path / "bad.csv"
    bad.write_text("s_px,force\n1,2\n")
    err = _err(capsys, ["calibrate", "--depth-pairs", str(depth), "--force-pairs", str(bad), *out])
    assert f"{bad}: line 1: missing column 'force_n'" in err
    err = _err(capsys, ["calibrate", "--depth-recording", str(tmp_path), "--force-pairs",
                        str(force), *out])  # fmt: skip
    assert "--depth-recording needs --displacements" in err
    err = _err(capsys, ["calibrate", "--depth-pairs", str(depth), "--force-recording",
                        str(tmp_path), *out])  # fmt: skip
    assert "not a recording" in err
    assert not (tmp_path / "c.json").exists()
