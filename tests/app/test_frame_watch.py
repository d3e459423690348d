"""The frame watch: a warning once frames stop, a line when they come again or came late."""

from __future__ import annotations

from stipi_daemon.app.frame_watch import FRAME_SILENCE_WARN_S, FrameWatch, frame_gap_meaning
from stipi_daemon.measurement.outputs import Phase

REC = Phase.RECOVERY


def test_no_warning_before_the_first_frame_nor_while_frames_come() -> None:
    w = FrameWatch()
    assert w.tick(100.0, REC) is None  # no frame yet: the first-frame lag rule's business
    for k in range(60):
        t = 10.0 + k / 60
        assert w.frame(t, t, measured=True, phase=REC) is None
        assert w.tick(t + 0.05, REC) is None
    assert w.warning is None


def test_the_warning_comes_once_at_the_bound_and_says_what_it_means() -> None:
    w = FrameWatch()
    w.frame(30.0, 30.0, measured=True, phase=REC)
    assert w.tick(30.0 + FRAME_SILENCE_WARN_S - 0.01, REC) is None
    line = w.tick(30.0 + FRAME_SILENCE_WARN_S, REC)
    assert line is not None
    assert line.startswith(
        "frames not processed for 0.5 s (none since the frame captured at 30.00 s)"
    )
    assert "recovery time T_r" in line and "cannot be read inside this gap" in line
    assert w.warning == "frames not processed since 30.00 s"
    assert w.tick(31.0, REC) is None  # once per stretch
    again = w.frame(50.0, 30.1, measured=True, phase=REC)
    assert again is not None and again.startswith(
        "frames arrive again after 20.0 s without (30.00-50.00 s)"
    )
    assert w.warning is None
    assert w.tick(50.2, REC) is None
    assert w.tick(50.0 + FRAME_SILENCE_WARN_S, REC) is not None  # a new stretch


def test_frames_that_came_too_late_are_named_when_a_measured_one_follows() -> None:
    w = FrameWatch()
    w.frame(30.0, 30.0, measured=True, phase=REC)
    w.tick(31.0, REC)
    captures = [30.0 + (k + 1) / 60 for k in range(300)]
    first = w.frame(50.0, captures[0], measured=False, phase=REC)
    assert first is not None and first.startswith("frames arrive again")
    for c in captures[1:]:
        assert w.frame(50.0, c, measured=False, phase=REC) is None
    line = w.frame(50.0, 35.02, measured=True, phase=REC)
    assert line is not None
    assert line.startswith("300 frames captured 30.02-35.00 s came too late to be measured")
    assert w.frame(50.01, 35.03, measured=True, phase=REC) is None


def test_the_meaning_follows_the_phase() -> None:
    assert "T_r" in frame_gap_meaning(Phase.RECOVERY)
    assert "S_0" in frame_gap_meaning(Phase.PITTING)
    assert frame_gap_meaning(Phase.ARMED) == "no result is read from frames yet"
