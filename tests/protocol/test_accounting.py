"""SampleAccounting: sent == received + lost, exactly, with gaps located."""

from __future__ import annotations

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.errors import ProtocolError
from stipi_daemon.protocol import (
    FrameDecoder,
    SampleAccounting,
    SampleGap,
    Samples,
    Status,
    encode_frame,
)


def test_contiguous_batches_lose_nothing() -> None:
    acc = SampleAccounting()
    for i in range(10):
        assert acc.observe(100 + 10 * i, 10) is None
    assert (acc.sent, acc.received, acc.lost, acc.gaps, acc.runs) == (100, 100, 0, (), 1)
    assert acc.next_index == 200


def test_gap_located_exactly() -> None:
    acc = SampleAccounting()
    acc.observe(0, 10)
    gap = acc.observe(25, 5)
    assert gap == SampleGap(start_index=10, count=15, run=0, link_frames_lost=0)
    assert (acc.sent, acc.received, acc.lost) == (30, 15, 15)


def test_index_wrap_is_not_a_gap() -> None:
    acc = SampleAccounting()
    acc.observe(2**32 - 10, 10)
    assert acc.observe(0, 10) is None
    gap = acc.observe(12, 1)
    assert gap is not None and gap.start_index == 10 and gap.count == 2
    assert (acc.sent, acc.received, acc.lost) == (23, 21, 2)


def test_gap_across_index_wrap() -> None:
    acc = SampleAccounting()
    acc.observe(2**32 - 20, 10)
    gap = acc.observe(5, 3)
    assert gap == SampleGap(2**32 - 10, 15, 0, 0)


def test_backwards_index_starts_new_run() -> None:
    acc = SampleAccounting()
    acc.observe(5000, 10)
    assert acc.observe(0, 10) is None
    acc.observe(20, 10)
    assert acc.runs == 2 and acc.gaps == (SampleGap(10, 10, 1, 0),)
    assert (acc.sent, acc.received, acc.lost) == (40, 30, 10)
    acc.observe(30, 1, restart=True)
    assert acc.runs == 3


@pytest.mark.parametrize(
    ("first_index", "count", "field"),
    [(-1, 1, "first_index"), (2**32, 1, "first_index"), (0, 0, "count"), (0, 25, "count")],
)
def test_range_checks(first_index: int, count: int, field: str) -> None:
    with pytest.raises(ProtocolError, match=field):
        SampleAccounting().observe(first_index, count)


def test_note_link_loss() -> None:
    acc = SampleAccounting()
    acc.observe(0, 1)
    acc.note_link_loss(2)
    with pytest.raises(ProtocolError, match="frames"):
        acc.note_link_loss(-1)
    assert acc.observe(5, 1) == SampleGap(1, 4, 0, 2)


@given(
    st.integers(0, 2**32 - 1),
    st.lists(st.tuples(st.integers(1, 24), st.integers(0, 50)), min_size=1, max_size=100),
)
def test_sent_minus_received_is_exact(start: int, batches: list[tuple[int, int]]) -> None:
    acc = SampleAccounting()
    index = start
    lost = 0
    for count, skip_after in batches:
        acc.observe(index % 2**32, count)
        index += count + skip_after
        lost += skip_after
    lost -= batches[-1][1]  # losses after the last batch are not known yet
    assert acc.lost == lost
    assert acc.received == sum(c for c, _ in batches)
    assert acc.sent - acc.received == lost == sum(g.count for g in acc.gaps)


def test_through_decoder_link_losses_attributed() -> None:
    """Frames lost on the link vs samples dropped in the probe, end to end."""
    rng = random.Random(5)
    wires = []
    index = 0
    sent_indices = []
    for seq in range(300):
        if seq % 7 == 3:
            wires.append(encode_frame(Status(0, 100, index, 5000), seq, seq))
            continue
        count = rng.randint(1, 24)
        if seq % 50 == 10:
            index += 5  # the probe dropped 5 samples (ring buffer full)
        wires.append(encode_frame(Samples(index, 1000, (1,) * count), seq, seq))
        sent_indices.append((seq, index, count))
        index += count
    lost_seqs = {20, 21, 22, 24, 100, 101}  # frames lost on the link (24 is a STATUS)
    stream = b"".join(w for s, w in enumerate(wires) if s not in lost_seqs)
    decoder = FrameDecoder()
    acc = SampleAccounting()
    for i in range(0, len(stream), 20):
        for frame in decoder.feed(stream[i : i + 20]):
            acc.observe_frame(frame)
    received = sum(c for s, _, c in sent_indices if s not in lost_seqs)
    first = sent_indices[0][1]
    _, last_index, last_count = sent_indices[-1]
    assert acc.received == received
    assert acc.sent == last_index + last_count - first
    assert acc.lost == acc.sent - received
    link_gaps = [g for g in acc.gaps if g.link_frames_lost]
    probe_gaps = [g for g in acc.gaps if not g.link_frames_lost]
    # a lost STATUS alone (24) loses no sample: no gap; 101 is a STATUS next to SAMPLES 100
    assert [g.link_frames_lost for g in link_gaps] == [3, 2]
    lost_samples = sum(c for s, _, c in sent_indices if s in lost_seqs)
    assert sum(g.count for g in link_gaps) == lost_samples
    assert {g.count for g in probe_gaps} == {5}
    assert decoder.stats.frames_lost == len(lost_seqs)
