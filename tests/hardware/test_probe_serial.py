"""Opt-in: ProbeLink against a real probe on a serial port (``pytest --probe-port=/dev/ttyACM0``).

Skipped unless a port is named: it needs the hardware. With it, checks GET_INFO and 2 s of
streaming at 100 Hz: contiguous sample indices, the rate in the probe's clock, ADC counts
within the 10-bit range, and STATUS heartbeats.
"""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ForceRow, ForceRows, Gap, ProbeEvent, ProbeLink, StatusReport
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig


@pytest.fixture
def probe_port(request: pytest.FixtureRequest) -> str:
    port = request.config.getoption("--probe-port")
    if not port:
        pytest.skip("no real probe: pass --probe-port=/dev/ttyACM0 to run")
    return str(port)


async def test_real_probe_info_and_two_seconds_of_streaming(probe_port: str) -> None:
    clock = ScaledClock(1.0)
    link = ProbeLink(SerialTransport(SerialTransportConfig(port=probe_port)), clock=clock)
    events: list[ProbeEvent] = []

    async def collect() -> None:
        async for ev in link.events():
            events.append(ev)

    info = await link.connect()
    task = asyncio.create_task(collect())
    try:
        assert info.proto == 1 and info.adc_bits == 10 and 1 <= info.batch <= 24
        await link.start_stream()
        await clock.sleep_until(clock.now() + 2.0)
        await link.stop_stream()
    finally:
        await link.close()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 5)
    rows: list[ForceRow] = [r for e in events if isinstance(e, ForceRows) for r in e.rows]
    assert len(rows) >= 150, len(rows)
    idx = np.array([r.sample_index for r in rows])
    assert not [e for e in events if isinstance(e, Gap)]
    assert np.array_equal(np.diff(idx), np.ones(len(idx) - 1, dtype=np.int64))
    t_mcu_s = np.array([r.t_mcu_us for r in rows]) * 1e-6
    rate_hz = (idx[-1] - idx[0]) / (t_mcu_s[-1] - t_mcu_s[0])
    assert abs(rate_hz / 100 - 1) < 0.01, rate_hz
    assert all(0 <= r.adc_counts <= 1023 for r in rows)
    assert [e for e in events if isinstance(e, StatusReport)]
