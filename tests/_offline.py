"""Recorded inputs for the offline-analysis tests: real sessions, simulator output, truncation.

Sessions are recorded by the real runner (simulated grade-I scene, accelerated, a few
seconds); an interrupted session is a real :class:`SessionWriter` that stops before
``finish`` (as a killed recorder leaves it: state ``recording``, no live writer).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from tests.daemon._support import kept_up

REPO_ROOT = Path(__file__).resolve().parent.parent
SCENES = REPO_ROOT / "configs" / "scenes"
#: Recordings made at most by :func:`run_with_whole_video` before it gives up [-].
VIDEO_ATTEMPTS = 3


def run_with_whole_video(config: Path) -> Path:
    """Run the daemon on ``config``; return a session whose video holds every frame.

    The lossless encoder runs at a lower priority than the measurement and leaves frames
    out when other load starves it (counted in the summary's ``run.video.left_out``:
    storage/video.py), as it should on a busy lab PC. The tests that read the video back
    need every frame, so a recording that left some out is removed and made again, at
    most :data:`VIDEO_ATTEMPTS` times; then the test fails with the counts.
    """
    left_out: list[int] = []
    for _ in range(VIDEO_ATTEMPTS):
        session = run_measurement(load_config(config), quiet=True).session_dir
        assert session is not None
        summary = json.loads((Path(session) / "summary.json").read_text())
        n = int((summary.get("run", {}).get("video") or {}).get("left_out") or 0)
        if n == 0:
            return Path(session)
        left_out.append(n)
        shutil.rmtree(session)
    raise AssertionError(f"every recording left frames out of its video: {left_out}")


def short_scene(directory: Path, name: str = "grade1", recovery_s: float = 14.0) -> Path:
    """A copy of a grade scene with a shorter recovery (grade I settles within ~3 s)."""
    doc = yaml.safe_load((SCENES / f"{name}.yaml").read_text())
    doc["force_profile"]["recovery_s"] = recovery_s
    doc["name"] = f"{name}_short"
    path = directory / f"{name}_short.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def record_session(
    directory: Path, scene: Path | None = None, calibration: Path | None = None
) -> Path:
    """Record one simulated measurement with the live daemon; returns the session dir.

    The probe is the emulated Feather on a pty (real pyserial path), the camera the
    simulator; both accelerated. ``calibration`` (a calibration file) replaces the
    scene's own.
    """
    if scene is None:
        # Grade I with an operator who follows the daemon's prompts: the daemon's 15 s
        # hold starts when the force enters the band (~0.9 s into the 1 s approach), so
        # the paper's 1 s + 14 s profile would let go before the release prompt.
        doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
        doc["force_profile"]["hold_s"] = 16.0
        doc["name"] = "grade1_daemon"
        scene = directory / "grade1_daemon.yaml"
        scene.write_text(yaml.safe_dump(doc))
    scene_path = str(scene)
    cfg: dict[str, object] = {
        "probe": {"transport": {"kind": "emulated", "scene": scene_path}},
        "camera": {"kind": "simulator", "scene": scene_path},
        # the video as the demo keeps it, the ROI's gray box: whole BGR frames encoded at
        # speed 8 fall behind on a 2-CPU machine (late frames stored as gaps)
        "storage": {"root": str(directory / "sessions"), "min_free_mb": 0, "video_roi_only": True},
        "run": {"speed": 8.0},
    }
    if calibration is not None:
        cfg["calibration"] = str(calibration)
    # The tests read a whole recording: one that did not keep up with its clock on a starved
    # machine (tests.daemon._support.kept_up: frames dropped, stored late or left out of the
    # video) is removed and made again at half the speed, down to speed 1 (the test
    # measures the analysis, not spare CPU); then the test fails with the counts.
    lost: list[tuple[float, int]] = []
    speed = 8.0
    while True:
        cfg["run"] = {"speed": speed}
        path = directory / "config.yaml"
        path.write_text(yaml.safe_dump(cfg))
        session = run_measurement(load_config(path), quiet=True).session_dir
        assert session is not None
        summary = json.loads((Path(session) / "summary.json").read_text())
        if kept_up(summary):
            return Path(session)
        run = summary["run"]
        left_out = int((run.get("video") or {}).get("left_out", 0))
        lost.append((speed, int(run["dropped_frames"]) + int(run["late_frames"]) + left_out))
        if speed <= 1.0:
            raise AssertionError(f"every recording lost camera frames (speed, frames): {lost}")
        shutil.rmtree(session)
        speed /= 2.0


def interrupted_copy(source: Path, root: Path, session_id: str, until_s: float) -> Path:
    """Copy a session's rows up to ``until_s`` into a new session left unfinished."""
    with SessionReader(source) as reader:
        manifest = reader.manifest
        force = reader.force_samples()
        frames = reader.frames()
        transitions = reader.transitions()
    with SessionWriter.create(
        root,
        manifest["config"],
        manifest["calibration"],
        manifest["firmware"],
        session_id=session_id,
        options=StorageOptions(min_free_bytes=0),
    ) as writer:
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
    return root / session_id
