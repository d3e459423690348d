"""Messages: round trips, field range checks naming the field, decode errors naming offsets."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.errors import ProtocolError
from stipi_daemon.protocol import (
    MAX_ENCODED_SIZE,
    Ack,
    AckStatus,
    CmdId,
    FrameError,
    FrameErrorKind,
    GetInfo,
    InfoResult,
    Message,
    MsgType,
    RawCommand,
    Samples,
    SetLed,
    SetRate,
    Status,
    StatusFlags,
    StreamStart,
    StreamStop,
    Tare,
    TareResult,
    WriteCal,
    crc16_ccitt,
    decode_frame,
    encode_frame,
    pack_frame,
    parse_command,
    unpack_frame,
)

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFF_FFFF)
i32 = st.integers(-(2**31), 2**31 - 1)

samples_st = st.builds(
    Samples,
    u32,
    st.integers(1, 0xFFFF),
    st.lists(u16, min_size=1, max_size=24).map(tuple),
)
status_st = st.builds(Status, u8, u16, u32, u16, u8.map(StatusFlags))
info_st = st.builds(InfoResult, u8, u8, u8, u8, u16, u8, u16, i32, u8, u8)
command_st: st.SearchStrategy[Message] = st.one_of(
    st.just(StreamStart()),
    st.just(StreamStop()),
    st.builds(SetRate, st.integers(16, 1000)),
    st.builds(SetLed, u8),
    st.just(Tare()),
    st.builds(WriteCal, u16, i32),
    st.just(GetInfo()),
)
ack_st: st.SearchStrategy[Message] = st.one_of(
    st.builds(
        Ack, u16, st.sampled_from([1, 2, 3, 4, 6]).map(int), st.just(AckStatus.OK), st.none()
    ),
    st.builds(
        Ack, u16, st.just(int(CmdId.TARE)), st.just(AckStatus.OK), st.builds(TareResult, u16)
    ),
    st.builds(Ack, u16, st.just(int(CmdId.GET_INFO)), st.just(AckStatus.OK), info_st),
    st.builds(Ack, u16, u8, st.just(AckStatus.UNKNOWN_COMMAND)),
    st.builds(Ack, u16, st.integers(1, 7), st.sampled_from(list(AckStatus)[2:])),
)
message_st: st.SearchStrategy[Message] = st.one_of(samples_st, status_st, command_st, ack_st)


@given(message_st, u16, u32)
def test_round_trip(msg: Message, seq: int, t_us: int) -> None:
    wire = encode_frame(msg, seq, t_us)
    assert wire[-1] == 0 and 0 not in wire[:-1]
    assert len(wire) <= MAX_ENCODED_SIZE + 1
    frame = decode_frame(wire)
    assert (frame.seq, frame.t_us, frame.message) == (seq, t_us, msg)
    assert decode_frame(wire[:-1]) == frame
    raw = pack_frame(msg, seq, t_us)
    assert raw[0] == 1 and raw[1] == msg.MSG_TYPE
    assert int.from_bytes(raw[-2:], "little") == crc16_ccitt(raw[:-2])


@given(st.lists(u16, min_size=1, max_size=24))
def test_samples_size_formula(adc: list[int]) -> None:
    """docs/protocol.md: 17 + 2n bytes framed, 19 + 2n on the wire."""
    msg = Samples(0, 1000, tuple(adc))
    assert len(pack_frame(msg, 1, 2)) == 17 + 2 * len(adc)
    assert len(encode_frame(msg, 1, 2)) == 19 + 2 * len(adc)


def test_samples_accepts_list_and_exposes_count() -> None:
    msg = Samples(3, 1000, [1, 2, 3])  # type: ignore[arg-type]
    assert msg.adc == (1, 2, 3) and msg.count == 3


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: Samples(0, 1000, ()), "count"),
        (lambda: Samples(0, 1000, tuple(range(25))), "count"),
        (lambda: Samples(0, 1000, (0x10000,)), "adc[0]"),
        (lambda: Samples(0, 1000, (1, -1)), "adc[1]"),
        (lambda: Samples(-1, 1000, (1,)), "first_index"),
        (lambda: Samples(2**32, 1000, (1,)), "first_index"),
        (lambda: Samples(0, 0, (1,)), "period_us"),
        (lambda: Samples(0, 65536, (1,)), "period_us"),
        (lambda: Status(256, 0, 0, 0), "led_level"),
        (lambda: Status(0, 70000, 0, 0), "rate_hz"),
        (lambda: Status(0, 0, 2**32, 0), "dropped"),
        (lambda: Status(0, 0, 0, -5), "supply_mv"),
        (lambda: Status(0, 0, 0, 0, 256), "flags"),  # type: ignore[arg-type]
        (lambda: SetRate(15), "rate_hz"),
        (lambda: SetRate(1001), "rate_hz"),
        (lambda: SetRate(0), "rate_hz"),
        (lambda: SetLed(256), "level"),
        (lambda: SetLed(True), "level"),
        (lambda: SetLed(1.0), "level"),  # type: ignore[arg-type]
        (lambda: WriteCal(65536, 0), "zero_counts"),
        (lambda: WriteCal(0, 2**31), "span_un_per_count"),
        (lambda: Ack(65536, 1), "ref_seq"),
        (lambda: Ack(0, 256, AckStatus.UNKNOWN_COMMAND), "cmd"),
        (lambda: Ack(0, 1, 5), "status"),  # type: ignore[arg-type]
        (lambda: Ack(0, 0x42, AckStatus.OK), "cmd"),
        (lambda: Ack(0, CmdId.TARE, AckStatus.OK), "result"),
        (lambda: Ack(0, CmdId.TARE, AckStatus.BUSY, TareResult(1)), "result"),
        (lambda: Ack(0, CmdId.SET_LED, AckStatus.OK, TareResult(1)), "result"),
        (lambda: TareResult(-1), "zero_counts"),
        (lambda: InfoResult(1, 1, 1, 1, 100, 1, 1, 1, 256, 10), "adc_bits"),
        (lambda: RawCommand(256), "cmd"),
        (lambda: RawCommand(9, bytes(64)), "args"),
    ],
)
def test_range_checks_name_the_field(build: object, field: str) -> None:
    with pytest.raises(ProtocolError, match=field.replace("[", r"\[")):
        build()  # type: ignore[operator]


@pytest.mark.parametrize(("seq", "t_us"), [(-1, 0), (65536, 0), (0, -1), (0, 2**32)])
def test_header_range_checks(seq: int, t_us: int) -> None:
    with pytest.raises(ProtocolError, match="seq" if seq not in (0,) else "t_us"):
        encode_frame(StreamStart(), seq, t_us)


def test_status_flags_and_reserved_bits() -> None:
    msg = Status(1, 100, 0, 5000, 0xF3)  # type: ignore[arg-type]
    assert isinstance(msg.flags, StatusFlags)
    assert StatusFlags.STREAMING in msg.flags and StatusFlags.USB_OPEN not in msg.flags
    assert decode_frame(encode_frame(msg, 0, 0)).message == msg


def test_ack_typed_results() -> None:
    info = InfoResult(1, 2, 3, 4, 100, 200, 512, -48828, 10, 10)
    ack = Ack(7, CmdId.GET_INFO, AckStatus.OK, info)
    assert ack.ok and ack.info() == info
    with pytest.raises(ProtocolError, match="no TARE result"):
        ack.tare()
    tare = Ack(8, CmdId.TARE, AckStatus.OK, TareResult(517))
    assert tare.tare().zero_counts == 517
    with pytest.raises(ProtocolError, match="no GET_INFO result"):
        tare.info()
    busy = Ack(9, CmdId.TARE, AckStatus.BUSY)
    assert not busy.ok
    with pytest.raises(ProtocolError, match="status=BUSY"):
        busy.tare()
    assert Ack(1, 2, 0).status is AckStatus.OK  # type: ignore[arg-type]


def test_parse_command_typed_and_refused() -> None:
    assert parse_command(CmdId.SET_RATE, struct.pack("<H", 500)) == SetRate(500)
    assert parse_command(CmdId.WRITE_CAL, struct.pack("<Hi", 3, -4)) == WriteCal(3, -4)
    assert parse_command(CmdId.GET_INFO, b"") == GetInfo()
    bad = parse_command(CmdId.SET_RATE, struct.pack("<H", 2000))
    assert isinstance(bad, RawCommand) and bad.refusal == AckStatus.BAD_ARGUMENT
    assert "rate_hz=2000" in bad.reason
    short = parse_command(CmdId.SET_LED, b"")
    assert isinstance(short, RawCommand) and "takes 1 argument bytes, got 0" in short.reason
    unknown = parse_command(0x99, b"\x01")
    assert isinstance(unknown, RawCommand) and unknown.refusal == AckStatus.UNKNOWN_COMMAND
    assert "0x99" in unknown.reason


def _frame(version: int, msg_type: int, body: bytes) -> bytes:
    head = bytes((version, msg_type)) + bytes(6) + body
    return head + crc16_ccitt(head).to_bytes(2, "little")


@pytest.mark.parametrize(
    ("raw", "kind", "offset", "words"),
    [
        (bytes(9), FrameErrorKind.LENGTH, 0, "9 bytes outside 10..74"),
        (bytes(75), FrameErrorKind.LENGTH, 0, "75 bytes"),
        (_frame(1, 1, b"")[:-1] + b"\x00", FrameErrorKind.CRC, 8, "does not match"),
        (_frame(2, 1, b""), FrameErrorKind.VERSION, 0, "version 2"),
        (_frame(1, 0x7F, b""), FrameErrorKind.TYPE, 1, "type 0x7F"),
        (_frame(1, MsgType.SAMPLES, b"\x00" * 6), FrameErrorKind.BODY, 8, "shorter"),
        (_frame(1, MsgType.SAMPLES, bytes(6) + b"\x00"), FrameErrorKind.BODY, 14, "count=0"),
        (_frame(1, MsgType.SAMPLES, bytes(6) + b"\x02" + bytes(2)), FrameErrorKind.BODY, 14, "11"),
        (
            _frame(1, MsgType.SAMPLES, bytes(4) + b"\x00\x00\x01\x05\x00"),
            FrameErrorKind.BODY,
            12,
            "period_us=0",
        ),
        (_frame(1, MsgType.STATUS, bytes(11)), FrameErrorKind.BODY, 8, "10 or 14 bytes, got 11"),
        (_frame(1, MsgType.COMMAND, b""), FrameErrorKind.BODY, 8, "empty"),
        (_frame(1, MsgType.ACK, b"\x00\x00\x01"), FrameErrorKind.BODY, 8, "shorter"),
        (_frame(1, MsgType.ACK, b"\x00\x00\x01\x09"), FrameErrorKind.BODY, 11, "status=9"),
        (_frame(1, MsgType.ACK, b"\x00\x00\x07\x00" + bytes(14)), FrameErrorKind.BODY, 12, "15"),
    ],
)
def test_unpack_errors_name_kind_and_offset(
    raw: bytes, kind: FrameErrorKind, offset: int, words: str
) -> None:
    with pytest.raises(FrameError) as info:
        unpack_frame(raw)
    assert info.value.kind == kind
    assert info.value.offset == offset
    assert words in str(info.value)
    assert f"at byte offset {offset}" in str(info.value)


def test_decode_frame_too_long_encoding() -> None:
    with pytest.raises(FrameError) as info:
        decode_frame(bytes(range(1, 78)))
    assert info.value.kind == FrameErrorKind.LENGTH


def test_messages_are_frozen_and_hashable() -> None:
    msg = Samples(0, 1000, (1,))
    with pytest.raises(AttributeError):
        msg.first_index = 3  # type: ignore[misc]
    assert len({msg, Samples(0, 1000, (1,))}) == 1


def test_status_health_fields_round_trip_and_old_probes_still_decode() -> None:
    """Firmware 1.1 appends ble_state, ble_restarts and reset_cause (14-byte body); a probe
    that predates them sends 10 bytes, which still decodes, with the fields None."""
    from stipi_daemon.protocol import BleState, ResetCause

    new = Status(0, 100, 3, 5000, StatusFlags.STREAMING, BleState.BOOTING, 2, ResetCause.WATCHDOG)
    body = new.body()
    assert len(body) == 14 and Status.from_body(body) == new
    old = Status.from_body(body[:10])
    assert (old.ble_state, old.ble_restarts, old.reset_cause) == (None, None, None)
    assert old.body() == body[:10]
    with pytest.raises(ProtocolError, match="come together"):
        Status(0, 100, 3, 5000, StatusFlags.NONE, BleState.UP)
    with pytest.raises(FrameError, match=r"ble_state must be 0\.\.3, got 7"):
        Status.from_body(body[:10] + b"\x07" + body[11:])
