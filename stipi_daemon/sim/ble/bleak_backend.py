"""A bleak backend that runs on Bumble's host stack instead of the operating system's.

This module owns :class:`BumbleAdapter` (a Bumble :class:`~bumble.device.Device` acting as
central on an HCI endpoint - a USB dongle, an HCI socket, or a controller on a
:class:`~stipi_daemon.sim.ble.radio.VirtualRadio`) and the two bleak backend classes built on
it, :class:`BumbleBleakScanner` (a :class:`bleak.backends.scanner.BaseBleakScanner`) and
:class:`BumbleBleakClient` (a :class:`bleak.backends.client.BaseBleakClient`). bleak accepts
them through ``BleakScanner(..., backend=...)`` and ``BleakClient(..., backend=...)``, so
code written against bleak's public API - our BLE transport - runs unchanged on Bumble:
in tests over a virtual radio with no adapter, or on a bench PC that drives a dongle
directly. Scanning, connecting, GATT discovery, MTU exchange, writes and notifications
are real Bumble GAP/ATT/GATT procedures. It does not implement pairing storage or
anything beyond what a Nordic UART central needs (descriptor writes, reads and pairing
are supported; unpairing is not).

Each adapter gives its own backend classes (:meth:`BumbleAdapter.backends`), bound to it,
because bleak instantiates backends from a class.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any, ClassVar, Final

from bleak.args import SizedBuffer
from bleak.assigned_numbers import CharacteristicPropertyName
from bleak.backends.characteristic import BleakGATTCharacteristic
from bleak.backends.client import BaseBleakClient, NotifyCallback
from bleak.backends.descriptor import BleakGATTDescriptor
from bleak.backends.device import BLEDevice
from bleak.backends.scanner import AdvertisementData, AdvertisementDataCallback, BaseBleakScanner
from bleak.backends.service import BleakGATTService, BleakGATTServiceCollection
from bleak.exc import BleakDeviceNotFoundError, BleakError
from bumble.core import UUID, AdvertisingData
from bumble.device import Advertisement, Connection, Device, DeviceConfiguration, Peer
from bumble.gatt import Characteristic
from bumble.gatt_client import CharacteristicProxy, DescriptorProxy
from bumble.hci import Address, HCI_Error

from stipi_daemon.sim.ble.radio import HciEndpoint, open_hci, static_address

__all__ = [
    "DEFAULT_CENTRAL_MTU",
    "BumbleAdapter",
    "BumbleBleakClient",
    "BumbleBleakScanner",
]

_log = logging.getLogger(__name__)

#: ATT MTU the central asks for after connecting [bytes], as BlueZ does; the peripheral
#: answers with what it supports (the probe's module: 23).
DEFAULT_CENTRAL_MTU: Final = 517
_REASON_LOCAL_TERMINATED: Final = 0x13
_CENTRAL_ADDRESS_BASE: Final = 0x5EA7_0000

_PROPERTY_NAMES: Final[tuple[tuple[Characteristic.Properties, CharacteristicPropertyName], ...]] = (
    (Characteristic.Properties.BROADCAST, "broadcast"),
    (Characteristic.Properties.READ, "read"),
    (Characteristic.Properties.WRITE_WITHOUT_RESPONSE, "write-without-response"),
    (Characteristic.Properties.WRITE, "write"),
    (Characteristic.Properties.NOTIFY, "notify"),
    (Characteristic.Properties.INDICATE, "indicate"),
    (Characteristic.Properties.AUTHENTICATED_SIGNED_WRITES, "authenticated-signed-writes"),
    (Characteristic.Properties.EXTENDED_PROPERTIES, "extended-properties"),
)


def _full_uuid(uuid: UUID) -> str:
    """bleak's normalised UUID form: lowercase 128-bit with dashes."""
    raw = bytes(uuid.to_bytes(force_128=True))[::-1].hex()
    return f"{raw[0:8]}-{raw[8:12]}-{raw[12:16]}-{raw[16:20]}-{raw[20:32]}"


