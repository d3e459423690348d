"""What the user sees when a device or a config is wrong: one line, non-zero, no traceback.

Device errors (and one config error) run the real CLI (``python -m stipi_daemon --config
FILE``) in a subprocess; the table of config errors calls the same entry point
(:func:`stipi_daemon.cli.main`) in-process, which is what the subprocess runs, to keep
the suite fast. Each checks that standard error is exactly one ``stipi-daemon: error: ...``
line naming the device, path or config field and file, that the exit status is 2, and
that no session directory (not even the sessions root) was created: the daemon opens its
devices before it creates the session.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import yaml

from stipi_daemon.analysis.calibration import save_calibration
from stipi_daemon.analysis.imaging import CircleROI, describe_roi
from stipi_daemon.cli import main
from stipi_daemon.sim.physics import scaled_calibration
from stipi_daemon.sim.scene import load_scene
from stipi_daemon.sim.truth import ground_truth
from tests.conftest import REPO_ROOT

SCENE = str(REPO_ROOT / "configs" / "scenes" / "grade1.yaml")
EMULATED = {"kind": "emulated", "scene": SCENE}
SIMULATOR = {"kind": "simulator", "scene": SCENE}


def write(directory: Path, config: dict[str, Any] | str) -> Path:
    """Write ``config`` (a mapping, or YAML text) as ``probe.yaml``, sessions next to it."""
    path = directory / "probe.yaml"
    if isinstance(config, str):
        path.write_text(config)
    else:
        path.write_text(yaml.safe_dump({"storage": {"root": "sessions"}, **config}))
    return path


def run_cli(directory: Path, config: dict[str, Any] | str) -> subprocess.CompletedProcess[str]:
    """Write ``config`` and run the CLI on it in a subprocess."""
    path = write(directory, config)
    return subprocess.run(
        [sys.executable, "-m", "stipi_daemon", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=directory,
    )


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *needles: str) -> str:
    err = proc.stderr
    assert proc.returncode == 2, (proc.returncode, err, proc.stdout)
    assert "Traceback" not in err and "Traceback" not in proc.stdout
    assert err.count("\n") == 1 and err.startswith("stipi-daemon: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def run_main(
    directory: Path, config: dict[str, Any] | str, capsys: pytest.CaptureFixture[str]
) -> subprocess.CompletedProcess[str]:
    """Write ``config`` and call the CLI's ``main`` in-process; its exit status and output."""
    path = write(directory, config)
    code = main(["--config", str(path)])
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["main"], code, out, err)


@pytest.fixture
def calibration(tmp_path: Path) -> Path:
    cal, _ = scaled_calibration(load_scene(SCENE))
    return save_calibration(tmp_path / "calibration.json", cal)


# ---------------------------------------------------------------------- devices


@pytest.mark.parametrize(
    ("camera", "needle"),
    [
        ({"kind": "v4l2", "device": "/dev/video99", "exposure_ms": 8.0}, "camera /dev/video99"),
        ({"kind": "file", "path": "missing.avi"}, "missing.avi: not found"),
    ],
    ids=["v4l2", "video-file"],
)
def test_unreadable_camera(
    tmp_path: Path, calibration: Path, camera: dict[str, Any], needle: str
) -> None:
    proc = run_cli(
        tmp_path,
        {
            "probe": {"transport": EMULATED},
            "camera": camera,
            "calibration": str(calibration),
            "imaging": {"threshold_p": 128},
        },
    )
    assert_one_line_error(proc, needle)
    assert not (tmp_path / "sessions").exists()


