"""FrameDecoder: arbitrary chunking, corruption and garbage, sequence and clock wrap, bounds.

The corruption tests use an exact oracle: each byte of the damaged stream remembers which
byte of the clean stream it came from (or none, if inserted or altered). An original frame
survives exactly when some run between two delimiters of the damaged stream consists of
all of its bytes, unaltered and in order; the decoder must deliver exactly those frames.
"""

from __future__ import annotations

import itertools
import random
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.protocol import (
    MAX_ENCODED_SIZE,
    Ack,
    AckStatus,
    CmdId,
    DecodedFrame,
    DecoderStats,
    FrameDecoder,
    FrameErrorKind,
    GetInfo,
    InfoResult,
    Message,
    Samples,
    SeqEvent,
    SetRate,
    Status,
    StreamStart,
    TareResult,
    cobs_encode,
    crc16_ccitt,
    encode_frame,
    pack_frame,
)

BLE_NOTIFICATION = 20


def make_messages(n: int, seed: int) -> list[Message]:
    """``n`` varied messages whose content never looks like a sender restart."""
    rng = random.Random(seed)
    out: list[Message] = []
    index = 0
    for i in range(n):
        kind = rng.randrange(6)
        if kind <= 2:
            count = rng.randint(1, 24)
            adc = tuple(rng.choice((0, 1023, rng.randrange(1024))) for _ in range(count))
            out.append(Samples(index, 1000, adc))
            index += count + rng.choice((0, 0, 0, 3))
        elif kind == 3:
            out.append(Status(rng.randrange(256), 100, i, 5000, rng.randrange(16)))  # type: ignore[arg-type]
        elif kind == 4:
            info = InfoResult(1, 0, 1, 2, 100, 10, 512, -1000, 10, 10)
            out.append(
                rng.choice(
                    [
                        Ack(i % 65536, CmdId.GET_INFO, AckStatus.OK, info),
                        Ack(i % 65536, CmdId.TARE, AckStatus.OK, TareResult(rng.randrange(1024))),
                        Ack(i % 65536, 0x42, AckStatus.UNKNOWN_COMMAND),
                    ]
                )
            )
        else:
            commands: list[Message] = [StreamStart(), GetInfo(), SetRate(rng.randint(16, 1000))]
            out.append(rng.choice(commands))
    return out


def encode_all(
    messages: Sequence[Message], seq0: int = 0, t0_us: int = 0
) -> tuple[bytes, list[tuple[int, int]]]:
    """Stream and, per frame, (first byte index, delimiter index)."""
    stream = bytearray()
    spans = []
    for i, msg in enumerate(messages):
        wire = encode_frame(msg, (seq0 + i) % 65536, (t0_us + 10_000 * i) % 2**32)
        spans.append((len(stream), len(stream) + len(wire) - 1))
        stream += wire
    return bytes(stream), spans


def feed_chunks(decoder: FrameDecoder, data: bytes, cuts: Sequence[int]) -> list[DecodedFrame]:
    out: list[DecodedFrame] = []
    prev = 0
    for cut in [*cuts, len(data)]:
        out += decoder.feed(data[prev:cut])
        prev = cut
    return out


def check_accounting(decoder: FrameDecoder) -> DecoderStats:
    s = decoder.stats
    assert s.bytes_received == s.bytes_ok + s.bytes_discarded + s.delimiters + (
        decoder.buffered_bytes
    )
    assert decoder.buffered_bytes <= MAX_ENCODED_SIZE
    return s


# --------------------------------------------------------------------- chunking


def _garbage_stream() -> bytes:
    msgs = make_messages(6, seed=1)
    stream, _ = encode_all(msgs, seq0=65533, t0_us=2**32 - 25_000)
    return b"\x17\x42" + stream[:30] + b"\x00\x00" + stream[30:] + b"\x99" * 90 + b"\x00"


EXHAUSTIVE_STREAMS = {
    "six_frames_across_wraps": encode_all(make_messages(6, seed=2), 65533, 2**32 - 25_000)[0],
    "garbage_partial_and_overlong": _garbage_stream(),
    "max_size_frames": encode_all([Samples(24 * i, 1000, (0, 1023) * 12) for i in range(3)])[0],
}


