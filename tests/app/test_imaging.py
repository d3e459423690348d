"""Which calibration, threshold and ROI apply: one rule for the daemon and for ``analyze``.

Precedence, most specific first: command-line override, config, stored manifest, the
chosen calibration's own threshold, simulated scene (or its ground truth).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.analysis.calibration import Calibration, save_calibration
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.app.config import ImagingSettings, load_config
from stipi_daemon.app.imaging import (
    Choice,
    ImagingSource,
    calibration_record,
    choose_imaging,
    recorded_source,
    resolve_imaging,
    settings_source,
    truth_source,
)
from stipi_daemon.errors import ConfigError

SCENE = Path(__file__).resolve().parents[2] / "configs" / "scenes" / "grade1.yaml"


def _cal(c1_px: float, threshold_p: int | None = None) -> Calibration:
    return Calibration(
        alpha1_mm_per_px2=0.0,
        alpha2_mm_per_px=0.001,
        c1_px=c1_px,
        c2_px_per_n=100.0,
        threshold_p=threshold_p,
        s0_valid_range_px=(10.0, 900.0),
        force_valid_range_n=(0.5, 5.0),
    )


def _roi(r: float) -> CircleROI:
    return CircleROI(kind="circle", cx_px=50.0, cy_px=40.0, radius_px=r)


def _source(tag: str, c1_px: float, p: int | None, r: float | None) -> ImagingSource:
    return ImagingSource(
        calibration=Choice(_cal(c1_px, threshold_p=None), tag),
        threshold_p=None if p is None else Choice(p, tag),
        roi=None if r is None else Choice(_roi(r), tag),
    )


def test_each_source_wins_over_the_less_specific_ones() -> None:
    over = _source("override", 1.0, 11, 1.0)
    conf = _source("config", 2.0, 22, 2.0)
    rec = _source("manifest", 3.0, 33, None)
    scene = _source("scene", 4.0, 44, 4.0)
    chosen = choose_imaging(override=over, config=conf, recorded=rec, scene=scene)
    assert chosen.calibration is not None and chosen.calibration.source == "override"
    assert chosen.threshold_p == Choice(11, "override")
    assert chosen.roi is not None and chosen.roi.source == "override"
    chosen = choose_imaging(config=conf, recorded=rec, scene=scene)
    assert chosen.calibration is not None and chosen.calibration.value.c1_px == 2.0
    assert chosen.threshold_p == Choice(22, "config")
    assert chosen.roi is not None and chosen.roi.source == "config"
    chosen = choose_imaging(recorded=rec, scene=scene)
    assert chosen.calibration is not None and chosen.calibration.source == "manifest"
    assert chosen.threshold_p == Choice(33, "manifest")
    # The manifest records no ROI here: the scene's waveguide disc applies.
    assert chosen.roi is not None and chosen.roi.source == "scene"
    chosen = choose_imaging(scene=scene)
    assert chosen.calibration is not None and chosen.calibration.source == "scene"
    assert chosen.threshold_p == Choice(44, "scene")
    nothing = choose_imaging()
    assert nothing.calibration is None and nothing.threshold_p is None
    assert nothing.roi is None and nothing.roi_value is None
    with pytest.raises(ConfigError, match="give a calibration"):
        nothing.need_calibration("give a calibration")


def test_the_calibrations_own_threshold_comes_after_manifest_before_scene() -> None:
    over = ImagingSource(calibration=Choice(_cal(1.0, threshold_p=120), "cal.json"))
    rec = _source("manifest", 3.0, 33, None)
    scene = _source("scene", 4.0, 44, 4.0)
    assert choose_imaging(override=over, recorded=rec).threshold_p == Choice(33, "manifest")
    assert choose_imaging(override=over, scene=scene).threshold_p == Choice(
        120, "calibration (cal.json)"
    )
    no_p = ImagingSource(calibration=Choice(_cal(1.0), "cal.json"))
    assert choose_imaging(override=no_p, scene=scene).threshold_p == Choice(44, "scene")


def test_the_calibrations_own_roi_comes_after_manifest_before_scene() -> None:
    """The ROI a calibration was made in is counted in unless the command line, the
    config or the session's manifest (the ROI the live run counted in) says otherwise;
    the scene's disc only when the calibration records none."""
    own = dataclasses.replace(_cal(1.0), roi=_roi(7.0))
    over = ImagingSource(calibration=Choice(own, "cal.json"))
    rec = ImagingSource(roi=Choice(_roi(3.0), "manifest"))
    scene = _source("scene", 4.0, 44, 4.0)
    assert choose_imaging(override=over, recorded=rec, scene=scene).roi == rec.roi
    assert choose_imaging(override=over, scene=scene).roi == Choice(
        _roi(7.0), "calibration (cal.json)"
    )
    no_roi = ImagingSource(calibration=Choice(_cal(1.0), "cal.json"))
    assert choose_imaging(override=no_roi, scene=scene).roi == Choice(_roi(4.0), "scene")


