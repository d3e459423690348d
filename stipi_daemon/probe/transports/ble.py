"""BLE UART transport: the probe's Nordic UART Service through bleak's public API.

This module owns :class:`BleTransportConfig` (``kind="ble"``) and :class:`BleTransport`, a
:class:`~stipi_daemon.probe.transports.base.Transport`. ``open()`` scans for the probe by
advertised name or by address (``BleakScanner``), connects (``BleakClient`` through
bleak-retry-connector's ``establish_connection``, which retries the transient failures of a
connection attempt - BlueZ's ``le-connection-abort-by-local``, a D-Bus hiccup, a link that
drops during service discovery - up to ``connect_attempts`` times), checks that
the Nordic UART Service is there and subscribes to its TX characteristic exactly once
(``start_notify``); every notification's bytes go to ``read()`` in order, whatever frame
boundaries they cut; ``write()`` sends through the RX characteristic in pieces of the
connection's write size (``write_gatt_char``). A disconnect - by the peripheral, the
radio or ``close()`` - makes ``read()`` raise :class:`~stipi_daemon.errors.LinkLostError`
once the bytes already received are read; the next ``open()`` connects afresh and
subscribes again, once. Retrying, backoff and the heartbeat watchdog belong to
:class:`~stipi_daemon.probe.link.ProbeLink`, which reopens transports of every kind.

bleak runs on the operating system's stack by default (BlueZ on Linux); with ``hci`` set it
runs on Bumble's host stack instead, either on a dongle (``usb:0``, ``hci-socket:0``), on
a virtual radio another process serves on the loopback interface (``loopback:9321``: the
bench without a radio, ``stipi-daemon mock-peripheral --transport loopback:9321``) or on
an in-process virtual radio (``virtual:NAME``). The bleak calls are the same in every case.
With ``emulate`` set
(:class:`~stipi_daemon.probe.transports.configs.BleEmulationConfig`), the transport also
starts an emulated probe playing a simulator scene on that virtual radio, so a whole
measurement runs over real BLE stacks in one process (tests, demo). Both come from
:mod:`stipi_daemon.sim.ble` through :mod:`stipi_daemon.registry` (``ble:bumble_adapter``,
``ble:emulated_probe``), imported by name only when a config asks for them. It does not
frame or decode anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from typing import TYPE_CHECKING, Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, model_validator

from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import DeviceNotFoundError, LinkLostError
from stipi_daemon.probe.nus import NUS_RX_UUID, NUS_TX_UUID, check_hci_spec_is_local
from stipi_daemon.probe.transports.configs import BleEmulationConfig
from stipi_daemon.registry import load

if TYPE_CHECKING:
    from bleak import BleakClient
    from bleak.backends.characteristic import BleakGATTCharacteristic
    from bleak.backends.client import BaseBleakClient
    from bleak.backends.device import BLEDevice
    from bleak.backends.scanner import AdvertisementData, BaseBleakScanner

__all__ = ["BleEmulationConfig", "BleTransport", "BleTransportConfig"]

#: Longest back-off bleak-retry-connector waits between two attempts [s] (a missing device).
_RETRY_BACKOFF_MAX_S = 4.0
_ADDRESS_RE = re.compile(r"^([0-9A-Fa-f]{2}:){5}[0-9A-Fa-f]{2}$|^[0-9A-Fa-f-]{36}$")


class _Adapter(Protocol):
    """bleak's backends on another host stack (registry ``"ble:bumble_adapter"``)."""

    def backends(self) -> tuple[type[BaseBleakScanner], type[BaseBleakClient]]:
        """bleak backend classes bound to this adapter: ``(scanner, client)``."""
        ...

    async def release(self) -> None:
        """Drop this user's reference; the last one closes the adapter."""
        ...


class _EmulatedProbe(Protocol):
    """A running emulated probe and its radio (registry ``"ble:emulated_probe"``)."""

    hci: str
    emulator: Any

    async def close(self) -> None:
        """Stop the probe and the radio created for it."""
        ...


