"""Time-ordered merging of force and frame streams."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.measurement.merge import TimeOrderedMerger


def test_releases_in_time_order_once_every_stream_passed() -> None:
    m: TimeOrderedMerger[str] = TimeOrderedMerger(["force", "frame"], max_hold_s=10.0)
    m.push("frame", 1.0, "f1", now_s=1.0)
    m.push("frame", 2.0, "f2", now_s=2.0)
    assert m.pop_ready(2.0) == []  # force has said nothing yet
    m.push("force", 1.5, "s1", now_s=2.1)
    assert m.pop_ready(2.1) == [("frame", "f1"), ("force", "s1")]
    m.push("force", 2.0, "s2", now_s=2.2)
    # Force first at equal times; the frame waits until force has passed 2.0 (more force
    # samples stamped 2.0 could still come).
    assert m.pop_ready(2.2) == [("force", "s2")]
    m.push("force", 2.01, "s3", now_s=2.3)
    assert m.pop_ready(2.3) == [("frame", "f2")]
    assert m.drain() == [("force", "s3")]


def test_stalled_stream_holds_at_most_max_hold() -> None:
    m: TimeOrderedMerger[int] = TimeOrderedMerger(["force", "frame"], max_hold_s=0.5)
    m.push("force", 0.0, 0, now_s=0.0)
    m.push("frame", 0.1, 1, now_s=0.1)
    assert m.pop_ready(0.1) == [("force", 0)]
    assert m.pop_ready(0.59) == []
    assert m.oldest_pending_s() == 0.1
    assert m.pop_ready(0.6) == [("frame", 1)]
    assert m.released_by_timeout == 1
    assert m.oldest_pending_s() is None


def test_closed_stream_does_not_hold() -> None:
    m: TimeOrderedMerger[int] = TimeOrderedMerger(["force", "frame"], max_hold_s=100.0)
    m.push("frame", 5.0, 1, now_s=5.0)
    m.close("force")
    assert m.pop_ready(5.0) == [("frame", 1)]
    m.reopen("force")
    m.push("frame", 6.0, 2, now_s=6.0)
    assert m.pop_ready(6.0) == []
    assert m.drain() == [("frame", 2)]


PER_RANK = {"force": 0, "frame": 1}


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(["force", "frame"]), st.floats(0, 100)), max_size=60),
    st.lists(st.floats(0, 0.2), min_size=60, max_size=60),
)
def test_output_is_a_time_ordered_permutation(
    items: list[tuple[str, float]], delays: list[float]
) -> None:
    # Each stream delivers its own items in time order (as force batches and frames do),
    # with a random delivery delay.
    per: dict[str, list[float]] = {"force": [], "frame": []}
    for s, t in items:
        per[s].append(t)
    events = []
    for s, ts in per.items():
        arrival = 0.0
        for i, t in enumerate(sorted(ts)):
            arrival = max(arrival, t + delays[i % len(delays)])
            events.append((arrival, PER_RANK[s], i, s, t))
    events.sort()
    m: TimeOrderedMerger[float] = TimeOrderedMerger(["force", "frame"], max_hold_s=1e9)
    out: list[tuple[str, float]] = []
    for now, _, _, s, t in events:
        m.push(s, t, t, now_s=now)
        out += m.pop_ready(now)
    out += m.drain()
    assert sorted(out, key=lambda x: (x[1], x[0])) == out
    assert len(out) == len(events)