def test_an_explicit_full_frame_overrides_every_roi() -> None:
    full = ImagingSource(roi=Choice(None, "--roi"))
    chosen = choose_imaging(override=full, config=_source("config", 2.0, 22, 2.0))
    assert chosen.roi == Choice(None, "--roi") and chosen.roi_value is None


def test_settings_source_reads_the_config(tmp_path: Path) -> None:
    path = save_calibration(tmp_path / "cal.json", _cal(5.0, threshold_p=90))
    rect = RectROI(kind="rect", x_px=1, y_px=2, width_px=30, height_px=40)
    src = settings_source(ImagingSettings(threshold_p=70, roi=rect), path)
    assert src.calibration is not None and src.calibration.source == str(path)
    assert src.calibration.value.c1_px == 5.0
    assert src.threshold_p == Choice(70, "config imaging.threshold_p")
    assert src.roi == Choice(rect, "config imaging.roi")
    assert settings_source(ImagingSettings(), None) == ImagingSource()


def test_manifest_record_round_trips_every_field_the_analysis_reads() -> None:
    cal = _cal(7.0, threshold_p=None)
    record = calibration_record(cal, 101, _roi(9.0), "cal.json")
    src = recorded_source(record, "manifest.json")
    assert src.threshold_p == Choice(101, "session manifest calibration")
    assert src.calibration is not None and src.calibration.source == "session manifest"
    back = src.calibration.value
    assert back.s0_valid_range_px == cal.s0_valid_range_px
    assert back.force_valid_range_n == cal.force_valid_range_n
    assert (back.c1_px, back.c2_px_per_n, back.alpha2_mm_per_px) == (7.0, 100.0, 0.001)
    # The frame size is the camera's, as it reports it; a calibration's own size is never
    # recorded in its place (nothing would have checked it).
    sized = dataclasses.replace(cal, frame_size_px=(640, 480))
    assert calibration_record(sized, 101, None, "cal.json")["frame_size_px"] is None
    record = calibration_record(sized, 101, None, "cal.json", (320, 240))
    assert record["frame_size_px"] == [320, 240]
    back = recorded_source(record, "manifest.json").calibration
    assert back is not None and back.value.frame_size_px == (320, 240)
    # The ROI counted in is read back as the source's and the calibration's: counting
    # again in another is then flagged. The whole frame is a choice; no key says nothing.
    src = recorded_source(calibration_record(cal, 101, _roi(9.0), "cal.json"), "m.json")
    assert src.roi == Choice(_roi(9.0), "session manifest calibration")
    assert src.calibration is not None and src.calibration.value.roi == _roi(9.0)
    whole = recorded_source(record, "m.json")
    assert whole.roi == Choice(None, "session manifest calibration")
    del record["roi"]
    assert recorded_source(record, "m.json").roi is None


def test_truth_source_offers_the_scenes_calibration_threshold_and_disc() -> None:
    truth: dict[str, Any] = {
        "calibration": {
            "alpha1_mm_per_px2": 0.0,
            "alpha2_mm_per_px": 0.002,
            "c1_px": 3.0,
            "c2_px_per_n": 50.0,
        },
        "frame": {"threshold_p": 77},
        "roi": {"cx_px": 10.0, "cy_px": 11.0, "radius_px": 12.0},
    }
    src = truth_source(truth, "gt.json", "simulator ground truth gt.json")
    assert src.threshold_p == Choice(77, "simulator ground truth gt.json")
    assert src.roi is not None and src.roi.value == CircleROI(
        kind="circle", cx_px=10.0, cy_px=11.0, radius_px=12.0
    )
    assert src.truth is truth
    assert truth_source({}, "gt.json", "x") == ImagingSource(truth={})


