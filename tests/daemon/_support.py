"""Shared pieces of the daemon's end-to-end tests: a short scene and config files.

The scene is the grade-I phantom with the demo's operator timing shortened: 1 s approach,
5.5 s hold (the daemon prompts the release after 5 s in the force band, the operator
releases 0.6 s later, as in ``configs/scenes/demo_grade3.yaml``), 20 s of recovery; the
measurement config asks for that 5 s pitting time. Grade I settles within ~3 s, so a
measurement ends about 19 s of scene time after the start (settling test: 10 s hold).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from tests.conftest import REPO_ROOT

SCENES = REPO_ROOT / "configs" / "scenes"

#: The measurement section matching :func:`short_scene`.
SHORT_MEASUREMENT: dict[str, Any] = {"pitting_duration_s": 5.0, "recovery_max_s": 20.0}
#: The simulator's tolerances against a scene's ground truth (relative errors, for
#: :func:`check_against_truth`): D_p, F_r and E 1 %, the fitted tau 2 %.
TRUTH_TOLERANCES: dict[str, float] = {
    "depth_mm": 0.01,
    "rebound_force_n": 0.01,
    "time_constant_s": 0.02,
    "elasticity_kpa": 0.01,
}


def kept_up(summary: dict[str, Any]) -> bool:
    """The run kept up with its clock: its camera delivered every frame (no stall, after
    which a live camera, as the simulator is, resumes at the current time; nothing dropped),
    every frame was handled in time (none stored as a gap for being late) and went into the
    video, and the acquisition did not end for falling behind. On a loaded machine the simulated
    camera at an accelerated speed can fall behind the session clock; the daemon then flags
    or refuses what that changes, so a test comparing two runs frame by frame makes such a
    run again (at a lower speed) instead of comparing it."""
    run, cam = summary["run"], summary["run"]["camera"]
    lost = cam["stalls"] or cam["dropped"] or cam["queue_dropped"] or run["dropped_frames"]
    # frames handled too late are stored as gaps (processing_behind), frames the encoders
    # could not take are left out of the video
    late = run.get("late_frames", 0) or (run.get("video") or {}).get("left_out", 0)
    behind = str(summary.get("end_reason") or "").startswith("falling behind")
    return not lost and not late and not behind


def short_scene(directory: Path, *, width: int = 320, height: int = 240) -> Path:
    """Write the short grade-I scene (smaller frames: faster rendering) and return its path."""
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["name"] = "grade1_daemon_e2e"
    doc["force_profile"].update({"approach_s": 1.0, "hold_s": 5.5, "recovery_s": 20.0})
    doc["camera"].update({"width": width, "height": height})
    path = directory / "grade1_daemon_e2e.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def write_config(directory: Path, doc: dict[str, Any], name: str = "daemon.yaml") -> Path:
    """Write a daemon config file; storage goes under ``directory/sessions`` by default."""
    doc = {"storage": {"root": str(directory / "sessions"), "min_free_mb": 0}, **doc}
    path = directory / name
    path.write_text(yaml.safe_dump(doc))
    return path


def check_against_truth(summary: dict[str, Any], *, rel: dict[str, float]) -> dict[str, float]:
    """Relative errors of the results against the summary's ground truth; assert ``rel``.

    ``rel`` maps ground-truth keys (``depth_mm``, ``rebound_force_n``, ``time_constant_s``,
    ``elasticity_kpa``) to the largest relative error allowed.
    """
    res, gt = summary["results"], summary["ground_truth"]
    measured = {
        "depth_mm": res["pitting"]["depth_mm"],
        "rebound_force_n": res["pitting"]["rebound_force_n"],
        "time_constant_s": res["fitted_recovery"]["tau_s"],
        "elasticity_kpa": res["paper_estimator"]["elasticity_kpa"],
    }
    errors = {k: abs(measured[k] / gt[k] - 1.0) for k in rel}
    bad = {k: (measured[k], gt[k], errors[k]) for k in rel if errors[k] > rel[k]}
    assert not bad, f"results off the ground truth (measured, truth, rel. error): {bad}"
    return errors


def short_config(
    directory: Path,
    storage: dict[str, Any],
    *,
    pixel_format: str | None = None,
    speed: float = 0.0,
    measurement: dict[str, Any] | None = None,
) -> Path:
    """Write the config of one short measurement of the 160x120 short scene
    (:func:`short_scene`; camera ``pixel_format``, None: the scene's own) at clock
    ``speed``, ``storage`` added to its storage section and ``measurement`` to
    :data:`SHORT_MEASUREMENT`; returns the config's path."""
    scene = short_scene(directory, width=160, height=120)
    if pixel_format is not None:
        doc = yaml.safe_load(scene.read_text())
        doc["camera"]["pixel_format"] = pixel_format
        scene.write_text(yaml.safe_dump(doc))
    path = write_config(
        directory,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": {**SHORT_MEASUREMENT, **(measurement or {})},
            "run": {"speed": speed},
        },
    )
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"].update(storage)
    path.write_text(yaml.safe_dump(cfg))
    return path


def short_session(
    directory: Path,
    storage: dict[str, Any],
    *,
    pixel_format: str | None = None,
    speed: float = 0.0,
    measurement: dict[str, Any] | None = None,
) -> Path:
    """Record the measurement of :func:`short_config` (quietly); returns the session
    directory."""
    from stipi_daemon.app.config import load_config
    from stipi_daemon.app.daemon import run_measurement

    path = short_config(
        directory, storage, pixel_format=pixel_format, speed=speed, measurement=measurement
    )
    session = run_measurement(load_config(path), quiet=True).session_dir
    assert session is not None
    return Path(session)


def session_record(session_dir: Path) -> dict[str, Any]:
    """Every row of every data table of a session (in storage order) and its summary."""
    import json
    import sqlite3

    con = sqlite3.connect(f"file:{session_dir / 'session.sqlite'}?mode=ro", uri=True)
    try:
        names = [
            n
            for (n,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            if n != "meta"
        ]
        tables = {n: con.execute(f"SELECT * FROM {n} ORDER BY id").fetchall() for n in names}
    finally:
        con.close()
    summary = json.loads((session_dir / "summary.json").read_text())
    return {"tables": tables, "summary": summary}


#: The measurement section matching :func:`tiny_scene` (2.5 s in the band, 6 s window).
TINY_MEASUREMENT: dict[str, Any] = {
    "pitting_duration_s": 2.5,
    "recovery_max_s": 6.0,
    "settle_hold_s": 3.0,
    "stop_when_settled": False,
}


def tiny_scene(directory: Path, name: str) -> Path:
    """Write a tiny grade-I scene (0.5 s approach, 3 s hold, 7 s recovery, 160x120 at
    60 fps) named ``name`` and return its path."""
    doc = yaml.safe_load((SCENES / "grade1.yaml").read_text())
    doc["name"] = name
    doc["force_profile"].update({"approach_s": 0.5, "hold_s": 3.0, "recovery_s": 7.0})
    doc["camera"].update({"width": 160, "height": 120})
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def tiny_config(directory: Path, scene: Path, **sections: dict[str, Any]) -> Path:
    """A config measuring :func:`tiny_scene` ``scene`` with the emulated probe and the
    simulator camera into ``directory/sessions`` (made), ``sections`` added."""
    directory.mkdir()
    doc: dict[str, Any] = {
        "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
        "camera": {"kind": "simulator", "scene": str(scene)},
        "measurement": TINY_MEASUREMENT,
        "storage": {"root": str(directory / "sessions"), "min_free_mb": 0},
        **sections,
    }
    return write_config(directory, doc)
