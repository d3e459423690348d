"""Messages of wire protocol version 1 and their byte layout (docs/protocol.md).

This module owns one frozen dataclass per message (:class:`Samples`, :class:`Status`,
:class:`Ack`) and per command (:class:`StreamStart` ... :class:`GetInfo`, plus
:class:`RawCommand` for command bytes that are not a valid command), the typed ACK results
(:class:`TareResult`, :class:`InfoResult`), and the conversion of one message to and from
one frame: :func:`pack_frame` / :func:`unpack_frame` (header, body, CRC) and
:func:`encode_frame` / :func:`decode_frame` (the same plus COBS and the 0x00 delimiter).
Every constructor checks its fields' ranges and raises
:class:`~stipi_daemon.errors.ProtocolError` naming the field, so an invalid message can
neither be built nor sent; decoding raises :class:`~stipi_daemon.protocol.errors.FrameError`
naming the byte offset. It does no I/O and keeps no state: splitting a byte stream into
frames, sequence numbers and timestamps are :mod:`~stipi_daemon.protocol.decoder`'s and
:mod:`~stipi_daemon.protocol.timestamps`' job.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import ClassVar, Final, TypeAlias

from stipi_daemon.errors import ProtocolError
from stipi_daemon.protocol.cobs import cobs_decode, cobs_encode, cobs_max_encoded_length
from stipi_daemon.protocol.crc import crc16_ccitt
from stipi_daemon.protocol.errors import FrameError, FrameErrorKind

__all__ = [
    "CRC_SIZE",
    "HEADER_SIZE",
    "MAX_BODY_SIZE",
    "MAX_ENCODED_SIZE",
    "MAX_FRAME_SIZE",
    "MAX_SAMPLES_PER_BATCH",
    "MIN_ENCODED_SIZE",
    "MIN_FRAME_SIZE",
    "PROTOCOL_VERSION",
    "RATE_MAX_HZ",
    "RATE_MIN_HZ",
    "Ack",
    "AckResult",
    "AckStatus",
    "BleState",
    "CmdId",
    "Command",
    "Frame",
    "GetInfo",
    "InfoResult",
    "Message",
    "MsgType",
    "RawCommand",
    "ResetCause",
    "Samples",
    "SetLed",
    "SetRate",
    "Status",
    "StatusFlags",
    "StreamStart",
    "StreamStop",
    "Tare",
    "TareResult",
    "WriteCal",
    "decode_frame",
    "encode_frame",
    "pack_frame",
    "parse_command",
    "unpack_frame",
]

PROTOCOL_VERSION: Final = 1
"""Value of the header's ``version`` byte."""
HEADER_SIZE: Final = 8
"""``version u8, type u8, seq u16, t_us u32`` [bytes]."""
CRC_SIZE: Final = 2
"""CRC-16 appended little-endian [bytes]."""
MAX_BODY_SIZE: Final = 64
"""Largest body the protocol allows [bytes] (the largest defined message uses 55)."""
MIN_FRAME_SIZE: Final = HEADER_SIZE + CRC_SIZE
"""Shortest decoded frame: header and CRC, empty body [bytes]."""
MAX_FRAME_SIZE: Final = HEADER_SIZE + MAX_BODY_SIZE + CRC_SIZE
"""Longest decoded frame (74) [bytes]."""
MAX_ENCODED_SIZE: Final = cobs_max_encoded_length(MAX_FRAME_SIZE)
"""Longest COBS-encoded frame without its delimiter (75) [bytes]."""
MIN_ENCODED_SIZE: Final = MIN_FRAME_SIZE + 1
"""Shortest COBS-encoded frame without its delimiter (11) [bytes]."""
MAX_SAMPLES_PER_BATCH: Final = 24
"""Largest ``count`` of a SAMPLES message."""
RATE_MIN_HZ: Final = 16
"""Lowest SET_RATE rate [Hz]: its period, 62 500 µs, still fits SAMPLES' u16 ``period_us``."""
RATE_MAX_HZ: Final = 1000
"""Highest SET_RATE rate [Hz]."""

