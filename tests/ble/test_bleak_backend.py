"""bleak's public API on the Bumble backend, against the emulated module over a virtual radio."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest
from bleak import BleakClient, BleakScanner
from bleak.exc import BleakError

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.nus import NUS_RX_UUID, NUS_SERVICE_UUID, NUS_TX_UUID
from stipi_daemon.sim.ble.bleak_backend import BumbleAdapter
from stipi_daemon.sim.ble.peripheral import BleModuleLimits, NusPeripheral
from stipi_daemon.sim.ble.radio import BleRadioError, VirtualRadio, open_hci


async def _peripheral(radio: VirtualRadio, **kwargs: object) -> NusPeripheral:
    p = NusPeripheral(await open_hci(radio.spec), ScaledClock(1.0), **kwargs)  # type: ignore[arg-type]
    await p.start()
    return p


async def _until_received(notes: list[bytes], n: int) -> None:
    """Poll (for about a second at most) until the notifications add up to ``n`` bytes."""
    for _ in range(200):
        if sum(map(len, notes)) >= n:
            break
        await asyncio.sleep(0.005)


@pytest.fixture
async def peripheral(radio: VirtualRadio) -> AsyncIterator[NusPeripheral]:
    p = await _peripheral(radio)
    try:
        yield p
    finally:
        await p.close()


async def test_scanner_finds_the_probe_by_name_address_and_service(
    adapter: BumbleAdapter, peripheral: NusPeripheral
) -> None:
    scanner_cls, _ = adapter.backends()
    by_name = await BleakScanner.find_device_by_name("STIPI-01", timeout=5, backend=scanner_cls)
    assert by_name is not None and by_name.name == "STIPI-01"
    address = peripheral.address.to_string(with_type_qualifier=False)
    assert by_name.address == address
    by_address = await BleakScanner.find_device_by_address(
        address.lower(), timeout=5, backend=scanner_cls
    )
    assert by_address is not None
    seen = await BleakScanner.discover(
        timeout=0.3, return_adv=True, service_uuids=[NUS_SERVICE_UUID], backend=scanner_cls
    )
    assert address in seen
    _, adv = seen[address]
    assert NUS_SERVICE_UUID in adv.service_uuids and adv.local_name == "STIPI-01"
    other = await BleakScanner.discover(
        timeout=0.2, service_uuids=["0000180d-0000-1000-8000-00805f9b34fb"], backend=scanner_cls
    )
    assert other == []  # the service filter applies


async def test_missing_device_is_not_found(adapter: BumbleAdapter) -> None:
    scanner_cls, _ = adapter.backends()
    assert (
        await BleakScanner.find_device_by_name("nobody", timeout=0.2, backend=scanner_cls) is None
    )


async def test_connect_discover_write_notify_and_disconnect(
    adapter: BumbleAdapter, peripheral: NusPeripheral
) -> None:
    scanner_cls, client_cls = adapter.backends()
    device = await BleakScanner.find_device_by_name("STIPI-01", timeout=5, backend=scanner_cls)
    assert device is not None
    received: list[bytes] = []
    peripheral.on_receive = received.append
    dropped: list[BleakClient] = []
    client = BleakClient(device, disconnected_callback=dropped.append, backend=client_cls)
    await client.connect()
    assert client.is_connected and client.mtu_size == 23  # the module keeps ATT MTU 23
    service = client.services.get_service(NUS_SERVICE_UUID)
    assert service is not None
    tx = client.services.get_characteristic(NUS_TX_UUID)
    rx = client.services.get_characteristic(NUS_RX_UUID)
    assert tx is not None and rx is not None
    assert tx.properties == ["notify"]
    assert sorted(rx.properties) == ["write", "write-without-response"]
    assert [d.uuid for d in tx.descriptors] == ["00002902-0000-1000-8000-00805f9b34fb"]
    assert rx.max_write_without_response_size == 20

    await client.write_gatt_char(rx, b"with", response=True)
    await client.write_gatt_char(rx, b"without", response=False)
    notes: list[bytes] = []
    await client.start_notify(tx, lambda _c, data: notes.append(bytes(data)))
    with pytest.raises(BleakError, match="already started"):
        await client.start_notify(tx, lambda _c, data: None)
    frame = bytes(range(1, 46)) + b"\x00"
    assert peripheral.offer_frame(frame, tag="f")
    await _until_received(notes, len(frame))
    assert received == [b"with", b"without"]
    assert b"".join(notes) == frame and [len(n) for n in notes] == [20, 20, 6]
    assert peripheral.counters.subscriptions_per_connection == [1]

    await client.stop_notify(tx)
    await client.disconnect()
    await asyncio.sleep(0.02)
    assert not client.is_connected and dropped == []  # our own disconnect: no callback


async def test_peripheral_drop_calls_the_disconnected_callback(
    adapter: BumbleAdapter, peripheral: NusPeripheral
) -> None:
    scanner_cls, client_cls = adapter.backends()
    device = await BleakScanner.find_device_by_name("STIPI-01", timeout=5, backend=scanner_cls)
    assert device is not None
    event = asyncio.Event()
    client = BleakClient(device, disconnected_callback=lambda _c: event.set(), backend=client_cls)
    await client.connect()
    assert await peripheral.drop_link()
    await asyncio.wait_for(event.wait(), 2)
    assert not client.is_connected
    with pytest.raises(BleakError):
        await client.write_gatt_char(NUS_RX_UUID, b"x", response=False)
    # The module advertises again and accepts a new connection.
    await client.connect()
    assert client.is_connected
    await client.disconnect()


async def test_larger_mtu_when_the_module_allows_it(
    radio: VirtualRadio, adapter: BumbleAdapter
) -> None:
    p = await _peripheral(radio, name="STIPI-02", limits=BleModuleLimits(max_mtu=100))
    try:
        scanner_cls, client_cls = adapter.backends()
        device = await BleakScanner.find_device_by_name("STIPI-02", timeout=5, backend=scanner_cls)
        assert device is not None
        async with BleakClient(device, backend=client_cls) as client:
            assert client.mtu_size == 100
            notes: list[bytes] = []
            await client.start_notify(NUS_TX_UUID, lambda _c, d: notes.append(bytes(d)))
            assert p.offer_frame(b"\x01" * 200 + b"\x00")
            await _until_received(notes, 201)
            assert [len(n) for n in notes] == [97, 97, 7]
    finally:
        await p.close()


async def test_client_by_address_string_and_unknown_radio(
    adapter: BumbleAdapter, peripheral: NusPeripheral
) -> None:
    _, client_cls = adapter.backends()
    address = peripheral.address.to_string(with_type_qualifier=False)
    async with BleakClient(address, backend=client_cls, timeout=5) as client:
        assert client.services.get_service(NUS_SERVICE_UUID) is not None
    with pytest.raises(BleRadioError, match="no virtual radio 'nope'"):
        await open_hci("virtual:nope")
