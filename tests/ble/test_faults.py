"""Fault injection on the peripheral side: damaged, delayed and vanishing links over BLE."""

from __future__ import annotations

import asyncio
import statistics

from stipi_daemon.app.devices import SceneStartProbeLink
from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ProbeLink
from stipi_daemon.probe.transports import open_transport
from stipi_daemon.probe.transports.ble import BleEmulationConfig, BleTransport, BleTransportConfig
from stipi_daemon.sim.ble.module import NotificationFaults
from stipi_daemon.sim.ble.peripheral import NusPeripheral
from stipi_daemon.sim.ble.radio import VirtualRadio

from .conftest import SCENES, ProbeRecorder, check_accounting_against_ledger


async def _start(
    radio: VirtualRadio,
    speed: float,
    *,
    stream: bool = True,
    link_type: type[ProbeLink] = ProbeLink,
) -> tuple[ProbeRecorder, BleTransport, ScaledClock]:
    clock = ScaledClock(speed)
    cfg = BleTransportConfig(
        name="STIPI-01",
        hci=radio.spec,
        scan_timeout_s=0.3,
        emulate=BleEmulationConfig(scene=SCENES / "grade1.yaml", seed=9),
    )
    transport = open_transport(cfg, clock)
    assert isinstance(transport, BleTransport)
    probe = link_type(
        transport,
        clock=clock,
        heartbeat_timeout_s=2.0,
        reconnect_total_s=30,
        reconnect_initial_s=0.05,
        reconnect_max_s=0.2,
    )
    await probe.connect()
    if stream:
        await probe.start_stream()
    return ProbeRecorder(probe), transport, clock


async def test_dropped_and_corrupted_notifications_are_accounted_exactly(
    radio: VirtualRadio,
) -> None:
    rec, transport, clock = await _start(radio, 10.0)
    emulator = transport.emulator
    try:
        await rec.until(lambda: rec.rows_since_up >= 20)
        emulator.peripheral.faults = NotificationFaults(
            drop_probability=0.1, corrupt_probability=0.1
        )
        await clock.sleep_until(clock.now() + 8.0)
        emulator.peripheral.faults = NotificationFaults()
        n = len(rec.indices)
        await rec.until(lambda: len(rec.indices) >= n + 30)
    finally:
        await rec.stop()
    counters = emulator.peripheral.counters
    assert counters.dropped_notifications >= 3 and counters.corrupted_notifications >= 3
    stats = rec.probe.decoder.stats
    assert stats.crc_errors + stats.cobs_errors + stats.length_errors > 0
    lost = check_accounting_against_ledger(rec, emulator.ledger)
    assert lost > 0 and len(rec.downs) == 0  # damage, but the link stayed up


async def test_delayed_notifications_arrive_later_and_complete(radio: VirtualRadio) -> None:
    rec, transport, _clock = await _start(radio, 2.0)
    emulator = transport.emulator
    delay_s = 0.3
    try:
        await rec.until(lambda: len(rec.clock_probes) >= 20)
        before = len(rec.clock_probes)
        emulator.peripheral.faults = NotificationFaults(delay_s=delay_s)
        await rec.until(lambda: len(rec.clock_probes) >= before + 40)
    finally:
        await rec.stop()

    def lag(probes: list) -> float:  # arrival minus sample time, offset removed below
        return statistics.median(p.host_s - p.mcu_unwrapped_us * 1e-6 for p in probes)

    fast = rec.clock_probes[5:before]
    slow = rec.clock_probes[before + 10 :]
    # At least the delay is added; a loaded test machine may add scheduling slack on top.
    assert delay_s - 0.03 <= lag(slow) - lag(fast) <= delay_s + 0.25
    assert check_accounting_against_ledger(rec, emulator.ledger) == 0


async def test_probe_disappears_and_comes_back(radio: VirtualRadio) -> None:
    rec, transport, clock = await _start(radio, 4.0)
    emulator = transport.emulator
    try:
        await rec.until(lambda: rec.rows_since_up >= 20)
        t0 = clock.now()
        await emulator.peripheral.disappear(1.5)  # returns when it advertises again
        await rec.until(lambda: len(rec.ups) == 2 and rec.rows_since_up >= 20)
    finally:
        await rec.stop()
    assert len(rec.downs) == 1
    assert rec.ups[1].t_s - t0 >= 1.5  # no reconnection while it was gone
    assert emulator.peripheral.counters.subscriptions_per_connection == [1, 1]
    lost = check_accounting_against_ledger(rec, emulator.ledger)
    assert lost >= 1.5 * 100 * 0.9  # about 1.5 s of samples at 100 Hz never reached the host
    assert len(rec.gaps) == 1


def _drop_on_next_write(peripheral: NusPeripheral) -> list[asyncio.Task[bool]]:
    """Make the radio drop the connection as the host's next write arrives (the probe never
    sees it); the drop's task, once it is started."""
    deliver = peripheral.on_receive
    drops: list[asyncio.Task[bool]] = []

    def drop_instead(data: bytes) -> None:
        peripheral.on_receive = deliver
        drops.append(asyncio.get_running_loop().create_task(peripheral.drop_link()))

    peripheral.on_receive = drop_instead
    return drops


async def test_a_drop_while_stream_start_waits_for_its_ack_starts_the_stream_on_return(
    radio: VirtualRadio,
) -> None:
    # the radio drops the connection as STREAM_START is written (the probe never sees it):
    # start_stream() returns, as while the link is down, and the reconnection starts the
    # stream; before, the daemon's start failed with "disconnected by the peripheral"
    rec, transport, _clock = await _start(radio, 4.0, stream=False)
    drops = _drop_on_next_write(transport.emulator.peripheral)
    try:
        await rec.probe.start_stream()
        await rec.until(lambda: len(rec.ups) >= 2 and rec.rows_since_up >= 20)
    finally:
        await rec.stop()
    assert len(drops) == 1 and await drops[0]
    assert len(rec.downs) == 1 and not rec.gaps  # nothing was streamed before the drop


async def _scheduled_start(radio: VirtualRadio, drop: bool) -> tuple[float, float, bool]:
    """A scheduled STREAM_START (the radio drops the link as it is written, if ``drop``),
    then 20 rows streamed; what ``on_stream_start`` was told."""
    rec, transport, clock = await _start(radio, 4.0, stream=False, link_type=SceneStartProbeLink)
    probe = rec.probe
    assert isinstance(probe, SceneStartProbeLink)
    seen: list[tuple[float, float, bool]] = []
    probe.on_stream_start = lambda at, sent, ack: seen.append((at, sent, ack))
    probe.stream_start_at_s = clock.now() + 0.2
    drops = _drop_on_next_write(transport.emulator.peripheral) if drop else []
    try:
        assert await probe.start_stream() is not drop
        await rec.until(lambda: rec.rows_since_up >= 20)
    finally:
        await rec.stop()
    assert len(drops) == int(drop) and all([await d for d in drops])
    (call,) = seen
    return call


async def test_a_scheduled_stream_start_says_whether_the_probe_acknowledged_it(
    radio: VirtualRadio,
) -> None:
    """The daemon's scheduled STREAM_START (a probe that plays its scene from it) reports
    whether the probe's ACK came: the session's ``stream_start`` event must not present the
    time of a STREAM_START the radio dropped as the probe's scene start."""
    at, sent, ack = await _scheduled_start(radio, drop=False)
    assert ack and sent >= at
    at, sent, ack = await _scheduled_start(radio, drop=True)
    assert not ack and sent >= at