_HEADER = struct.Struct("<BBHI")
_CRC = struct.Struct("<H")
_SAMPLES_HEAD = struct.Struct("<IHB")
_STATUS = struct.Struct("<BHIHB")
_STATUS_HEALTH = struct.Struct("<BHB")  # ble_state, ble_restarts, reset_cause (firmware 1.1 on)
_ACK_HEAD = struct.Struct("<HBB")
_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_WRITE_CAL = struct.Struct("<Hi")
_INFO = struct.Struct("<BBBBHBHiBB")


class MsgType(IntEnum):
    """Header ``type`` byte."""

    SAMPLES = 0x01
    STATUS = 0x02
    COMMAND = 0x10
    ACK = 0x11


class CmdId(IntEnum):
    """COMMAND ``cmd`` byte."""

    STREAM_START = 0x01
    STREAM_STOP = 0x02
    SET_RATE = 0x03
    SET_LED = 0x04
    TARE = 0x05
    WRITE_CAL = 0x06
    GET_INFO = 0x07


class AckStatus(IntEnum):
    """ACK ``status`` byte."""

    OK = 0
    UNKNOWN_COMMAND = 1
    BAD_ARGUMENT = 2
    BUSY = 3
    EEPROM_FAILED = 4


class BleState(IntEnum):
    """STATUS ``ble_state``: the probe's BLE module as its firmware sees it."""

    NOT_BUILT = 0
    ABSENT = 1  # nothing answers; the probe resets it and looks again with a back-off
    BOOTING = 2  # reset or answering "busy" (0xFE), being probed
    UP = 3


class ResetCause(IntFlag):
    """STATUS ``reset_cause``: why the probe last started, in the ATmega32u4's MCUSR bit
    order. On a Feather the Caterina bootloader clears MCUSR, so the firmware infers the
    cause: ``WATCHDOG`` from a mark its watchdog interrupt leaves, ``POWER_ON`` when RAM
    lost its contents, and ``EXTERNAL | BROWN_OUT`` (both bits: one of the two) otherwise."""

    UNKNOWN = 0
    POWER_ON = 0x01
    EXTERNAL = 0x02
    BROWN_OUT = 0x04
    WATCHDOG = 0x08


class StatusFlags(IntFlag):
    """STATUS ``flags`` bits (bits 5..7 reserved, kept if set).

    ``SUPPLY_UNCORRECTED`` (bit 4, firmware 1.0 on): the load-cell counts are not corrected
    for the FC22's 5 V supply (no supply sense wired), so they carry its error (up to
    +/-5 % of reading on USB power, docs/firmware.md). Probes that predate the bit send 0.
    """

    NONE = 0
    STREAMING = 0x01
    BLE_CONNECTED = 0x02
    USB_OPEN = 0x04
    CAL_VALID = 0x08
    SUPPLY_UNCORRECTED = 0x10


