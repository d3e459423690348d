"""Fixtures for the storage tests: a fully populated, finished session."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stipi_daemon.storage import SessionWriter, StorageOptions
from stipi_daemon.storage.video import VideoRecorder

CONFIG: dict[str, Any] = {"transport": "sim:scenes/grade3.yaml", "camera": {"fps": 60}}
CALIBRATION: dict[str, Any] = {"alpha1": 1.2e-9, "alpha2": 3.4e-4, "c1": 120.0, "c2": 55.0}
FIRMWARE: dict[str, Any] = {"proto": 1, "fw": "1.0.0", "adc_bits": 10}
#: What the caller adds to the manifest's software versions (the daemon names its S_k kernel).
SOFTWARE: dict[str, str | None] = {"sk_kernel": "test-kernel"}
SUMMARY: dict[str, Any] = {
    "severity": {"severity": "severe", "nearest_grade": "3+", "decay_rate_per_s": 0.02},
    "d_p_mm": 4.2,
    "t_r_s": 31.5,
    "flags": ["not_settled"],
}

#: Options for tests: no free-space requirement, default interval.
OPTIONS = StorageOptions(min_free_bytes=0)


@dataclass
class Recorded:
    """A finished session and every row written into it, in column order."""

    root: Path
    session_id: str
    rows: dict[str, list[tuple[Any, ...]]]

    @property
    def directory(self) -> Path:
        return self.root / self.session_id


def write_full_session(
    root: Path,
    session_id: str = "s-full",
    *,
    finish: str | None = "complete",
    summary: dict[str, Any] | None = None,
) -> Recorded:
    """Write every kind of row (edge values included) and optionally finish the session
    (with ``summary``, default :data:`SUMMARY`)."""
    t0 = 1000.0
    force = [
        (i, 500 + i, (4_294_967_000 + 1000 * i) % 2**32, 4_294_967_000 + 1000 * i, t0 + i * 1e-3, f)
        for i, f in enumerate([0.0, 1.5, None, -0.25, 16.0, 15.999999999999998])
    ]
    frames = [
        (0, t0, t0 + 0.004, 0, ""),
        (1, t0 + 1 / 60, t0 + 1 / 60 + 0.004, 123_456, "saturated_frame"),
        (3, t0 + 3 / 60, t0 + 3 / 60 + 0.004, 99, "saturated_frame,roi_clipped"),
    ]
    events: list[tuple[float, str, dict[str, Any]]] = [
        (t0, "probe_status", {"supply_mv": 4100, "flags": [1, 0]}),
        (t0 + 0.5, "note", {"text": "operator: patient moved, ünïcode ok"}),
    ]
    transitions = [
        (t0 + 0.1, "idle", "pressing", "force above 2 N"),
        (t0 + 15.1, "pressing", "released", "force below 0.5 N"),
    ]
    gaps = [("force", 6, 3, t0 + 0.2, "link"), ("frames", 2, 1, t0 + 0.3, "camera")]
    clock = [(4_294_967_000, 4_294_967_000, t0), (704, 4_294_968_000 + 704, t0 + 0.001704)]
    live = [
        (t0 + 1.0, "d_p_mm", 4.2),
        (t0 + 1.0, "e_kpa", None),
        (t0 + 2.0, "t_r_s", math.inf),
    ]
    with SessionWriter.create(
        root,
        CONFIG,
        CALIBRATION,
        FIRMWARE,
        session_id=session_id,
        video=True,
        options=OPTIONS,
        software=SOFTWARE,
    ) as writer:
        writer.add_force_samples(force)
        writer.add_frames(frames[:1])
        writer.add_frames([(s, tc, th, k, f.split(",")) for s, tc, th, k, f in frames[1:]])
        for t, kind, detail in events:
            writer.add_event(t, kind, detail)
        for t, old, new, reason in transitions:
            writer.add_transition(t, old, new, reason)
        for stream, start, count, t, cause in gaps:
            writer.add_gap(stream, start, count, t, cause)
        for raw, unwrapped, host in clock:
            writer.add_clock_probe(raw, unwrapped, host)
        writer.add_live_parameters(t0 + 1.0, {"d_p_mm": 4.2, "e_kpa": float("nan")})
        writer.add_live_parameters(t0 + 2.0, {"t_r_s": math.inf})
        assert writer.video_path is not None
        recorder = VideoRecorder(writer.video_path, writer, "lossless")
        for seq, t_capture, *_ in frames:
            recorder.record(seq, t_capture, np.full((8, 8), seq, dtype=np.uint8), None)
        recorder.close()
        events.append(
            (
                frames[0][1],
                "video_started",
                {
                    "file": "video.mkv",
                    "mode": "lossless",
                    "codec": "ffv1",
                    "image": "gray",
                    "size": [8, 8],
                    "crop": None,
                    "t0_s": frames[0][1],
                },
            )
        )
        if finish is not None:
            writer.finish(finish, SUMMARY if summary is None else summary)
    return Recorded(
        root,
        session_id,
        {
            "force_samples": force,
            "frames": frames,
            "events": events,
            "transitions": transitions,
            "gaps": gaps,
            "clock_probes": clock,
            "live_parameters": live,
            "video_frames": [
                (seq, i, round((tc - t0) * 1000), tc) for i, (seq, tc, *_) in enumerate(frames)
            ],
        },
    )


@pytest.fixture
def recorded(tmp_path: Path) -> Recorded:
    return write_full_session(tmp_path / "sessions")
