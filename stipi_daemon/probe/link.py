"""The daemon's probe-side adapter: one probe, over any transport, as a stream of events.

This module owns :class:`ProbeLink`. Over a :class:`~stipi_daemon.probe.transports.base.Transport`
it decodes the probe's frames (:class:`~stipi_daemon.protocol.FrameDecoder`), accounts for
every sample (:class:`~stipi_daemon.protocol.SampleAccounting`: gaps are exact, samples
sent = received + lost), maps the probe's microsecond clock onto the session clock
(:class:`~stipi_daemon.protocol.clocksync.ClockSync`, fed the last sample time of each SAMPLES
batch), converts ADC counts to force (``force_n = (adc - zero_counts) * span_un_per_count
* 1e-6``, docs/protocol.md), sends commands and matches their ACKs (``ref_seq``), with a
timeout and retries, configures the probe at connect (GET_INFO, SET_RATE, SET_LED, and
STREAM_START once streaming was asked for), watches the heartbeat (no valid frame for
``heartbeat_timeout_s`` means the link is lost even if the port is still open), and
reconnects with exponential backoff bounded in total time, configuring the probe again.

Output: :meth:`ProbeLink.events`, an async iterator of :class:`ForceRows`, :class:`Gap`,
:class:`ClockProbe`, :class:`LinkDown`, :class:`LinkUp`, :class:`StatusReport` and
:class:`DecoderErrors`. All times are on the session clock
(:class:`~stipi_daemon.clock.SessionClock`), including timeouts and the reconnect budget
(the same as wall time for real devices, speed 1). On an accelerated clock (simulated
probes) the heartbeat and command timeouts are never shorter than ``min(timeout,
min_wall_s)`` of wall time (:func:`wall_floored_timeout_s`): a loaded host's scheduling
hiccup does not shrink with the speed-up. It does not store, analyse or display
anything, and it knows nothing of pyserial or BLE.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field, replace
from typing import Any, Final, Literal, TypeAlias

from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import DeviceNotFoundError, LinkLostError, ProtocolError, StipiError
from stipi_daemon.probe.transports.base import Releasable, Transport
from stipi_daemon.protocol.accounting import SampleAccounting, SampleGap
from stipi_daemon.protocol.clocksync import ClockSync, ClockSyncConfig
from stipi_daemon.protocol.decoder import PROBE_TO_HOST_TYPES, DecodedFrame, FrameDecoder
from stipi_daemon.protocol.messages import (
    RATE_MAX_HZ,
    RATE_MIN_HZ,
    Ack,
    AckStatus,
    BleState,
    Command,
    GetInfo,
    InfoResult,
    ResetCause,
    Samples,
    SetLed,
    SetRate,
    Status,
    StatusFlags,
    StreamStart,
    StreamStop,
    Tare,
    WriteCal,
    encode_frame,
)
from stipi_daemon.protocol.timestamps import SeqEvent

__all__ = [
    "FAULT_COUNTERS",
    "LINK_MIN_WALL_S",
    "ClockProbe",
    "DecoderErrors",
    "ForceRow",
    "ForceRows",
    "Gap",
    "LinkDown",
    "LinkUp",
    "ProbeEvent",
    "ProbeLink",
    "StatusReport",
    "wall_floored_timeout_s",
]

_U32: Final = 1 << 32
FAULT_COUNTERS: Final = (
    "bytes_discarded",
    "crc_errors",
    "cobs_errors",
    "length_errors",
    "version_errors",
    "unknown_type",
    "body_errors",
    "wrong_direction",
    "gaps",
    "frames_lost",
    "duplicates",
    "restarts",
)
"""DecoderStats counters reported by :class:`DecoderErrors` (zero on a clean link)."""


# ============================================================================ events


@dataclass(frozen=True, slots=True)
class ForceRow:
    """One load-cell sample.

    Parameters
    ----------
    sample_index : int
        The probe's sample counter (``first_index`` numbering, u32; restarts at a reboot).
    adc_counts : int
        Raw ADC reading [counts].
    t_mcu_raw_us : int
        Probe clock when the sample was taken, as sent (mod 2^32) [µs].
    t_mcu_us : int
        The same, unwrapped to 64 bits [µs].
    t_host_s : float
        The same mapped onto the session clock by the clock sync [s].
    force_n : float or None
        ``(adc - zero_counts) * span_un_per_count * 1e-6`` [N]; None without a calibration.
    """

    sample_index: int
    adc_counts: int
    t_mcu_raw_us: int
    t_mcu_us: int
    t_host_s: float
    force_n: float | None


@dataclass(frozen=True, slots=True)
class ForceRows:
    """The samples of one SAMPLES frame, in order."""

    rows: list[ForceRow]


@dataclass(frozen=True, slots=True)
class Gap:
    """Samples the probe took that the host never received.

    Parameters
    ----------
    start_index : int
        Index of the first missing sample (u32).
    count : int
        Number of missing samples.
    cause : "link" or "probe"
        ``link``: frames were lost on the link (sequence gap or disconnection); ``probe``:
        the probe dropped them (its ring overflowed, STATUS ``dropped``).
    t_host_s : float
        Session time of the first missing sample (mapped from the probe clock) [s].
    """

    start_index: int
    count: int
    cause: Literal["link", "probe"]
    t_host_s: float


@dataclass(frozen=True, slots=True)
class ClockProbe:
    """One clock observation: the last sample time of a SAMPLES frame and its arrival.

    Parameters
    ----------
    mcu_raw_us : int
        Probe clock as sent (mod 2^32) [µs].
    mcu_unwrapped_us : int
        The same, unwrapped [µs].
    host_s : float
        Session time the frame was received [s].
    """

    mcu_raw_us: int
    mcu_unwrapped_us: int
    host_s: float


@dataclass(frozen=True, slots=True)
class LinkDown:
    """The link was lost (``reason`` names what was seen) at session time ``t_s`` [s]."""

    t_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class LinkUp:
    """The probe answered and is configured, at session time ``t_s`` [s]."""

    t_s: float
    info: InfoResult
    reconnect: bool = False
    """False for the first connection, True after a :class:`LinkDown`."""


@dataclass(frozen=True, slots=True)
class StatusReport:
    """A STATUS heartbeat.

    Parameters
    ----------
    t_host_s : float
        Session time it was received [s].
    t_mcu_us : int
        Probe clock when it was sent, unwrapped [µs].
    led_level, rate_hz, dropped, supply_mv, flags
        As in STATUS (docs/protocol.md): LED duty, rate [Hz], samples dropped in the probe
        since boot, supply [mV], flags.
    ble_state, ble_restarts, reset_cause
        The probe's health (firmware 1.1 on); ``None`` from a probe that does not send it.
    """

    t_host_s: float
    t_mcu_us: int
    led_level: int
    rate_hz: int
    dropped: int
    supply_mv: int
    flags: StatusFlags
    ble_state: BleState | None = None
    ble_restarts: int | None = None
    reset_cause: ResetCause | None = None


def _flag_names(cause: ResetCause) -> str:
    names = [m.name.lower() for m in ResetCause if m and m in cause and m.name]
    return " or ".join(names) if names else "unknown"


class ProbeHealth:
    """Which STATUS heartbeats the session records as a ``probe_health`` event: the first
    one that reports the probe's health (why it started, its BLE module's state and
    restarts), then each one where that changed. :meth:`forget` after the link came back,
    so that a restarted probe's reason is recorded even when it is the same as before."""

    def __init__(self) -> None:
        self._last: tuple[object, ...] | None = None

    def forget(self) -> None:
        self._last = None

    def observe(self, report: StatusReport) -> dict[str, object] | None:
        """The event's detail when ``report`` should be recorded, else None."""
        if report.reset_cause is None or report.ble_state is None:
            return None  # a probe that predates the health fields
        now = (report.reset_cause, report.ble_state, report.ble_restarts)
        if now == self._last:
            return None
        self._last = now
        return {
            "reset_cause": _flag_names(report.reset_cause),
            "ble_state": report.ble_state.name.lower(),
            "ble_restarts": report.ble_restarts,
        }