@pytest.mark.parametrize("name", sorted(EXHAUSTIVE_STREAMS))
def test_every_single_split_point_decodes_identically(name: str) -> None:
    data = EXHAUSTIVE_STREAMS[name]
    ref = FrameDecoder()
    want = ref.feed(data)
    assert want
    for cut in range(len(data) + 1):
        d = FrameDecoder()
        assert feed_chunks(d, data, [cut]) == want, cut
        assert d.stats == ref.stats
        assert list(d.errors) == list(ref.errors)


def test_every_pair_of_split_points_decodes_identically() -> None:
    data = encode_all(make_messages(3, seed=3))[0] + b"\x05\x01\x00"
    want = FrameDecoder().feed(data)
    n = len(data)
    for i in range(n + 1):
        for j in range(i, n + 1):
            assert feed_chunks(FrameDecoder(), data, [i, j]) == want, (i, j)


@settings(max_examples=150)
@given(st.integers(1, 40), st.integers(0, 2**32 - 1), st.data())
def test_random_chunking_equals_one_feed(n: int, seed: int, data: st.DataObject) -> None:
    msgs = make_messages(n, seed)
    stream, _ = encode_all(msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=30)))
    d = FrameDecoder()
    frames = feed_chunks(d, stream, cuts)
    assert [f.message for f in frames] == msgs
    assert [f.seq for f in frames] == list(range(n))
    assert frames[0].event == SeqEvent.FIRST
    assert all(f.event == SeqEvent.IN_ORDER and f.lost_before == 0 for f in frames[1:])
    s = check_accounting(d)
    assert s.frames_ok == n and s.errors == 0 and s.bytes_discarded == 0
    assert d.buffered_bytes == 0


def test_ble_notifications_of_20_bytes() -> None:
    msgs = make_messages(200, seed=4)
    stream, spans = encode_all(msgs)
    d = FrameDecoder()
    frames = feed_chunks(d, stream, range(BLE_NOTIFICATION, len(stream), BLE_NOTIFICATION))
    assert [f.message for f in frames] == msgs
    assert [f.stream_offset for f in frames] == [start for start, _ in spans]


def test_accepts_bytearray_and_memoryview_and_empty_chunks() -> None:
    wire = encode_frame(StreamStart(), 1, 2)
    d = FrameDecoder()
    assert d.feed(b"") == []
    assert d.feed(bytearray(wire[:5])) == []
    (frame,) = d.feed(memoryview(wire)[5:])
    assert frame.message == StreamStart()


# --------------------------------------------------------------------- corruption


def apply_damage(
    stream: bytes, ops: Sequence[tuple[str, float, int, bytes]]
) -> list[tuple[int, int | None]]:
    """Damaged stream as (byte, index of the clean byte it replaced, None if inserted)."""
    tagged: list[tuple[int, int | None]] = [(b, i) for i, b in enumerate(stream)]
    for op, where, arg, garbage in ops:
        pos = min(int(where * (len(tagged) + 1)), len(tagged))
        if op == "insert":
            tagged[pos:pos] = [(b, None) for b in garbage]
        elif not tagged:
            continue
        elif op == "flip":
            pos = min(pos, len(tagged) - 1)
            tagged[pos] = (tagged[pos][0] ^ (1 << (arg % 8)), tagged[pos][1])
        elif op == "delete":
            del tagged[pos : pos + 1 + arg % 4]
        else:  # set a byte, possibly to 0x00 or to a delimiter's neighbour
            pos = min(pos, len(tagged) - 1)
            tagged[pos] = (arg % 256, tagged[pos][1])
    return tagged


def survivors(
    stream: bytes, tagged: list[tuple[int, int | None]], spans: list[tuple[int, int]]
) -> list[int]:
    """Original frames whose bytes form an intact run between delimiters."""
    wanted: dict[tuple[int | None, ...], int] = {
        tuple(range(start, delim)): k for k, (start, delim) in enumerate(spans)
    }
    out = []
    run: list[int | None] = []
    for byte, origin in tagged:
        if byte == 0:
            key = tuple(run)
            if key in wanted:
                out.append(wanted[key])
            run = []
        else:
            run.append(origin if origin is not None and stream[origin] == byte else None)
    return out