def _config(tmp_path: Path, **extra: Any) -> Path:
    doc: dict[str, Any] = {
        "probe": {"transport": {"kind": "emulated", "scene": str(SCENE)}},
        "camera": {"kind": "simulator", "scene": str(SCENE)},
        "storage": {"root": str(tmp_path / "sessions")},
    }
    doc.update(extra)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_daemon_simulated_scene_then_config_overrides(tmp_path: Path) -> None:
    cal, p, roi, truth = resolve_imaging(load_config(_config(tmp_path)))
    assert truth is not None and isinstance(roi, CircleROI)
    assert p == int(truth["frame"]["threshold_p"])
    assert roi.radius_px == truth["roi"]["radius_px"]
    assert cal.c1_px == pytest.approx(truth["calibration"]["c1_px"])
    cal_path = save_calibration(tmp_path / "cal.json", _cal(5.0, threshold_p=90))
    cfg = load_config(_config(tmp_path, calibration=str(cal_path)))
    cal, p, roi, truth = resolve_imaging(cfg)
    assert cal.c1_px == 5.0 and p == 90 and isinstance(roi, CircleROI) and truth is not None
    rect = {"kind": "rect", "x_px": 0, "y_px": 0, "width_px": 8, "height_px": 8}
    cfg = load_config(
        _config(tmp_path, calibration=str(cal_path), imaging={"threshold_p": 90, "roi": rect})
    )
    cal, p, roi, _ = resolve_imaging(cfg)
    assert p == 90 and isinstance(roi, RectROI)
    # Another p than the calibration's: its S values and these S_k would not compare.
    imaging = {"threshold_p": 60, "roi": rect}
    cfg = load_config(_config(tmp_path, calibration=str(cal_path), imaging=imaging))
    with pytest.raises(ConfigError, match=r"field 'imaging\.threshold_p': 60 differs from the"):
        resolve_imaging(cfg)
    # A calibration that records no p takes the config's.
    save_calibration(cal_path, _cal(5.0))
    cal, p, roi, _ = resolve_imaging(
        load_config(_config(tmp_path, calibration=str(cal_path), imaging=imaging))
    )
    assert p == 60 and cal.threshold_p is None


def test_daemon_refuses_an_roi_other_than_the_calibrations(tmp_path: Path) -> None:
    """The config's ROI must be the one the calibration was made in; left out, the
    calibration's is counted in; a calibration that records none takes the config's."""
    made_in = {"kind": "circle", "cx_px": 320.0, "cy_px": 240.0, "radius_px": 150.0}
    cal_path = save_calibration(
        tmp_path / "cal.json", dataclasses.replace(_cal(5.0, 90), roi=CircleROI(**made_in))
    )
    for same in ({}, {"roi": made_in}):
        cfg = load_config(_config(tmp_path, calibration=str(cal_path), imaging=same))
        assert resolve_imaging(cfg)[2] == CircleROI(**made_in)
    rect = {"kind": "rect", "x_px": 170, "y_px": 90, "width_px": 300, "height_px": 300}
    for other in ({**made_in, "radius_px": 151.0}, {**made_in, "cx_px": 319.0}, rect):
        cfg = load_config(_config(tmp_path, calibration=str(cal_path), imaging={"roi": other}))
        with pytest.raises(ConfigError) as info:
            resolve_imaging(cfg)
        msg = str(info.value)
        assert msg.startswith("field 'imaging.roi' counts S in "), msg
        assert "made in circle centre (320, 240) r 150 px" in msg
        assert msg.endswith("or calibrate in this one"), msg
    save_calibration(cal_path, _cal(5.0, 90))
    cfg = load_config(_config(tmp_path, calibration=str(cal_path), imaging={"roi": rect}))
    assert isinstance(resolve_imaging(cfg)[2], RectROI)


def test_daemon_real_camera_needs_a_calibration(tmp_path: Path) -> None:
    doc = {
        "probe": {"transport": {"kind": "emulated", "scene": str(SCENE)}},
        "camera": {"kind": "file", "path": str(tmp_path / "video.mkv")},
        "storage": {"root": str(tmp_path / "sessions")},
    }
    path = tmp_path / "real.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="a calibration file is required"):
        resolve_imaging(load_config(path))
    save_calibration(tmp_path / "cal.json", _cal(5.0))
    doc["calibration"] = str(tmp_path / "cal.json")
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"imaging\.threshold_p"):
        resolve_imaging(load_config(path))
