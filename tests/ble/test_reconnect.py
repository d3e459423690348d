"""Reconnection over BLE: forced disconnects, re-subscription, silent links, exact accounting."""

from __future__ import annotations

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import LINK_MIN_WALL_S, ProbeLink, wall_floored_timeout_s
from stipi_daemon.probe.transports import open_transport
from stipi_daemon.probe.transports.ble import BleEmulationConfig, BleTransport, BleTransportConfig
from stipi_daemon.sim.ble.radio import VirtualRadio

from .conftest import SCENES, ProbeRecorder, check_accounting_against_ledger

#: How late a loaded machine's event loop may wake the link's watchdog [s of wall time].
LATE_WAKE_WALL_S = 0.2


def _ble_probe(
    radio: VirtualRadio, clock: ScaledClock, **link: float
) -> tuple[ProbeLink, BleTransport]:
    cfg = BleTransportConfig(
        name="STIPI-01",
        hci=radio.spec,
        scan_timeout_s=2.0,
        emulate=BleEmulationConfig(scene=SCENES / "grade1.yaml", seed=5),
    )
    transport = open_transport(cfg, clock)
    assert isinstance(transport, BleTransport)
    probe = ProbeLink(
        transport, clock=clock, reconnect_initial_s=0.05, command_timeout_s=2.0, **link
    )
    return probe, transport


async def _forced_disconnects(radio: VirtualRadio, n: int) -> None:
    clock = ScaledClock(10.0)
    probe, transport = _ble_probe(radio, clock, heartbeat_timeout_s=2.5, reconnect_total_s=30)
    await probe.connect()
    await probe.start_stream()
    rec = ProbeRecorder(probe)
    emulator = transport.emulator
    try:
        for i in range(n):
            # Data flows on this connection, then the link drops (a supervision timeout).
            await rec.until(lambda: rec.rows_since_up >= 10)
            assert await emulator.peripheral.drop_link()
            await rec.until(lambda i=i: len(rec.ups) == i + 2)  # + the first LinkUp
        await rec.until(lambda: rec.rows_since_up >= 30)
        await probe.stop_stream()
    finally:
        await rec.stop()
    counters = emulator.peripheral.counters
    assert len(rec.downs) == n and len(rec.ups) == n + 1
    assert [u.reconnect for u in rec.ups] == [False] + [True] * n
    # n + 1 connections; a loaded host may need an extra attempt (a command timing out), which
    # is one more connection, never a second subscription on one.
    assert counters.connections == counters.disconnections == transport.connections
    assert n + 1 <= counters.connections <= n + 3
    # Notifications re-subscribed exactly once per connection, never twice.
    assert counters.subscriptions_per_connection == [1] * counters.connections
    assert transport.subscriptions == transport.connections
    lost = check_accounting_against_ledger(rec, emulator.ledger, counters.connections)
    # Mostly one gap per disconnect; a slow host can add TX-buffer overflows (still exact).
    assert lost > 0 and len(rec.gaps) >= 1
    assert all(g.cause == "link" for g in rec.gaps)


async def test_hundred_forced_disconnects(radio: VirtualRadio) -> None:
    await _forced_disconnects(radio, 100)


async def test_silent_link_is_detected_within_the_heartbeat_timeout(radio: VirtualRadio) -> None:
    clock = ScaledClock(4.0)
    # 1 s of session time is 0.25 s of wall time at speed 4: the link's wall-time floor makes
    # it 1 s of wall time, 4 s of session time.
    timeout_s = wall_floored_timeout_s(1.0, clock.speed, LINK_MIN_WALL_S)
    assert timeout_s == 4.0
    probe, transport = _ble_probe(radio, clock, heartbeat_timeout_s=1.0, reconnect_total_s=30)
    await probe.connect()
    await probe.start_stream()
    rec = ProbeRecorder(probe)
    emulator = transport.emulator
    peripheral = emulator.peripheral
    try:
        await rec.until(lambda: rec.rows_since_up >= 20)
        t_silent = clock.now()
        peripheral.set_silent(True)  # connected, CCCD on, but no notifications
        await rec.until(lambda: len(rec.downs) == 1)
        down = rec.downs[0]
        assert "no frame from the probe for 4 s" in down.reason
        # The last frame arrived at most one batch (0.1 s) before the silence began; the
        # watchdog wakes at the deadline, later only by the loop's own lateness (up to
        # LATE_WAKE_WALL_S on a loaded machine: 0.1 s of session time, 25 ms of wall time,
        # was exceeded beside a busy loop on every CPU). A watchdog that checked once per
        # timeout would be up to a whole timeout late.
        late_s = 0.1 + LATE_WAKE_WALL_S * clock.speed
        assert timeout_s - 0.15 <= down.t_s - t_silent <= timeout_s + late_s
        peripheral.set_silent(False)
        await rec.until(lambda: len(rec.ups) == 2 and rec.rows_since_up >= 10)
        await probe.stop_stream()
    finally:
        await rec.stop()
    check_accounting_against_ledger(rec, emulator.ledger)
    assert peripheral.counters.subscriptions_per_connection[-1] == 1