@pytest.mark.parametrize("with_file", [False, True], ids=["scene", "calibration-file"])
def test_a_threshold_other_than_the_calibrations_is_a_config_error_before_recording(
    tmp_path: Path, with_file: bool
) -> None:
    """S_k depends on p (Eq. 1): ``imaging.threshold_p`` other than the p the calibration
    (a file's, or the scene's) was made with counted S values that its Eqs. 4-5 do not
    describe, and D_p and F_r came out wrong with no flag. One line naming the field, both
    thresholds and the calibration; exit 2, nothing recorded."""
    cal, _ = scaled_calibration(load_scene(SCENE))
    assert cal.threshold_p == 128
    doc: dict[str, Any] = {
        "probe": {"transport": EMULATED},
        "camera": SIMULATOR,
        "imaging": {"threshold_p": 100},
    }
    source = "simulated scene"
    if with_file:
        source = str(save_calibration(tmp_path / "cal.json", cal))
        doc["calibration"] = source
    proc = run_cli(tmp_path, doc)
    assert_one_line_error(
        proc,
        "field 'imaging.threshold_p': 100 differs from the threshold p 128 the calibration "
        f"({source}) was made with",
        "leave imaging.threshold_p out to count with 128, or calibrate with p 100",
    )
    assert not (tmp_path / "sessions").exists()


@pytest.mark.parametrize("with_file", [False, True], ids=["scene", "calibration-file"])
def test_an_roi_other_than_the_calibrations_is_a_config_error_before_recording(
    tmp_path: Path, with_file: bool
) -> None:
    """S counts the occluded pixels within the ROI: ``imaging.roi`` other than the ROI the
    calibration (a file's, or the scene's waveguide disc) was made in counts S values its
    Eqs. 4-5 do not describe (a smaller circle cuts the pit, a larger one adds dark pixels
    beyond the lit disc), and D_p and F_r came out wrong with no flag. One line naming the
    field, both ROIs and the calibration; exit 2, nothing recorded."""
    cal, _ = scaled_calibration(load_scene(SCENE))
    disc = ground_truth(load_scene(SCENE)).roi
    own = CircleROI(kind="circle", **disc)
    doc: dict[str, Any] = {
        "probe": {"transport": EMULATED},
        "camera": SIMULATOR,
        "imaging": {"roi": {"kind": "circle", "cx_px": 320, "cy_px": 240, "radius_px": 100}},
    }
    source = "simulated scene"
    if with_file:
        source = str(save_calibration(tmp_path / "cal.json", replace(cal, roi=own)))
        doc["calibration"] = source
    proc = run_cli(tmp_path, doc)
    assert_one_line_error(
        proc,
        "field 'imaging.roi' counts S in circle centre (320, 240) r 100 px, but the "
        f"calibration was made in {describe_roi(own)} (its field 'roi')",
        f"({source}); leave imaging.roi out to count in the calibration's ROI, or calibrate "
        "in this one",
    )
    assert not (tmp_path / "sessions").exists()


def _run_with_scene_calibration(
    tmp_path: Path, **changes: Any
) -> tuple[subprocess.CompletedProcess[str], Path]:
    """The CLI on the simulated scene with the scene's calibration, ``changes`` made, as a
    calibration file; its result and the file."""
    cal, _ = scaled_calibration(load_scene(SCENE))
    path = save_calibration(tmp_path / "cal.json", replace(cal, **changes))
    doc = {"probe": {"transport": EMULATED}, "camera": SIMULATOR, "calibration": str(path)}
    return run_cli(tmp_path, doc), path


def test_a_calibrations_own_roi_outside_the_frame_is_named_as_the_calibrations(
    tmp_path: Path,
) -> None:
    """With ``imaging.roi`` left out, S is counted in the calibration's ROI: one that lies
    off the camera's frame is refused naming the calibration's field, not the scene's."""
    off = CircleROI(kind="circle", cx_px=900.0, cy_px=100.0, radius_px=200.0)
    proc, path = _run_with_scene_calibration(tmp_path, roi=off)
    assert_one_line_error(
        proc,
        f"field 'roi' of the calibration ({path}): circle centre (900, 100) r 200 px lies "
        "outside the 640x480 frame",
    )
    assert not (tmp_path / "sessions").exists()


