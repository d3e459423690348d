"""The report's facts on gaps count from the records its figures draw."""

from __future__ import annotations

import numpy as np

from stipi_daemon.report.figures import force_figure, s_k_figure
from stipi_daemon.report.inputs import GapRecord, ReportInput
from stipi_daemon.report.series import gap_facts

FPS = 60.0


def _input(gap_records: tuple[GapRecord, ...]) -> ReportInput:
    """60 fps frames over 0-80 s without those captured in (20, 67) s, and 100 Hz force
    samples without 0.5 s from 10 s."""
    t = np.arange(0, 80 * FPS + 1) / FPS
    frames = t[(t <= 20.0) | (t >= 67.0)]
    f = np.arange(0, 8001) / 100.0
    force = f[(f < 10.0) | (f >= 10.5)]
    return ReportInput(
        session_id="s",
        status="complete",
        created_utc=None,
        frame_seq=np.arange(frames.size, dtype=np.int64),
        frame_times_s=frames,
        s_k_px=np.full(frames.size, 1000.0),
        force_times_s=force,
        force_n=np.zeros(force.size),
        transitions=(),
        summary={"run": {"gaps": 0, "dropped_frames": 0}},  # what the row said before
        config={},
        calibration={},
        gap_records=gap_records,
    )


def test_the_facts_count_the_gaps_the_figures_shade_and_the_gap_records() -> None:
    # the frames 20-67 s came too late (2819 frames between them at 60 fps), the force
    # samples 10.00-10.49 s were lost on the link
    records = (
        GapRecord("frames", 1201, 2819, 67.0, "processing_behind"),
        GapRecord("force", 1000, 50, 10.6, "link"),
    )
    inp = _input(records)
    facts = gap_facts(inp)
    assert facts == (
        "frames: 1 frame gap (longest 47.00 s; 2819 frames recorded missing: 2819 "
        "processing_behind); force: 1 force gap (longest 0.51 s; 50 samples recorded "
        "missing: 50 link)"
    )
    # the figures shade the same gaps
    assert len(s_k_figure(inp).gaps) == 1 and len(force_figure(inp).gaps) == 1
    assert round(s_k_figure(inp).gaps[0].duration_s, 2) == 47.0


def test_a_session_without_gaps_says_so() -> None:
    inp = _input(())
    inp = ReportInput(
        **{
            **inp.__dict__,
            "frame_times_s": np.arange(100) / FPS,
            "frame_seq": np.arange(100, dtype=np.int64),
            "s_k_px": np.zeros(100),
            "force_times_s": np.arange(100) / 100.0,
            "force_n": np.zeros(100),
        }
    )
    assert gap_facts(inp) == "frames: 0 frame gaps; force: 0 force gaps"