def advertisement_to_bleak(adv: Advertisement) -> AdvertisementData:
    """bleak's :class:`AdvertisementData` for a Bumble advertisement (pure conversion)."""
    data = adv.data
    name: str | None = None
    for kind in (
        AdvertisingData.Type.COMPLETE_LOCAL_NAME,
        AdvertisingData.Type.SHORTENED_LOCAL_NAME,
    ):
        value = data.get(kind)
        if isinstance(value, str):
            name = value
            break
    uuids: list[str] = []
    for kind in (
        AdvertisingData.Type.COMPLETE_LIST_OF_16_BIT_SERVICE_CLASS_UUIDS,
        AdvertisingData.Type.INCOMPLETE_LIST_OF_16_BIT_SERVICE_CLASS_UUIDS,
        AdvertisingData.Type.COMPLETE_LIST_OF_32_BIT_SERVICE_CLASS_UUIDS,
        AdvertisingData.Type.INCOMPLETE_LIST_OF_32_BIT_SERVICE_CLASS_UUIDS,
        AdvertisingData.Type.COMPLETE_LIST_OF_128_BIT_SERVICE_CLASS_UUIDS,
        AdvertisingData.Type.INCOMPLETE_LIST_OF_128_BIT_SERVICE_CLASS_UUIDS,
    ):
        for entry in data.get_all(kind):
            items = entry if isinstance(entry, list) else [entry]
            uuids.extend(_full_uuid(u) for u in items if isinstance(u, UUID))
    manufacturer: dict[int, bytes] = {}
    for entry in data.get_all(AdvertisingData.Type.MANUFACTURER_SPECIFIC_DATA):
        if isinstance(entry, tuple) and len(entry) == 2:
            manufacturer[int(entry[0])] = bytes(entry[1])
    service_data: dict[str, bytes] = {}
    for kind in (
        AdvertisingData.Type.SERVICE_DATA_16_BIT_UUID,
        AdvertisingData.Type.SERVICE_DATA_32_BIT_UUID,
        AdvertisingData.Type.SERVICE_DATA_128_BIT_UUID,
    ):
        for entry in data.get_all(kind):
            if isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], UUID):
                service_data[_full_uuid(entry[0])] = bytes(entry[1])
    tx_power = data.get(AdvertisingData.Type.TX_POWER_LEVEL)
    return AdvertisementData(
        local_name=name,
        manufacturer_data=manufacturer,
        service_data=service_data,
        service_uuids=uuids,
        tx_power=int(tx_power) if isinstance(tx_power, int) else None,
        rssi=int(adv.rssi),
        platform_data=(adv,),
    )


