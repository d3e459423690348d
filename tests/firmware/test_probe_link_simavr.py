"""ProbeLink against the REAL firmware: the ATmega32u4 ELF on simavr, over the harness's pty.

The harness (tests/firmware/simavr_probe.py) runs the firmware at real-time speed
(``--speed 1``) with a sine on the load-cell pin and logs every ADC conversion; ProbeLink
opens the harness's pty through SerialTransport (pyserial) like a real port. Checked:
GET_INFO, configuration and streaming through ProbeLink, every ADC count against the value
the harness fed at that conversion, forces from the configured calibration, exact sample
accounting across a host-side disconnection, and the clock sync against simulated time.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import (
    ForceRow,
    ForceRows,
    Gap,
    LinkDown,
    LinkUp,
    ProbeEvent,
    ProbeLink,
)
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig
from tests.conftest import require_path, require_tool
from tests.firmware.simavr_probe import (
    BLE_PROBE_DONE_S,
    FIRMWARE_ELF,
    SIMAVR_HEADER,
    Harness,
    assert_samples_are_fed_bursts,
    build,
    nearest,
    write_wave,
)

pytestmark = pytest.mark.toolchain


@pytest.fixture(scope="module")
def built() -> None:
    require_tool("avr-gcc", "avr-g++", "cc", "make")
    require_path(SIMAVR_HEADER, "libsimavr-dev headers")
    build("harness", "firmware")


@pytest.fixture
def sine_harness(built: None, tmp_path: Path) -> Iterator[tuple[Harness, np.ndarray, np.ndarray]]:
    t_s = np.arange(0.0, 60.0, 0.01)
    mv = 1650.0 + 1200.0 * np.sin(2 * np.pi * 0.8 * t_s)
    h = Harness(
        FIRMWARE_ELF,
        write_wave(tmp_path / "sine.txt", t_s, mv),
        ["--speed", "1", "--no-exit-on-hangup", "--sim-time", "60"],
    )
    try:
        yield h, t_s, mv
    finally:
        h.close()


async def test_probe_link_streams_the_real_firmware(
    sine_harness: tuple[Harness, np.ndarray, np.ndarray],
) -> None:
    h, t_wave, mv = sine_harness
    # Let the firmware give up on the absent BLE module (its main loop is blocked meanwhile),
    # then hand the pty from the harness's own pyserial handle to ProbeLink.
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 10
    while h.sim_time_s() < BLE_PROBE_DONE_S:
        assert loop.time() < deadline, "simulation did not pass the BLE probe"
        h.check_alive("the BLE probe")
        await asyncio.sleep(0.05)
    path = h.log.of("PTY")[0]["path"]
    assert h.port is not None
    h.port.close()
    h.port = None

    clock = ScaledClock(1.0)
    link = ProbeLink(
        SerialTransport(SerialTransportConfig(port=path)),
        clock=clock,
        rate_hz=100,
        led_level=40,
        command_timeout_s=1.0,
        zero_counts=512,
        span_un_per_count=10_000,
    )
    events: list[ProbeEvent] = []

    async def collect() -> None:
        async for ev in link.events():
            events.append(ev)

    def rows() -> list[ForceRow]:
        return [r for e in events if isinstance(e, ForceRows) for r in e.rows]

    async def until(pred: object, what: str, wall_s: float = 15.0) -> None:
        end = loop.time() + wall_s
        while not pred():  # type: ignore[operator]
            assert loop.time() < end, f"timed out waiting for {what}"
            h.check_alive(what)
            await asyncio.sleep(0.02)

    info = await link.connect()
    task = asyncio.create_task(collect())
    try:
        assert (info.proto, info.fw_major, info.adc_bits, info.batch) == (1, 1, 10, 10)
        assert info.span_un_per_count == 0  # fresh EEPROM: the configured calibration is used
        assert link.calibration_source == "config"
        await link.start_stream()
        await until(lambda: len(rows()) >= 200, "2 s of samples")
        # the LED duty reached the PWM register
        await until(lambda: any(kv["value"] == "40" for kv in h.log.of("REG")), "OCR3AL = 40")

        # a host-side disconnection: the firmware keeps streaming into the void
        await link.transport.close()
        await until(lambda: sum(isinstance(e, LinkUp) for e in events) >= 1, "the link back")
        n = len(rows())
        await until(lambda: len(rows()) >= n + 150, "samples after the reconnection")
    finally:
        await link.close()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 5)

    got = rows()
    gaps = [e for e in events if isinstance(e, Gap)]
    assert any(isinstance(e, LinkDown) for e in events)
    idx = [r.sample_index for r in got]
    lost = [i for g in gaps for i in range(g.start_index, g.start_index + g.count)]
    assert all(g.cause == "link" for g in gaps)
    assert sorted(idx + lost) == list(range(min(idx), max(idx) + 1)), "accounting not exact"
    assert link.accounting.lost == len(lost) and link.accounting.received == len(idx)

    # every count is what the harness fed at that sample's conversion (once the harness's
    # log, read by a thread that lags on a loaded machine, covers the last sample)
    t_mcu_s = np.array([r.t_mcu_us for r in got]) * 1e-6
    await until(lambda: h.logged_through(t_mcu_s[-1] + 0.01), "the log of the last sample")
    conv, burst_t, burst_mv = h.log.bursts()
    k = nearest(conv, t_mcu_s)
    offset_s = conv[k] - t_mcu_s
    # micros() ticks every 8 us at 8 MHz and the ISR's entry latency varies with the other
    # interrupts (Timer0, UART): the spread stays within a few ticks.
    assert 0 <= np.median(offset_s) < 3e-3 and np.ptp(offset_s) < 5 * 8e-6
    adc = np.array([r.adc_counts for r in got])
    assert_samples_are_fed_bursts(
        adc, [burst_mv[i] for i in k], [np.interp(burst_t[i], t_wave, mv) for i in k]
    )
    force = np.array([r.force_n for r in got], dtype=np.float64)
    assert np.allclose(force, (adc - 512) * 0.01)
    # rate and clock: simulated time runs at wall speed, so the mapped times follow it
    t_host = np.array([r.t_host_s for r in got])
    rate_mcu = (idx[-1] - idx[0]) / (t_mcu_s[-1] - t_mcu_s[0])
    assert abs(rate_mcu / 100 - 1) < 0.01, rate_mcu
    rate_host = (idx[-1] - idx[0]) / (t_host[-1] - t_host[0])
    assert abs(rate_host / 100 - 1) < 0.02, rate_host
    assert abs(link.clock_sync.drift_ppm) < 20_000
