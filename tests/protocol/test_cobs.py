"""COBS: literature examples, round trip, bounds, and errors naming the byte offset."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.protocol import FrameError, FrameErrorKind
from stipi_daemon.protocol.cobs import cobs_decode, cobs_encode, cobs_max_encoded_length

# Examples from Cheshire & Baker's paper as tabulated on Wikipedia ("Consistent Overhead
# Byte Stuffing", encoding examples 1-11), delimiter not included.
EXAMPLES = [
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize(("raw", "encoded"), EXAMPLES)
def test_literature_examples(raw: bytes, encoded: bytes) -> None:
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_empty() -> None:
    assert cobs_encode(b"") == b"\x01"
    assert cobs_decode(b"\x01") == b""


@given(st.binary(max_size=800))
def test_round_trip_no_zero_and_length_bound(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert len(data) + 1 <= len(enc) <= cobs_max_encoded_length(len(data))
    assert cobs_decode(enc) == data


@given(st.binary(min_size=10, max_size=74))
def test_frame_sized_data_has_exactly_one_overhead_byte(data: bytes) -> None:
    assert len(cobs_encode(data)) == len(data) + 1


@pytest.mark.parametrize(
    ("encoded", "offset", "words"),
    [
        (b"", 0, "empty"),
        (b"\x05\x11\x22", 0, "past the end"),
        (b"\x02\x11\x04\x22", 2, "past the end"),
        (b"\x03\x11\x00\x22", 2, "0x00 inside"),
    ],
)
def test_errors_name_offset(encoded: bytes, offset: int, words: str) -> None:
    with pytest.raises(FrameError) as info:
        cobs_decode(encoded)
    assert info.value.kind == FrameErrorKind.COBS
    assert info.value.offset == offset
    assert words in str(info.value)
    assert f"at byte offset {offset}" in str(info.value)


@given(st.binary(min_size=1, max_size=100).filter(lambda b: 0 not in b))
def test_decode_of_arbitrary_nonzero_bytes_never_crashes(data: bytes) -> None:
    try:
        out = cobs_decode(data)
    except FrameError as exc:
        assert exc.kind == FrameErrorKind.COBS
        assert 0 <= exc.offset < len(data)
    else:
        assert len(out) <= len(data)
