"""The shared vectors file: committed text equals the generator's, and every vector holds."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from stipi_daemon.protocol import (
    Ack,
    AckStatus,
    BleState,
    FrameDecoder,
    FrameError,
    FrameErrorKind,
    GetInfo,
    InfoResult,
    Message,
    RawCommand,
    ResetCause,
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
    cobs_decode,
    cobs_encode,
    crc16_ccitt,
    crc16_ccitt_table,
    decode_frame,
    encode_frame,
    pack_frame,
    unpack_frame,
)
from tests.vectors import generate_vectors

VECTORS = Path(__file__).resolve().parents[1] / "vectors" / "protocol_vectors.txt"


@dataclass(frozen=True)
class Line:
    name: str
    kind: str
    fields: dict[str, str]
    frame: bytes
    wire: bytes

    def int(self, key: str) -> int:
        return int(self.fields[key])


def parse_vectors(text: str) -> list[Line]:
    """Parse the file the way the C++ tests do: TAB-separated, '#' comments, '-' for none."""
    out = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line or line.startswith("#"):
            continue
        cols = line.split("\t")
        assert len(cols) == 5, f"line {lineno}: {len(cols)} columns"
        name, kind, fields, frame, wire = cols
        kv = {}
        if fields != "-":
            for pair in fields.split(","):
                key, value = pair.split("=")
                kv[key] = value
        out.append(
            Line(
                name,
                kind,
                kv,
                b"" if frame == "-" else bytes.fromhex(frame),
                b"" if wire == "-" else bytes.fromhex(wire),
            )
        )
    return out


LINES = parse_vectors(VECTORS.read_text(encoding="utf-8"))


def build_message(line: Line) -> Message:
    """Message described by a vector's fields (independent of the generator's code)."""
    f = line.int
    if line.kind == "samples":
        return Samples(
            f("first_index"), f("period_us"), tuple(f(f"adc{i}") for i in range(f("count")))
        )
    if line.kind == "status":
        base = (f("led_level"), f("rate_hz"), f("dropped"), f("supply_mv"), StatusFlags(f("flags")))
        if "ble_state" not in line.fields:  # the 10-byte body of probes before firmware 1.1
            return Status(*base)
        health = (BleState(f("ble_state")), f("ble_restarts"), ResetCause(f("reset_cause")))
        return Status(*base, *health)
    if line.kind == "command":
        cmd = f("cmd")
        simple: dict[int, Message] = {1: StreamStart(), 2: StreamStop(), 5: Tare(), 7: GetInfo()}
        if cmd in simple:
            return simple[cmd]
        if cmd == 3:
            return SetRate(f("rate_hz"))
        if cmd == 4:
            return SetLed(f("level"))
        assert cmd == 6
        return WriteCal(f("zero_counts"), f("span_un_per_count"))
    assert line.kind == "ack"
    cmd, status = f("cmd"), AckStatus(f("status"))
    result: TareResult | InfoResult | None = None
    if "proto" in line.fields:
        names = (
            "proto fw_major fw_minor fw_patch rate_hz led_level zero_counts "
            "span_un_per_count adc_bits batch"
        ).split()
        result = InfoResult(*(f(n) for n in names))
    elif "zero_counts" in line.fields:
        result = TareResult(f("zero_counts"))
    return Ack(f("ref_seq"), cmd, status, result)


def test_committed_file_equals_generator_output() -> None:
    assert VECTORS.read_text(encoding="utf-8") == generate_vectors.render()


def test_names_unique_and_every_kind_present() -> None:
    names = [line.name for line in LINES]
    assert len(names) == len(set(names))
    kinds = {line.kind for line in LINES}
    assert kinds == {
        "crc",
        "cobs",
        "samples",
        "status",
        "command",
        "ack",
        "command_refused",
        "invalid",
        "stream",
    }
    cmds = {line.int("cmd") for line in LINES if line.kind == "command"}
    assert cmds == set(range(1, 8))
    statuses = {line.int("status") for line in LINES if line.kind == "ack"}
    assert statuses == {0, 1, 2, 3, 4}
    ok_acks = {line.int("cmd") for line in LINES if line.kind == "ack" and line.int("status") == 0}
    assert ok_acks == set(range(1, 8))


def test_crc_check_value_line() -> None:
    (check,) = [line for line in LINES if line.name == "crc_check_123456789"]
    assert check.frame == b"123456789"
    assert check.int("crc") == 0x29B1


@pytest.mark.parametrize("line", [x for x in LINES if x.kind == "crc"], ids=lambda x: x.name)
def test_crc_vectors(line: Line) -> None:
    assert crc16_ccitt_table(line.frame) == line.int("crc")
    assert crc16_ccitt(line.frame) == line.int("crc")


@pytest.mark.parametrize("line", [x for x in LINES if x.kind == "cobs"], ids=lambda x: x.name)
def test_cobs_vectors(line: Line) -> None:
    assert len(line.frame) == line.int("len")
    assert line.wire.endswith(b"\x00") and line.wire.count(0) == 1
    assert cobs_encode(line.frame) + b"\x00" == line.wire
    assert cobs_decode(line.wire[:-1]) == line.frame


MESSAGE_KINDS = ("samples", "status", "command", "ack")


@pytest.mark.parametrize(
    "line", [x for x in LINES if x.kind in MESSAGE_KINDS], ids=lambda x: x.name
)
def test_message_vectors_encode_and_decode_byte_exact(line: Line) -> None:
    msg = build_message(line)
    seq, t_us = line.int("seq"), line.int("t_us")
    assert pack_frame(msg, seq, t_us) == line.frame
    assert encode_frame(msg, seq, t_us) == line.wire
    frame = decode_frame(line.wire)
    assert (frame.seq, frame.t_us, frame.message) == (seq, t_us, msg)
    assert unpack_frame(line.frame) == frame
    # frames never exceed the protocol's bounds
    assert 10 <= len(line.frame) <= 74
    assert len(line.wire) == len(line.frame) + 2


@pytest.mark.parametrize(
    "line", [x for x in LINES if x.kind == "command_refused"], ids=lambda x: x.name
)
def test_refused_command_vectors(line: Line) -> None:
    frame = decode_frame(line.wire)
    assert (frame.seq, frame.t_us) == (line.int("seq"), line.int("t_us"))
    msg = frame.message
    assert isinstance(msg, RawCommand)
    assert msg.cmd == line.int("cmd")
    assert len(msg.args) == line.int("nargs")
    assert msg.reason
    assert msg.refusal == AckStatus(line.int("status"))
    assert encode_frame(msg, frame.seq, frame.t_us) == line.wire


@pytest.mark.parametrize("line", [x for x in LINES if x.kind == "invalid"], ids=lambda x: x.name)
def test_invalid_vectors_rejected_for_the_stated_reason(line: Line) -> None:
    kind = FrameErrorKind(line.fields["error"])
    with pytest.raises(FrameError) as info:
        decode_frame(line.wire)
    assert info.value.kind == kind
    assert f"at byte offset {info.value.offset}" in str(info.value)
    if line.frame:
        assert cobs_encode(line.frame) + b"\x00" == line.wire
    decoder = FrameDecoder()
    assert decoder.feed(line.wire) == []
    assert decoder.stats.errors == 1
    (event,) = decoder.errors
    assert event.kind == kind
    assert event.stream_offset == 0


@pytest.mark.parametrize("line", [x for x in LINES if x.kind == "stream"], ids=lambda x: x.name)
def test_stream_vectors(line: Line) -> None:
    decoder = FrameDecoder()
    frames = decoder.feed(line.wire)
    assert [f.seq for f in frames] == [line.int(f"seq{i}") for i in range(line.int("frames"))]
    assert decoder.stats.errors == line.int("errors")
    # byte by byte gives the same
    one_by_one = FrameDecoder()
    seqs = [f.seq for i in range(len(line.wire)) for f in one_by_one.feed(line.wire[i : i + 1])]
    assert seqs == [f.seq for f in frames]
    assert one_by_one.stats == decoder.stats


def test_hand_assembled_frame_matches_encoder() -> None:
    """One frame built byte by byte from the spec's tables, independent of the encoder."""
    # first_index 12345, period_us 1000, count 2, adc 0 and 1023
    body = bytes.fromhex("39300000") + bytes.fromhex("e803") + b"\x02" + bytes.fromhex("0000ff03")
    header = bytes((1, 0x01)) + (0x1234).to_bytes(2, "little") + (10**6).to_bytes(4, "little")
    raw = header + body
    raw += crc16_ccitt_table(raw).to_bytes(2, "little")
    assert pack_frame(Samples(12345, 1000, (0, 1023)), 0x1234, 10**6) == raw
    assert len(raw) == 17 + 2 * 2
