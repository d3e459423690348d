"""A host → probe COMMAND frame on the probe's stream is dropped, not sequenced (issue: one
such frame with seq 40000 used to raise a RESTART, then a false gap, and reset clock sync).

The stream is built with the protocol's own encoder (docs/protocol.md, "Framing" and
"Messages": SAMPLES/STATUS/ACK go probe → host, COMMAND host → probe); the expectation is
the clean stream's decode without the foreign frame.
"""

from __future__ import annotations

import asyncio

import pytest

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ClockProbe, ForceRows, Gap, ProbeLink
from stipi_daemon.protocol import (
    FrameDecoder,
    FrameErrorKind,
    Samples,
    SeqEvent,
    StreamStart,
    encode_frame,
)
from stipi_daemon.protocol.decoder import HOST_TO_PROBE_TYPES, PROBE_TO_HOST_TYPES

PERIOD_US = 10_000
N_FRAMES = 60
FOREIGN_AT = 30


def _probe_frames() -> list[bytes]:
    """SAMPLES frames seq 0..59, 5 samples each, on the probe's clock."""
    return [
        encode_frame(Samples(5 * i, PERIOD_US, tuple(range(500, 505))), i, 5 * i * PERIOD_US)
        for i in range(N_FRAMES)
    ]


def _stream_with_command(seq: int = 40_000) -> bytes:
    frames = _probe_frames()
    foreign = encode_frame(StreamStart(), seq, 3_000_000_000)
    return b"".join(frames[:FOREIGN_AT]) + foreign + b"".join(frames[FOREIGN_AT:])


def test_direction_sets_cover_every_type_once() -> None:
    assert not PROBE_TO_HOST_TYPES & HOST_TO_PROBE_TYPES
    from stipi_daemon.protocol.messages import MsgType

    assert PROBE_TO_HOST_TYPES | HOST_TO_PROBE_TYPES == set(MsgType)


def test_probe_stream_decoder_drops_a_command_at_seq_40000() -> None:
    clean = FrameDecoder(accept=PROBE_TO_HOST_TYPES).feed(b"".join(_probe_frames()))
    d = FrameDecoder(accept=PROBE_TO_HOST_TYPES)
    frames = d.feed(_stream_with_command())
    assert [(f.seq, f.t_us_unwrapped, f.event) for f in frames] == [
        (f.seq, f.t_us_unwrapped, f.event) for f in clean
    ]
    s = d.stats
    assert (s.restarts, s.gaps, s.frames_lost) == (0, 0, 0)
    assert s.wrong_direction == 1 and s.errors == 1 and s.frames_ok == N_FRAMES
    (event,) = d.pop_errors()
    assert event.kind is FrameErrorKind.DIRECTION
    assert "COMMAND" in event.detail and "40000" in event.detail
    assert event.stream_offset == sum(len(f) for f in _probe_frames()[:FOREIGN_AT])
    # Byte accounting still closes.
    assert s.bytes_received == s.bytes_ok + s.bytes_discarded + s.delimiters + d.buffered_bytes


def test_without_the_direction_rule_the_same_stream_fakes_a_restart() -> None:
    """The failure the rule prevents, reproduced on an unrestricted decoder."""
    d = FrameDecoder()
    odd = [(f.seq, f.event, f.lost_before) for f in d.feed(_stream_with_command())]
    odd = [x for x in odd if x[1] != SeqEvent.IN_ORDER]
    false_gap = (FOREIGN_AT - 40_001) % 65_536  # 25565 frames "lost" after the restart
    assert odd == [
        (0, SeqEvent.FIRST, 0),
        (40_000, SeqEvent.RESTART, 0),
        (FOREIGN_AT, SeqEvent.GAP, false_gap),
    ]


@pytest.mark.parametrize("seq", [0, 29, 30, 31, 40_000, 65_535])
def test_any_seq_of_the_foreign_frame_leaves_sequence_untouched(seq: int) -> None:
    d = FrameDecoder(accept=PROBE_TO_HOST_TYPES)
    frames = d.feed(_stream_with_command(seq))
    assert [f.seq for f in frames] == list(range(N_FRAMES))
    assert all(f.event in (SeqEvent.FIRST, SeqEvent.IN_ORDER) for f in frames)


class _BytesTransport:
    """A Transport (stipi_daemon.probe.transports.base) reading a fixed byte stream.

    After the stream it blocks, as an idle link does; writes are accepted and dropped.
    """

    name = "bytes"

    def __init__(self, data: bytes) -> None:
        self._data = data
        self._sent = False

    async def open(self) -> None:
        return None

    async def read(self) -> bytes:
        if not self._sent:
            self._sent = True
            return self._data
        await asyncio.Event().wait()
        return b""

    async def write(self, data: bytes) -> None:
        return None

    async def close(self) -> None:
        return None


def _run_link(data: bytes) -> tuple[ProbeLink, list[int], list[Gap], list[ClockProbe]]:
    """Feed ``data`` through a ProbeLink's decoder and frame dispatch (the read loop's
    body, without a handshake); return the link and the events it queued."""
    clock = ScaledClock(1.0)
    link = ProbeLink(_BytesTransport(data), clock=clock)
    link._dispatch_frames(link.decoder.feed(data), clock.now())
    rows: list[int] = []
    gaps: list[Gap] = []
    probes: list[ClockProbe] = []
    while not link._queue.empty():
        ev = link._queue.get_nowait()
        if isinstance(ev, ForceRows):
            rows.extend(r.sample_index for r in ev.rows)
        elif isinstance(ev, Gap):
            gaps.append(ev)
        elif isinstance(ev, ClockProbe):
            probes.append(ev)
    return link, rows, gaps, probes


def test_probe_link_drops_it_and_keeps_rows_gaps_and_clock_sync() -> None:
    clean, clean_rows, _, clean_probes = _run_link(b"".join(_probe_frames()))
    link, rows, gaps, probes = _run_link(_stream_with_command())
    assert rows == clean_rows == list(range(5 * N_FRAMES))
    assert gaps == []
    assert [p.mcu_unwrapped_us for p in probes] == [p.mcu_unwrapped_us for p in clean_probes]
    # Clock sync never reset: same segment, same fit as the clean stream.
    model, clean_model = link.clock_sync.model, clean.clock_sync.model
    assert model.epoch_mcu_us == clean_model.epoch_mcu_us == 40_000
    assert model.n_observations == clean_model.n_observations
    assert (model.first_mcu_us, model.last_mcu_us) == (
        clean_model.first_mcu_us,
        clean_model.last_mcu_us,
    )
    assert link.clock_sync.resets == ()
    assert link.decoder.stats.wrong_direction == 1
    assert link.accounting.lost == clean.accounting.lost == 0