def test_a_calibration_made_at_another_frame_size_is_a_config_error_before_recording(
    tmp_path: Path,
) -> None:
    """S is a pixel count: frames of 1280x720 read with the scene's calibration, exact at
    640x480, would give D_p and F_r from areas 2.25 times as large, unflagged. A
    calibration that records its frame size is checked against the camera's once it is
    open: one line naming the field and both sizes, exit 2, nothing recorded."""
    assert scaled_calibration(load_scene(SCENE))[0].frame_size_px == (640, 480)  # the camera's
    proc, path = _run_with_scene_calibration(tmp_path, frame_size_px=(1280, 720))
    assert_one_line_error(
        proc,
        f"field 'calibration' ({path}): the camera has 640x480 px frames, but the "
        "calibration was made at 1280x720 px",
        "set the camera to 1280x720 or calibrate at 640x480",
    )
    assert not (tmp_path / "sessions").exists()


def test_missing_serial_port(tmp_path: Path) -> None:
    proc = run_cli(
        tmp_path,
        {"probe": {"transport": {"kind": "serial", "port": "/dev/ttyNOPE0"}}, "camera": SIMULATOR},
    )
    assert_one_line_error(proc, "serial port /dev/ttyNOPE0 not found")
    assert not (tmp_path / "sessions").exists()


def test_ble_probe_not_found(tmp_path: Path) -> None:
    # A virtual radio with an emulated probe on it, but the config asks for another
    # address: the scan finds nothing.
    transport = {
        "kind": "ble",
        "address": "AA:BB:CC:DD:EE:FF",
        "emulate": {"scene": SCENE},
        "scan_timeout_s": 0.5,
    }
    proc = run_cli(tmp_path, {"probe": {"transport": transport}, "camera": SIMULATOR})
    assert_one_line_error(proc, "BLE probe AA:BB:CC:DD:EE:FF not found")
    assert not (tmp_path / "sessions").exists()


# ---------------------------------------------------------------------- config errors


def test_config_error_in_a_subprocess(tmp_path: Path) -> None:
    transport = {"kind": "serial", "port": "/dev/ttyACM0", "baud": 9600}
    proc = run_cli(tmp_path, {"probe": {"transport": transport}, "camera": SIMULATOR})
    assert_one_line_error(
        proc, str(tmp_path / "probe.yaml"), "field 'probe.transport.baud': unknown key"
    )
    assert not (tmp_path / "sessions").exists()


BASE: dict[str, Any] = {"probe": {"transport": EMULATED}, "camera": SIMULATOR}


def _with(path: str, value: Any, *, drop: bool = False) -> dict[str, Any]:
    """BASE with ``value`` set at dotted ``path`` (or that key dropped)."""
    doc = yaml.safe_load(yaml.safe_dump(BASE))
    *parents, last = path.split(".")
    node = doc
    for p in parents:
        node = node.setdefault(p, {})
    if drop:
        del node[last]
    else:
        node[last] = value
    return doc