def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    """Return ``value`` if it is an integer in ``lo..hi``, else raise naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{name} must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ProtocolError(f"{name}={value} out of range {lo}..{hi}")
    return int(value)


def _u8(name: str, value: object) -> int:
    return _check_int(name, value, 0, 0xFF)


def _u16(name: str, value: object) -> int:
    return _check_int(name, value, 0, 0xFFFF)


def _u32(name: str, value: object) -> int:
    return _check_int(name, value, 0, 0xFFFF_FFFF)


def _i32(name: str, value: object) -> int:
    return _check_int(name, value, -0x8000_0000, 0x7FFF_FFFF)


# --------------------------------------------------------------------------- probe → host


@dataclass(frozen=True, slots=True)
class Samples:
    """SAMPLES: a batch of consecutive raw load-cell readings.

    Parameters
    ----------
    first_index : int
        Index of the batch's first sample among every sample taken since boot, 0..2^32-1.
    period_us : int
        Sampling period [µs], 1..65535; sample ``i`` was taken at ``t_us + i * period_us``.
    adc : tuple of int
        Raw ADC counts, 1..24 of them, each 0..65535 (0..1023 on the 10-bit 32u4).
    """

    MSG_TYPE: ClassVar[MsgType] = MsgType.SAMPLES

    first_index: int
    period_us: int
    adc: tuple[int, ...]

    def __post_init__(self) -> None:
        _u32("first_index", self.first_index)
        _check_int("period_us", self.period_us, 1, 0xFFFF)
        adc: object = self.adc
        if not isinstance(adc, tuple):  # a list or array given by the caller
            object.__setattr__(self, "adc", tuple(self.adc))
        _check_int("count", len(self.adc), 1, MAX_SAMPLES_PER_BATCH)
        for i, v in enumerate(self.adc):
            _u16(f"adc[{i}]", v)

    @property
    def count(self) -> int:
        """Number of samples in the batch."""
        return len(self.adc)

    def body(self) -> bytes:
        """Body bytes (7 + 2 * count)."""
        n = len(self.adc)
        return _SAMPLES_HEAD.pack(self.first_index, self.period_us, n) + struct.pack(
            f"<{n}H", *self.adc
        )

    @classmethod
    def from_body(cls, body: bytes) -> Samples:
        """Parse a SAMPLES body; raise :class:`FrameError` (kind ``body``) naming the offset."""
        if len(body) < _SAMPLES_HEAD.size:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE,
                f"SAMPLES body of {len(body)} bytes is shorter than its 7-byte head",
            )
        first_index, period_us, count = _SAMPLES_HEAD.unpack_from(body)
        if not 1 <= count <= MAX_SAMPLES_PER_BATCH:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE + 6,
                f"SAMPLES count={count} out of range 1..{MAX_SAMPLES_PER_BATCH}",
            )
        if len(body) != _SAMPLES_HEAD.size + 2 * count:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE + 6,
                f"SAMPLES count={count} needs a {_SAMPLES_HEAD.size + 2 * count}-byte body, "
                f"got {len(body)} bytes",
            )
        if period_us == 0:
            raise FrameError(FrameErrorKind.BODY, HEADER_SIZE + 4, "SAMPLES period_us=0")
        adc = struct.unpack_from(f"<{count}H", body, _SAMPLES_HEAD.size)
        return cls(first_index, period_us, adc)


@dataclass(frozen=True, slots=True)
class Status:
    """STATUS: the probe's heartbeat, at least once per second.

    Parameters
    ----------
    led_level : int
        LED PWM duty, 0..255.
    rate_hz : int
        Sampling rate [Hz], 0..65535 as reported.
    dropped : int
        Samples the probe could not queue since boot, 0..2^32-1.
    supply_mv : int
        Supply voltage [mV], 0..65535.
    flags : StatusFlags
        Streaming, BLE connected, USB CDC open, calibration valid (bits 0..3).
    ble_state, ble_restarts, reset_cause : optional
        The probe's health, sent by firmware 1.1 on after the ten bytes above (a 14-byte
        body); ``None`` for a probe that sends the original 10-byte body. ``ble_restarts``
        counts the times the BLE module, once up, restarted and was probed again.
    """

    MSG_TYPE: ClassVar[MsgType] = MsgType.STATUS

    led_level: int
    rate_hz: int
    dropped: int
    supply_mv: int
    flags: StatusFlags = StatusFlags.NONE
    ble_state: BleState | None = None
    ble_restarts: int | None = None
    reset_cause: ResetCause | None = None

    def __post_init__(self) -> None:
        _u8("led_level", self.led_level)
        _u16("rate_hz", self.rate_hz)
        _u32("dropped", self.dropped)
        _u16("supply_mv", self.supply_mv)
        given: object = self.flags
        flags = _u8("flags", given)
        if not isinstance(given, StatusFlags):
            object.__setattr__(self, "flags", StatusFlags(flags))
        health = (self.ble_state, self.ble_restarts, self.reset_cause)
        if all(h is None for h in health):
            return
        if any(h is None for h in health):
            raise ProtocolError("ble_state, ble_restarts and reset_cause come together")
        state = _check_int("ble_state", self.ble_state, 0, 3)
        _u16("ble_restarts", self.ble_restarts)
        cause = _u8("reset_cause", self.reset_cause)
        object.__setattr__(self, "ble_state", BleState(state))
        object.__setattr__(self, "reset_cause", ResetCause(cause))

    def body(self) -> bytes:
        """Body bytes (10, or 14 with the health fields)."""
        base = _STATUS.pack(
            self.led_level, self.rate_hz, self.dropped, self.supply_mv, int(self.flags)
        )
        if self.ble_state is None or self.ble_restarts is None or self.reset_cause is None:
            return base
        return base + _STATUS_HEALTH.pack(
            int(self.ble_state), self.ble_restarts, int(self.reset_cause)
        )

    @classmethod
    def from_body(cls, body: bytes) -> Status:
        """Parse a STATUS body; raise :class:`FrameError` (kind ``body``) naming the offset."""
        full = _STATUS.size + _STATUS_HEALTH.size
        if len(body) not in (_STATUS.size, full):
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE,
                f"STATUS body must be {_STATUS.size} or {full} bytes, got {len(body)}",
            )
        led, rate, dropped, supply, flags = _STATUS.unpack_from(body)
        if len(body) == _STATUS.size:
            return cls(led, rate, dropped, supply, StatusFlags(flags))
        state, restarts, cause = _STATUS_HEALTH.unpack_from(body, _STATUS.size)
        if state > BleState.UP:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE + _STATUS.size,
                f"STATUS ble_state must be 0..3, got {state}",
            )
        return cls(
            led, rate, dropped, supply, StatusFlags(flags),
            BleState(state), restarts, ResetCause(cause),
        )  # fmt: skip


# --------------------------------------------------------------------------- host → probe


class _TypedCommand:
    """Shared behaviour of the typed COMMAND messages: ``cmd`` byte, arguments, body.

    Subclasses set ``CMD`` and override :meth:`args` when the command takes arguments.
    """

    __slots__ = ()
    MSG_TYPE: ClassVar[MsgType] = MsgType.COMMAND
    CMD: ClassVar[CmdId]

    @property
    def cmd(self) -> int:
        """Command id byte."""
        return int(self.CMD)

    def args(self) -> bytes:
        """Argument bytes (none unless the command overrides this)."""
        return b""

    def body(self) -> bytes:
        """Body bytes: ``cmd`` then arguments."""
        return bytes((self.CMD,)) + self.args()


@dataclass(frozen=True, slots=True)
class StreamStart(_TypedCommand):
    """STREAM_START: begin sending SAMPLES."""

    CMD: ClassVar[CmdId] = CmdId.STREAM_START


@dataclass(frozen=True, slots=True)
class StreamStop(_TypedCommand):
    """STREAM_STOP: stop sending SAMPLES."""

    CMD: ClassVar[CmdId] = CmdId.STREAM_STOP


@dataclass(frozen=True, slots=True)
class SetRate(_TypedCommand):
    """SET_RATE: sampling rate [Hz], ``RATE_MIN_HZ``..``RATE_MAX_HZ`` (16..1000)."""

    CMD: ClassVar[CmdId] = CmdId.SET_RATE

    rate_hz: int

    def __post_init__(self) -> None:
        _check_int("rate_hz", self.rate_hz, RATE_MIN_HZ, RATE_MAX_HZ)

    def args(self) -> bytes:
        """Argument bytes: ``rate_hz u16``."""
        return _U16.pack(self.rate_hz)


@dataclass(frozen=True, slots=True)
class SetLed(_TypedCommand):
    """SET_LED: LED PWM duty ``level``, 0..255."""

    CMD: ClassVar[CmdId] = CmdId.SET_LED

    level: int

    def __post_init__(self) -> None:
        _u8("level", self.level)

    def args(self) -> bytes:
        """Argument bytes: ``level u8``."""
        return _U8.pack(self.level)


@dataclass(frozen=True, slots=True)
class Tare(_TypedCommand):
    """TARE: average the next 16 samples into ``zero_counts`` and store it in EEPROM."""

    CMD: ClassVar[CmdId] = CmdId.TARE


@dataclass(frozen=True, slots=True)
class WriteCal(_TypedCommand):
    """WRITE_CAL: store tare and span in EEPROM.

    Parameters
    ----------
    zero_counts : int
        ADC count at zero force, 0..65535.
    span_un_per_count : int
        Force per ADC count [µN/count], -2^31..2^31-1.
    """

    CMD: ClassVar[CmdId] = CmdId.WRITE_CAL

    zero_counts: int
    span_un_per_count: int

    def __post_init__(self) -> None:
        _u16("zero_counts", self.zero_counts)
        _i32("span_un_per_count", self.span_un_per_count)

    def args(self) -> bytes:
        """Argument bytes: ``zero_counts u16, span_un_per_count i32``."""
        return _WRITE_CAL.pack(self.zero_counts, self.span_un_per_count)


@dataclass(frozen=True, slots=True)
class GetInfo(_TypedCommand):
    """GET_INFO: ask for firmware version, settings and calibration (:class:`InfoResult`)."""

    CMD: ClassVar[CmdId] = CmdId.GET_INFO


@dataclass(frozen=True, slots=True)
class RawCommand:
    """COMMAND bytes that are not a valid command: an unknown id or bad arguments.

    Decoding gives one of these instead of failing, because the probe must answer such a
    command with an ACK (:attr:`refusal`). Encoding one sends ``cmd`` and ``args``
    unchecked, to test that refusal.

    Parameters
    ----------
    cmd : int
        Command id byte, 0..255.
    args : bytes
        Argument bytes, at most 63.
    reason : str
        Why the bytes are not a valid command (empty for a hand-built one).
    """

    MSG_TYPE: ClassVar[MsgType] = MsgType.COMMAND

    cmd: int
    args: bytes = b""
    reason: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        _u8("cmd", self.cmd)
        if len(self.args) > MAX_BODY_SIZE - 1:
            raise ProtocolError(f"args of {len(self.args)} bytes exceed {MAX_BODY_SIZE - 1}")
        object.__setattr__(self, "args", bytes(self.args))

    @property
    def refusal(self) -> AckStatus:
        """ACK status the probe answers with: unknown command or bad argument."""
        return (
            AckStatus.BAD_ARGUMENT
            if self.cmd in CmdId._value2member_map_
            else AckStatus.UNKNOWN_COMMAND
        )

    def body(self) -> bytes:
        """Body bytes: ``cmd`` then arguments."""
        return bytes((self.cmd,)) + self.args


Command: TypeAlias = (
    StreamStart | StreamStop | SetRate | SetLed | Tare | WriteCal | GetInfo | RawCommand
)
"""A COMMAND message."""

_NO_ARG_COMMANDS: Final[dict[int, Command]] = {
    CmdId.STREAM_START: StreamStart(),
    CmdId.STREAM_STOP: StreamStop(),
    CmdId.TARE: Tare(),
    CmdId.GET_INFO: GetInfo(),
}


def parse_command(cmd: int, args: bytes) -> Command:
    """Typed command for ``cmd`` and ``args``, or a :class:`RawCommand` saying why not.

    Parameters
    ----------
    cmd : int
        Command id byte.
    args : bytes
        Argument bytes after the id.

    Returns
    -------
    Command
        The typed command, or :class:`RawCommand` with ``reason`` set for an unknown id,
        arguments of the wrong length, or an argument out of range.
    """
    if cmd not in CmdId._value2member_map_:
        return RawCommand(cmd, args, reason=f"unknown command 0x{cmd:02X}")
    cid = CmdId(cmd)
    expected = {CmdId.SET_RATE: 2, CmdId.SET_LED: 1, CmdId.WRITE_CAL: _WRITE_CAL.size}.get(cid, 0)
    if len(args) != expected:
        return RawCommand(
            cmd, args, reason=f"{cid.name} takes {expected} argument bytes, got {len(args)}"
        )
    try:
        if cid == CmdId.SET_RATE:
            return SetRate(_U16.unpack(args)[0])
        if cid == CmdId.SET_LED:
            return SetLed(args[0])
        if cid == CmdId.WRITE_CAL:
            zero, span = _WRITE_CAL.unpack(args)
            return WriteCal(zero, span)
    except ProtocolError as exc:
        return RawCommand(cmd, args, reason=f"{cid.name}: {exc}")
    return _NO_ARG_COMMANDS[cid]


# --------------------------------------------------------------------------- ACK


@dataclass(frozen=True, slots=True)
class TareResult:
    """Result of an accepted TARE: ``zero_counts`` [ADC counts], 0..65535."""

    zero_counts: int

    def __post_init__(self) -> None:
        _u16("zero_counts", self.zero_counts)

    def to_bytes(self) -> bytes:
        """Result bytes in the ACK (2)."""
        return _U16.pack(self.zero_counts)


@dataclass(frozen=True, slots=True)
class InfoResult:
    """Result of GET_INFO.

    Parameters
    ----------
    proto : int
        Protocol version the firmware speaks, 0..255.
    fw_major, fw_minor, fw_patch : int
        Firmware version, 0..255 each.
    rate_hz : int
        Current sampling rate [Hz], 0..65535.
    led_level : int
        Current LED PWM duty, 0..255.
    zero_counts : int
        Stored tare [ADC counts], 0..65535.
    span_un_per_count : int
        Stored span [µN/count], -2^31..2^31-1.
    adc_bits : int
        ADC resolution [bits], 0..255 (10 on the 32u4).
    batch : int
        Samples per SAMPLES message, 0..255.
    """

    proto: int
    fw_major: int
    fw_minor: int
    fw_patch: int
    rate_hz: int
    led_level: int
    zero_counts: int
    span_un_per_count: int
    adc_bits: int
    batch: int

    def __post_init__(self) -> None:
        for name in ("proto", "fw_major", "fw_minor", "fw_patch", "led_level", "adc_bits", "batch"):
            _u8(name, getattr(self, name))
        _u16("rate_hz", self.rate_hz)
        _u16("zero_counts", self.zero_counts)
        _i32("span_un_per_count", self.span_un_per_count)

    def to_bytes(self) -> bytes:
        """Result bytes in the ACK (15)."""
        return _INFO.pack(
            self.proto,
            self.fw_major,
            self.fw_minor,
            self.fw_patch,
            self.rate_hz,
            self.led_level,
            self.zero_counts,
            self.span_un_per_count,
            self.adc_bits,
            self.batch,
        )


AckResult: TypeAlias = TareResult | InfoResult
"""Typed result carried by an OK ACK."""

_RESULT_TYPES: Final[dict[int, type[TareResult] | type[InfoResult]]] = {
    CmdId.TARE: TareResult,
    CmdId.GET_INFO: InfoResult,
}


@dataclass(frozen=True, slots=True)
class Ack:
    """ACK: the probe's answer to the command with sequence number ``ref_seq``.

    Parameters
    ----------
    ref_seq : int
        ``seq`` of the command answered, 0..65535.
    cmd : int
        Command id repeated (any byte when ``status`` is UNKNOWN_COMMAND), 0..255.
    status : AckStatus
        Outcome.
    result : TareResult or InfoResult or None
        Present exactly for an OK answer to TARE (:class:`TareResult`) or GET_INFO
        (:class:`InfoResult`).
    """

    MSG_TYPE: ClassVar[MsgType] = MsgType.ACK

    ref_seq: int
    cmd: int
    status: AckStatus = AckStatus.OK
    result: AckResult | None = None

    def __post_init__(self) -> None:
        _u16("ref_seq", self.ref_seq)
        _u8("cmd", self.cmd)
        given: object = self.status
        status = _check_int("status", given, 0, max(AckStatus))
        if not isinstance(given, AckStatus):
            object.__setattr__(self, "status", AckStatus(status))
        want = _RESULT_TYPES.get(self.cmd) if status == AckStatus.OK else None
        if status == AckStatus.OK and self.cmd not in CmdId._value2member_map_:
            raise ProtocolError(f"cmd=0x{self.cmd:02X} is not a command; it cannot be OK")
        if want is None and self.result is not None:
            raise ProtocolError(
                f"result must be None for cmd=0x{self.cmd:02X} status={AckStatus(status).name}"
            )
        if want is not None and not isinstance(self.result, want):
            raise ProtocolError(
                f"result must be a {want.__name__} for an OK {CmdId(self.cmd).name}, "
                f"got {self.result!r}"
            )

    @property
    def ok(self) -> bool:
        """Whether the command was executed."""
        return self.status == AckStatus.OK

    def info(self) -> InfoResult:
        """The GET_INFO result; raise :class:`ProtocolError` if this ACK carries none."""
        if not isinstance(self.result, InfoResult):
            raise ProtocolError(
                f"ACK of cmd=0x{self.cmd:02X} status={self.status.name} carries no GET_INFO result"
            )
        return self.result

    def tare(self) -> TareResult:
        """The TARE result; raise :class:`ProtocolError` if this ACK carries none."""
        if not isinstance(self.result, TareResult):
            raise ProtocolError(
                f"ACK of cmd=0x{self.cmd:02X} status={self.status.name} carries no TARE result"
            )
        return self.result

    def body(self) -> bytes:
        """Body bytes: ``ref_seq, cmd, status`` then the result."""
        head = _ACK_HEAD.pack(self.ref_seq, self.cmd, self.status)
        return head if self.result is None else head + self.result.to_bytes()

    @classmethod
    def from_body(cls, body: bytes) -> Ack:
        """Parse an ACK body; raise :class:`FrameError` (kind ``body``) naming the offset."""
        if len(body) < _ACK_HEAD.size:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE,
                f"ACK body of {len(body)} bytes is shorter than its 4-byte head",
            )
        ref_seq, cmd, status = _ACK_HEAD.unpack_from(body)
        if status > max(AckStatus):
            raise FrameError(FrameErrorKind.BODY, HEADER_SIZE + 3, f"ACK status={status} unknown")
        if status == AckStatus.OK and cmd not in CmdId._value2member_map_:
            raise FrameError(
                FrameErrorKind.BODY, HEADER_SIZE + 2, f"OK ACK of unknown cmd=0x{cmd:02X}"
            )
        rtype = _RESULT_TYPES.get(cmd) if status == AckStatus.OK else None
        rest = body[_ACK_HEAD.size :]
        want_len = 0 if rtype is None else (2 if rtype is TareResult else _INFO.size)
        if len(rest) != want_len:
            raise FrameError(
                FrameErrorKind.BODY,
                HEADER_SIZE + _ACK_HEAD.size,
                f"ACK of cmd=0x{cmd:02X} status={status} needs a {want_len}-byte result, "
                f"got {len(rest)} bytes",
            )
        result: AckResult | None = None
        if rtype is TareResult:
            result = TareResult(_U16.unpack(rest)[0])
        elif rtype is InfoResult:
            result = InfoResult(*_INFO.unpack(rest))
        return cls(ref_seq, cmd, AckStatus(status), result)


Message: TypeAlias = Samples | Status | Command | Ack
"""Any message of protocol version 1."""


# --------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame: header fields and message.

    Parameters
    ----------
    seq : int
        Sender's frame counter, 0..65535.
    t_us : int
        Sender clock when the content was produced [µs], raw u32 (wraps every ~71.6 min).
    message : Message
        The message carried.
    """

    seq: int
    t_us: int
    message: Message