@dataclass(frozen=True, slots=True)
class DecoderErrors:
    """Link damage seen since the previous report: decoder counters that increased.

    ``delta`` maps :class:`~stipi_daemon.protocol.DecoderStats` counter names (``crc_errors``,
    ``frames_lost``, ``bytes_discarded`` ...) to their increase; ``t_s`` is the session
    time [s].
    """

    t_s: float
    delta: dict[str, int] = field(default_factory=dict)


ProbeEvent: TypeAlias = (
    ForceRows | Gap | ClockProbe | LinkDown | LinkUp | StatusReport | DecoderErrors
)
"""Anything :meth:`ProbeLink.events` yields."""


@dataclass(frozen=True, slots=True)
class _End:
    error: BaseException | None


class _Restarted(Exception):
    """The probe restarted under a live link: it must be configured again."""


# ============================================================================ the link

#: Wall time below which the link's timeouts do not shrink on an accelerated clock [s].
LINK_MIN_WALL_S: Final = 1.0
#: Longest a command whose write failed waits for the reader to declare the link lost
#: (it does within a few loop iterations: the transport wakes it) [s of wall time].
_LOST_NOTICE_WALL_S: Final = 0.5


def wall_floored_timeout_s(timeout_s: float, speed: float, min_wall_s: float) -> float:
    """A timeout on a session clock running ``speed`` times wall time, floored in wall time.

    Returns ``max(timeout_s, min(timeout_s, min_wall_s) * speed)`` [session s]: unchanged at
    speed <= 1 or with ``min_wall_s`` 0, otherwise at least ``min(timeout_s, min_wall_s)``
    of wall time, so that a host's hiccup of a fraction of a second, which lasts ``speed``
    times longer in session time, is not taken for a silent probe (the camera's stall
    timeout has the same kind of floor, ``cameras.stream.STALL_MIN_WALL_S``). Domain:
    ``timeout_s`` > 0, ``speed`` > 0, ``min_wall_s`` >= 0, all finite.
    """
    return max(timeout_s, min(timeout_s, min_wall_s) * speed)