class BumbleAdapter:
    """A Bumble central on one HCI endpoint, shared by the scanners and clients bound to it.

    Parameters
    ----------
    hci : HciEndpoint
        The controller to drive.
    address : Address, optional
        Random static address of the central (default derived from the spec).
    name : str
        GAP device name of the central.
    mtu : int
        ATT MTU requested after each connection [bytes] (>= 23).
    """

    _shared: ClassVar[dict[tuple[int, str], tuple[BumbleAdapter, int]]] = {}

    def __init__(
        self,
        hci: HciEndpoint,
        *,
        address: Address | None = None,
        name: str = "stipi-daemon",
        mtu: int = DEFAULT_CENTRAL_MTU,
    ) -> None:
        if not 23 <= mtu <= 517:
            raise ValueError(f"requested ATT MTU must be within 23..517 bytes, got {mtu}")
        self.hci = hci
        self.mtu = mtu
        addr = address or static_address(_CENTRAL_ADDRESS_BASE + (hash(hci.spec) & 0xFFFF))
        config = DeviceConfiguration(name=name, address=addr)
        self.device = Device.from_config_with_hci(config, hci.source, hci.sink)  # type: ignore[arg-type]
        self._listeners: dict[object, Callable[[Advertisement], None]] = {}
        self._scan_users = 0
        self._scan_lock = asyncio.Lock()
        self._connect_lock = asyncio.Lock()
        self._started = False
        self.device.on(Device.EVENT_ADVERTISEMENT, self._on_advertisement)
        scanner_cls, client_cls = _bind(self)
        self.scanner_backend: type[BumbleBleakScanner] = scanner_cls
        self.client_backend: type[BumbleBleakClient] = client_cls

    # -------------------------------------------------------------- lifecycle

    @classmethod
    async def open(cls, spec: str, **kwargs: Any) -> BumbleAdapter:
        """Open the HCI endpoint ``spec`` and power a central on it."""
        hci = await open_hci(spec)
        adapter = cls(hci, **kwargs)
        try:
            await adapter.start()
        except BaseException:
            await hci.close()
            raise
        return adapter

    @classmethod
    async def acquire(cls, spec: str) -> BumbleAdapter:
        """The shared adapter for ``spec`` in this event loop (opened on first use).

        Every :meth:`acquire` must be paired with one :meth:`release`.
        """
        key = (id(asyncio.get_running_loop()), spec)
        entry = cls._shared.get(key)
        if entry is None:
            adapter = await cls.open(spec)
            entry = cls._shared.get(key) or (adapter, 0)
            if entry[0] is not adapter:  # another task opened it meanwhile
                await adapter.close()
        cls._shared[key] = (entry[0], entry[1] + 1)
        return entry[0]

    async def release(self) -> None:
        """Drop one :meth:`acquire` reference; the last one closes the adapter."""
        for key, (adapter, count) in list(self._shared.items()):
            if adapter is self:
                if count <= 1:
                    del self._shared[key]
                    await self.close()
                else:
                    self._shared[key] = (adapter, count - 1)
                return

    def backends(self) -> tuple[type[BumbleBleakScanner], type[BumbleBleakClient]]:
        """bleak backend classes bound to this adapter: ``(scanner, client)``."""
        return self.scanner_backend, self.client_backend

    async def start(self) -> None:
        """Power the central on."""
        if not self._started:
            await self.device.power_on()
            self._started = True

    async def close(self) -> None:
        """Disconnect everything, power off and release the HCI endpoint."""
        if self._started:
            for conn in list(self.device.connections.values()):
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(1.0):
                        await conn.disconnect(_REASON_LOCAL_TERMINATED)
            with contextlib.suppress(Exception):
                await self.device.power_off()
            self._started = False
        await self.hci.close()

    # --------------------------------------------------------------- scanning

    def add_listener(self, callback: Callable[[Advertisement], None]) -> Callable[[], None]:
        """Receive every advertisement while scanning; returns the function that removes it."""
        token = object()
        self._listeners[token] = callback

        def remove() -> None:
            self._listeners.pop(token, None)

        return remove

    async def start_scanning(self, *, active: bool) -> None:
        """Start scanning (reference-counted: one scan serves every scanner)."""
        async with self._scan_lock:
            self._scan_users += 1
            if self._scan_users == 1:
                await self.device.start_scanning(active=active, filter_duplicates=False)

    async def stop_scanning(self) -> None:
        """Undo one :meth:`start_scanning`."""
        async with self._scan_lock:
            if self._scan_users == 0:
                return
            self._scan_users -= 1
            if self._scan_users == 0 and self.device.is_scanning:
                await self.device.stop_scanning()

    def _on_advertisement(self, adv: Advertisement) -> None:
        for callback in list(self._listeners.values()):
            callback(adv)

    # ------------------------------------------------------------- connecting

    async def connect(self, address: Address, timeout_s: float) -> Connection:
        """Connect to ``address`` as central (one connection attempt at a time)."""
        async with self._connect_lock:
            # A controller cannot initiate a connection while it scans on some chips;
            # Bumble's software controller can, but keep the real constraint simple: none.
            return await self.device.connect(address, timeout=timeout_s)


class BumbleBleakScanner(BaseBleakScanner):
    """bleak scanner backend on a :class:`BumbleAdapter` (bound by :func:`_bind`)."""

    adapter: ClassVar[BumbleAdapter]

    def __init__(
        self,
        detection_callback: AdvertisementDataCallback | None,
        service_uuids: list[str] | None,
        scanning_mode: str = "active",
        **kwargs: Any,
    ) -> None:
        super().__init__(detection_callback, service_uuids)
        if scanning_mode not in ("active", "passive"):
            raise BleakError(f"scanning_mode must be 'active' or 'passive', got {scanning_mode!r}")
        self._active = scanning_mode == "active"
        self._remove: Callable[[], None] | None = None

    async def start(self) -> None:
        self.seen_devices = {}
        self._remove = self.adapter.add_listener(self._on_advertisement)
        try:
            await self.adapter.start_scanning(active=self._active)
        except BaseException:
            self._remove()
            self._remove = None
            raise

    async def stop(self) -> None:
        if self._remove is None:
            return
        self._remove()
        self._remove = None
        await self.adapter.stop_scanning()

    def _on_advertisement(self, adv: Advertisement) -> None:
        data = advertisement_to_bleak(adv)
        if not self.is_allowed_uuid(data.service_uuids):
            return
        address = adv.address.to_string(with_type_qualifier=False)
        device = self.create_or_update_device(
            key=address, address=address, name=data.local_name, details=adv.address, adv=data
        )
        self.call_detection_callbacks(device, data)