def pack_frame(message: Message, seq: int, t_us: int) -> bytes:
    """Header, body and CRC of ``message`` (before COBS).

    Parameters
    ----------
    message : Message
        Message to send (already range-checked by its constructor).
    seq : int
        Frame counter, 0..65535.
    t_us : int
        Sender clock [µs], 0..2^32-1.

    Returns
    -------
    bytes
        The frame, 10..74 bytes.
    """
    _u16("seq", seq)
    _u32("t_us", t_us)
    body = message.body()
    if len(body) > MAX_BODY_SIZE:
        raise ProtocolError(f"body of {len(body)} bytes exceeds {MAX_BODY_SIZE}")
    frame = _HEADER.pack(PROTOCOL_VERSION, message.MSG_TYPE, seq, t_us) + body
    return frame + _CRC.pack(crc16_ccitt(frame))


def encode_frame(message: Message, seq: int, t_us: int) -> bytes:
    """Wire bytes of ``message``: COBS-encoded frame followed by the 0x00 delimiter.

    Parameters
    ----------
    message : Message
        Message to send.
    seq : int
        Frame counter, 0..65535.
    t_us : int
        Sender clock [µs], 0..2^32-1.

    Returns
    -------
    bytes
        12..76 bytes, the last one 0x00 and no other.
    """
    return cobs_encode(pack_frame(message, seq, t_us)) + b"\x00"


