"""Frames left out of the session video are said in the verdict, not an exit status."""

from __future__ import annotations

from stipi_daemon.app.finish import note_video_left_out


def test_frames_left_out_are_said_in_the_verdict_line_and_notes() -> None:
    summary = {
        "verdict": {"status": "complete", "line": "Complete: every result is valid."},
        "notes": ["T_0 at the frame that shows the release"],
    }
    noted = note_video_left_out(summary, 3)
    assert noted["verdict"]["status"] == "complete"  # the results do not change
    assert noted["verdict"]["line"].startswith("Complete: every result is valid. Video: 3")
    assert "3 frames left out of the session video" in noted["notes"][-1]
    assert noted["notes"][0] == summary["notes"][0]
    assert summary["verdict"]["line"] == "Complete: every result is valid."  # not changed


def test_no_frame_left_out_changes_nothing() -> None:
    summary = {"verdict": {"status": "flagged", "line": "x"}, "notes": []}
    assert note_video_left_out(summary, 0) is summary
