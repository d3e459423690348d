"""Sessions with video for the re-analysis tests: one daemon recording, then clones.

:func:`record_session` runs the real daemon (emulated probe, simulator camera, the short
grade-I scene of ``tests/daemon/_support.py`` at 160x120, its MJPG video passed through)
once; the recording is kept under pytest's base temporary directory and reused by every test of the
run. :func:`clone_session` writes a new session with the storage writer from a recorded
one: another session id and site, the same rows of every table (read back with the
reader, in insertion order) and a copy of its video, so that each clone is a distinct
session (its manifest, hence its data hash, differs) that ``analyze --recompute-sk`` reads
exactly as it reads the original. Nothing is written by hand besides what the writer is
given.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.schema import (
    CLOCK_PROBES,
    FORCE_SAMPLES,
    FRAMES,
    GAPS,
    LIVE_PARAMETERS,
    VIDEO_FRAMES,
)
from stipi_daemon.study.index import index_sessions
from tests._offline import run_with_whole_video
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config


def record_session(directory: Path, lossless: bool = False) -> Path:
    """Record one session with video into ``directory/sessions`` (the daemon, for real),
    every frame in its video.

    The tests' recording has an MJPG camera, whose JPEGs are stored as they came
    (passthrough: muxed as they arrive, never left out, and recounted exactly as the camera
    decoded them). ``lossless`` (the benchmark's): raw frames encoded with FFV1, whose
    encoder thread leaves frames out when other load starves it (storage/video.py), so the
    recording is made again until its video holds every frame
    (:func:`tests._offline.run_with_whole_video`).
    """
    scene = short_scene(directory, width=160, height=120)
    if not lossless:
        doc = yaml.safe_load(scene.read_text())
        doc["camera"]["pixel_format"] = "mjpg"
        scene.write_text(yaml.safe_dump(doc))
    doc = {
        "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
        "camera": {"kind": "simulator", "scene": str(scene)},
        "measurement": SHORT_MEASUREMENT,
        "run": {"speed": 0.0},
    }
    path = write_config(directory, doc)
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"].update({"video": "lossless" if lossless else "passthrough"})
    path.write_text(yaml.safe_dump(cfg))
    return run_with_whole_video(path)


def recorded_session(factory: pytest.TempPathFactory) -> Path:
    """The run's one recorded session (recorded on first use)."""
    base = factory.getbasetemp() / "reanalyze-recording"
    done = base / "session.txt"
    if done.is_file():
        return Path(done.read_text())
    if base.exists():
        shutil.rmtree(base)
    base.mkdir()
    session = record_session(base)
    done.write_text(str(session))
    return session


def clone_session(source: Path, root: Path, session_id: str, site: str) -> Path:
    """A new session ``root/session_id`` at ``site`` holding ``source``'s data and video."""
    with SessionReader(source) as reader:
        manifest = reader.manifest
        summary = reader.summary
        status = reader.status
        rows = {
            t: list(reader.iter_rows(t))
            for t in (FORCE_SAMPLES, FRAMES, VIDEO_FRAMES, GAPS, CLOCK_PROBES, LIVE_PARAMETERS)
        }
        events = reader.events()
        transitions = reader.transitions()
        video = reader.video_path
    metadata = dict(manifest.get("metadata") or {}) | {"site": site}
    writer = SessionWriter.create(
        root,
        manifest["config"],
        manifest["calibration"],
        manifest.get("firmware"),
        session_id=session_id,
        video=video is not None,
        options=StorageOptions(min_free_bytes=0, background_commit=False),
        metadata=metadata,
    )
    with writer:
        writer.add_force_samples(rows[FORCE_SAMPLES])
        writer.add_frames(rows[FRAMES])
        writer.add_video_frames(rows[VIDEO_FRAMES])
        for g in rows[GAPS]:
            writer.add_gap(*g)
        for c in rows[CLOCK_PROBES]:
            writer.add_clock_probe(*c)
        for e in events:
            writer.add_event(e.t_host_s, e.kind, e.detail)
        for t in transitions:
            writer.add_transition(*t)
        if video is not None and writer.video_path is not None:
            shutil.copyfile(video, writer.video_path)
        writer.finish(str(status), summary)
    return root / session_id


def make_study(
    factory: pytest.TempPathFactory, directory: Path, n: int, *, corrupt: tuple[int, ...] = ()
) -> Path:
    """A dataset of ``n`` clones of the recorded session (sites alternate); the video of
    each clone in ``corrupt`` is overwritten with bytes that are no video. Returns DATASET."""
    source = recorded_session(factory)
    root = directory / "sessions"
    for i in range(n):
        clone = clone_session(source, root, f"R{i:03d}", ("Lab A", "Clinic B")[i % 2])
        if i in corrupt:
            video = clone / "video.mkv"
            video.write_bytes(b"not a video\n" * 64)
    dataset = directory / "study"
    report = index_sessions([root], dataset)
    assert not report.skipped, report.skipped
    return dataset