@pytest.mark.parametrize(
    ("config", "needles"),
    [
        (_with("measurment", {}), ["field 'measurment': unknown key"]),
        (
            _with("probe.transport", {"kind": "serial", "prot": "/dev/ttyACM0"}),
            ["field 'probe.transport.port'"],
        ),
        (
            _with("probe.transport", {"kind": "serial", "port": "/dev/x", "baud": 9600}),
            ["field 'probe.transport.baud': unknown key"],
        ),
        (_with("probe.transport", {"kind": "usb"}), ["field 'probe.transport'"]),
        (_with("probe.rate_hz", 5000), ["field 'probe.rate_hz'", "1000"]),
        (_with("probe.led_level", "bright"), ["field 'probe.led_level'"]),
        (_with("camera.kind", "webcam"), ["field 'camera'"]),
        (_with("camera", {"kind": "v4l2"}), ["field 'camera.exposure_ms'"]),
        (_with("imaging.roi", {"kind": "circle", "cx_px": 10}), ["field 'imaging.roi"]),
        (_with("measurement.target_force_n", -1.0), ["field 'measurement.target_force_n'"]),
        (_with("storage.commit_interval_s", 5.0), ["field 'storage.commit_interval_s'"]),
        (_with("run.speed", -1), ["field 'run.speed'"]),
        (_with("probe", None, drop=True), ["field 'probe'"]),
    ],
    ids=lambda v: None if isinstance(v, dict) else v[0].split("'")[1],
)
def test_config_error_names_field_and_file(
    tmp_path: Path, config: dict[str, Any], needles: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    proc = run_main(tmp_path, config, capsys)
    assert_one_line_error(proc, str(tmp_path / "probe.yaml"), *needles)
    assert not (tmp_path / "sessions").exists()


def test_yaml_syntax_error_names_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    proc = run_main(tmp_path, "probe: {transport: {kind: emulated\ncamera: [\n", capsys)
    assert_one_line_error(proc, "probe.yaml", "not valid YAML at line")


def test_missing_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--config", str(tmp_path / "nope.yaml")])
    out, err = capsys.readouterr()
    proc = subprocess.CompletedProcess(["main"], code, out, err)
    assert_one_line_error(proc, "nope.yaml", "cannot read config file")


def test_bad_scene_field_names_scene_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = yaml.safe_load(Path(SCENE).read_text())
    doc["camera"]["fps"] = -60
    scene = tmp_path / "bad_scene.yaml"
    scene.write_text(yaml.safe_dump(doc))
    proc = run_main(
        tmp_path,
        {
            "probe": {"transport": {**EMULATED, "scene": str(scene)}},
            "camera": {**SIMULATOR, "scene": str(scene)},
        },
        capsys,
    )
    assert_one_line_error(proc, "bad_scene.yaml", "camera.fps")
    assert not (tmp_path / "sessions").exists()


def test_bad_calibration_file_names_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "cal.json").write_text('{"format": "stipi-calibration", "version": 1')
    proc = run_main(tmp_path, {**BASE, "calibration": "cal.json"}, capsys)
    assert_one_line_error(proc, str(tmp_path / "cal.json"), "invalid JSON")
    assert not (tmp_path / "sessions").exists()


# ---------------------------------------------------------------------- the ROI against the frame


@pytest.mark.parametrize(
    ("roi", "needle"),
    [
        (
            {"kind": "circle", "cx_px": 900.0, "cy_px": 100.0, "radius_px": 200.0},
            "field 'imaging.roi': circle centre (900, 100) r 200 px lies outside the 640x480 frame",
        ),
        (
            {"kind": "rect", "x_px": 600, "y_px": 10, "width_px": 100, "height_px": 50},
            "field 'imaging.roi': rect at (600, 10) size 100x50 px lies partly outside the "
            "640x480 frame",
        ),
    ],
    ids=["entirely-outside", "partly-outside"],
)
def test_roi_outside_the_frame_is_a_config_error_before_recording(
    tmp_path: Path, calibration: Path, roi: dict[str, Any], needle: str
) -> None:
    """Issue 14 case 6: an ROI off the camera's frame recorded 105 s of empty_roi frames
    and reported D_p 12 mm, F_r 0 N, exit 0. Now: one line naming the field, exit 2,
    nothing recorded (the check runs once the camera is open, before the session). The
    calibration records no ROI (the scene's own, made in its disc, would refuse any
    other ROI first)."""
    doc = {"probe": {"transport": EMULATED}, "camera": SIMULATOR, "imaging": {"roi": roi}}
    proc = run_cli(tmp_path, {**doc, "calibration": str(calibration)})
    assert_one_line_error(proc, needle)
    assert not (tmp_path / "sessions").exists()
