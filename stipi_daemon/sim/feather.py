"""An emulated Feather 32u4 probe that speaks the real wire protocol over a pseudo-terminal.

This module owns three pure parts and one thin I/O shell:

* :class:`FeatherCore` mirrors the firmware's behaviour (``firmware/feather32u4/src/core/``:
  ``probe.cpp``, ``sampler.cpp``, ``heartbeat.h``, ``config.h``) as a discrete-event model
  in MCU time: fed host bytes and advanced to an MCU time, it produces the exact frames
  the firmware would send - command handling and ACK status codes, STREAM_START/STOP,
  SET_RATE (the timer restarts, samples taken at the old period leave first), SET_LED,
  TARE over the next 16 samples, WRITE_CAL (with an optional EEPROM failure), GET_INFO,
  the STATUS heartbeat every 500 ms, SAMPLES batches of 10, ``first_index`` counting every
  sample taken, the 64-sample ring with its drop-until-empty overflow and the ``dropped``
  counter. No I/O, no clock: tested directly.
* :class:`McuClock` maps session time onto the MCU's ``micros()`` with a boot offset and a
  rate error [ppm] (clock drift).
* :class:`SceneAdc` gives the ADC reading at each MCU sample time from a simulator scene
  (:mod:`stipi_daemon.sim`): the scene's force model at that time through the scene's
  force effects (drift, noise) and the load cell's ADC (its rails), as the offline
  pipeline makes the scene's own samples (exactly those where the MCU's samples fall on
  the scene's grid), and which samples a ``force_dropout`` loses on the link (the core
  leaves them out of its SAMPLES frames).
* :class:`EmulatedFeather` runs a core on a :class:`~stipi_daemon.clock.SessionClock` behind a
  pty pair: the slave is what a serial transport opens (through pyserial, the real path),
  reached through a stable symlink that disappears while the probe is "unplugged". It
  injects link faults: unplug and return, garbage bursts, bit flips, silence, main-loop
  stalls (probe-side drops), and MCU clock drift.

It does not decode what the host does with the frames (that is :mod:`stipi_daemon.probe.link`),
and it does not model BLE.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import tempfile
import termios
import tty
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Protocol

import numpy as np
from numpy.typing import NDArray

from stipi_daemon.clock import SessionClock
from stipi_daemon.protocol.cobs import cobs_decode
from stipi_daemon.protocol.errors import FrameError
from stipi_daemon.protocol.messages import (
    MAX_ENCODED_SIZE,
    PROTOCOL_VERSION,
    RATE_MAX_HZ,
    RATE_MIN_HZ,
    Ack,
    AckStatus,
    CmdId,
    Command,
    GetInfo,
    InfoResult,
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
    TareResult,
    WriteCal,
    encode_frame,
    unpack_frame,
)

__all__ = [
    "ADC_BITS",
    "BATCH_SIZE",
    "DEFAULT_RATE_HZ",
    "HEARTBEAT_PERIOD_US",
    "RING_CAPACITY",
    "TARE_SAMPLES",
    "AdcSource",
    "ConstantAdc",
    "EmulatedFeather",
    "FeatherCore",
    "McuClock",
    "SceneAdc",
    "flip_bits",
    "period_for_rate",
    "scene_core",
]

# ---- firmware constants (firmware/feather32u4/config.h) -----------------------------------
FW_VERSION: Final = (1, 0, 0)
"""STIPI_FW_MAJOR/MINOR/PATCH."""
ADC_BITS: Final = 10
"""STIPI_ADC_BITS [bit]."""
DEFAULT_RATE_HZ: Final = 100
"""STIPI_DEFAULT_RATE_HZ [Hz]."""
BATCH_SIZE: Final = 10
"""STIPI_BATCH_SIZE: samples per SAMPLES frame while streaming."""
RING_CAPACITY: Final = 64
"""STIPI_RING_CAPACITY: ISR -> main loop ring [samples]."""
TARE_SAMPLES: Final = 16
"""STIPI_TARE_SAMPLES: samples averaged by TARE."""
HEARTBEAT_PERIOD_US: Final = 500_000
"""STIPI_HEARTBEAT_PERIOD_US: STATUS period [µs]."""
MAX_POPS_PER_PASS: Final = 4
"""Batches the main loop sends per pass (probe.cpp ``service_samples``)."""
SUPPLY_MV: Final = 4200
"""Default supply voltage the emulated probe reports [mV] (LiPo charging on USB)."""

_ADC_MAX: Final = (1 << ADC_BITS) - 1
_U32: Final = 1 << 32
_CACHE_SAMPLES: Final = 256


def period_for_rate(rate_hz: int) -> int:
    """Sampling period for ``rate_hz``, rounded to the nearest microsecond (probe.cpp) [µs]."""
    return (1_000_000 + rate_hz // 2) // rate_hz


class AdcSource(Protocol):
    """The voltage on the load-cell pin, as ADC counts, at given MCU times."""

    def counts(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.int64]:
        """ADC counts (0..1023) of samples taken at unwrapped MCU times ``t_mcu_us`` [µs]."""
        ...


@dataclass(frozen=True)
class ConstantAdc:
    """A constant ADC reading (a fixed voltage on the pin) [counts]."""

    value: int

    def counts(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.int64]:
        return np.full(t_mcu_us.shape, self.value, dtype=np.int64)


@dataclass(frozen=True)
class McuClock:
    """The MCU's ``micros()`` against session time.

    ``mcu_us(t) = boot_offset_us + floor((t - boot_session_s) * 1e6 * (1 + rate_error_ppm * 1e-6))``

    Parameters
    ----------
    boot_session_s : float
        Session time at which the MCU booted [s].
    boot_offset_us : int
        ``micros()`` at boot [µs] (0 on a real chip; large values test the 2^32 wrap).
    rate_error_ppm : float
        How fast the MCU's resonator runs against the session clock [ppm] (+: fast).
    """

    boot_session_s: float = 0.0
    boot_offset_us: int = 0
    rate_error_ppm: float = 0.0

    @property
    def _k(self) -> float:
        return 1.0 + self.rate_error_ppm * 1e-6

    def mcu_us(self, session_s: float) -> int:
        """Unwrapped MCU time at session time ``session_s`` [µs]."""
        return self.boot_offset_us + math.floor((session_s - self.boot_session_s) * 1e6 * self._k)

    def session_s(self, mcu_us: int) -> float:
        """Session time at which the MCU clock reads ``mcu_us`` (unwrapped) [s]."""
        return self.boot_session_s + (mcu_us - self.boot_offset_us) * 1e-6 / self._k


#: Scene time the emulated probe's precomputed samples reach past the scene's end [s].
SCHEDULE_MARGIN_S: Final = 60.0


class SceneAdc:
    """ADC counts from a simulator scene at the MCU's sample times, its force effects played.

    The scene's time 0 is the MCU time ``start_mcu_us`` (by default the first sample the
    probe takes); scene time is true time, so an MCU clock that runs ``rate_error_ppm``
    fast takes its samples at ``(t_mcu - start) / (1 + rate_error_ppm * 1e-6)`` scene
    seconds. Every sample reads the scene's force model at that time through the scene's
    force effects (``force_drift``, ``force_noise``: ``Pipeline.force_counts``) and the
    load cell's ADC (quantised, clipped at its rails), as the offline pipeline
    (``Pipeline.force_batch``) makes the scene's own samples.

    The probe samples every ``period_us`` of MCU time; the counts are computed ahead over
    that schedule, which starts at the schedule's first sample at or after scene time 0
    (so that its j-th sample draws the effects' j-th random numbers, as the scene's j-th
    sample does: where the MCU's samples fall on the scene's grid, with the scene's rate,
    they read exactly the scene's own counts) and reaches :data:`SCHEDULE_MARGIN_S` past
    the scene's end (or past its first sample, after the end). A sample off that schedule
    (the rate was changed, the schedule's end was passed) starts a new one from it.

    Samples a ``force_dropout`` loses (taken at a true time in its span) are taken but not
    delivered (:meth:`lost`): the firmware model leaves them out of its SAMPLES frames, so
    the host sees an index gap and a link loss, as the effect defines.

    Parameters
    ----------
    scene : stipi_daemon.sim.Scene
        The scene.
    seed : int, optional
        Random seed of the scene's effects (default: the scene's).
    start_mcu_us : int, optional
        MCU time of scene time 0 [µs]; default: the first sample asked for.
    rate_error_ppm : float
        MCU clock rate error [ppm] (as :class:`McuClock`).
    """

    def __init__(
        self,
        scene: object,
        seed: int | None = None,
        *,
        start_mcu_us: int | None = None,
        rate_error_ppm: float = 0.0,
    ) -> None:
        from stipi_daemon.sim import Pipeline, Scene

        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a stipi_daemon.sim.Scene, got {type(scene).__name__}")
        self._pipeline = Pipeline(scene, seed)
        self.scene = scene
        self.rate_hz = float(scene.load_cell.sample_rate_hz)
        self._end_s = float(scene.force_profile.duration_s) + SCHEDULE_MARGIN_S
        load_cell = self._pipeline.load_cell
        self.start_mcu_us = start_mcu_us
        self._k = 1.0 + rate_error_ppm * 1e-6
        # the schedule: MCU time of its sample 0 [µs], its period [µs], counts, losses
        self._anchor_us = 0
        self._period_us = 0
        self._counts: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self._lost: NDArray[np.bool_] = np.zeros(0, dtype=np.bool_)
        self.zero_counts = round(load_cell.zero_counts)
        """Tare of the scene's load cell, rounded as GET_INFO reports it [counts]."""
        self.span_un_per_count = load_cell.span_un_per_count
        """Span of the scene's load cell as GET_INFO reports it [µN/count]."""

    def scene_time_s(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.float64]:
        """Scene time of samples taken at MCU times ``t_mcu_us`` [s]."""
        if self.start_mcu_us is None:
            raise ValueError("scene start unknown before the first sample")
        t: NDArray[np.float64] = (t_mcu_us - self.start_mcu_us).astype(np.float64) * 1e-6 / self._k
        return t

    def _on_schedule(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.int64] | None:
        """Rows of the schedule of samples at MCU times ``t_mcu_us``; None when one is not
        on it."""
        if not self._period_us:
            return None
        d = t_mcu_us - self._anchor_us
        j = d // self._period_us
        ok = bool(np.all((d % self._period_us == 0) & (j >= 0) & (j < self._counts.size)))
        return j if ok else None

    def _rows(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.int64]:
        """Rows of the schedule of samples at MCU times ``t_mcu_us``, a new schedule made
        from the first of them and the step to the second when they are not on the current
        one. Raises ValueError for times not evenly spaced (not a sampling timer's)."""
        if self.start_mcu_us is None:
            self.start_mcu_us = int(t_mcu_us[0])
        rows = self._on_schedule(t_mcu_us)
        if rows is not None:
            return rows
        period = int(t_mcu_us[1] - t_mcu_us[0]) if t_mcu_us.size > 1 else 0
        if period <= 0:
            period = round(1e6 / self.rate_hz)
        first_s = float(self.scene_time_s(t_mcu_us[:1])[0])
        step_s = period * 1e-6 / self._k
        j0 = max(0, math.floor(first_s / step_s + 1e-9))
        horizon_s = max(self._end_s, first_s + SCHEDULE_MARGIN_S)
        n = j0 + max(t_mcu_us.size, math.ceil((horizon_s - first_s) / step_s) + 1)
        self._anchor_us = int(t_mcu_us[0]) - j0 * period
        self._period_us = period
        times_s = self.scene_time_s(self._anchor_us + period * np.arange(n, dtype=np.int64))
        self._counts = self._pipeline.force_counts(times_s)
        self._lost = self._pipeline.link_lost(times_s)
        rows = self._on_schedule(t_mcu_us)
        if rows is None:
            raise ValueError("sample times are not evenly spaced (a sampling timer's are)")
        return rows

    def counts(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.int64]:
        if t_mcu_us.size == 0:
            return np.zeros(0, dtype=np.int64)
        rows = self._rows(t_mcu_us)  # (may make a new schedule: before its counts are read)
        out: NDArray[np.int64] = self._counts[rows]
        return out

    def lost(self, t_mcu_us: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which samples taken at MCU times ``t_mcu_us`` the link loses (the scene's
        ``force_dropout`` spans, in true time)."""
        if t_mcu_us.size == 0:
            return np.zeros(0, dtype=np.bool_)
        rows = self._rows(t_mcu_us)
        out: NDArray[np.bool_] = self._lost[rows]
        return out


def flip_bits(data: bytes, bit_error_rate: float, rng: np.random.Generator) -> tuple[bytes, int]:
    """Flip each bit of ``data`` independently with probability ``bit_error_rate``.

    Returns
    -------
    bytes, int
        The damaged bytes and the number of bits flipped.
    """
    if not 0.0 <= bit_error_rate <= 1.0:
        raise ValueError(f"bit_error_rate={bit_error_rate} outside 0..1")
    if bit_error_rate == 0.0 or not data:
        return data, 0
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8))
    flips = rng.random(bits.size) < bit_error_rate
    n = int(flips.sum())
    if n == 0:
        return data, 0
    return np.packbits(bits ^ flips.astype(np.uint8)).tobytes(), n


class _Heartbeat:
    """heartbeat.h on unwrapped times: due at boot, then every period, no drift."""

    def __init__(self, period_us: int) -> None:
        self.period_us = period_us
        self.last_us = 0
        self.started = False

    def due_at(self, boot_us: int) -> int:
        return boot_us if not self.started else self.last_us + self.period_us

    def due(self, now_us: int) -> bool:
        return not self.started or now_us - self.last_us >= self.period_us

    def sent(self, now_us: int) -> None:
        if self.started and now_us - self.last_us < 2 * self.period_us:
            self.last_us += self.period_us
        else:
            self.last_us = now_us
        self.started = True


@dataclass(frozen=True)
class _Batch:
    first_index: int
    t_us: int
    period_us: int
    adc: tuple[int, ...]


class FeatherCore:
    """The probe firmware's behaviour as a pure discrete-event model in MCU time.

    Every time is the MCU's unwrapped ``micros()`` [µs]; frames carry it mod 2^32. The main
    loop is modelled as running continuously (it reacts at the instant of each event)
    except while :meth:`stall` holds it, when, as on the chip, the sampling interrupt
    keeps filling the 64-sample ring and overflows it.

    Parameters
    ----------
    adc : AdcSource
        The ADC reading at each sample time.
    boot_us : int
        MCU time at boot [µs]: the first STATUS is sent then, after a lone 0x00.
    zero_counts, span_un_per_count : int
        Calibration in EEPROM at boot [counts], [µN/count]; span 0 = not calibrated.
    supply_mv : int
        Supply voltage STATUS reports [mV].
    fw_version : tuple of int
        Firmware version GET_INFO reports.
    """

    def __init__(
        self,
        adc: AdcSource,
        *,
        boot_us: int = 0,
        zero_counts: int = 0,
        span_un_per_count: int = 0,
        supply_mv: int = SUPPLY_MV,
        fw_version: tuple[int, int, int] = FW_VERSION,
    ) -> None:
        self._adc = adc
        self._boot_us = boot_us
        self._now = boot_us
        self.supply_mv = supply_mv
        self.fw_version = fw_version
        self.seq = 0
        """Sequence number of the next frame sent (settable, e.g. to test vectors)."""
        self.rx_errors = 0
        """Received runs that were not a valid COMMAND frame."""
        self.frames_sent = 0
        self.eeprom_fails = False
        """Fault: EEPROM writes fail their readback (WRITE_CAL and TARE answer status 4)."""
        self.zero_counts = zero_counts
        self.span_un_per_count = span_un_per_count
        self.cal_valid = span_un_per_count != 0
        self.streaming = False
        self.rate_hz = DEFAULT_RATE_HZ
        self.led_level = 0
        # sampler (sampler.cpp)
        self._period_us = period_for_rate(self.rate_hz)
        self._sampling = False
        self._next_sample_us = 0
        self._ring: deque[int] = deque()
        self._overflow = False
        self.taken = 0
        """Samples taken since boot (the next sample's index)."""
        self.dropped = 0
        """Samples the probe could not queue since boot."""
        self._first_index = 0
        self._first_t_us = 0
        self._cache_t0 = 0
        self._cache: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        # tare
        self.tare_pending = False
        self._tare_owns_timer = False
        self._tare_ref_seq = 0
        self._tare_from_index = 0
        self._tare_count = 0
        self._tare_sum = 0
        # main loop
        self._stall_until = boot_us
        self._heartbeat = _Heartbeat(HEARTBEAT_PERIOD_US)
        self._rx = bytearray()
        self._rx_overlong = False
        self._rx_pending = b""
        self._out: list[bytes] = [b"\x00"]  # begin(): flush the host's receiver
        self._main_passes()  # the first loop pass: STATUS at boot

    # ------------------------------------------------------------------ public

    @property
    def now_us(self) -> int:
        """MCU time the model has reached [µs]."""
        return self._now

    @property
    def period_us(self) -> int:
        """Current sampling period [µs]."""
        return self._period_us

    @property
    def stalled(self) -> bool:
        """Whether the main loop is held by :meth:`stall`."""
        return self._now < self._stall_until

    def take_output(self) -> list[bytes]:
        """Wire frames (COBS + 0x00; the boot flush is a lone 0x00) sent since the last call."""
        out, self._out = self._out, []
        return out

    def feed(self, data: bytes, now_us: int) -> None:
        """Host bytes received at MCU time ``now_us``: advance, then handle any commands.

        While the main loop is stalled the bytes wait (in the UART buffer) and are handled
        when it resumes.
        """
        self.advance(now_us)
        self._rx_pending += bytes(data)
        if not self.stalled:
            self._read_link()

    def advance(self, now_us: int) -> None:
        """Run the model up to MCU time ``now_us`` [µs] (earlier times are ignored)."""
        if now_us < self._now:
            return
        while True:
            t_sample = self._next_sample_us if self._sampling else math.inf
            t_loop = self._loop_event_us()
            t = min(t_sample, t_loop)
            if t > now_us:
                break
            self._now = int(t)
            if self._sampling and self._next_sample_us == t:
                self._isr_sample()
            if not self.stalled:
                self._read_link()
                self._main_passes()
        self._now = now_us

    def next_event_us(self) -> int:
        """Earliest MCU time after :attr:`now_us` at which the model sends a frame [µs].

        A conservative bound: a batch (when the ring will hold a whole one), the heartbeat,
        the end of a stall, or the next sample while a TARE is waiting for samples.
        """
        candidates = [self._loop_event_us()]
        if self._sampling:
            need = BATCH_SIZE if self.streaming and not self._overflow else 1
            missing = max(1, need - len(self._ring))
            candidates.append(self._next_sample_us + (missing - 1) * self._period_us)
        return int(max(min(candidates), self._now))

    def stall(self, duration_us: int) -> None:
        """Fault: hold the main loop for ``duration_us`` from now (interrupts keep sampling)."""
        if duration_us < 0:
            raise ValueError(f"duration_us={duration_us} must not be negative")
        self._stall_until = max(self._stall_until, self._now + duration_us)

    def status_flags(self) -> StatusFlags:
        """STATUS flags: streaming, USB CDC open (the emulated link), calibration valid."""
        flags = StatusFlags.USB_OPEN
        if self.streaming:
            flags |= StatusFlags.STREAMING
        if self.cal_valid:
            flags |= StatusFlags.CAL_VALID
        return flags

    # ------------------------------------------------------------------ main loop

    def _loop_event_us(self) -> float:
        # A stalled loop does nothing until the stall ends, then catches up at once.
        if self._now < self._stall_until:
            return self._stall_until
        return self._heartbeat.due_at(self._boot_us)

    def _main_passes(self) -> None:
        while True:
            pops = self._service_samples()
            if self._heartbeat.due(self._now):
                self._send_status()
                self._heartbeat.sent(self._now)
            if pops < MAX_POPS_PER_PASS:
                return

    def _read_link(self) -> None:
        data, self._rx_pending = self._rx_pending, b""
        for b in data:
            if b != 0:
                if len(self._rx) >= MAX_ENCODED_SIZE:
                    self._rx_overlong = True
                else:
                    self._rx.append(b)
                continue
            run, overlong = bytes(self._rx), self._rx_overlong
            self._rx.clear()
            self._rx_overlong = False
            if not run and not overlong:
                continue  # empty frame
            if overlong:
                self.rx_errors += 1
                continue
            try:
                frame = unpack_frame(cobs_decode(run))
            except FrameError:
                self.rx_errors += 1
                continue
            if not isinstance(
                frame.message,
                StreamStart
                | StreamStop
                | SetRate
                | SetLed
                | Tare
                | WriteCal
                | GetInfo
                | RawCommand,
            ):
                self.rx_errors += 1
                continue
            self._handle(frame.seq, frame.message)

    # ------------------------------------------------------------------ commands

    def _handle(self, seq: int, msg: Command) -> None:
        busy = self.tare_pending
        ok, bad, busy_s = AckStatus.OK, AckStatus.BAD_ARGUMENT, AckStatus.BUSY
        if isinstance(msg, RawCommand):
            self._send_ack(seq, msg.cmd, msg.refusal)
            return
        status = ok
        if isinstance(msg, StreamStart):
            if busy:
                status = busy_s
            elif not self.streaming:
                self._start_sampling()
                self.streaming = True
        elif isinstance(msg, StreamStop):
            if busy:
                status = busy_s
            elif self.streaming:
                self._stop_and_flush()
                self.streaming = False
        elif isinstance(msg, SetRate):
            if not RATE_MIN_HZ <= msg.rate_hz <= RATE_MAX_HZ:
                status = bad
            elif busy:
                status = busy_s
            else:
                if self.streaming:
                    self._stop_and_flush()
                self.rate_hz = msg.rate_hz
                if self.streaming:
                    self._start_sampling()
                else:
                    self._period_us = period_for_rate(self.rate_hz)
        elif isinstance(msg, SetLed):
            self.led_level = msg.level
        elif isinstance(msg, Tare):
            if busy:
                status = busy_s
            else:
                self.tare_pending = True
                self._tare_ref_seq = seq
                self._tare_count = 0
                self._tare_sum = 0
                self._tare_from_index = self.taken
                self._tare_owns_timer = not self.streaming
                if self._tare_owns_timer:
                    self._start_sampling()
                return  # answered with the 16th sample
        elif isinstance(msg, WriteCal):
            if msg.zero_counts > _ADC_MAX or msg.span_un_per_count == 0:
                status = bad
            elif busy:
                status = busy_s
            elif self.eeprom_fails:
                status = AckStatus.EEPROM_FAILED
            else:
                self.zero_counts = msg.zero_counts
                self.span_un_per_count = msg.span_un_per_count
                self.cal_valid = True
        elif isinstance(msg, GetInfo):
            info = InfoResult(
                PROTOCOL_VERSION,
                *self.fw_version,
                self.rate_hz,
                self.led_level,
                self.zero_counts,
                self.span_un_per_count,
                ADC_BITS,
                BATCH_SIZE,
            )
            self._emit(Ack(seq, CmdId.GET_INFO, ok, info), self._now)
            return
        self._send_ack(seq, int(msg.CMD), status)

    # ------------------------------------------------------------------ sampler

    def _start_sampling(self) -> None:
        self._period_us = period_for_rate(self.rate_hz)
        self._sampling = True
        self._next_sample_us = self._now + self._period_us  # CTC: first match one period later
        self._cache = np.zeros(0, dtype=np.int64)

    def _stop_and_flush(self) -> None:
        self._sampling = False
        while self._ring:
            self._send_batch(self._pop(BATCH_SIZE))

    def _adc_at(self, t_us: int) -> int:
        j = (t_us - self._cache_t0) // self._period_us if self._cache.size else -1
        if not 0 <= j < self._cache.size or self._cache_t0 + j * self._period_us != t_us:
            times = t_us + self._period_us * np.arange(_CACHE_SAMPLES, dtype=np.int64)
            self._cache = np.clip(self._adc.counts(times), 0, _ADC_MAX).astype(np.int64)
            self._cache_t0, j = t_us, 0
        return int(self._cache[j])

    def _isr_sample(self) -> None:
        t = self._next_sample_us
        self._next_sample_us = t + self._period_us
        adc = self._adc_at(t)
        index = self.taken
        self.taken += 1
        if self._overflow:
            if self._ring:
                self.dropped += 1
                return
            self._overflow = False
        if len(self._ring) == RING_CAPACITY:
            self._overflow = True
            self.dropped += 1
            return
        if not self._ring:
            self._first_index = index
            self._first_t_us = t
        self._ring.append(adc)

    def _pop(self, max_n: int) -> _Batch:
        n = min(len(self._ring), max_n, max(BATCH_SIZE, TARE_SAMPLES))
        adc = tuple(self._ring.popleft() for _ in range(n))
        batch = _Batch(self._first_index, self._first_t_us, self._period_us, adc)
        self._first_index += n
        self._first_t_us += n * self._period_us
        return batch

    def _service_samples(self) -> int:
        if not self.streaming and not self.tare_pending:
            return 0
        pops = 0
        for _ in range(MAX_POPS_PER_PASS):
            want = BATCH_SIZE if self.streaming and not self._overflow else 1
            if len(self._ring) < want:
                break
            batch = self._pop(BATCH_SIZE if self.streaming else TARE_SAMPLES)
            pops += 1
            if self.tare_pending:
                self._feed_tare(batch)
            if self.streaming:
                self._send_batch(batch)
        return pops

    def _feed_tare(self, batch: _Batch) -> None:
        for i, adc in enumerate(batch.adc):
            if self._tare_count >= TARE_SAMPLES:
                break
            if batch.first_index + i < self._tare_from_index:
                continue  # taken before the TARE
            self._tare_sum += adc
            self._tare_count += 1
        if self._tare_count == TARE_SAMPLES:
            self._finish_tare()

    def _finish_tare(self) -> None:
        self.tare_pending = False
        if self._tare_owns_timer:
            self._sampling = False
            self._ring.clear()  # the tare's own samples are not streamed
            self._tare_owns_timer = False
        zero = (self._tare_sum + TARE_SAMPLES // 2) // TARE_SAMPLES
        if self.eeprom_fails:
            self._send_ack(self._tare_ref_seq, CmdId.TARE, AckStatus.EEPROM_FAILED)
            return
        self.zero_counts = zero
        self.cal_valid = self.span_un_per_count != 0
        self._emit(Ack(self._tare_ref_seq, CmdId.TARE, AckStatus.OK, TareResult(zero)), self._now)

    # ------------------------------------------------------------------ frames out

    def _send_batch(self, batch: _Batch) -> None:
        """One SAMPLES frame per batch; samples the ADC source says the link loses
        (:meth:`SceneAdc.lost`, a scene's ``force_dropout``) are left out: each run of
        delivered samples goes in a frame of its own, and each run of lost ones takes the
        sequence number of a frame the link lost (the host sees an index gap, cause link)."""
        if not batch.adc:
            return
        lost_of = getattr(self._adc, "lost", None)
        n = len(batch.adc)
        lost = (
            np.zeros(n, dtype=np.bool_)
            if lost_of is None
            else np.asarray(lost_of(batch.t_us + batch.period_us * np.arange(n, dtype=np.int64)))
        )
        start = 0
        while start < n:
            end = start + 1
            while end < n and lost[end] == lost[start]:
                end += 1
            if lost[start]:  # a frame sent and lost on the link
                self.seq = (self.seq + 1) & 0xFFFF
                self.frames_sent += 1
            else:
                first = (batch.first_index + start) % _U32
                msg = Samples(first, batch.period_us, batch.adc[start:end])
                self._emit(msg, batch.t_us + start * batch.period_us)
            start = end

    def _send_status(self) -> None:
        msg = Status(
            self.led_level, self.rate_hz, self.dropped % _U32, self.supply_mv, self.status_flags()
        )
        self._emit(msg, self._now)

    def _send_ack(self, ref_seq: int, cmd: int, status: AckStatus) -> None:
        self._emit(Ack(ref_seq, cmd, status), self._now)

    def _emit(self, msg: Message, t_us: int) -> None:
        self._out.append(encode_frame(msg, self.seq, t_us % _U32))
        self.seq = (self.seq + 1) & 0xFFFF
        self.frames_sent += 1


# ====================================================================== pty shell


def scene_core(
    scene: object,
    seed: int | None,
    mcu_clock: McuClock,
    now_s: float,
    *,
    calibrated: bool = True,
    scene_start_s: float | None = None,
    core_type: type[FeatherCore] = FeatherCore,
) -> FeatherCore:
    """A firmware model reading a simulator scene, booted at session time ``now_s``.

    The scene's load-cell samples (``seed``) at the MCU's sample times, and its load cell's
    tare and span in EEPROM when ``calibrated``; the serial emulator and the BLE mock probe
    both build theirs here.

    Parameters
    ----------
    scene : stipi_daemon.sim.Scene
        The scene.
    seed : int, optional
        Seed of the scene's effects (default: the scene's).
    mcu_clock : McuClock
        Session time to MCU time.
    now_s : float
        Session time of the boot [s].
    calibrated : bool
        EEPROM holds the scene's calibration (else span 0).
    scene_start_s : float, optional
        Session time of the scene's t = 0 [s] (default: the first sample).
    core_type : type
        :class:`FeatherCore` or a subclass (the BLE probe's reports its BLE link).
    """
    start = None if scene_start_s is None else mcu_clock.mcu_us(scene_start_s)
    adc = SceneAdc(scene, seed, start_mcu_us=start, rate_error_ppm=mcu_clock.rate_error_ppm)
    return core_type(
        adc,
        boot_us=mcu_clock.mcu_us(now_s),
        zero_counts=adc.zero_counts if calibrated else 0,
        span_un_per_count=adc.span_un_per_count if calibrated else 0,
    )


def _set_raw(fd: int) -> None:
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[3] &= ~termios.ECHO
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class EmulatedFeather:
    """A :class:`FeatherCore` behind a pty, paced on a session clock.

    The host opens :attr:`path` (a symlink to the pty slave) with pyserial like a real
    ``/dev/ttyACM0``. The shell keeps its own handle on the slave so that the master never
    sees a hang-up while the host closes and reopens the port; frames the host's tty buffer
    cannot take are dropped, as the firmware drops a frame its link cannot queue.

    Parameters
    ----------
    core : FeatherCore
        The probe model (its MCU time is ``mcu_clock.mcu_us(clock.now())``).
    clock : SessionClock
        The session clock the probe paces itself on.
    mcu_clock : McuClock
        Session time to MCU time (boot time, drift).
    link_path : Path, optional
        Where to create the symlink (default: a fresh temporary directory).
    seed : int
        Seed of the fault generator (bit flips, garbage).
    max_tick_s : float
        Longest session-time sleep between two runs of the model [s].
    """

    def __init__(
        self,
        core: FeatherCore,
        clock: SessionClock,
        mcu_clock: McuClock,
        *,
        link_path: Path | None = None,
        seed: int = 0,
        max_tick_s: float = 0.1,
    ) -> None:
        self.core = core
        self.clock = clock
        self.mcu_clock = mcu_clock
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        if link_path is None:
            self._tmpdir = tempfile.TemporaryDirectory(prefix="stipi-feather-")
            link_path = Path(self._tmpdir.name) / "ttyFEATHER"
        self.path = link_path
        """Stable path of the serial device (exists only while plugged in)."""
        self._rng = np.random.default_rng(seed)
        self._max_tick_s = max_tick_s
        self._master: int | None = None
        self._slave: int | None = None
        self._pending = bytearray()
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._silent_until = -math.inf
        self._replug_at: float | None = None
        self.bit_error_rate = 0.0
        """Fault: probability of flipping each bit the probe sends."""
        self._garbage: list[bytes] = []
        # counters
        self.frames_written = 0
        """Frames that reached the pty."""
        self.frames_dropped = 0
        """Frames lost before the pty: unplugged, silent, or the host's buffer full."""
        self.bits_flipped = 0
        self.garbage_bytes = 0
        #: Bytes written to / read from the pty since it was plugged in (a simulated run's
        #: clock waits while the host has not read what was written, or the probe not what
        #: the host wrote: :meth:`in_flight`).
        self.bytes_out = 0
        self.bytes_in = 0
        self.host_bytes_read = 0
        self.host_bytes_written = 0

    # ------------------------------------------------------------------ lifecycle

    @property
    def plugged(self) -> bool:
        """Whether the serial device exists."""
        return self._master is not None

    def _mcu_now(self) -> int:
        return self.mcu_clock.mcu_us(self.clock.now())

    async def start(self) -> None:
        """Plug the probe in and start running it."""
        if self._task is not None:
            return
        self.plug()
        self._task = asyncio.get_running_loop().create_task(self._run(), name="emulated-feather")

    async def stop(self) -> None:
        """Stop the probe and remove the device; safe to call twice."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.unplug()
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None

    async def __aenter__(self) -> EmulatedFeather:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def plug(self) -> None:
        """Create the pty and the device path (the probe is plugged in)."""
        if self._master is not None:
            return
        master, slave = os.openpty()
        _set_raw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._pending.clear()
        self.reset_flight()
        tmp = self.path.with_name(self.path.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.path)
        with contextlib.suppress(RuntimeError):
            asyncio.get_running_loop().add_reader(master, self._on_readable)
        self._wake.set()

    def unplug(self, duration_s: float | None = None) -> None:
        """Fault: remove the device (the host's open port reports a hang-up).

        The probe keeps running on its battery; what it sends meanwhile is lost. With
        ``duration_s`` it comes back (a new pty, same path) after that much session time.
        """
        if self._master is not None:
            with contextlib.suppress(RuntimeError):
                asyncio.get_running_loop().remove_reader(self._master)
                asyncio.get_running_loop().remove_writer(self._master)
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
            os.close(self._master)
            if self._slave is not None:
                os.close(self._slave)
            self._master = self._slave = None
        self._replug_at = None if duration_s is None else self.clock.now() + duration_s
        self._wake.set()

    def silence(self, duration_s: float) -> None:
        """Fault: for ``duration_s`` of session time nothing crosses the link either way."""
        self._silent_until = max(self._silent_until, self.clock.now() + duration_s)
        self._wake.set()

    def inject_garbage(self, data: bytes | None = None, n_bytes: int = 32) -> None:
        """Fault: send ``data`` (default ``n_bytes`` random non-zero bytes) before a frame."""
        if data is None:
            data = bytes(self._rng.integers(1, 256, size=n_bytes, dtype=np.uint8))
        self._garbage.append(bytes(data))

    def stall(self, duration_s: float) -> None:
        """Fault: hold the MCU's main loop for ``duration_s`` (the ring overflows: probe drops)."""
        self.core.advance(self._mcu_now())
        self.core.stall(round(duration_s * 1e6))
        self._wake.set()

    # ------------------------------------------------------------------ I/O

    def _silent(self) -> bool:
        return self.clock.now() < self._silent_until

    def _on_readable(self) -> None:
        if self._master is None:
            return
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # EIO: no reader on the slave side; nothing to do
        self.bytes_in += len(data)
        if not data or self._silent():
            return
        self.core.feed(data, self._mcu_now())
        self._flush()
        self._wake.set()

    def _flush(self) -> None:
        frames = self.core.take_output()
        if self._master is None or self._silent():
            self.frames_dropped += len(frames)
            return
        for frame in frames:
            if frame == b"\x00":  # the boot flush: a lone delimiter, not a frame
                self._pending += frame
                self._write_pending()
                continue
            if self._garbage:
                garbage = b"".join(self._garbage)
                self._garbage.clear()
                self.garbage_bytes += len(garbage)
                self._pending += garbage
            data, flipped = flip_bits(frame, self.bit_error_rate, self._rng)
            self.bits_flipped += flipped
            if len(self._pending) > 4 * MAX_ENCODED_SIZE:
                self.frames_dropped += 1  # the host is not reading: the probe's link is full
                continue
            self._pending += data
            self.frames_written += 1
            self._write_pending()

    def _write_pending(self) -> None:
        while self._pending and self._master is not None:
            try:
                n = os.write(self._master, self._pending)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._pending.clear()
                return
            del self._pending[:n]
            self.bytes_out += n
        if self._pending and self._master is not None:  # the pty is full: write when it drains
            with contextlib.suppress(RuntimeError):
                asyncio.get_running_loop().add_writer(self._master, self._drain)

    def _drain(self) -> None:
        if self._master is not None:
            asyncio.get_running_loop().remove_writer(self._master)
            self._write_pending()

    def reset_flight(self) -> None:
        """Start counting bytes in flight anew (the pty was plugged in, the host opened it)."""
        self.bytes_out = self.bytes_in = 0
        self.host_bytes_read = self.host_bytes_written = 0

    def in_flight(self) -> bool:
        """Whether bytes are on their way across the pty: written by the probe and not yet
        read by the host, written by the host and not yet read by the probe, or waiting
        for room in the pty."""
        if self._master is None:
            return False
        return (
            bool(self._pending)
            or self.host_bytes_read < self.bytes_out
            or self.bytes_in < self.host_bytes_written
        )

    async def _run(self) -> None:
        clock = self.clock
        while True:
            now = clock.now()
            if self._replug_at is not None and now >= self._replug_at:
                self._replug_at = None
                self.plug()
            self.core.advance(self.mcu_clock.mcu_us(now))
            self._flush()
            t_next = self.mcu_clock.session_s(self.core.next_event_us() + 1)
            deadline = min(t_next, now + self._max_tick_s)
            if self._replug_at is not None:
                deadline = min(deadline, self._replug_at)
            self._wake.clear()
            # ends on a cancel that comes with a wake-up (clock.wait_event)
            await clock.wait_event(self._wake, max(0.0, deadline - clock.now()))
