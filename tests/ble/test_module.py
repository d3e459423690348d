"""Pure model of the BLE module's transmit side: TX buffer, connection events, faults."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.protocol.decoder import FrameDecoder
from stipi_daemon.protocol.messages import Samples, encode_frame
from stipi_daemon.sim.ble.module import (
    ConnectionEventPacer,
    FaultInjector,
    NotificationFaults,
    ReceiverSyncModel,
    UartTxFifo,
)


def test_fifo_takes_whole_frames_or_refuses_them() -> None:
    fifo = UartTxFifo(50)
    assert fifo.offer(b"a" * 30, "f1")
    assert not fifo.offer(b"b" * 21, "f2")  # 30 + 21 > 50: refused whole
    assert fifo.refused_frames == 1 and fifo.refused_bytes == 21
    assert fifo.offer(b"c" * 20, "f3")
    assert fifo.free_bytes == 0
    c1 = fifo.take(20)
    assert c1 is not None and c1.payload == b"a" * 20 and c1.finished == ()
    c2 = fifo.take(20)
    assert c2 is not None and c2.payload == b"a" * 10 + b"c" * 10
    assert c2.touched == ("f1", "f3") and c2.finished == ("f1",)
    assert fifo.clear() == ("f3",)
    assert fifo.take(20) is None and fifo.used_bytes == 0


def test_fifo_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="capacity"):
        UartTxFifo(0)
    fifo = UartTxFifo(10)
    with pytest.raises(ValueError, match="empty"):
        fifo.offer(b"")
    with pytest.raises(ValueError, match="payload size"):
        fifo.take(0)


@given(
    frames=st.lists(st.binary(min_size=1, max_size=75), min_size=1, max_size=40),
    mtu_payload=st.integers(1, 244),
)
def test_fifo_chunks_concatenate_to_the_frames_and_finish_each_once(
    frames: list[bytes], mtu_payload: int
) -> None:
    fifo = UartTxFifo(10_000)
    for i, f in enumerate(frames):
        assert fifo.offer(f, i)
    out, finished = bytearray(), []
    while (chunk := fifo.take(mtu_payload)) is not None:
        assert 1 <= len(chunk.payload) <= mtu_payload
        out += chunk.payload
        finished.extend(chunk.finished)
    assert bytes(out) == b"".join(frames)
    assert finished == list(range(len(frames)))


def test_pacer_grants_per_event_budget_at_each_connection_event() -> None:
    p = ConnectionEventPacer(0.015, 4, start_s=1.0)
    assert p.grant(0.999) == 0
    assert p.grant(1.0) == 4  # the event at t = 1.000
    assert p.grant(1.01) == 0
    assert p.grant(1.046) == 3 * 4  # events at 1.015, 1.030, 1.045
    assert p.next_event_s == pytest.approx(1.06)


def test_pacer_caps_the_backlog_after_a_stall() -> None:
    p = ConnectionEventPacer(0.01, 2, start_s=0.0, max_backlog_events=5)
    assert p.grant(10.0) == 10  # 1001 events elapsed, at most 5 granted
    assert p.grant(10.005) == 0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"interval_s": 0.0, "per_event": 1}, "interval"),
        ({"interval_s": float("nan"), "per_event": 1}, "interval"),
        ({"interval_s": 0.01, "per_event": 0}, "per connection event"),
    ],
)
def test_pacer_rejects_bad_arguments(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ConnectionEventPacer(start_s=0.0, **kwargs)  # type: ignore[arg-type]


def test_faults_validate_their_ranges() -> None:
    with pytest.raises(ValueError, match="drop_probability"):
        NotificationFaults(drop_probability=1.5)
    with pytest.raises(ValueError, match="corrupt_probability"):
        NotificationFaults(corrupt_probability=-0.1)
    with pytest.raises(ValueError, match="delay_s"):
        NotificationFaults(delay_s=float("inf"))
    assert not NotificationFaults().active
    assert NotificationFaults(delay_s=0.1).active


def test_injector_is_reproducible_and_flips_exactly_one_bit() -> None:
    payload = bytes(range(20))
    faults = NotificationFaults(drop_probability=0.3, corrupt_probability=0.5)
    a = [FaultInjector(faults, seed=7).apply(payload) for _ in range(1)]
    runs = []
    for _ in range(2):
        inj = FaultInjector(faults, seed=7)
        runs.append([inj.apply(payload) for _ in range(200)])
    assert runs[0] == runs[1] and a[0] == runs[0][0]
    outcomes = runs[0]
    dropped = sum(o.dropped for o in outcomes)
    corrupted = [o for o in outcomes if o.corrupted]
    assert 30 <= dropped <= 90  # Binomial(200, 0.3): mean 60, sd 6.5
    assert 40 <= len(corrupted) <= 100  # Binomial(140, 0.5) around 70
    for o in corrupted:
        assert o.payload is not None
        diff = int.from_bytes(o.payload, "big") ^ int.from_bytes(payload, "big")
        assert bin(diff).count("1") == 1
    clean = [o for o in outcomes if not o.dropped and not o.corrupted]
    assert all(o.payload == payload for o in clean)


def test_injector_without_faults_passes_everything() -> None:
    inj = FaultInjector()
    for n in range(1, 30):
        out = inj.apply(bytes(n))
        assert out.payload == bytes(n) and not out.dropped and not out.corrupted
    assert inj.dropped == inj.corrupted == 0


@given(
    data=st.data(),
    n_frames=st.integers(1, 30),
    mtu_payload=st.sampled_from([20, 7, 61, 244]),
    drop_p=st.sampled_from([0.0, 0.1, 0.3]),
    corrupt_p=st.sampled_from([0.0, 0.1, 0.3]),
    seed=st.integers(0, 2**16),
)
def test_receiver_model_predicts_exactly_what_the_real_decoder_accepts(
    data: st.DataObject, n_frames: int, mtu_payload: int, drop_p: float, corrupt_p: float, seed: int
) -> None:
    """The ledger's model of the host decoder agrees with FrameDecoder frame by frame."""
    fifo = UartTxFifo(100_000)
    for i in range(n_frames):
        count = data.draw(st.integers(1, 24))
        adc = data.draw(st.lists(st.integers(0, 1023), min_size=count, max_size=count))
        frame = encode_frame(Samples(1000 * i, 10_000, tuple(adc)), i, 777 * i)
        if data.draw(st.booleans()):
            assert fifo.offer(b"\x00", None)  # resync bytes between frames
        assert fifo.offer(frame, i)
    model = ReceiverSyncModel()
    inj = FaultInjector(NotificationFaults(drop_p, corrupt_p), seed=seed)
    wire = bytearray()
    predicted: list[object] = []
    while (chunk := fifo.take(mtu_payload)) is not None:
        outcome = inj.apply(chunk.payload)
        if outcome.payload is not None:
            wire += outcome.payload
        predicted += [t for t in model.observe(chunk, outcome) if t is not None]
    decoder = FrameDecoder()
    got = [f.message.first_index // 1000 for f in decoder.feed(bytes(wire))]  # type: ignore[union-attr]
    assert got == predicted
