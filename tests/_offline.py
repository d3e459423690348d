"""Recorded inputs for the offline-analysis tests: real sessions, simulator output, truncation.

Sessions are recorded by the real runner (simulated grade-I scene, accelerated, a few
seconds); an interrupted session is a real :class:`SessionWriter` that stops before
``finish`` (as a killed recorder leaves it: state ``recording``, no live writer).
"""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from tests.daemon._support import kept_up

REPO_ROOT = Path(__file__).resolve().parent.parent
SCENES = REPO_ROOT / "configs" / "scenes"


def run_with_whole_video(config: Path) -> Path:
    """Run the daemon on ``config``; return its session, whose video holds every frame.

    A simulated run waits for the daemon (its clock is a
    :class:`~stipi_daemon.clock.VirtualClock`), so the encoders never leave a frame out,
    however busy the machine is.
    """
    session = run_measurement(load_config(config), quiet=True).session_dir
    assert session is not None
    summary = json.loads((Path(session) / "summary.json").read_text())
    assert kept_up(summary), summary["run"]
    return Path(session)


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
        # hold starts when the force enters the band (~0.9 s into the 1 s approach).
        doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
        doc["force_profile"]["hold_s"] = 16.0
        doc["name"] = "grade1_daemon"
        scene = directory / "grade1_daemon.yaml"
        scene.write_text(yaml.safe_dump(doc))
    scene_path = str(scene)
    cfg: dict[str, object] = {
        "probe": {"transport": {"kind": "emulated", "scene": scene_path}},
        "camera": {"kind": "simulator", "scene": scene_path},
        # the video as the demo keeps it, the ROI's gray box; as fast as the daemon goes
        "storage": {"root": str(directory / "sessions"), "min_free_mb": 0, "video_roi_only": True},
        "run": {"speed": 0.0},
    }
    if calibration is not None:
        cfg["calibration"] = str(calibration)
    # A simulated run waits for the daemon: every frame is measured and in the video.
    path = directory / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    session = run_measurement(load_config(path), quiet=True).session_dir
    assert session is not None
    summary = json.loads((Path(session) / "summary.json").read_text())
    assert kept_up(summary), summary["run"]
    return Path(session)


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
