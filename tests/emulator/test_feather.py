"""FeatherCore, the firmware's behaviour as a pure model: byte-exact answers and sampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.protocol import (
    Ack,
    AckStatus,
    CmdId,
    DecodedFrame,
    FrameDecoder,
    GetInfo,
    Message,
    RawCommand,
    Samples,
    SetLed,
    SetRate,
    Status,
    StatusFlags,
    StreamStart,
    StreamStop,
    Tare,
    WriteCal,
    decode_frame,
    encode_frame,
)
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.sim.feather import (
    BATCH_SIZE,
    HEARTBEAT_PERIOD_US,
    RING_CAPACITY,
    ConstantAdc,
    FeatherCore,
    McuClock,
    SceneAdc,
    flip_bits,
    period_for_rate,
)
from tests.protocol.test_vectors import LINES, Line

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"


def _frames(core: FeatherCore, decoder: FrameDecoder | None = None) -> list[DecodedFrame]:
    dec = decoder if decoder is not None else FrameDecoder()
    return dec.feed(b"".join(core.take_output()))


def _send(core: FeatherCore, msg: Message, seq: int, t_us: int) -> None:
    core.feed(encode_frame(msg, seq, t_us % 2**32), t_us)


def _only_ack(core: FeatherCore) -> Ack:
    frames = [decode_frame(w) for w in core.take_output()]
    assert len(frames) == 1, frames
    assert isinstance(frames[0].message, Ack)
    return frames[0].message


# ----------------------------------------------------------------------------- vectors


def _ack_setup(line: Line) -> tuple[FeatherCore, Message, int]:
    """A core and the command that make the probe answer exactly ``line`` at its t_us."""
    f = line.int
    t = f("t_us")
    cmd, status = f("cmd"), AckStatus(f("status"))
    if cmd == CmdId.TARE and status == AckStatus.OK:
        t0 = t - 16 * period_for_rate(100)  # answered with the 16th sample after the command
        return FeatherCore(ConstantAdc(f("zero_counts")), boot_us=t0 - 1), Tare(), t0
    core = FeatherCore(
        ConstantAdc(0),
        boot_us=t - 1,
        zero_counts=f("zero_counts") if "proto" in line.fields else 0,
        span_un_per_count=f("span_un_per_count") if "proto" in line.fields else 0,
        fw_version=(f("fw_major"), f("fw_minor"), f("fw_patch"))
        if "proto" in line.fields
        else (1, 0, 0),
    )
    if "proto" in line.fields:
        core.led_level = f("led_level")
    if status == AckStatus.UNKNOWN_COMMAND:
        return core, RawCommand(cmd, b"\x01\x02"), t
    if status == AckStatus.BAD_ARGUMENT:
        assert cmd == CmdId.SET_RATE
        return core, RawCommand(cmd, b"\x0f\x00"), t
    if status == AckStatus.BUSY:
        assert cmd == CmdId.TARE
        _send(core, Tare(), 1, t - 1)
        core.take_output()
        return core, Tare(), t
    if status == AckStatus.EEPROM_FAILED:
        core.eeprom_fails = True
        return core, WriteCal(512, -48828), t
    commands: dict[int, Message] = {
        CmdId.STREAM_START: StreamStart(),
        CmdId.STREAM_STOP: StreamStop(),
        CmdId.SET_RATE: SetRate(100),
        CmdId.SET_LED: SetLed(7),
        CmdId.WRITE_CAL: WriteCal(512, -48828),
        CmdId.GET_INFO: GetInfo(),
    }
    return core, commands[cmd], t


@pytest.mark.parametrize("line", [ln for ln in LINES if ln.kind == "ack"], ids=lambda ln: ln.name)
def test_ack_vectors_byte_exact(line: Line) -> None:
    core, command, t_cmd = _ack_setup(line)
    core.advance(t_cmd)
    core.take_output()
    core.seq = line.int("seq")
    _send(core, command, line.int("ref_seq"), t_cmd)
    core.advance(line.int("t_us"))
    assert core.take_output() == [line.wire]


@pytest.mark.parametrize(
    "line",
    [ln for ln in LINES if ln.kind in ("command", "command_refused")],
    ids=lambda ln: ln.name,
)
def test_command_vectors_are_answered_like_the_firmware(line: Line) -> None:
    t = line.int("t_us")
    core = FeatherCore(ConstantAdc(300), boot_us=t - 1, zero_counts=100, span_un_per_count=5)
    core.advance(t)
    core.take_output()
    core.feed(line.wire, t)
    cmd = line.int("cmd")
    if line.kind == "command_refused":
        want = AckStatus(line.int("status"))
    elif cmd == CmdId.WRITE_CAL and line.int("zero_counts") > 1023:
        want = AckStatus.BAD_ARGUMENT  # probe.cpp: zero beyond the 10-bit ADC is refused
    else:
        want = AckStatus.OK
    if cmd == CmdId.TARE and want == AckStatus.OK:
        assert core.take_output() == [] and core.tare_pending
        core.advance(t + 16 * period_for_rate(100))
    ack = _only_ack(core)
    assert (ack.ref_seq, ack.cmd, ack.status) == (line.int("seq"), cmd, want)
    if cmd == CmdId.TARE and want == AckStatus.OK:
        assert ack.tare().zero_counts == 300
    if cmd == CmdId.GET_INFO and want == AckStatus.OK:
        info = ack.info()
        assert (info.proto, info.rate_hz, info.zero_counts, info.span_un_per_count) == (
            1,
            100,
            100,
            5,
        )
        assert (info.adc_bits, info.batch) == (10, BATCH_SIZE)


def test_invalid_and_foreign_frames_count_as_rx_errors() -> None:
    core = FeatherCore(ConstantAdc(0))
    core.take_output()
    core.feed(b"\x05garbage\x00" + b"\x01" * 200 + b"\x00", 10)
    core.feed(encode_frame(Status(0, 100, 0, 0), 0, 0), 20)  # valid, but not a COMMAND
    bad_crc = bytearray(encode_frame(GetInfo(), 1, 0))
    bad_crc[5] ^= 0x40
    core.feed(bytes(bad_crc) + b"\x00\x00", 30)
    assert core.rx_errors == 4
    assert core.take_output() == []


# ----------------------------------------------------------------------------- sampling


def test_stream_batches_indices_times_and_heartbeat() -> None:
    adc = SceneAdcLike()
    core = FeatherCore(adc, boot_us=1_000, zero_counts=100, span_un_per_count=5)
    dec = FrameDecoder()
    _send(core, StreamStart(), 0, 2_000)
    core.advance(3_000_000)
    frames = _frames(core, dec)
    samples = [f for f in frames if isinstance(f.message, Samples)]
    statuses = [f for f in frames if isinstance(f.message, Status)]
    acks = [f for f in frames if isinstance(f.message, Ack)]
    assert len(acks) == 1 and acks[0].t_us == 2_000
    # first sample one period after STREAM_START; 10 per batch; indices and times contiguous
    assert all(len(f.message.adc) == BATCH_SIZE for f in samples if isinstance(f.message, Samples))
    first = [f.message.first_index for f in samples if isinstance(f.message, Samples)]
    assert first == list(range(0, 10 * len(samples), 10))
    assert [f.t_us for f in samples] == [12_000 + 100_000 * k for k in range(len(samples))]
    # the 29th full batch ends at 2_000 + 290 * 10 ms = 2.902 s
    assert len(samples) == 29
    values = [v for f in samples if isinstance(f.message, Samples) for v in f.message.adc]
    assert values == [adc.value_at(12_000 + 10_000 * i) for i in range(290)]
    # heartbeat at boot then every 500 ms, flags follow the state
    assert [f.t_us for f in statuses] == [1_000 + k * HEARTBEAT_PERIOD_US for k in range(6)]
    st0, st1 = (f.message for f in statuses[:2])
    assert isinstance(st0, Status) and isinstance(st1, Status)
    assert st0.flags == StatusFlags.USB_OPEN | StatusFlags.CAL_VALID
    assert StatusFlags.STREAMING in st1.flags
    assert dec.stats.gaps == 0 and dec.stats.errors == 0
    # frames go out in time order of their sending
    seqs = [f.seq for f in frames]
    assert seqs == list(range(len(frames)))


class SceneAdcLike:
    """A deterministic non-constant pin voltage: counts = (t_us // 1000) mod 1024."""

    def counts(self, t_mcu_us: np.ndarray) -> np.ndarray:
        return (t_mcu_us // 1000) % 1024

    def value_at(self, t_us: int) -> int:
        return (t_us // 1000) % 1024


def test_set_rate_while_streaming_flushes_and_restarts_the_timer() -> None:
    core = FeatherCore(ConstantAdc(5))
    _send(core, StreamStart(), 0, 0)
    core.advance(125_000)  # 12 samples taken, one batch sent, 2 in the ring
    _send(core, SetRate(250), 1, 125_000)
    core.advance(125_000 + 10 * 4_000)
    msgs = [f.message for f in _frames(core)]
    batches = [m for m in msgs if isinstance(m, Samples)]
    assert [(b.first_index, b.count, b.period_us) for b in batches] == [
        (0, 10, 10_000),
        (10, 2, 10_000),  # the old period's samples leave first
        (12, 10, 4_000),
    ]
    ack = next(m for m in msgs if isinstance(m, Ack))
    assert ack.ok and core.rate_hz == 250 and core.period_us == 4_000


def test_tare_idle_uses_own_samples_and_blocks_commands() -> None:
    core = FeatherCore(ConstantAdc(321), span_un_per_count=0)
    core.take_output()
    _send(core, Tare(), 0, 1_000)
    _send(core, StreamStart(), 1, 2_000)  # busy while the tare owns the sampler
    _send(core, SetLed(9), 2, 3_000)  # SET_LED is never busy
    core.advance(1_000 + 16 * 10_000)
    acks = [f.message for f in _frames(core) if isinstance(f.message, Ack)]
    assert [(a.cmd, a.status) for a in acks] == [
        (CmdId.STREAM_START, AckStatus.BUSY),
        (CmdId.SET_LED, AckStatus.OK),
        (CmdId.TARE, AckStatus.OK),
    ]
    assert acks[2].tare().zero_counts == 321 and core.zero_counts == 321
    assert not core.cal_valid  # a tare alone does not make a calibration
    assert core.taken == 16 and not core.streaming
    core.advance(1_000_000)
    assert not any(isinstance(f.message, Samples) for f in _frames(core))


def test_write_cal_ranges_and_eeprom_failure() -> None:
    core = FeatherCore(ConstantAdc(0))
    core.take_output()
    for seq, (zero, span, want) in enumerate(
        [
            (1024, 5, AckStatus.BAD_ARGUMENT),
            (10, 0, AckStatus.BAD_ARGUMENT),
            (10, -7, AckStatus.OK),
        ]
    ):
        _send(core, WriteCal(zero, span), seq, 100 + seq)
        assert _only_ack(core).status == want
    assert (core.zero_counts, core.span_un_per_count, core.cal_valid) == (10, -7, True)
    core.eeprom_fails = True
    _send(core, WriteCal(11, 3), 9, 200)
    assert _only_ack(core).status == AckStatus.EEPROM_FAILED
    assert (core.zero_counts, core.span_un_per_count) == (10, -7)


def test_stalled_main_loop_overflows_the_ring_like_the_firmware() -> None:
    core = FeatherCore(ConstantAdc(1))
    dec = FrameDecoder()
    _send(core, StreamStart(), 0, 0)
    core.advance(55_000)  # 5 samples in the ring
    core.stall(1_000_000)  # 100 sample periods
    core.advance(1_055_000)
    core.advance(3_000_000)
    frames = _frames(core, dec)
    batches = [f.message for f in frames if isinstance(f.message, Samples)]
    # ring fills to 64 (indices 0..63); 64..99 + the sample at 1.055 s... are dropped until
    # the loop has emptied the ring; then sampling resumes at the next sample
    covered = [i for b in batches for i in range(b.first_index, b.first_index + b.count)]
    assert covered[:RING_CAPACITY] == list(range(RING_CAPACITY))
    resumed = covered[RING_CAPACITY]
    assert core.dropped == resumed - RING_CAPACITY > 0
    assert covered[RING_CAPACITY:] == list(range(resumed, resumed + len(covered) - RING_CAPACITY))
    last_status = [f.message for f in frames if isinstance(f.message, Status)][-1]
    assert last_status.dropped == core.dropped
    assert dec.stats.gaps == 0  # no frame was lost: the gap is in the probe


def test_next_event_is_when_the_next_frame_leaves() -> None:
    core = FeatherCore(ConstantAdc(1))
    core.take_output()
    _send(core, StreamStart(), 0, 0)
    core.take_output()
    for _ in range(30):
        t = core.next_event_us()
        core.advance(t - 1)
        assert core.take_output() == []
        core.advance(t)
        assert core.take_output() != []


def test_u32_clock_wrap_in_frames() -> None:
    boot = 2**32 - 250_000
    core = FeatherCore(ConstantAdc(1), boot_us=boot)
    dec = FrameDecoder()
    _send(core, StreamStart(), 0, boot)
    core.advance(boot + 1_000_000)
    samples = [f for f in _frames(core, dec) if isinstance(f.message, Samples)]
    assert samples[0].t_us > samples[-1].t_us  # raw times wrapped
    unwrapped = [f.t_us_unwrapped for f in samples]
    assert np.all(np.diff(unwrapped) == 100_000)


# ----------------------------------------------------------------------------- pieces


@given(
    st.floats(-10.0, 1e4),
    st.integers(0, 2**32 - 1),
    st.floats(-5000.0, 5000.0),
    st.floats(0.0, 1e4),
)
def test_mcu_clock_inverse(boot_s: float, offset_us: int, ppm: float, t_s: float) -> None:
    clock = McuClock(boot_s, offset_us, ppm)
    us = clock.mcu_us(boot_s + t_s)
    assert clock.mcu_us(clock.session_s(us)) in (us - 1, us)
    assert abs(clock.session_s(us) - (boot_s + t_s)) <= 2e-6 + 1e-9 * abs(boot_s + t_s)


def test_scene_adc_reads_the_scene_on_its_grid_and_the_model_off_it() -> None:
    scene = load_scene(SCENES / "grade2.yaml")
    pipeline = Pipeline(scene)
    batch = pipeline.force_batch()
    adc = SceneAdc(scene, start_mcu_us=5_000_000)
    on_grid = 5_000_000 + np.arange(0, 3000, dtype=np.int64) * 10_000
    assert np.array_equal(adc.counts(on_grid), batch.adc_counts[:3000])
    off = 5_000_000 + 3_333 + np.arange(0, 3000, dtype=np.int64) * 7_000
    t_s = (off - 5_000_000) * 1e-6
    want = pipeline.load_cell.counts(pipeline.model.force_n(t_s))
    assert np.array_equal(adc.counts(off), want)
    assert (adc.zero_counts, adc.span_un_per_count) == (102, 54297)


def _effects_scene(tmp_path: Path, effects: list[dict[str, object]]) -> Path:
    import yaml

    doc = yaml.safe_load((SCENES / "grade2.yaml").read_text())
    doc["effects"] = effects
    path = tmp_path / "effects.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_scene_adc_plays_the_force_effects_between_the_scenes_samples(tmp_path: Path) -> None:
    """Drift at any sample time (F + offset + rate t, the effect's definition, in counts of
    the FC22's 54.3 mN); on the scene's grid the scene's own counts, noise included."""
    drift = {"name": "force_drift", "offset_n": 0.5, "rate_n_per_s": 0.05}
    scene = load_scene(_effects_scene(tmp_path, [drift]))
    pipeline = Pipeline(scene)
    adc = SceneAdc(scene, start_mcu_us=5_000_000)
    off = 5_000_000 + 3_333 + np.arange(0, 3000, dtype=np.int64) * 10_000
    t_s = (off - 5_000_000) * 1e-6
    n_per_count = 44.48 / 819.2
    want = np.rint(102.4 + (pipeline.model.force_n(t_s) + 0.5 + 0.05 * t_s) / n_per_count)
    assert np.array_equal(adc.counts(off), want.astype(np.int64))

    noisy = load_scene(_effects_scene(tmp_path, [drift, {"name": "force_noise", "sigma_n": 0.3}]))
    batch = Pipeline(noisy).force_batch()
    on_grid = 5_000_000 + np.arange(0, 3000, dtype=np.int64) * 10_000
    a, b = SceneAdc(noisy, start_mcu_us=5_000_000), SceneAdc(noisy, start_mcu_us=5_000_000)
    got = np.concatenate([a.counts(on_grid[i : i + 256]) for i in range(0, 3000, 256)])
    assert np.array_equal(got, batch.adc_counts[:3000])  # in batches as the firmware asks
    assert np.array_equal(b.counts(on_grid), got)  # the same for the same seed
    other = SceneAdc(noisy, seed=noisy.seed + 1, start_mcu_us=5_000_000).counts(on_grid)
    assert not np.array_equal(other, got)


def test_a_force_dropout_is_an_index_gap_lost_on_the_link(tmp_path: Path) -> None:
    """The samples taken in [1.5, 2.0) s are not sent: the SAMPLES frames around them leave
    out exactly those 50 indices, and the frames that held them took sequence numbers (lost
    on the link, not in the probe: STATUS ``dropped`` stays 0)."""
    span = {"name": "force_dropout", "t_start_s": 1.5, "t_end_s": 2.0}
    scene = load_scene(_effects_scene(tmp_path, [span]))
    adc = SceneAdc(scene)
    core = FeatherCore(adc, boot_us=1_000, zero_counts=102, span_un_per_count=54297)
    dec = FrameDecoder()
    _send(core, StreamStart(), 0, 2_000)
    core.advance(4_000_000)
    frames = _frames(core, dec)
    got: list[int] = []
    for f in frames:
        if isinstance(f.message, Samples):
            got += range(f.message.first_index, f.message.first_index + len(f.message.adc))
    period = period_for_rate(100)
    missing = sorted(set(range(got[0], got[-1] + 1)) - set(got))
    times_s = [(k - got[0]) * period * 1e-6 for k in missing]
    assert len(missing) == 50 and min(times_s) >= 1.5 - 1e-9 and max(times_s) < 2.0
    every = [f.seq for f in frames]  # SAMPLES and STATUS
    lost_frames = set(range(every[0], every[-1] + 1)) - set(every)
    assert len(lost_frames) in (5, 6)  # 50 samples in batches of 10, on the link
    assert core.dropped == 0


def test_flip_bits_counts_exactly() -> None:
    rng = np.random.default_rng(3)
    data = bytes(range(1, 200))
    assert flip_bits(data, 0.0, rng) == (data, 0)
    out, n = flip_bits(data, 0.01, rng)
    hamming = sum(bin(a ^ b).count("1") for a, b in zip(data, out, strict=True))
    assert n == hamming > 0
    with pytest.raises(ValueError, match="bit_error_rate"):
        flip_bits(data, 1.5, rng)