class ProbeLink:
    """One probe over one transport: connect, configure, stream, watch, reconnect.

    Parameters
    ----------
    transport : Transport
        The link (unopened; :meth:`connect` opens it, reconnects reopen it).
    clock : SessionClock
        Session clock: host timestamps, timeouts, watchdog and backoff.
    rate_hz : int
        Sampling rate to configure [Hz], 16..1000.
    led_level : int
        LED PWM duty to configure, 0..255.
    heartbeat_timeout_s : float
        No valid frame for this long means the link is lost [s] (the probe sends STATUS
        at least every 1 s).
    reconnect_total_s : float
        Give up reconnecting after this long [s] (then :meth:`events` raises
        :class:`~stipi_daemon.errors.LinkLostError`).
    command_timeout_s : float
        Wait for an ACK this long per attempt [s].
    command_retries : int
        Extra attempts for commands that are safe to repeat (all but TARE).
    reconnect_initial_s, reconnect_max_s : float
        First and longest pause between reconnect attempts (doubling) [s].
    zero_counts, span_un_per_count : int, optional
        Calibration to use when the probe has none (span 0 in GET_INFO), or always with
        ``prefer_config_calibration`` [counts], [µN/count].
    prefer_config_calibration : bool
        Use the given calibration even when the probe has one.
    clock_sync : ClockSyncConfig, optional
        Parameters of the clock fit.
    min_wall_s : float
        On an accelerated clock, the heartbeat and command timeouts last at least
        ``min(timeout, min_wall_s)`` of wall time [s] (:func:`wall_floored_timeout_s`);
        0 scales them with the clock exactly.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        clock: SessionClock,
        rate_hz: int = 100,
        led_level: int = 0,
        heartbeat_timeout_s: float = 2.5,
        reconnect_total_s: float = 30.0,
        command_timeout_s: float = 0.5,
        command_retries: int = 3,
        reconnect_initial_s: float = 0.1,
        reconnect_max_s: float = 2.0,
        zero_counts: int | None = None,
        span_un_per_count: int | None = None,
        prefer_config_calibration: bool = False,
        clock_sync: ClockSyncConfig | None = None,
        min_wall_s: float = LINK_MIN_WALL_S,
    ) -> None:
        if not RATE_MIN_HZ <= rate_hz <= RATE_MAX_HZ:
            raise ProtocolError(f"rate_hz={rate_hz} out of range {RATE_MIN_HZ}..{RATE_MAX_HZ}")
        if not 0 <= led_level <= 255:
            raise ProtocolError(f"led_level={led_level} out of range 0..255")
        for name, value in (
            ("heartbeat_timeout_s", heartbeat_timeout_s),
            ("reconnect_total_s", reconnect_total_s),
            ("command_timeout_s", command_timeout_s),
            ("reconnect_initial_s", reconnect_initial_s),
            ("reconnect_max_s", reconnect_max_s),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value} must be a positive number of seconds")
        if not (math.isfinite(min_wall_s) and min_wall_s >= 0):
            raise ValueError(f"min_wall_s={min_wall_s} must be a non-negative number of seconds")
        if command_retries < 0:
            raise ValueError(f"command_retries={command_retries} must not be negative")
        if (zero_counts is None) != (span_un_per_count is None):
            raise ValueError("zero_counts and span_un_per_count must be given together")
        self.transport = transport
        self.clock = clock
        self.rate_hz = rate_hz
        self.led_level = led_level
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.reconnect_total_s = reconnect_total_s
        self.command_timeout_s = command_timeout_s
        self.command_retries = command_retries
        self.min_wall_s = min_wall_s
        self.reconnect_initial_s = reconnect_initial_s
        self.reconnect_max_s = reconnect_max_s
        self._config_cal = (
            None
            if zero_counts is None or span_un_per_count is None
            else (zero_counts, span_un_per_count)
        )
        self._prefer_config_cal = prefer_config_calibration
        # The probe sends SAMPLES, STATUS and ACK only: a COMMAND on its stream (the host's
        # own bytes echoed back) is dropped, counted, and never sequenced.
        self.decoder = FrameDecoder(accept=PROBE_TO_HOST_TYPES)
        self.accounting = SampleAccounting()
        self.clock_sync = ClockSync(clock_sync)
        #: Mapped time of the last sample [s] and how often a sample's mapped time was held
        #: after it because the clock fit moved back (see ``_on_samples``).
        self._last_t_host: float | None = None
        self.monotone_clamped = 0
        self.info: InfoResult | None = None
        """The last GET_INFO answer."""
        self.calibration: tuple[int, int] | None = None
        """(zero_counts, span_un_per_count) in use, None when forces cannot be computed."""
        self.calibration_source: Literal["probe", "config", "none"] = "none"
        self.connects = 0
        """Successful connections (1 + reconnects)."""
        self._seq = 0
        self._pending: dict[int, tuple[asyncio.Future[Ack], int]] = {}
        self._queue: asyncio.Queue[ProbeEvent | _End] = asyncio.Queue()
        self._want_stream = False
        self._up = False
        self._closed = False
        self._lost: asyncio.Future[str] | None = None
        self._conn_tasks: list[asyncio.Task[None]] = []
        self._supervisor: asyncio.Task[None] | None = None
        self._last_frame_s = 0.0
        self._reported: dict[str, int] = dict.fromkeys(FAULT_COUNTERS, 0)

    # ------------------------------------------------------------------ public API

    @property
    def name(self) -> str:
        """The transport's name."""
        return self.transport.name

    @property
    def is_up(self) -> bool:
        """Whether the link is connected and configured."""
        return self._up

    async def connect(self) -> InfoResult:
        """Open the transport, ask GET_INFO and configure rate and LED.

        Returns
        -------
        InfoResult
            The probe's answer to GET_INFO.

        Raises
        ------
        DeviceNotFoundError
            The device is not there (one line naming it).
        LinkLostError
            The device is there but does not answer.
        """
        if self._supervisor is not None:
            raise RuntimeError("ProbeLink.connect called twice")
        if self._closed:
            raise RuntimeError("ProbeLink is closed")
        try:
            info = await self._establish()
        except BaseException:
            await self._teardown()
            raise
        self._queue.put_nowait(LinkUp(self.clock.now(), info))
        self._supervisor = asyncio.get_running_loop().create_task(
            self._supervise(), name=f"probe-link {self.name}"
        )
        return info

    async def start_stream(self) -> bool:
        """Ask the probe to stream, now and after every reconnect; whether the probe
        acknowledged this STREAM_START (False: only the wish is recorded).

        While the link is down this only records the wish; the reconnection starts the stream.
        So does a link that goes down while STREAM_START waits for its ACK (a BLE drop at that
        moment): the reconnection sends it again, and a link that does not come back ends
        :meth:`events` with :class:`~stipi_daemon.errors.LinkLostError`.

        Raises
        ------
        LinkLostError
            The link stayed up and the probe did not answer.
        ProtocolError
            The probe refused.
        """
        self._want_stream = True
        if not self._up:
            return False
        lost = self._lost
        try:
            await self._command_ok(StreamStart())
        except LinkLostError:
            if self._closed or lost is None:
                raise
            if not lost.done():  # a failed write: the reader declares the link lost at once
                with contextlib.suppress(TimeoutError):
                    async with self.clock.timeout(_LOST_NOTICE_WALL_S * self.clock.speed):
                        await asyncio.wait([lost])
            if not lost.done():  # the link is up and the probe did not answer
                raise
            # the link went down meanwhile (LinkDown is queued): its return starts the stream
            return False
        return True

    async def stop_stream(self) -> None:
        """Ask the probe to stop streaming (and not to stream after a reconnect)."""
        self._want_stream = False
        if self._up:
            await self._command_ok(StreamStop())

    async def set_led(self, level: int) -> None:
        """Set the LED PWM duty (kept across reconnects)."""
        await self._command_ok(SetLed(level))
        self.led_level = level

    async def set_rate(self, rate_hz: int) -> None:
        """Set the sampling rate [Hz] (kept across reconnects)."""
        await self._command_ok(SetRate(rate_hz))
        self.rate_hz = rate_hz

    async def tare(self) -> int:
        """Tare the probe (mean of its next 16 samples, stored in EEPROM); return the zero."""
        ack = await self._command_ok(Tare())
        zero = ack.tare().zero_counts
        if self.info is not None:
            self._set_info(replace(self.info, zero_counts=zero))
        return zero

    async def write_calibration(self, zero_counts: int, span_un_per_count: int) -> None:
        """Store a calibration in the probe's EEPROM and use it."""
        await self._command_ok(WriteCal(zero_counts, span_un_per_count))
        if self.info is not None:
            self._set_info(
                replace(self.info, zero_counts=zero_counts, span_un_per_count=span_un_per_count)
            )

    async def command(
        self, command: Command, *, timeout_s: float | None = None, retries: int | None = None
    ) -> Ack:
        """Send ``command`` and return its ACK (any status).

        Each attempt has a new ``seq``; an ACK to any attempt answers the command. TARE is
        never repeated (a second one would be refused as busy), and waits for its 16
        samples on top of ``timeout_s``.

        Raises
        ------
        LinkLostError
            No ACK after every attempt, or the link is down.
        """
        if self._closed:
            raise LinkLostError(f"{self.name}: the probe link is closed")
        if self._lost is None or self._lost.done():
            raise LinkLostError(f"{self.name}: the probe link is down")
        per_try = self.command_timeout_s if timeout_s is None else timeout_s
        tries = 1 + (self.command_retries if retries is None else retries)
        if isinstance(command, Tare):
            tries = 1
            per_try += 1.5 * 16 / self.rate_hz
        per_try = self._floored(per_try)
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Ack] = loop.create_future()
        seqs: list[int] = []
        try:
            for _ in range(tries):
                seq = self._seq
                self._seq = (self._seq + 1) & 0xFFFF
                seqs.append(seq)
                self._pending[seq] = (fut, command.cmd)
                t_us = int(self.clock.now() * 1e6) % _U32
                await self.transport.write(encode_frame(command, seq, t_us))
                # asyncio.timeout, not wait_for, whose Python 3.11 version drops a cancel
                # that comes with the answer (clock.wait_event)
                with contextlib.suppress(TimeoutError):
                    async with self.clock.timeout(per_try):
                        return await asyncio.shield(fut)
        finally:
            for seq in seqs:
                self._pending.pop(seq, None)
        raise LinkLostError(
            f"{self.name}: no answer to {type(command).__name__} after {tries} "
            f"attempt{'s' if tries > 1 else ''} of {per_try:g} s"
        )

    async def events(self) -> AsyncIterator[ProbeEvent]:
        """The probe's events, in order, until :meth:`close`.

        Raises
        ------
        LinkLostError
            The link was lost and did not come back within ``reconnect_total_s``.
        """
        while True:
            ev = await self._queue.get()
            if isinstance(ev, _End):
                self._queue.put_nowait(ev)  # later calls end too
                if ev.error is not None:
                    raise ev.error
                return
            yield ev

    async def close(self) -> None:
        """Stop, close the transport (and release an emulated device); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        sup, self._supervisor = self._supervisor, None
        if sup is not None:
            sup.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sup
        await self._teardown()
        if isinstance(self.transport, Releasable):
            await self.transport.release()
        self._queue.put_nowait(_End(None))

    async def __aenter__(self) -> ProbeLink:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def info_dict(self) -> dict[str, Any]:
        """What the session metadata records about the probe and the link."""
        info = self.info
        out: dict[str, Any] = {
            "transport": self.name,
            "probe_id": probe_id_of(self.transport),
            "rate_hz": self.rate_hz,
            "led_level": self.led_level,
            "calibration_source": self.calibration_source,
        }
        if info is not None:
            out.update(
                proto=info.proto,
                firmware=f"{info.fw_major}.{info.fw_minor}.{info.fw_patch}",
                probe_rate_hz=info.rate_hz,
                zero_counts=info.zero_counts,
                span_un_per_count=info.span_un_per_count,
                adc_bits=info.adc_bits,
                batch=info.batch,
            )
        if self.calibration is not None:
            out["zero_counts_used"], out["span_un_per_count_used"] = self.calibration
        return out

    def stats_dict(self) -> dict[str, Any]:
        """Link statistics for the session summary (JSON-serialisable).

        Samples received, lost and sent (exact: sent = received + lost), gaps by cause,
        connections, decoder counters, and the clock fit (drift [ppm], transport delay
        above the fitted line [s]).
        """
        acc = self.accounting
        out: dict[str, Any] = {
            "samples_received": acc.received,
            "samples_lost": acc.lost,
            "samples_sent": acc.sent,
            "gaps_link": sum(1 for g in acc.gaps if g.link_frames_lost > 0),
            "gaps_probe": sum(1 for g in acc.gaps if g.link_frames_lost == 0),
            "probe_runs": acc.runs,
            "connects": self.connects,
            "decoder": self.decoder.stats.as_dict(),
            "mapped_times_held": self.monotone_clamped,
        }
        sync = self.clock_sync
        if sync.n_observations:
            out["clock_drift_ppm"] = sync.drift_ppm
            res = sync.residual_stats
            if res is not None:
                out["clock_delay_median_s"] = res.median_s
                out["clock_delay_p95_s"] = res.p95_s
        return out

    # ------------------------------------------------------------------ connection

    async def _establish(self) -> InfoResult:
        """Open the transport, start reading, GET_INFO, configure; raise if any step fails."""
        await self.transport.open()
        # A partial frame from before a disconnection cannot continue in the new stream.
        self._dispatch_frames(self.decoder.feed(b"\x00"), self.clock.now())
        loop = asyncio.get_running_loop()
        self._lost = loop.create_future()
        self._last_frame_s = self.clock.now()
        self._conn_tasks = [
            loop.create_task(self._read_loop(), name=f"probe-read {self.name}"),
            loop.create_task(self._watchdog(), name=f"probe-watchdog {self.name}"),
        ]
        ack = await self._command_ok(GetInfo())
        info = ack.info()
        self._set_info(info)
        await self._command_ok(SetRate(self.rate_hz))
        await self._command_ok(SetLed(self.led_level))
        if self._want_stream:
            await self._command_ok(StreamStart())
        self.connects += 1
        self._up = True
        return self.info or info

    async def _teardown(self) -> None:
        """Stop this connection's tasks, fail pending commands, close the transport."""
        self._up = False
        if self._lost is not None and not self._lost.done():
            self._lost.set_result("closed")
        tasks, self._conn_tasks = self._conn_tasks, []
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self._fail_pending("the link went down")
        with contextlib.suppress(StipiError, OSError):
            await self.transport.close()

    def _link_lost(self, reason: str) -> None:
        if self._lost is not None and not self._lost.done():
            self._lost.set_result(reason)
        self._fail_pending(reason)

    def _fail_pending(self, reason: str) -> None:
        for fut, _ in self._pending.values():
            if not fut.done():
                fut.set_exception(LinkLostError(f"{self.name}: {reason}"))
        self._pending.clear()

    async def _supervise(self) -> None:
        try:
            while True:
                assert self._lost is not None
                reason = await self._lost
                await self._teardown()
                self._queue.put_nowait(LinkDown(self.clock.now(), reason))
                info = await self._reconnect(reason)
                self._queue.put_nowait(LinkUp(self.clock.now(), info, reconnect=True))
        except asyncio.CancelledError:
            raise
        except BaseException as exc:
            await self._teardown()
            self._queue.put_nowait(_End(exc))

    async def _reconnect(self, reason: str) -> InfoResult:
        clock = self.clock
        t0 = clock.now()
        delay = self.reconnect_initial_s
        last = reason
        attempts = 0
        while True:
            attempts += 1
            try:
                return await self._establish()
            except (DeviceNotFoundError, LinkLostError) as exc:
                last = str(exc)
            await self._teardown()
            elapsed = clock.now() - t0
            if elapsed + delay > self.reconnect_total_s:
                raise LinkLostError(
                    f"{self.name}: link lost ({reason}) and not back after {attempts} "
                    f"attempts in {elapsed:.1f} s; last: {last}"
                )
            await clock.sleep_until(clock.now() + delay)
            delay = min(2 * delay, self.reconnect_max_s)

    async def _read_loop(self) -> None:
        try:
            while True:
                data = await self.transport.read()
                now = self.clock.now()
                frames = self.decoder.feed(data)
                if frames:
                    self._last_frame_s = now
                self._dispatch_frames(frames, now)
        except LinkLostError as exc:
            self._link_lost(str(exc))
        except _Restarted:
            self._link_lost("the probe restarted")
        except Exception as exc:  # a bug: end the link loudly rather than hang
            if self._lost is not None and not self._lost.done():
                self._lost.set_exception(exc)
            self._fail_pending(repr(exc))

    async def _watchdog(self) -> None:
        clock = self.clock
        timeout = self._floored(self.heartbeat_timeout_s)
        while True:
            deadline = self._last_frame_s + timeout
            if clock.now() >= deadline:
                # Bytes that arrived while the event loop was busy are handled by the reader
                # in the next loop iterations; let it run before judging the link.
                for _ in range(3):
                    await asyncio.sleep(0)
                if self._last_frame_s + timeout <= clock.now():
                    self._link_lost(f"no frame from the probe for {timeout:g} s")
                    return
                continue
            await clock.sleep_until(deadline)

    def _floored(self, timeout_s: float) -> float:
        return wall_floored_timeout_s(timeout_s, self.clock.speed, self.min_wall_s)

    async def _command_ok(self, command: Command) -> Ack:
        ack = await self.command(command)
        if ack.status != AckStatus.OK:
            raise ProtocolError(
                f"{self.name}: the probe refused {type(command).__name__} "
                f"with status {ack.status.name}"
            )
        return ack

    def _set_info(self, info: InfoResult) -> None:
        self.info = info
        if self._config_cal is not None and (
            self._prefer_config_cal or info.span_un_per_count == 0
        ):
            self.calibration, self.calibration_source = self._config_cal, "config"
        elif info.span_un_per_count != 0:
            self.calibration = (info.zero_counts, info.span_un_per_count)
            self.calibration_source = "probe"
        else:
            self.calibration, self.calibration_source = None, "none"

    # ------------------------------------------------------------------ frames

    def _dispatch_frames(self, frames: list[DecodedFrame], now: float) -> None:
        restarted = False
        for f in frames:
            if f.event == SeqEvent.RESTART:
                self.clock_sync.reset()
                restarted = True
            msg = f.message
            gap = self.accounting.observe_frame(f)
            if isinstance(msg, Samples):
                self._on_samples(f, msg, now, gap)
            elif isinstance(msg, Status):
                self._queue.put_nowait(
                    StatusReport(
                        now,
                        f.t_us_unwrapped,
                        msg.led_level,
                        msg.rate_hz,
                        msg.dropped,
                        msg.supply_mv,
                        msg.flags,
                        msg.ble_state,
                        msg.ble_restarts,
                        msg.reset_cause,
                    )
                )
            elif isinstance(msg, Ack):
                entry = self._pending.get(msg.ref_seq)
                if entry is not None and not entry[0].done() and msg.cmd == entry[1]:
                    entry[0].set_result(msg)
        self._report_errors(now)
        if restarted and self._up:
            raise _Restarted

    def _on_samples(self, f: DecodedFrame, msg: Samples, now: float, gap: SampleGap | None) -> None:
        n = len(msg.adc)
        period = msg.period_us
        last_us = f.t_us_unwrapped + (n - 1) * period
        last_raw = (f.t_us + (n - 1) * period) % _U32
        self.clock_sync.observe(last_us, now)
        self._queue.put_nowait(ClockProbe(last_raw, last_us, now))
        to_host = self.clock_sync.to_host
        if gap is not None:
            back = (msg.first_index - gap.start_index) % _U32
            self._queue.put_nowait(
                Gap(
                    gap.start_index,
                    gap.count,
                    "link" if gap.link_frames_lost > 0 else "probe",
                    to_host(f.t_us_unwrapped - back * period),
                )
            )
        cal = self.calibration
        rows = []
        for i, adc in enumerate(msg.adc):
            t_us = f.t_us_unwrapped + i * period
            force = None if cal is None else (adc - cal[0]) * cal[1] * 1e-6
            # Mapped times never go backwards: a burst of late notifications (BLE
            # connection events) can move the clock fit back by a few ms; such samples
            # are held 1 us after the previous one (counted) rather than reordered. The
            # raw and unwrapped probe times are kept, so the mapping can be redone offline.
            t_host = to_host(t_us)
            if self._last_t_host is not None and t_host <= self._last_t_host:
                t_host = self._last_t_host + 1e-6
                self.monotone_clamped += 1
            self._last_t_host = t_host
            rows.append(
                ForceRow(
                    (msg.first_index + i) % _U32,
                    adc,
                    (f.t_us + i * period) % _U32,
                    t_us,
                    t_host,
                    force,
                )
            )
        self._queue.put_nowait(ForceRows(rows))

    def _report_errors(self, now: float) -> None:
        stats = self.decoder.stats
        delta: dict[str, int] = {}
        for name in FAULT_COUNTERS:
            value = getattr(stats, name)
            if value != self._reported[name]:
                delta[name] = value - self._reported[name]
                self._reported[name] = value
        if delta:
            self._queue.put_nowait(DecoderErrors(now, delta))


def probe_id_of(transport: Transport) -> str:
    """Which probe a transport reaches, for telling probes apart across sessions.

    The transport's own ``probe_id`` when it has one (the serial port's USB serial
    number, the BLE device's address), else the transport kind for an emulated probe
    (``emulated``), else the transport's name (``serial:/dev/ttyACM0``: a port, not a probe).
    """
    given = getattr(transport, "probe_id", None)
    if isinstance(given, str) and given:
        return given
    kind, _, _ = transport.name.partition(":")
    return "emulated" if kind == "emulated" else transport.name
