"""Host side of the simavr hardware-in-the-loop harness (firmware/feather32u4/simavr/).

Owns: building the harness, its self-test program and the firmware ELF (serialised with a
file lock, since pytest-xdist workers share the tree); running one harness process with a
load-cell waveform; parsing its stdout log (``KEYWORD key=value ...`` lines); and the host end
of the firmware's UART over the harness's pty (pyserial), speaking the wire protocol through
:mod:`stipi_daemon.protocol` (:class:`FrameDecoder`, :func:`encode_frame`). It does not judge
the firmware: the tests in ``test_simavr_hil.py`` and ``benchmarks/simavr_link_budget.py``
do. Times the harness reports are SIMULATED seconds (CPU cycles / 8 MHz).
"""

from __future__ import annotations

import fcntl
import re
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import serial

from stipi_daemon.probe.link import FAULT_COUNTERS
from stipi_daemon.protocol.decoder import DecodedFrame, FrameDecoder
from stipi_daemon.protocol.messages import Ack, Command, Samples, Status, encode_frame

REPO_ROOT = Path(__file__).resolve().parents[2]
FW_DIR = REPO_ROOT / "firmware" / "feather32u4"
SIM_DIR = FW_DIR / "simavr"
FIRMWARE_ELF = FW_DIR / "build" / "stipi_feather32u4.elf"
FIRMWARE_ADC12_ELF = FW_DIR / "build" / "adc12" / "stipi_feather32u4.elf"
"""The firmware built with ``STIPI_ADC_EXTRA_BITS=2`` (12-bit SAMPLES.adc)."""
FIRMWARE_SUPPLY5_ELF = FW_DIR / "build" / "supply5" / "stipi_feather32u4.elf"
"""The firmware built with the 5 V sense on A1 (``STIPI_PIN_SUPPLY5=19``; ADC6 in simavr)."""
HARNESS = SIM_DIR / "build" / "stipi_simavr_harness"
TESTPROG_ELF = SIM_DIR / "build" / "testprog.elf"
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")

VREF_MV = 3300
"""AVcc reference the firmware selects (config.h ``STIPI_ADC_REF_MV``) [mV]."""
ADC_EXTRA_BITS = 0
"""Bits oversampling adds to the 10-bit count (config.h ``STIPI_ADC_EXTRA_BITS``)."""
ADC_CHANNEL = 7
"""A0 = PF7 = ADC7, the load-cell input (config.h ``STIPI_PIN_LOADCELL``)."""
OCR3AL_ADDR = 0x98
"""Data address of OCR3AL, the LED PWM duty: D5 = PC6 = OC3A (config.h ``STIPI_PIN_LED_PWM``)."""
BLE_PROBE_DONE_S = 2.0
"""Simulated time by which the firmware has given up on an absent nRF51822 (or, with the
harness's ``--nrf51``, has it booted and ready) [s]: reset 20 ms + boot wait 1 s + up to two
250 ms SDEP probes (config.h). The probes no longer block the main loop; the tests still start
their streams after this so that the boot sequence is not part of what they measure."""

_KV = re.compile(r"(\w+)=(\S+)")
LINK_FAULTS = frozenset(FAULT_COUNTERS)
"""DecoderStats counters that must stay zero on a clean link."""


