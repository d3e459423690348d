"""Garbage on the link: bursts of 1-1000 random bytes and bit flips, between and inside frames.

A long stream of valid frames is damaged at known places: bursts of 1-1000 random bytes
(zeros included) between frames and inside frames, and 1-3 bit flips inside frames. The
frames that must survive are known exactly (untouched, and not merged with a burst's tail);
the decoder must deliver every one of those, in order, with exact loss counts. A damaged
frame passes the 16-bit CRC only by chance (about 2^-16 for damage the CRC does not
detect by construction: COBS code bytes hit, bursts merged into a frame); such false
acceptances are counted and must stay within the Poisson bound of that rate, and a stream
of purely random frames must yield none. 2x10^4 frames in the normal suite, 10^6 behind
``slow`` (measured: 1 false acceptance in 10^6 damaged-stream frames, 0 in 10^6 random
frames; docs/reliability.md). The hypothesis fuzz test at the end (bursts up to 1000 bytes, random
chunking) runs in CI with the normal suite; tests/protocol/test_decoder.py holds the
smaller-damage property tests and the false-acceptance statistics.
"""

from __future__ import annotations

import itertools
import math
import random
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.protocol.decoder import FrameDecoder
from stipi_daemon.protocol.messages import encode_frame
from tests.protocol.test_decoder import (
    _random_content_frames,
    apply_damage,
    check_accounting,
    damage_ops,
    encode_all,
    feed_chunks,
    make_messages,
    survivors,
)

from .conftest import report

P_BURST_BETWEEN = 0.02
P_BURST_INSIDE = 0.01
P_FLIPS = 0.03


def _damaged_stream(n: int, seed: int) -> tuple[bytes, list[int], list[object], dict[str, int]]:
    """(stream, indices of the frames that must survive, messages, damage counters)."""
    rng = random.Random(seed)
    msgs = make_messages(n, seed)
    out = bytearray()
    keep: list[int] = []
    counts = {"bursts_between": 0, "bursts_inside": 0, "flipped_frames": 0, "garbage_bytes": 0}
    for k, msg in enumerate(msgs):
        wire = bytearray(encode_frame(msg, k % 65536, (10_000 * k) % 2**32))
        intact = True
        if rng.random() < P_BURST_BETWEEN:
            burst = rng.randbytes(rng.randint(1, 1000))
            out += burst
            counts["bursts_between"] += 1
            counts["garbage_bytes"] += len(burst)
            intact = burst[-1] == 0  # a tail after the burst's last zero joins the frame
        if rng.random() < P_BURST_INSIDE:
            burst = rng.randbytes(rng.randint(1, 1000))
            pos = rng.randint(1, len(wire) - 1)
            wire[pos:pos] = burst
            counts["bursts_inside"] += 1
            counts["garbage_bytes"] += len(burst)
            intact = False
        if rng.random() < P_FLIPS:
            before = bytes(wire)
            for _ in range(rng.randint(1, 3)):
                pos = rng.randrange(len(wire) - 1)  # not the delimiter
                wire[pos] ^= 1 << rng.randrange(8)
            if bytes(wire) != before:
                counts["flipped_frames"] += 1
                intact = False
        out += wire
        if intact:
            keep.append(k)
    return bytes(out), keep, list(msgs), counts


def _check(n: int, seed: int, name: str) -> None:
    stream, keep, msgs, counts = _damaged_stream(n, seed)
    t0 = time.perf_counter()
    d = FrameDecoder()
    frames = []
    rng = random.Random(seed + 1)
    pos = 0
    while pos < len(stream):  # arbitrary chunking, as a serial port or BLE delivers
        step = rng.choice((20, 64, 512, 4096))
        frames += d.feed(stream[pos : pos + step])
        pos += step
    elapsed_s = time.perf_counter() - t0
    got = [f.message for f in frames]
    want = [msgs[k] for k in keep]
    # Every intact frame is delivered, in order; anything else is a false acceptance.
    j = false = 0
    for m in got:
        if j < len(want) and m == want[j]:
            j += 1
        else:
            false += 1
    assert j == len(want)
    damaged = n - len(keep) + counts["bursts_between"]
    # P(X > bound) < 1e-4 for X ~ Poisson(damaged * 2^-16) (the CRC's chance rate).
    lam = damaged / 65536
    bound = 0
    while sum(math.exp(-lam) * lam**k / math.factorial(k) for k in range(bound + 1)) < 1 - 1e-4:
        bound += 1
    assert false <= bound, (false, bound)
    s = check_accounting(d)
    assert s.frames_ok == len(keep) + false and s.duplicates == 0
    if false == 0:  # loss counts are exact (a false frame's seq would blur them)
        assert s.restarts == 0
        assert s.frames_lost == sum(b - a - 1 for a, b in itertools.pairwise(keep))
        assert s.gaps == sum(1 for a, b in itertools.pairwise(keep) if b > a + 1)
        lost = [b - a - 1 for a, b in itertools.pairwise(keep)]
        assert [f.lost_before for f in frames[1:]] == lost
    report(
        name,
        frames=n,
        delivered=len(keep),
        lost=n - len(keep),
        false_accepted=false,
        false_bound=bound,
        rejected_runs=s.errors,
        decode_s=elapsed_s,
        **counts,
    )


def test_garbage_and_bit_flips_2e4_frames() -> None:
    _check(20_000, seed=1, name="garbage_2e4")


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_garbage_and_bit_flips_1e6_frames() -> None:
    _check(1_000_000, seed=2, name="garbage_1e6")


def _random_frames(n: int, name: str) -> None:
    d = FrameDecoder()
    assert d.feed(_random_content_frames(n, seed=n + 7)) == []
    s = check_accounting(d)
    assert s.errors == n and s.frames_ok == 0
    report(name, random_frames=n, accepted=0, crc_errors=s.crc_errors)


def test_no_false_frame_in_2e4_random_frames() -> None:
    _random_frames(20_000, "random_frames_2e4")


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_no_false_frame_in_1e6_random_frames() -> None:
    _random_frames(1_000_000, "random_frames_1e6")


@settings(max_examples=200, deadline=None)
@given(
    st.integers(2, 30), st.integers(0, 2**32 - 1), st.lists(damage_ops(1000), max_size=8), st.data()
)
def test_fuzz_decoder_with_bursts_up_to_1000_bytes(
    n: int, seed: int, ops: list[tuple[str, float, int, bytes]], data: st.DataObject
) -> None:
    msgs = make_messages(n, seed)
    stream, spans = encode_all(msgs)
    tagged = apply_damage(stream, ops)
    damaged = bytes(b for b, _ in tagged)
    keep = survivors(stream, tagged, spans)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(damaged)), max_size=20)))
    d = FrameDecoder()
    frames = feed_chunks(d, damaged, cuts)
    assert [f.message for f in frames] == [msgs[k] for k in keep]
    s = check_accounting(d)
    assert s.frames_lost == ((keep[-1] - keep[0] + 1 - len(keep)) if keep else 0)
