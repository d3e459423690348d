"""Files: the video decodes (also truncated), CSVs and JSON are complete, runs are deterministic."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.cli import main
from stipi_daemon.sim import Pipeline, load_scene, write_outputs
from stipi_daemon.sim.scene import Scene

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"


def _short(name: str = "grade1", effects: list[dict[str, object]] | None = None) -> Scene:
    s = load_scene(SCENES / f"{name}.yaml").with_camera(width=320, height=240, fps=20.0)
    fp = s.force_profile.model_copy(update={"hold_s": 2.0, "recovery_s": 4.0})
    s = s.model_copy(update={"force_profile": fp})
    return s.with_effects(effects) if effects else s


def test_write_outputs_and_truncated_video(tmp_path: Path) -> None:
    paths = write_outputs(_short(), tmp_path / "a")
    cap = cv2.VideoCapture(str(paths.video))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == paths.frames_written == 141
    with paths.frames_csv.open() as f:
        assert len(list(csv.reader(f))) == n + 1
    with paths.force_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == paths.samples_written == 701
    assert int(rows[-1]["t_mcu_us"]) == 7_000_000
    truth = json.loads(paths.ground_truth_json.read_text())
    assert truth["t0_s"] == 3.0 and truth["frame"]["width_px"] == 320
    # Cut the file in the middle: the frames before the cut still decode.
    data = paths.video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    cap = cv2.VideoCapture(str(cut))
    m = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (240, 320, 3)
        m += 1
    cap.release()
    assert 0.3 * n < m < n


def test_deterministic_for_a_seed(tmp_path: Path) -> None:
    effects: list[dict[str, object]] = [
        {"name": "sensor_noise", "sigma_levels": 3.0},
        {"name": "force_noise", "sigma_n": 0.1},
    ]
    a = write_outputs(_short(effects=effects), tmp_path / "a", seed=7)
    b = write_outputs(_short(effects=effects), tmp_path / "b", seed=7)
    assert a.ground_truth_json.read_bytes() == b.ground_truth_json.read_bytes()
    assert a.force_csv.read_bytes() == b.force_csv.read_bytes()
    fa = [f.image for f in Pipeline(_short(effects=effects), 7).frames()]
    fb = [f.image for f in Pipeline(_short(effects=effects), 7).frames()]
    assert all(np.array_equal(x, y) for x, y in zip(fa, fb, strict=True))
    fc = [f.image for f in Pipeline(_short(effects=effects), 8).frames()]
    assert not all(np.array_equal(x, y) for x, y in zip(fa, fc, strict=True))
    # A window of frames equals the same frames of the full run.
    part = list(Pipeline(_short(effects=effects), 7).frames(2.0, 3.0))
    assert all(np.array_equal(f.image, fa[f.index]) for f in part)


def test_no_effects_imports_and_runs_no_effect_code() -> None:
    code = (
        "import sys\n"
        "from stipi_daemon.sim import Pipeline, load_scene, ground_truth\n"
        f"s = load_scene({str(SCENES / 'grade3.yaml')!r}).with_camera(width=160, height=120)\n"
        "p = Pipeline(s)\n"
        "assert p.effects == []\n"
        "for i, f in enumerate(p.frames(14.0, 16.0)): pass\n"
        "p.force_batch(); ground_truth(s)\n"
        "mods = [m for m in sys.modules if m.startswith('stipi_daemon.sim.effects.')]\n"
        "print(','.join(sorted(mods)))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "stipi_daemon.sim.effects.base"
    code2 = code.replace(
        ".with_camera(width=160, height=120)",
        ".with_camera(width=160, height=120).with_effects([{'name': 'sensor_noise'}])",
    ).replace("assert p.effects == []", "assert len(p.effects) == 1")
    out = subprocess.run(
        [sys.executable, "-c", code2], capture_output=True, text=True, check=True, timeout=60
    )
    assert "stipi_daemon.sim.effects.sensor_noise" in out.stdout


def test_cli_simulate(tmp_path: Path) -> None:
    rc = main(
        [
            "simulate",
            str(SCENES / "grade1.yaml"),
            "--out",
            str(tmp_path / "o"),
            "--resolution",
            "160x120",
            "--fps",
            "2",
            "--quiet",
        ]
    )
    assert rc == 0
    truth = json.loads((tmp_path / "o" / "ground_truth.json").read_text())
    assert truth["frame"]["fps"] == 2.0 and truth["calibration"]["area_scale"] == 0.0625
    assert main(["simulate", str(tmp_path / "missing.yaml"), "--out", str(tmp_path)]) == 2


def test_cli_simulate_never_replaces_an_earlier_rendering_silently(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "o"
    argv = ["simulate", str(SCENES / "grade1.yaml"), "--out", str(out)]
    small = ["--resolution", "160x120", "--fps", "2", "--quiet"]
    assert main([*argv, *small]) == 0
    before = (out / "ground_truth.json").read_bytes()
    assert main([*argv, *small, "--seed", "9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds an earlier rendering" in err[0] and "--overwrite" in err[0]
    assert (out / "ground_truth.json").read_bytes() == before  # nothing touched
    assert main([*argv, *small, "--seed", "9", "--overwrite"]) == 0
    assert json.loads((out / "ground_truth.json").read_text())["seed"] == 9


def test_cli_simulate_refuses_a_session_directory_and_a_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = tmp_path / "s"
    session.mkdir()
    (session / "manifest.json").write_text("{}")
    small = ["--resolution", "160x120", "--fps", "2", "--quiet", "--overwrite"]
    assert main(["simulate", str(SCENES / "grade1.yaml"), "--out", str(session), *small]) == 2
    assert "session directory" in capsys.readouterr().err
    assert sorted(p.name for p in session.iterdir()) == ["manifest.json"]
    f = tmp_path / "f"
    f.write_text("x")
    assert main(["simulate", str(SCENES / "grade1.yaml"), "--out", str(f), *small]) == 2
    assert "is a file" in capsys.readouterr().err