def damage_ops(max_burst: int) -> st.SearchStrategy[tuple[str, float, int, bytes]]:
    """One damage operation for :func:`apply_damage`; bursts of at most ``max_burst`` bytes."""
    return st.tuples(
        st.sampled_from(["flip", "insert", "delete", "set"]),
        st.floats(0, 1),
        st.integers(0, 255),
        st.binary(min_size=1, max_size=max_burst),
    )


@settings(max_examples=300, derandomize=True)
@given(st.integers(2, 25), st.integers(0, 2**32 - 1), st.lists(damage_ops(90), max_size=6))
def test_damage_loses_exactly_the_damaged_frames(
    n: int, seed: int, ops: list[tuple[str, float, int, bytes]]
) -> None:
    msgs = make_messages(n, seed)
    stream, spans = encode_all(msgs, seq0=65530)
    tagged = apply_damage(stream, ops)
    damaged = bytes(b for b, _ in tagged)
    keep = survivors(stream, tagged, spans)

    d = FrameDecoder()
    frames = feed_chunks(d, damaged, range(BLE_NOTIFICATION, len(damaged), BLE_NOTIFICATION))
    assert [f.message for f in frames] == [msgs[k] for k in keep]
    assert [f.seq for f in frames] == [(65530 + k) % 65536 for k in keep]
    # gaps between survivors are counted exactly (losses after the last one are unknowable)
    assert [f.lost_before for f in frames[1:]] == [b - a - 1 for a, b in itertools.pairwise(keep)]
    s = check_accounting(d)
    lost_between = (keep[-1] - keep[0] + 1 - len(keep)) if keep else 0
    assert s.frames_lost == lost_between
    assert s.gaps == sum(1 for a, b in itertools.pairwise(keep) if b > a + 1)
    assert s.frames_ok == len(keep)
    assert s.seq_wraps == (1 if keep and keep[0] <= 5 < keep[-1] else 0)
    for event in d.errors:  # every rejected run starts the stream or follows a delimiter
        assert event.stream_offset == 0 or damaged[event.stream_offset - 1] == 0
    # one feed gives the same
    whole = FrameDecoder()
    assert whole.feed(damaged) == frames
    assert whole.stats == d.stats


@settings(max_examples=100)
@given(st.binary(max_size=3000))
def test_random_bytes_never_crash_and_bytes_are_accounted(data: bytes) -> None:
    d = FrameDecoder()
    feed_chunks(d, data, range(7, len(data), 7))
    check_accounting(d)
    for event in d.errors:
        assert event.stream_offset == 0 or data[event.stream_offset - 1] == 0
        assert str(event).startswith(f"{event.kind.value} error in {event.length}-byte frame")


def test_errors_report_stream_offsets() -> None:
    good = encode_frame(StreamStart(), 1, 0)
    raw = bytearray(pack_frame(StreamStart(), 2, 0))
    raw[-1] ^= 0x01
    bad = cobs_encode(bytes(raw)) + b"\x00"
    stream = good + bytes(bad) + b"\x05\x01\x00" + good
    d = FrameDecoder()
    d.feed(stream)
    events = d.pop_errors()
    assert [(e.kind, e.stream_offset) for e in events] == [
        (FrameErrorKind.CRC, len(good)),
        (FrameErrorKind.COBS, len(good) + len(bad)),
    ]
    assert f"at stream byte offset {len(good)}: CRC" in str(events[0])
    assert d.stats.resyncs == 1 and d.stats.duplicates == 1  # the last frame repeats the first
    assert not d.errors


# --------------------------------------------------------------------- bounds


@pytest.mark.parametrize("chunk", [1, 20, 75, 76, 4096, 1 << 20])
def test_overlong_garbage_is_bounded_and_counted(chunk: int) -> None:
    size = 1 << (16 if chunk == 1 else 20)
    garbage = random.Random(chunk).randbytes(size).replace(b"\x00", b"\x01")
    d = FrameDecoder()
    for i in range(0, len(garbage), chunk):
        assert d.feed(garbage[i : i + chunk]) == []
        assert d.buffered_bytes <= MAX_ENCODED_SIZE
    s = d.stats
    assert s.length_errors == 1 and s.bytes_discarded == len(garbage)
    (frame,) = d.feed(b"\x00" + encode_frame(StreamStart(), 9, 9))
    s = check_accounting(d)
    assert frame.seq == 9 and s.resyncs == 1 and s.length_errors == 1
    assert s.bytes_discarded == len(garbage) and d.buffered_bytes == 0


