"""Clock unwrapping across 2^32 µs and u16 sequence tracking across 65535 → 0."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.protocol import (
    SeqEvent,
    SequenceTracker,
    TimestampUnwrapper,
    seq_distance,
    unwrap_t_us,
)

U32 = 2**32


def test_unwrap_first_value_is_raw() -> None:
    assert unwrap_t_us(None, 123) == 123


def test_unwrap_across_wrap() -> None:
    u = TimestampUnwrapper()
    values = [U32 - 2_000_000, U32 - 1, 0, 999_999, 2_000_000]
    out = [u.unwrap(v) for v in values]
    assert out == [U32 - 2_000_000, U32 - 1, U32, U32 + 999_999, U32 + 2_000_000]
    assert u.wraps == 1


def test_unwrap_slightly_older_across_wrap_goes_back() -> None:
    u = TimestampUnwrapper()
    assert u.unwrap(5) == 5
    assert u.unwrap(U32 - 10) == -10  # 15 µs older than the reference, before the wrap
    assert u.unwrap(20) == 20
    assert u.wraps == 0
    u2 = TimestampUnwrapper()
    u2.unwrap(U32 - 5)
    assert u2.unwrap(3) == U32 + 3
    assert u2.unwrap(U32 - 8) == U32 - 8  # older frame after the wrap: before it
    assert u2.peek(10) == U32 + 10


def test_unwrap_half_range_boundary() -> None:
    assert unwrap_t_us(0, 2**31 - 1) == 2**31 - 1  # forward, just inside
    assert unwrap_t_us(0, 2**31) == -(2**31)  # exactly half: treated as older
    with pytest.raises(ValueError, match="raw_us"):
        unwrap_t_us(0, U32)


@given(
    st.integers(0, 2**40),
    st.lists(st.integers(-(2**31) + 1, 2**31 - 1), min_size=1, max_size=50),
)
def test_unwrap_recovers_true_time_for_steps_below_half_range(
    start_us: int, steps: list[int]
) -> None:
    """Any sequence whose consecutive true times differ by less than 2^31 µs unwraps exactly."""
    u = TimestampUnwrapper()
    true_t = start_us
    first = u.unwrap(true_t % U32)
    offset = true_t - first  # the unwrapper cannot know whole wraps before the first frame
    assert offset % U32 == 0
    for step in steps:
        true_t += step
        assert u.unwrap(true_t % U32) + offset == true_t


def test_unwrap_70_hours_of_one_second_heartbeats() -> None:
    u = TimestampUnwrapper()
    t = 0
    for _ in range(70 * 3600):
        t += 1_000_003
        got = u.unwrap(t % U32)
    assert got == t
    assert u.wraps == t // U32 == 58


def test_seq_distance() -> None:
    assert seq_distance(0, 65535) == 1
    assert seq_distance(65535, 0) == 65535
    assert seq_distance(5, 5) == 0


def test_tracker_in_order_across_wrap() -> None:
    t = SequenceTracker()
    assert t.observe(65534).event == SeqEvent.FIRST
    assert t.observe(65535).event == SeqEvent.IN_ORDER
    obs = t.observe(0)
    assert obs.event == SeqEvent.IN_ORDER and obs.wrapped and obs.lost == 0
    assert t.observe(1) == type(obs)(SeqEvent.IN_ORDER, 0, False)
    assert t.expected == 2


def test_tracker_gap_across_wrap_counts_exactly() -> None:
    t = SequenceTracker()
    t.observe(65530)
    obs = t.observe(4)  # 65531..65535, 0..3 lost: 9 frames
    assert obs.event == SeqEvent.GAP and obs.lost == 9 and obs.wrapped


def test_tracker_largest_gap_and_older_boundary() -> None:
    t = SequenceTracker()
    t.observe(0)
    assert t.observe(1 + 32767).lost == 32767  # d = 32767: still a gap
    t2 = SequenceTracker()
    t2.observe(0)
    assert t2.observe(1 + 32768).event == SeqEvent.RESTART  # d = 32768: older


def test_tracker_duplicates_and_restart() -> None:
    t = SequenceTracker()
    for s in range(10):
        t.observe(s, bytes([s]))
    dup = t.observe(7, bytes([7]))
    assert dup.event == SeqEvent.DUPLICATE and not dup.deliver
    assert t.expected == 10  # a duplicate does not move the state
    assert t.observe(9, None).event == SeqEvent.DUPLICATE  # no fingerprint: seq alone
    restart = t.observe(3, b"different content")
    assert restart.event == SeqEvent.RESTART and restart.deliver
    assert t.expected == 4
    assert t.observe(4).event == SeqEvent.IN_ORDER
    assert t.observe(0, bytes([0])).event == SeqEvent.RESTART  # pre-restart history is gone


def test_tracker_restart_hint_overrides_order_not_duplicate() -> None:
    t = SequenceTracker()
    t.observe(1, b"a")
    assert t.observe(2, b"b", restart=True).event == SeqEvent.RESTART
    assert t.observe(2, b"b", restart=True).event == SeqEvent.DUPLICATE


def test_tracker_history_is_bounded() -> None:
    t = SequenceTracker(history=4)
    for s in range(10):
        t.observe(s, b"x")
    assert t.observe(6, b"x").event == SeqEvent.DUPLICATE
    assert t.observe(5, b"x").event == SeqEvent.RESTART  # forgotten: not a duplicate
    with pytest.raises(ValueError, match="history"):
        SequenceTracker(history=0)
    with pytest.raises(ValueError, match="seq"):
        t.observe(65536)


@given(st.integers(0, 65535), st.lists(st.integers(1, 40), max_size=60))
def test_tracker_sum_of_gaps_equals_frames_skipped(start: int, steps: list[int]) -> None:
    t = SequenceTracker()
    t.observe(start)
    seq, lost, wraps = start, 0, 0
    for step in steps:
        new = (seq + step) % 65536
        obs = t.observe(new)
        lost += obs.lost
        wraps += obs.wrapped
        assert obs.event == (SeqEvent.IN_ORDER if step == 1 else SeqEvent.GAP)
        seq = new
    assert lost == sum(steps) - len(steps)
    assert wraps == (start + sum(steps)) // 65536