def _parse_body(msg_type: int, body: bytes) -> Message:
    if msg_type == MsgType.SAMPLES:
        return Samples.from_body(body)
    if msg_type == MsgType.STATUS:
        return Status.from_body(body)
    if msg_type == MsgType.ACK:
        return Ack.from_body(body)
    # COMMAND
    if not body:
        raise FrameError(FrameErrorKind.BODY, HEADER_SIZE, "COMMAND body is empty (no cmd byte)")
    return parse_command(body[0], body[1:])


def unpack_frame(frame: bytes | bytearray | memoryview) -> Frame:
    """Check and parse one frame (header, body, CRC; COBS already removed).

    The checks run in this order: length (10..74 bytes), CRC, version, type, body.

    Parameters
    ----------
    frame : bytes-like
        The decoded frame.

    Returns
    -------
    Frame
        Its header fields and message.

    Raises
    ------
    FrameError
        Naming the failed check and the byte offset inside ``frame``.
    """
    raw = bytes(frame)
    n = len(raw)
    if not MIN_FRAME_SIZE <= n <= MAX_FRAME_SIZE:
        raise FrameError(
            FrameErrorKind.LENGTH,
            0,
            f"frame of {n} bytes outside {MIN_FRAME_SIZE}..{MAX_FRAME_SIZE}",
        )
    got = raw[-2] | (raw[-1] << 8)
    want = crc16_ccitt(raw[:-2])
    if got != want:
        raise FrameError(
            FrameErrorKind.CRC,
            n - 2,
            f"CRC 0x{got:04X} does not match 0x{want:04X} computed over {n - 2} bytes",
        )
    version, msg_type, seq, t_us = _HEADER.unpack_from(raw)
    if version != PROTOCOL_VERSION:
        raise FrameError(
            FrameErrorKind.VERSION, 0, f"protocol version {version}, expected {PROTOCOL_VERSION}"
        )
    if msg_type not in MsgType._value2member_map_:
        raise FrameError(FrameErrorKind.TYPE, 1, f"unknown message type 0x{msg_type:02X}")
    try:
        message = _parse_body(msg_type, raw[HEADER_SIZE:-2])
    except FrameError:
        raise
    except ProtocolError as exc:  # a constructor's range check
        raise FrameError(FrameErrorKind.BODY, HEADER_SIZE, str(exc)) from exc
    return Frame(seq, t_us, message)


def decode_frame(encoded: bytes | bytearray | memoryview) -> Frame:
    """Decode the wire bytes of one frame (COBS, with or without its 0x00 delimiter).

    Parameters
    ----------
    encoded : bytes-like
        One COBS-encoded frame, optionally followed by one 0x00.

    Returns
    -------
    Frame
        Its header fields and message.

    Raises
    ------
    FrameError
        Naming the failed check; the offset is inside ``encoded`` for ``cobs`` errors and
        an over-long encoding, inside the decoded frame otherwise.
    """
    enc = bytes(encoded)
    if enc.endswith(b"\x00"):
        enc = enc[:-1]
    if len(enc) > MAX_ENCODED_SIZE:
        raise FrameError(
            FrameErrorKind.LENGTH,
            MAX_ENCODED_SIZE,
            f"encoded frame of {len(enc)} bytes exceeds {MAX_ENCODED_SIZE}",
        )
    return unpack_frame(cobs_decode(enc))