class BumbleBleakClient(BaseBleakClient):
    """bleak client backend on a :class:`BumbleAdapter` (bound by :func:`_bind`)."""

    adapter: ClassVar[BumbleAdapter]

    def __init__(
        self,
        address_or_ble_device: BLEDevice | str,
        *,
        disconnected_callback: Callable[[], None] | None,
        timeout: float,
        services: set[str] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            address_or_ble_device, disconnected_callback=disconnected_callback, timeout=timeout
        )
        if isinstance(address_or_ble_device, BLEDevice) and isinstance(
            address_or_ble_device.details, Address
        ):
            self._peer_address = address_or_ble_device.details
            self._name = address_or_ble_device.name
        else:
            try:
                self._peer_address = Address(self.address, Address.RANDOM_DEVICE_ADDRESS)
            except Exception as exc:
                raise BleakError(f"not a Bluetooth address: {self.address!r}") from exc
            self._name = None
        self._service_filter = services
        self._connection: Connection | None = None
        self._peer: Peer | None = None
        self._proxies: dict[int, CharacteristicProxy[bytes]] = {}
        self._descriptor_proxies: dict[int, DescriptorProxy] = {}
        self._subscribers: dict[int, Callable[[bytes], None]] = {}
        self._lost_reason: int | None = None

    # ------------------------------------------------------------ properties

    @property
    def name(self) -> str:
        if self._name:
            return self._name
        return self.address.replace(":", "-")

    @property
    def mtu_size(self) -> int:
        if self._connection is None:
            raise BleakError("not connected")
        return int(self._connection.att_mtu)

    @property
    def is_connected(self) -> bool:
        return self._connection is not None

    # ----------------------------------------------------------- connection

    async def connect(self, pair: bool, **kwargs: Any) -> None:
        if self._connection is not None:
            return
        try:
            connection = await self.adapter.connect(self._peer_address, self._timeout)
        except TimeoutError as exc:
            raise BleakDeviceNotFoundError(
                self.address, f"device {self.address} did not answer within {self._timeout} s"
            ) from exc
        except HCI_Error as exc:
            raise BleakError(f"connection to {self.address} failed: {exc}") from exc
        self._connection = connection
        self._lost_reason = None
        connection.on(connection.EVENT_DISCONNECTION, self._on_disconnection)
        try:
            peer = Peer(connection)
            self._peer = peer
            if self.adapter.mtu > 23:
                await peer.request_mtu(self.adapter.mtu)
            self.services = await self._discover(peer)
            if pair:
                await connection.pair()
        except BaseException as exc:
            await self.disconnect()
            reason = self._disconnect_reason()
            task = asyncio.current_task()
            if reason is None or (task is not None and task.cancelling()):
                raise
            # The link dropped under the MTU exchange or the discovery: Bumble cancels the
            # pending ATT request. bleak's backends report that as a BleakError (BlueZ:
            # "failed to discover services, device disconnected"), which callers retry.
            raise BleakError(
                f"{self.address} disconnected during connection set-up (HCI reason 0x{reason:02X})"
            ) from exc

    async def _discover(self, peer: Peer) -> BleakGATTServiceCollection:
        collection = BleakGATTServiceCollection()
        self._proxies.clear()
        self._descriptor_proxies.clear()
        services = await peer.discover_services()
        for svc in services:
            svc_uuid = _full_uuid(svc.uuid)
            if self._service_filter is not None and svc_uuid not in self._service_filter:
                continue
            bleak_service = BleakGATTService(svc, svc.handle, svc_uuid)
            collection.add_service(bleak_service)
            characteristics = await peer.discover_characteristics(service=svc)
            for char in characteristics:
                props = [name for bit, name in _PROPERTY_NAMES if char.properties & bit]
                bleak_char = BleakGATTCharacteristic(
                    char,
                    char.handle,
                    _full_uuid(char.uuid),
                    props,
                    self._max_write_without_response,
                    bleak_service,
                )
                collection.add_characteristic(bleak_char)
                self._proxies[char.handle] = char
                descriptors = await peer.discover_descriptors(characteristic=char)
                for desc in descriptors:
                    collection.add_descriptor(
                        BleakGATTDescriptor(desc, desc.handle, _full_uuid(desc.type), bleak_char)
                    )
                    self._descriptor_proxies[desc.handle] = desc
        return collection

    def _max_write_without_response(self) -> int:
        conn = self._connection
        return (int(conn.att_mtu) if conn is not None else 23) - 3

    def _disconnect_reason(self) -> int | None:
        """HCI reason of the last disconnection of this client (None: none since connect)."""
        return self._lost_reason

    def _on_disconnection(self, reason: int) -> None:
        self._lost_reason = reason
        self._connection = None
        self._peer = None
        self._subscribers.clear()
        _log.debug("peripheral %s disconnected (reason 0x%02X)", self.address, reason)
        callback = self._disconnected_callback
        if callback is not None:
            callback()

    async def disconnect(self) -> None:
        conn = self._connection
        if conn is None:
            return
        # A user-requested disconnect is not an unsolicited one: no callback.
        self._disconnected_callback, saved = None, self._disconnected_callback
        try:
            with contextlib.suppress(HCI_Error):
                await conn.disconnect(_REASON_LOCAL_TERMINATED)
        finally:
            self._connection = None
            self._peer = None
            self._subscribers.clear()
            self._disconnected_callback = saved

    async def pair(self, *args: Any, **kwargs: Any) -> None:
        await self._require_connection().pair()

    async def unpair(self) -> None:
        raise NotImplementedError("the Bumble backend keeps no bonds, there is nothing to unpair")

    # ------------------------------------------------------------------ I/O

    def _require_connection(self) -> Connection:
        if self._connection is None:
            raise BleakError(f"not connected to {self.address}")
        return self._connection

    def _require_peer(self) -> Peer:
        self._require_connection()
        assert self._peer is not None
        return self._peer

    def _proxy(self, characteristic: BleakGATTCharacteristic) -> CharacteristicProxy[bytes]:
        try:
            return self._proxies[characteristic.handle]
        except KeyError:
            raise BleakError(
                f"characteristic {characteristic.uuid} is not on this connection"
            ) from None

    async def read_gatt_char(
        self, characteristic: BleakGATTCharacteristic, *, use_cached: bool = False, **kwargs: Any
    ) -> bytearray:
        return bytearray(await self._require_peer().read_value(self._proxy(characteristic)))

    async def read_gatt_descriptor(
        self, descriptor: BleakGATTDescriptor, *, use_cached: bool = False, **kwargs: Any
    ) -> bytearray:
        proxy = self._descriptor_proxies.get(descriptor.handle)
        if proxy is None:
            raise BleakError(f"descriptor {descriptor.handle} is not on this connection")
        return bytearray(await self._require_peer().read_value(proxy))

    async def write_gatt_char(
        self, characteristic: BleakGATTCharacteristic, data: SizedBuffer, response: bool
    ) -> None:
        await self._require_peer().write_value(
            self._proxy(characteristic), bytes(data), with_response=response
        )

    async def write_gatt_descriptor(
        self, descriptor: BleakGATTDescriptor, data: SizedBuffer
    ) -> None:
        proxy = self._descriptor_proxies.get(descriptor.handle)
        if proxy is None:
            raise BleakError(f"descriptor {descriptor.handle} is not on this connection")
        await self._require_peer().write_value(proxy, bytes(data), with_response=True)

    async def start_notify(
        self, characteristic: BleakGATTCharacteristic, callback: NotifyCallback, **kwargs: Any
    ) -> None:
        peer = self._require_peer()
        handle = characteristic.handle
        if handle in self._subscribers:
            raise BleakError(f"notifications on {characteristic.uuid} are already started")

        def on_value(value: bytes) -> None:
            callback(bytearray(value))

        self._subscribers[handle] = on_value
        try:
            await peer.subscribe(self._proxy(characteristic), on_value)
        except BaseException:
            self._subscribers.pop(handle, None)
            raise

    async def stop_notify(self, characteristic: BleakGATTCharacteristic) -> None:
        peer = self._require_peer()
        subscriber = self._subscribers.pop(characteristic.handle, None)
        if subscriber is not None:
            await peer.unsubscribe(self._proxy(characteristic), subscriber)


def _bind(adapter: BumbleAdapter) -> tuple[type[BumbleBleakScanner], type[BumbleBleakClient]]:
    """Subclasses of the two backends whose ``adapter`` is ``adapter``."""
    scanner = type("BumbleBleakScanner", (BumbleBleakScanner,), {"adapter": adapter})
    client = type("BumbleBleakClient", (BumbleBleakClient,), {"adapter": adapter})
    return scanner, client