def test_length_boundary_75_vs_76_encoded_bytes() -> None:
    d = FrameDecoder()
    d.feed(bytes(range(1, 76)) + b"\x00")  # 75 bytes: decoded and rejected by a later check
    assert d.stats.length_errors == 0 and d.stats.errors == 1
    d.feed(bytes(range(1, 77)) + b"\x00")  # 76 bytes: too long before decoding
    assert d.stats.length_errors == 1
    d.feed(bytes(range(1, 40)))
    d.feed(bytes(range(1, 38)) + b"\x00")  # 76 bytes over two chunks
    assert d.stats.length_errors == 2
    check_accounting(d)


def test_empty_frames_are_ignored_not_errors() -> None:
    d = FrameDecoder()
    frames = d.feed(b"\x00\x00" + encode_frame(StreamStart(), 0, 0) + b"\x00")
    assert len(frames) == 1
    s = check_accounting(d)
    assert s.empty_frames == 3 and s.errors == 0 and s.resyncs == 0


# --------------------------------------------------------------------- sequence and clock


def test_gap_across_seq_wrap_duplicates_and_clock_wrap() -> None:
    msgs = [Status(0, 100, i, 5000) for i in range(8)]
    wires = [
        encode_frame(m, (65532 + i) % 65536, (2**32 - 20_000 + 10_000 * i) % 2**32)
        for i, m in enumerate(msgs)
    ]
    # seqs 65532, 65533, [65534, 65535 lost], 0, 0 again (duplicate), 1, ...
    stream = wires[0] + wires[1] + wires[4] + wires[4] + b"".join(wires[5:])
    d = FrameDecoder()
    frames = d.feed(stream)
    assert [f.seq for f in frames] == [65532, 65533, 0, 1, 2, 3]
    assert [f.event for f in frames] == [
        SeqEvent.FIRST,
        SeqEvent.IN_ORDER,
        SeqEvent.GAP,
        SeqEvent.IN_ORDER,
        SeqEvent.IN_ORDER,
        SeqEvent.IN_ORDER,
    ]
    assert frames[2].lost_before == 2 and frames[2].seq_wrapped
    assert [f.t_us_unwrapped for f in frames] == [
        2**32 - 20_000 + 10_000 * i for i in (0, 1, 4, 5, 6, 7)
    ]
    assert frames[2].t_us < frames[1].t_us  # raw clock wrapped, unwrapped did not
    s = d.stats
    assert (s.gaps, s.frames_lost, s.duplicates, s.seq_wraps, s.t_us_wraps) == (1, 2, 1, 1, 1)
    assert s.frames_ok == 7

    d2 = FrameDecoder(deliver_duplicates=True)
    frames2 = d2.feed(stream)
    dup = [f for f in frames2 if f.is_duplicate]
    assert len(dup) == 1 and dup[0].seq == 0 and dup[0].t_us_unwrapped == 2**32 + 20_000


def test_probe_restart_is_detected_and_delivered() -> None:
    before = [Samples(100 * i, 1000, (i,)) for i in range(5)]
    after = [Samples(i, 1000, (7,)) for i in range(3)]
    stream_a, _ = encode_all(before, seq0=0, t0_us=5_000_000)
    stream_b, _ = encode_all(after, seq0=0, t0_us=1_000)  # seq restarts at 0: "older"
    d = FrameDecoder()
    frames = d.feed(stream_a + stream_b)
    assert [f.message for f in frames] == before + after
    assert frames[5].event == SeqEvent.RESTART and frames[5].lost_before == 0
    assert frames[5].t_us_unwrapped == 1_000  # clock unwrapper re-anchored
    s = d.stats
    assert (s.restarts, s.gaps, s.frames_lost, s.duplicates) == (1, 0, 0, 0)