def counts_of_mv(mv: np.ndarray) -> np.ndarray:
    """simavr 1.6's ADC transfer function: ``floor(round(mV) * 1023 / Vref)`` [counts].

    The harness hands simavr integer millivolts; simavr scales by 1023 (the chip by 1024)
    and truncates, then clips at 1023.

    Parameters
    ----------
    mv : numpy.ndarray
        Voltage at the ADC pin [mV].

    Returns
    -------
    numpy.ndarray
        ADC counts, int64, 0..1023.
    """
    imv = np.clip(np.rint(mv), 0, None).astype(np.int64)
    counts: np.ndarray = np.minimum((imv * 1023) // VREF_MV, 1023)
    return counts


def build(*targets: str) -> None:
    """Run ``make`` for ``targets`` ("firmware", "harness", "testprog") under a file lock.

    Raises
    ------
    AssertionError
        When a build fails, with make's output.
    """
    commands = {
        "firmware": ["make", "-C", str(FW_DIR)],
        "harness": ["make", "-C", str(SIM_DIR)],
        "testprog": ["make", "-C", str(SIM_DIR), "testprog"],
        # the 5 V sense on A1 (ratiometric correction, config.h STIPI_PIN_SUPPLY5)
        "firmware-supply5": [
            "make",
            "-C",
            str(FW_DIR),
            "BUILD=build/supply5",
            "STIPI_DEFS=-DSTIPI_PIN_SUPPLY5=19",
        ],
        # the 12-bit variant: 16 conversions summed / 4 on the wire (config.h)
        "firmware-adc12": [
            "make",
            "-C",
            str(FW_DIR),
            "BUILD=build/adc12",
            "STIPI_DEFS=-DSTIPI_ADC_EXTRA_BITS=2",
        ],
    }
    (SIM_DIR / "build").mkdir(exist_ok=True)
    with open(SIM_DIR / "build" / ".build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        for t in targets:
            proc = subprocess.run(commands[t], capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, (
                f"{' '.join(commands[t])} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
            )


@dataclass
class HarnessLog:
    """Lines the harness printed, as (keyword, {key: value}) in order. Thread-safe."""

    lines: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def of(self, keyword: str) -> list[dict[str, str]]:
        """Every line with ``keyword``, oldest first."""
        with self.lock:
            return [kv for k, kv in self.lines if k == keyword]

    def conversion_times_s(self) -> np.ndarray:
        """Simulated instants the firmware started a load-cell conversion [s]."""
        return np.array([float(kv["sim_s"]) for kv in self.of("ADC")])

    def other_conversion_times_s(self) -> np.ndarray:
        """Simulated instants the firmware started a conversion of another channel (the
        supply reading) [s]."""
        return np.array([float(kv["sim_s"]) for kv in self.of("AUX")])

    def conversion_mv(self) -> np.ndarray:
        """Integer millivolts the harness fed at each of those conversions [mV]."""
        return np.array([int(kv["mv"]) for kv in self.of("ADC")], dtype=np.int64)

    def bursts(
        self, gap_s: float = 200e-6
    ) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
        """The firmware's samples as the harness saw them: each sample is a burst of 2^k
        back-to-back conversions (~115 us apart; config.h ``STIPI_OVERSAMPLE_MAX``), bursts
        separated by more than ``gap_s``. Returns the start of each burst [s], the conversion
        instants [s] and the millivolts fed, per burst."""
        t = self.conversion_times_s()
        mv = self.conversion_mv()
        if len(t) == 0:
            return t, [], []
        starts = np.flatnonzero(np.r_[True, np.diff(t) > gap_s])
        ends = np.r_[starts[1:], len(t)]
        return (
            t[starts],
            [t[a:b] for a, b in zip(starts, ends, strict=True)],
            [mv[a:b] for a, b in zip(starts, ends, strict=True)],
        )

    def burst_starts_from(self, t_s: float) -> np.ndarray:
        """Starts of the bursts (:meth:`bursts`) at or after simulated ``t_s`` [s]: a
        stream's samples chosen by time. A count of the bursts logged when a command's ACK
        arrived is no boundary: on a loaded host the next sample's burst may already be
        logged by then."""
        starts = self.bursts()[0]
        return starts[starts >= t_s]

    def last_speed(self) -> float:
        """Simulated seconds per wall second at the last TIME or EXIT line."""
        rows = self.of("TIME") + self.of("EXIT")
        return float(rows[-1]["speed"]) if rows else float("nan")


class Harness:
    """One ``stipi_simavr_harness`` process and the host end of its pty.

    Parameters
    ----------
    elf : Path
        Firmware to run.
    wave : str
        ``--wave`` spec: voltage at the load-cell pin [mV] over simulated time.
    extra : list of str, optional
        More harness options (``--uart-bytes-per-s``, ``--sim-time`` ...).

    The CPU is held until the host has opened the pty and sent one byte (``--wait-host``);
    :meth:`close` always closes the pty and terminates the process.
    """

    def __init__(self, elf: Path, wave: str, extra: list[str] | None = None) -> None:
        args = [
            str(HARNESS),
            "--wave",
            wave,
            "--adc-channel",
            str(ADC_CHANNEL),
            "--vcc-mv",
            str(VREF_MV),
            "--wait-host",
            "--log-adc",
            "--watch",
            f"{OCR3AL_ADDR:#x}:OCR3AL",
            "--report-interval",
            "0.25",
            "--linger",
            "1",
            *(extra or []),
            str(elf),
        ]
        self.log = HarnessLog()
        self._new_line = threading.Event()
        self._stderr = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=self._stderr, text=True, bufsize=1
        )
        self._reader = threading.Thread(target=self._read_stdout, daemon=True)
        self._reader.start()
        self.port: serial.Serial | None = None
        try:
            pty = self.wait_line("PTY", 10.0)["path"]
            self.port = serial.Serial(pty, 250000, timeout=0.02)
            # Wake the harness; a lone 0x00 is an empty frame, which the protocol ignores.
            self.port.write(b"\x00")
            # time.monotonic() at simulated time 0: the harness starts its clock on this
            # byte, within its poll latency (~0.1 ms).
            self.started_s = time.monotonic()
            self.wait_line("START", 10.0)
        except BaseException:
            self.close()
            raise

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            parts = line.split(maxsplit=1)
            if parts:
                kv = dict(_KV.findall(parts[1])) if len(parts) > 1 else {}
                with self.log.lock:
                    self.log.lines.append((parts[0], kv))
                self._new_line.set()

    def stderr_text(self) -> str:
        """What the harness (and simavr) wrote on stderr so far."""
        self._stderr.seek(0)
        return self._stderr.read()

    def wait_line(self, keyword: str, timeout_s: float) -> dict[str, str]:
        """Wait for the first ``keyword`` line; return its fields."""
        deadline = time.monotonic() + timeout_s
        while True:
            rows = self.log.of(keyword)
            if rows:
                return rows[0]
            if time.monotonic() > deadline or (
                self.proc.poll() is not None and not self._reader.is_alive()
            ):
                raise AssertionError(
                    f"harness printed no {keyword} line within {timeout_s} s "
                    f"(exit {self.proc.poll()}); stderr:\n{self.stderr_text()[-2000:]}"
                )
            self._new_line.wait(0.05)
            self._new_line.clear()

    def sim_time_s(self) -> float:
        """Latest simulated time the harness reported (TIME lines, every 0.25 s) [s]."""
        rows = self.log.of("TIME")
        return float(rows[-1]["sim_s"]) if rows else 0.0

    def logged_through(self, t_s: float) -> bool:
        """True once the log holds every line the harness printed up to simulated ``t_s``.

        The harness prints in simulated-time order on one line-buffered pipe, so a TIME line
        (every ``--report-interval``) at or past ``t_s`` comes after every ADC/AUX line
        before it. The log is read by a thread that can lag the pty by many milliseconds
        on a loaded machine; read a time range from it only once this holds."""
        if self.sim_time_s() >= t_s:
            return True
        return bool(self.log.of("EXIT")) and not self._reader.is_alive()

    def wait_logged_through(self, t_s: float, timeout_s: float = 20.0) -> None:
        """Wait until :meth:`logged_through` holds for ``t_s`` (simulated seconds)."""
        deadline = time.monotonic() + timeout_s
        while not self.logged_through(t_s):
            if time.monotonic() > deadline:
                raise AssertionError(f"harness log did not reach simulated {t_s} s")
            self.check_alive(f"the log through simulated {t_s} s")
            self._new_line.wait(0.05)
            self._new_line.clear()

    def read(self) -> bytes:
        """Bytes the firmware sent that are waiting on the pty (waits up to 20 ms)."""
        assert self.port is not None
        data: bytes = self.port.read(max(1, self.port.in_waiting))
        return data

    def check_alive(self, what: str) -> None:
        if self.proc.poll() is not None:
            raise AssertionError(
                f"harness exited ({self.proc.returncode}) while waiting for {what}; "
                f"stderr:\n{self.stderr_text()[-2000:]}"
            )

    def close(self) -> None:
        """Close the pty and stop the harness; safe to call twice."""
        if self.port is not None:
            self.port.close()
            self.port = None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self._reader.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._stderr.close()


@dataclass
class Received:
    """Frames decoded from the probe, all and by kind, in arrival order."""

    frames: list[DecodedFrame] = field(default_factory=list)
    samples: list[DecodedFrame] = field(default_factory=list)
    statuses: list[DecodedFrame] = field(default_factory=list)
    acks: list[DecodedFrame] = field(default_factory=list)


def samples_of(frame: DecodedFrame) -> Samples:
    assert isinstance(frame.message, Samples)
    return frame.message


def status_of(frame: DecodedFrame) -> Status:
    assert isinstance(frame.message, Status)
    return frame.message


class SimProbe(Harness):
    """The probe firmware in the harness, spoken to in the wire protocol over Serial1."""

    def __init__(self, wave: str, extra: list[str] | None = None, elf: Path = FIRMWARE_ELF) -> None:
        self.decoder = FrameDecoder()
        self.rx = Received()
        self._seq = 0
        super().__init__(elf, wave, extra)

    def pump(self) -> None:
        """Decode whatever arrived into :attr:`rx`."""
        for frame in self.decoder.feed(self.read()):
            self.rx.frames.append(frame)
            if isinstance(frame.message, Samples):
                self.rx.samples.append(frame)
            elif isinstance(frame.message, Status):
                self.rx.statuses.append(frame)
            elif isinstance(frame.message, Ack):
                self.rx.acks.append(frame)

    def link_faults(self) -> dict[str, int]:
        """Non-zero decoder counters that a clean link never shows."""
        return {k: v for k, v in self.decoder.stats.as_dict().items() if k in LINK_FAULTS and v}

    def send(self, command: Command) -> int:
        """Send one COMMAND; return its ``seq``."""
        assert self.port is not None
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFFFF
        self.port.write(encode_frame(command, seq, time.monotonic_ns() // 1000 % 2**32))
        return seq

    def wait_for(self, predicate: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
        """Pump frames until ``predicate()`` holds; fail after ``timeout_s`` wall seconds."""
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
            self.check_alive(what)
            self.pump()

    def wait_sim_time(self, t_s: float, timeout_s: float = 20.0) -> None:
        """Keep reading until the simulation has passed ``t_s`` simulated seconds."""
        self.wait_for(lambda: self.sim_time_s() >= t_s, f"simulated time {t_s} s", timeout_s)

    def command(self, command: Command, timeout_s: float = 10.0) -> Ack:
        """Send ``command``; return the ACK whose ``ref_seq`` is its ``seq``."""
        seq = self.send(command)
        found: list[Ack] = []

        def acked() -> bool:
            found.extend(
                f.message
                for f in self.rx.acks
                if isinstance(f.message, Ack) and f.message.ref_seq == seq
            )
            return bool(found)

        self.wait_for(acked, f"the ACK of {command!r} (seq {seq})", timeout_s)
        return found[0]

    def command_retry(self, command: Command, timeout_s: float = 10.0) -> Ack:
        """Like :meth:`command`, resending every 0.5 s wall time (ACKs can be lost on a
        congested link); only for idempotent commands."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self.command(command, timeout_s=0.5)
            except AssertionError:
                if time.monotonic() > deadline:
                    raise

    def next_status(self, timeout_s: float = 10.0) -> Status:
        """The first STATUS that arrives after this call (heartbeat ≤ 1 s simulated)."""
        n = len(self.rx.statuses)
        self.wait_for(lambda: len(self.rx.statuses) > n, "a STATUS heartbeat", timeout_s)
        return status_of(self.rx.statuses[n])

    def collect_samples(self, n: int, timeout_s: float = 30.0) -> list[DecodedFrame]:
        """Wait for ``n`` more samples; return the SAMPLES frames that carried them."""
        start = len(self.rx.samples)

        def enough() -> bool:
            return sum(samples_of(f).count for f in self.rx.samples[start:]) >= n

        self.wait_for(enough, f"{n} samples", timeout_s)
        return self.rx.samples[start:]


@dataclass(frozen=True)
class Stream:
    """Samples flattened.

    Attributes: ``index`` (sample index since boot), ``t_us`` (probe clock at each sample,
    unwrapped [µs]), ``adc`` (counts), ``period_us`` (of the batch carrying it [µs]).
    """

    index: np.ndarray
    t_us: np.ndarray
    adc: np.ndarray
    period_us: np.ndarray


def flatten(frames: list[DecodedFrame]) -> Stream:
    """Per-sample arrays from SAMPLES frames (sample i at ``t_us + i * period_us``)."""
    idx: list[int] = []
    t: list[int] = []
    adc: list[int] = []
    per: list[int] = []
    for f in frames:
        s = samples_of(f)
        for i, a in enumerate(s.adc):
            idx.append(s.first_index + i)
            t.append(f.t_us_unwrapped + i * s.period_us)
            adc.append(a)
            per.append(s.period_us)
    return Stream(
        np.array(idx, dtype=np.int64),
        np.array(t, dtype=np.float64),
        np.array(adc, dtype=np.int64),
        np.array(per, dtype=np.int64),
    )


def rate_hz(stream: Stream) -> float:
    """Samples per simulated second, from the probe's timestamps across the stream."""
    span_s = (stream.t_us[-1] - stream.t_us[0]) * 1e-6
    return float((stream.index[-1] - stream.index[0]) / span_s)


def assert_counts_are_fed_wave(adc: np.ndarray, fed_mv: np.ndarray, wave_mv: np.ndarray) -> None:
    """Each count is simavr's conversion of the millivolts the harness fed, and those are
    the waveform at the conversion, rounded to integer mV.

    The fed value is compared, not the waveform recomputed here: the harness interpolates
    the waveform file (times to 1 us, voltages to 1 uV), so a value within a few uV of a
    half millivolt can round either way on the two sides.
    """
    assert np.array_equal(adc, counts_of_mv(fed_mv))
    assert np.max(np.abs(fed_mv - wave_mv)) <= 0.5 + 2e-3, np.max(np.abs(fed_mv - wave_mv))


def oversampled_counts(fed_mv: list[np.ndarray], extra_bits: int = ADC_EXTRA_BITS) -> np.ndarray:
    """What the firmware sends for bursts of conversions fed ``fed_mv`` (src/core/oversample.h
    without supply correction): the sum of simavr's counts scaled to 10 + ``extra_bits`` bits,
    rounded half up."""
    out = []
    for mv in fed_mv:
        n = len(mv)
        log2n = n.bit_length() - 1
        assert n == 1 << log2n, f"a burst of {n} conversions"
        total = int(counts_of_mv(mv).sum())
        shift = log2n - extra_bits
        out.append((total + (1 << (shift - 1))) >> shift if shift > 0 else total << -shift)
    return np.array(out, dtype=np.int64)


def assert_samples_are_fed_bursts(
    adc: np.ndarray, fed_mv: list[np.ndarray], wave_mv: list[np.ndarray]
) -> None:
    """Each sample is the oversampled value of the millivolts the harness fed during its
    burst, and those are the waveform at each conversion, rounded to integer mV."""
    assert np.array_equal(adc, oversampled_counts(fed_mv))
    dev = max(float(np.max(np.abs(f - w))) for f, w in zip(fed_mv, wave_mv, strict=True))
    assert dev <= 0.5 + 2e-3, dev


def nearest(times_s: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Index into sorted ``times_s`` of the element nearest to each of ``t_s``."""
    right = np.clip(np.searchsorted(times_s, t_s), 1, len(times_s) - 1)
    left = right - 1
    return np.where(np.abs(times_s[left] - t_s) <= np.abs(times_s[right] - t_s), left, right)


def write_wave(path: Path, t_s: np.ndarray, mv: np.ndarray) -> str:
    """Write a harness waveform file (``time_s millivolts`` lines); return its ``--wave`` spec."""
    rows = "".join(f"{a:.6f} {b:.3f}\n" for a, b in zip(t_s, mv, strict=True))
    path.write_text("# time_s millivolts\n" + rows)
    return f"file:{path}"