class BleTransportConfig(BaseModel):
    """The probe over BLE UART (Nordic UART Service).

    Parameters
    ----------
    kind : "ble"
        Discriminator.
    name : str, optional
        Advertised local name to connect to (e.g. ``STIPI-01``).
    address : str, optional
        Bluetooth address (``AA:BB:CC:DD:EE:FF``; a UUID on macOS). Give ``name`` or
        ``address`` (with both, both must match).
    hci : str, optional
        Run bleak on Bumble's host stack on this controller instead of the operating
        system's: ``usb:0``, ``hci-socket:0``, ``serial:/dev/ttyACM0,1000000``,
        ``loopback:PORT`` for a virtual radio served on 127.0.0.1:PORT by ``stipi-daemon
        mock-peripheral --transport loopback:PORT`` (network specs must name loopback
        addresses), or ``virtual:NAME`` for an in-process virtual radio. Default: the OS
        stack (BlueZ).
    scan_timeout_s : float
        How long one ``open()`` scans for the probe before it reports it missing [s, wall].
    connect_timeout_s : float
        How long one connection attempt and its service discovery may take [s, wall].
    connect_attempts : int
        Connection attempts of one ``open()`` (bleak-retry-connector's ``max_attempts``);
        transient errors are retried, each after bleak-retry-connector's back-off.
    write_with_response : bool
        Send commands as ATT write requests (acknowledged) instead of write commands.
    emulate : BleEmulationConfig, optional
        Start an emulated probe on the virtual radio ``hci`` names (default: a private one).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["ble"] = "ble"
    name: str | None = Field(None, min_length=1, max_length=29)
    address: str | None = None
    hci: str | None = Field(None, min_length=1)
    scan_timeout_s: float = Field(10.0, gt=0.0, le=600.0)
    connect_timeout_s: float = Field(10.0, gt=0.0, le=600.0)
    connect_attempts: int = Field(3, ge=1, le=10)
    write_with_response: bool = False
    emulate: BleEmulationConfig | None = None

    @model_validator(mode="after")
    def _check(self) -> BleTransportConfig:
        if self.name is None and self.address is None:
            raise ValueError("give the probe's advertised 'name' or its 'address'")
        if self.address is not None and not _ADDRESS_RE.match(self.address):
            raise ValueError(f"address {self.address!r} is not AA:BB:CC:DD:EE:FF (or a UUID)")
        if self.hci is not None:
            check_hci_spec_is_local(self.hci)
        if (
            self.emulate is not None
            and self.hci is not None
            and not self.hci.startswith("virtual:")
        ):
            raise ValueError(
                "'emulate' runs on a virtual radio: leave 'hci' empty or use virtual:NAME"
            )
        return self

    @property
    def target(self) -> str:
        """The probe as users name it (name, address or both)."""
        if self.name and self.address:
            return f"{self.name} ({self.address})"
        return self.name or self.address or "?"


class BleTransport:
    """A :class:`~stipi_daemon.probe.transports.base.Transport` to the probe's Nordic UART Service.

    Parameters
    ----------
    config : BleTransportConfig
        Which probe, which stack, timeouts.
    clock : SessionClock
        Session clock (an emulated probe paces itself on it).
    """

    def __init__(self, config: BleTransportConfig, clock: SessionClock) -> None:
        self.config = config
        self.clock = clock
        self._hci = config.hci
        self._client: BleakClient | None = None
        self._adapter: _Adapter | None = None
        self._emulated: _EmulatedProbe | None = None
        self._buffer = bytearray()
        self._event = asyncio.Event()
        self._connected = False
        self._lost_reason = "not open"
        self._tx: BleakGATTCharacteristic | None = None
        self.connections = 0
        """Successful ``open()`` calls."""
        self.subscriptions = 0
        """``start_notify`` calls that succeeded (one per connection)."""
        self.notifications = 0
        """Notifications received."""
        self.bytes_received = 0

    # ------------------------------------------------------------ properties

    @property
    def name(self) -> str:
        return f"ble:{self.config.target}"

    @property
    def probe_id(self) -> str:
        """The probe: ``ble:<address>`` of the device connected to (else of the config)."""
        client = self._client
        address = client.address if client is not None else self.config.address
        return f"ble:{address}" if address else self.name

    @property
    def emulator(self) -> Any:
        """The emulated probe (``emulate`` set), for fault injection; after the first open.

        A :class:`stipi_daemon.sim.ble.mock_probe.BleProbeEmulator` (typed loosely: runtime
        code does not import the simulator).
        """
        if self._emulated is None:
            raise LinkLostError(f"{self.name}: no emulated probe has been started")
        return self._emulated.emulator

    @property
    def is_connected(self) -> bool:
        """Whether a connection is up."""
        return self._connected

    @property
    def mtu_size(self) -> int:
        """ATT MTU of the current connection [bytes]."""
        if self._client is None or not self._connected:
            raise LinkLostError(f"{self.name} is not connected")
        return int(self._client.mtu_size)

    # ------------------------------------------------------------- lifecycle

    async def _start_emulation(self) -> None:
        emu = self.config.emulate
        if emu is None or self._emulated is not None:
            return
        start = load("ble:emulated_probe")
        name = self.config.name or "STIPI-01"
        self._emulated = await start(emu, self._hci, self.clock, name=name)
        self._hci = self._emulated.hci

    async def _backends(
        self,
    ) -> tuple[type[BaseBleakScanner] | None, type[BaseBleakClient] | None]:
        if self._hci is None:
            return None, None
        if self._adapter is None:
            self._adapter = await load("ble:bumble_adapter").acquire(self._hci)
        return self._adapter.backends()

    async def open(self) -> None:
        from bleak import BleakClient
        from bleak.exc import BleakError
        from bleak_retry_connector import establish_connection

        cfg = self.config
        await self.close()
        await self._start_emulation()
        scanner_cls, client_cls = await self._backends()
        device = await self._find(scanner_cls)
        # Every attempt may take connect_timeout_s, then back off before the next one.
        limit_s = cfg.connect_attempts * (cfg.connect_timeout_s + _RETRY_BACKOFF_MAX_S)
        try:
            async with asyncio.timeout(limit_s):
                client = await establish_connection(
                    BleakClient,
                    device,
                    cfg.target,
                    disconnected_callback=self._on_disconnect,
                    max_attempts=cfg.connect_attempts,
                    use_services_cache=False,  # discover afresh, as after a firmware change
                    timeout=cfg.connect_timeout_s,
                    backend=client_cls,
                )
        except TimeoutError:
            raise LinkLostError(
                f"{self.name}: no connection within {limit_s:g} s "
                f"({cfg.connect_attempts} attempt(s) of up to {cfg.connect_timeout_s:g} s)"
            ) from None
        except (BleakError, OSError) as exc:
            raise LinkLostError(f"{self.name}: connection failed: {_one_line(exc)}") from exc
        tx = client.services.get_characteristic(NUS_TX_UUID)
        rx = client.services.get_characteristic(NUS_RX_UUID)
        if tx is None or rx is None:
            with contextlib.suppress(BleakError, TimeoutError, OSError):
                await client.disconnect()
            raise DeviceNotFoundError(
                f"{self.name}: device {device.address} has no Nordic UART Service"
            )
        self._client = client
        self._tx = rx
        self._buffer.clear()
        self._connected = True
        self._lost_reason = "disconnected"
        try:
            await client.start_notify(tx, self._on_notify)
        except (BleakError, TimeoutError, OSError) as exc:
            await self.close()
            raise LinkLostError(f"{self.name}: cannot subscribe to TX: {_one_line(exc)}") from exc
        self.subscriptions += 1
        self.connections += 1

    async def _find(self, scanner_cls: type[BaseBleakScanner] | None) -> BLEDevice:
        from bleak import BleakScanner
        from bleak.exc import BleakError

        cfg = self.config
        found: asyncio.Future[BLEDevice] = asyncio.get_running_loop().create_future()

        def match(device: BLEDevice, adv: AdvertisementData) -> None:
            if found.done():
                return
            if cfg.address is not None and device.address.lower() != cfg.address.lower():
                return
            if cfg.name is not None and cfg.name not in (adv.local_name, device.name):
                return
            found.set_result(device)

        scanner = BleakScanner(match, backend=scanner_cls)
        try:
            async with scanner:
                async with asyncio.timeout(cfg.scan_timeout_s):
                    return await found
        except TimeoutError:
            raise DeviceNotFoundError(
                f"BLE probe {cfg.target} not found within {cfg.scan_timeout_s:g} s of scanning"
            ) from None
        except (BleakError, OSError) as exc:
            raise DeviceNotFoundError(
                f"BLE probe {cfg.target}: cannot scan ({_one_line(exc)})"
            ) from exc

    def _on_notify(self, _sender: BleakGATTCharacteristic, data: bytearray) -> None:
        self.notifications += 1
        self.bytes_received += len(data)
        self._buffer += data
        self._event.set()

    def _on_disconnect(self, client: BleakClient) -> None:
        if client is not self._client:
            return  # a stale callback from an earlier connection
        self._connected = False
        self._lost_reason = "disconnected by the peripheral or the radio"
        self._event.set()

    async def read(self) -> bytes:
        while True:
            if self._buffer:
                data = bytes(self._buffer)
                self._buffer.clear()
                return data
            if not self._connected:
                raise LinkLostError(f"{self.name}: {self._lost_reason}")
            self._event.clear()
            await self._event.wait()

    async def write(self, data: bytes) -> None:
        from bleak.exc import BleakError

        client, rx = self._client, self._tx
        if client is None or rx is None or not self._connected:
            raise LinkLostError(f"{self.name}: {self._lost_reason}")
        size = max(1, rx.max_write_without_response_size)
        try:
            for off in range(0, len(data), size):
                await client.write_gatt_char(
                    rx, data[off : off + size], response=self.config.write_with_response
                )
        except (BleakError, TimeoutError, OSError) as exc:
            raise LinkLostError(f"{self.name}: write failed: {_one_line(exc)}") from exc

    async def close(self) -> None:
        from bleak.exc import BleakError

        client, self._client = self._client, None
        self._tx = None
        was = self._connected
        self._connected = False
        if was:
            self._lost_reason = "closed"
        self._event.set()
        if client is not None:
            with contextlib.suppress(BleakError, TimeoutError, OSError):
                async with asyncio.timeout(self.config.connect_timeout_s):
                    await client.disconnect()
        adapter, self._adapter = self._adapter, None
        if adapter is not None:
            await adapter.release()

    async def release(self) -> None:
        """Close, and stop the emulated probe and its radio if this transport started them."""
        await self.close()
        emulated, self._emulated = self._emulated, None
        if emulated is not None:
            await emulated.close()
            self._hci = self.config.hci


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text