def test_restart_detected_from_content_when_seq_looks_in_order() -> None:
    stream_a, _ = encode_all([Samples(1000, 1000, (1,)), Status(0, 100, 50, 5000)], seq0=7)
    stream_b, _ = encode_all([Samples(0, 1000, (1,)), Status(0, 100, 0, 5000)], seq0=9)
    frames = FrameDecoder().feed(stream_a + stream_b)
    assert [f.event for f in frames] == [
        SeqEvent.FIRST,
        SeqEvent.IN_ORDER,
        SeqEvent.RESTART,
        SeqEvent.IN_ORDER,
    ]
    stream_c, _ = encode_all([Status(0, 100, 3, 5000)], seq0=11)  # dropped 50 -> 3
    d = FrameDecoder()
    d.feed(stream_a)
    (frame,) = d.feed(stream_c)
    assert frame.event == SeqEvent.RESTART and d.stats.frames_lost == 0


def test_restart_shortly_after_boot_is_not_a_duplicate() -> None:
    """Same seq values as frames just received, different content: a restart, delivered."""
    first, _ = encode_all([Samples(10 * i, 1000, (1,) * 10) for i in range(4)])
    second, _ = encode_all([Samples(10 * i, 1000, (2,) * 10) for i in range(4)])
    d = FrameDecoder()
    frames = d.feed(first + second)
    assert len(frames) == 8 and frames[4].event == SeqEvent.RESTART
    assert d.stats.duplicates == 0


def test_reset_clears_everything() -> None:
    d = FrameDecoder()
    d.feed(encode_frame(StreamStart(), 3, 3) + b"\x01\x02")
    d.reset()
    assert d.buffered_bytes == 0 and d.stats == DecoderStats() and d.stream_offset == 0
    (frame,) = d.feed(encode_frame(StreamStart(), 3, 3))
    assert frame.event == SeqEvent.FIRST


# --------------------------------------------------------------------- false acceptance
#
# docs/protocol.md, "False acceptance": a candidate frame whose CRC field is uniformly
# random passes the CRC with probability exactly 2^-16, independently of the rest. The test
# replaces the CRC of N valid frames by random values; the decoder must accept exactly the
# frames whose random CRC happens to be right (known in advance), and that number must be
# consistent with Poisson(N / 65536). The bounds are the smallest k with
# P(X > k) < 1e-4: N = 1e4 (λ = 0.153): k = 3; N = 1e5 (λ = 1.53): k = 8.


def _random_crc_frames(n: int, seed: int) -> tuple[bytes, int]:
    rng = random.Random(seed)
    msgs = make_messages(n, seed)
    out = bytearray()
    matches = 0
    for i, msg in enumerate(msgs):
        raw = bytearray(pack_frame(msg, rng.randrange(65536), rng.randrange(2**32)))
        crc = rng.randrange(65536)
        matches += crc == crc16_ccitt(bytes(raw[:-2]))
        raw[-2:] = crc.to_bytes(2, "little")
        out += cobs_encode(bytes(raw)) + b"\x00"
        del i
    return bytes(out), matches


def _random_content_frames(n: int, seed: int) -> bytes:
    rng = random.Random(seed)
    out = bytearray()
    for _ in range(n):
        raw = rng.randbytes(rng.randint(10, 74))
        out += cobs_encode(raw) + b"\x00"
    return bytes(out)


def _false_acceptance(n: int, bound: int) -> None:
    stream, matches = _random_crc_frames(n, seed=n)
    d = FrameDecoder()
    frames = d.feed(stream)
    s = check_accounting(d)
    assert s.frames_ok == matches == len(frames) + s.duplicates
    assert s.crc_errors == n - matches
    assert matches <= bound
    # random content: version, type and body must also fit, ~2^-30 per candidate
    d2 = FrameDecoder()
    assert d2.feed(_random_content_frames(n, seed=n + 1)) == []
    s2 = check_accounting(d2)
    assert s2.errors == n and s2.cobs_errors == 0
    assert s2.crc_errors >= n - bound  # passing the CRC by chance: same Poisson law


def test_false_acceptance_1e4_candidates() -> None:
    _false_acceptance(10_000, bound=3)


@pytest.mark.slow
def test_false_acceptance_1e5_candidates() -> None:
    _false_acceptance(100_000, bound=8)
