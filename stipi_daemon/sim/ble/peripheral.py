"""The probe's BLE module as a Bumble peripheral: Nordic UART Service with the module's limits.

This module owns :class:`NusPeripheral`, a Bumble :class:`~bumble.device.Device` that plays
the part of the Feather's nRF51822 running Adafruit's Bluefruit firmware: it advertises the
probe's name and the Nordic UART Service, accepts one central, passes the central's writes
to RX on to the firmware, and sends the firmware's bytes as TX notifications with the real
module's limits - ATT MTU 23 (20-byte notifications) unless configured otherwise, a bounded
number of notifications per connection event, a ~1 KB transmit buffer that refuses whole
frames when full (:mod:`stipi_daemon.sim.ble.module`). Real ATT/GATT runs underneath, over a
USB dongle or a :class:`~stipi_daemon.sim.ble.radio.VirtualRadio`. It also injects link faults:
drop the link, stay connected but stop notifying, delay / drop / corrupt notifications,
disappear for a while. It knows nothing of the wire protocol or the firmware; the
emulated probe (:mod:`stipi_daemon.sim.ble.mock_probe`) drives it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, Final

from bumble.att import ATT_CID
from bumble.core import UUID
from bumble.device import Connection, Device, DeviceConfiguration
from bumble.gatt import Characteristic, CharacteristicValue, Service
from bumble.hci import Address, HCI_Error, Role

from stipi_daemon.clock import SessionClock, wait_event
from stipi_daemon.probe.nus import (
    ATT_DEFAULT_MTU,
    ATT_NOTIFY_OVERHEAD,
    DEFAULT_PROBE_NAME,
    NUS_RX_UUID,
    NUS_SERVICE_UUID,
    NUS_TX_UUID,
    advertising_payloads,
)
from stipi_daemon.sim.ble.module import (
    BLUEFRUIT_TX_BUFFER_BYTES,
    ConnectionEventPacer,
    FaultInjector,
    FaultOutcome,
    NotificationFaults,
    ReceiverSyncModel,
    TxChunk,
    UartTxFifo,
)
from stipi_daemon.sim.ble.radio import HciEndpoint, static_address

__all__ = ["BleModuleLimits", "LinkCounters", "NusPeripheral"]

_log = logging.getLogger(__name__)

#: HCI reason "connection timeout": what a central sees when the peripheral vanishes.
REASON_CONNECTION_TIMEOUT: Final = 0x08
#: Longest a dropped link waits for the notifications already queued [s of wall time].
DROP_FLUSH_WALL_S: Final = 0.5
#: HCI reason "remote user terminated connection".
REASON_REMOTE_USER_TERMINATED: Final = 0x13
#: HCI reason "connection failed to be established": the first connection events were
#: missed (BlueZ reports it as ``le-connection-abort-by-local``).
REASON_FAILED_TO_ESTABLISH: Final = 0x3E
#: Longest a refused connection lasts when the central sends nothing [s].
REFUSED_CONNECTION_S: Final = 1.0
_MIN_TICK_WALL_S: Final = 0.002


@dataclass(frozen=True, slots=True)
class BleModuleLimits:
    """Radio limits of the emulated module.

    Parameters
    ----------
    max_mtu : int
        Largest ATT MTU the module accepts in an MTU exchange [bytes], >= 23. The
        nRF51822 Bluefruit firmware keeps 23: 20-byte notifications.
    connection_interval_s : float
        Connection interval [s] (session time); Linux centrals grant 15..50 ms.
    notifications_per_event : int
        Notifications sent per connection event, >= 1.
    tx_buffer_bytes : int
        Module transmit buffer [bytes].
    advertising_interval_ms : float
        Advertising interval [ms] (wall time of the controller), 20..10240.
    """

    max_mtu: int = ATT_DEFAULT_MTU
    connection_interval_s: float = 0.015
    notifications_per_event: int = 4
    tx_buffer_bytes: int = BLUEFRUIT_TX_BUFFER_BYTES
    advertising_interval_ms: float = 20.0

    def __post_init__(self) -> None:
        if not ATT_DEFAULT_MTU <= self.max_mtu <= 517:
            raise ValueError(f"max_mtu must be within 23..517 bytes, got {self.max_mtu}")
        if not 0.0075 <= self.connection_interval_s <= 4.0:
            interval = self.connection_interval_s
            raise ValueError(f"connection_interval_s must be within 0.0075..4 s, got {interval}")
        if self.notifications_per_event < 1:
            raise ValueError(
                f"notifications_per_event must be >= 1, got {self.notifications_per_event}"
            )
        if self.tx_buffer_bytes < 80:
            raise ValueError(
                f"tx_buffer_bytes must hold a frame (>= 80), got {self.tx_buffer_bytes}"
            )
        if not 20.0 <= self.advertising_interval_ms <= 10240.0:
            adv = self.advertising_interval_ms
            raise ValueError(f"advertising_interval_ms must be within 20..10240, got {adv}")

    @property
    def bytes_per_second(self) -> float:
        """Throughput ceiling at the default MTU [bytes/s]."""
        payload = self.max_mtu - ATT_NOTIFY_OVERHEAD
        return payload * self.notifications_per_event / self.connection_interval_s


@dataclass(slots=True)
class LinkCounters:
    """What the emulated module did, for tests and the bench log.

    Every attribute counts since :class:`NusPeripheral` was created.
    """

    connections: int = 0
    disconnections: int = 0
    #: CCCD writes enabling TX notifications, one list entry per connection (in order).
    subscriptions_per_connection: list[int] = field(default_factory=list)
    notifications: int = 0
    notified_bytes: int = 0
    dropped_notifications: int = 0
    corrupted_notifications: int = 0
    rx_writes: int = 0
    rx_bytes: int = 0
    frames_refused: int = 0
    frames_discarded_on_disconnect: int = 0
    #: Connections dropped at once by :meth:`NusPeripheral.refuse_connections`.
    connections_refused: int = 0


@dataclass(slots=True)
class _Pending:
    send_at_s: float
    chunk: TxChunk
    outcome: FaultOutcome


class NusPeripheral:
    """A Bumble peripheral exposing the Nordic UART Service like the probe's BLE module.

    Parameters
    ----------
    hci : HciEndpoint
        Controller to run on (:func:`~stipi_daemon.sim.ble.radio.open_hci`).
    clock : SessionClock
        Session clock pacing connection events and fault timings.
    name : str
        Advertised complete local name.
    address : Address, optional
        Random static address (default derived from ``name``).
    limits : BleModuleLimits
        Radio limits.
    faults : NotificationFaults, optional
        Initial notification faults.
    seed : int
        Seed of the fault generator.
    """

    def __init__(
        self,
        hci: HciEndpoint,
        clock: SessionClock,
        *,
        name: str = DEFAULT_PROBE_NAME,
        address: Address | None = None,
        limits: BleModuleLimits | None = None,
        faults: NotificationFaults | None = None,
        seed: int = 0,
    ) -> None:
        self.hci = hci
        self.clock = clock
        self.name = name
        self.limits = limits or BleModuleLimits()
        self.address = address or static_address(sum(name.encode()) * 7919 + len(name))
        self._adv_data, self._scan_response = advertising_payloads(name)
        self.counters = LinkCounters()
        self.injector = FaultInjector(faults, seed=seed)
        self.fifo = UartTxFifo(self.limits.tx_buffer_bytes)
        #: Called with host → probe bytes written to RX.
        self.on_receive: Callable[[bytes], None] | None = None
        #: Called when a central connects (True) or the link drops (False).
        self.on_link_change: Callable[[bool], None] | None = None
        #: Called with the tag of every frame a correct receiver decodes (its bytes and the
        #: delimiter before it arrived intact; :class:`ReceiverSyncModel`).
        self.on_frame_delivered: Callable[[Hashable], None] | None = None

        config = DeviceConfiguration(
            name=name,
            address=self.address,
            advertising_interval_min=self.limits.advertising_interval_ms,
            advertising_interval_max=self.limits.advertising_interval_ms,
            advertising_data=self._adv_data,
            scan_response_data=self._scan_response,
        )
        self.device = Device.from_config_with_hci(config, hci.source, hci.sink)  # type: ignore[arg-type]
        self.device.gatt_server.max_mtu = self.limits.max_mtu
        self._tx: Characteristic[bytes] = Characteristic(
            UUID(NUS_TX_UUID),
            Characteristic.Properties.NOTIFY,
            Characteristic.Permissions(0),
            b"",
        )
        self._rx: Characteristic[bytes] = Characteristic(
            UUID(NUS_RX_UUID),
            Characteristic.Properties.WRITE | Characteristic.Properties.WRITE_WITHOUT_RESPONSE,
            Characteristic.Permissions.WRITEABLE,
            CharacteristicValue(write=self._on_rx_write),
        )
        self.device.add_service(Service(UUID(NUS_SERVICE_UUID), [self._tx, self._rx]))
        self.device.on(Device.EVENT_CONNECTION, self._on_connection)
        self.device.on("characteristic_subscription", self._on_subscription)
        #: Handles of refused connections, dropped at the central's first ATT request.
        self._refusing: set[int] = set()
        self.device.l2cap_channel_manager.register_fixed_channel(ATT_CID, self._on_att_pdu)

        self._connection: Connection | None = None
        self._subscribed = False
        self._silent = False
        self._absent = False
        self._dropping: Connection | None = None  # the link drop_link is taking down
        self._refuse_left = 0
        self._pacer: ConnectionEventPacer | None = None
        self._pending: deque[_Pending] = deque()
        self._receiver = ReceiverSyncModel()
        self._task: asyncio.Task[None] | None = None
        self._adv_task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self._closed = False

    # ------------------------------------------------------------------ state

    @property
    def connected(self) -> bool:
        """Whether a central is connected."""
        return self._connection is not None

    @property
    def link_up(self) -> bool:
        """Whether the module takes frames to send (connected and present)."""
        return self._connection is not None and not self._absent

    @property
    def subscribed(self) -> bool:
        """Whether the connected central has enabled TX notifications."""
        return self._subscribed

    @property
    def att_mtu(self) -> int:
        """ATT MTU of the current connection [bytes] (23 when not connected)."""
        return int(self._connection.att_mtu) if self._connection is not None else ATT_DEFAULT_MTU

    @property
    def faults(self) -> NotificationFaults:
        """Current notification faults (assign to change)."""
        return self.injector.faults

    @faults.setter
    def faults(self, value: NotificationFaults) -> None:
        self.injector.faults = value

    # -------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        """Power the device on, start advertising and the notification pump."""
        await self.device.power_on()
        await self._advertise()
        self._task = asyncio.create_task(self._pump(), name=f"nus-pump-{self.name}")

    async def close(self) -> None:
        """Stop the pump, drop any connection, power off and release the HCI endpoint."""
        if self._closed:
            return
        self._closed = True
        for task in (self._task, self._adv_task):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        conn = self._connection
        if conn is not None:
            with contextlib.suppress(HCI_Error, asyncio.TimeoutError, Exception):
                await asyncio.wait_for(conn.disconnect(REASON_REMOTE_USER_TERMINATED), 1.0)
        with contextlib.suppress(Exception):
            await self.device.power_off()
        await self.hci.close()

    # ------------------------------------------------------------ firmware side

    def offer_frame(self, data: bytes, tag: Hashable = None) -> bool:
        """Hand one frame (or a resync 0x00) to the module, whole or not at all.

        Returns False, and counts the refusal, when no central is connected or the TX
        buffer cannot take all of ``data`` - as the Bluefruit module answers ERROR.
        """
        if not self.link_up:
            self.counters.frames_refused += 1
            return False
        ok = self.fifo.offer(data, tag)
        if not ok:
            self.counters.frames_refused += 1
        return ok

    # ------------------------------------------------------------------ faults

    async def drop_link(self, reason: int = REASON_CONNECTION_TIMEOUT) -> bool:
        """Terminate the current connection (as a supervision timeout would); False if none.

        The link drops between notifications: those the module already sent (and the frame
        ledger counts as delivered) reach the central first, and none is sent after. The
        host stack queues a notification for its controller, while the Disconnect command
        goes straight to it and overtook the queue: the central then lacked notifications
        reported sent (once in six runs of 100 drops beside a busy CPU). And the pump sent
        while the Disconnect command was on its way: the last frame before each drop, counted
        as delivered, was lost (one run in three with the suite beside a CPU hog).
        """
        conn = self._connection
        if conn is None:
            return False
        self._dropping = conn  # the pump sends nothing more on it (_send_due)
        await self._hand_queued_notifications()
        try:
            await conn.disconnect(reason)
        except HCI_Error:
            if self._dropping is conn:
                self._dropping = None
            return False
        return True

    async def _hand_queued_notifications(self) -> None:
        """Wait until the host stack has handed every queued packet to the controller (at
        most :data:`DROP_FLUSH_WALL_S` of wall time)."""
        host = self.device.host
        queue = host.le_acl_packet_queue or host.acl_packet_queue
        loop = asyncio.get_running_loop()
        deadline = loop.time() + DROP_FLUSH_WALL_S
        while queue is not None and queue.pending > 0 and loop.time() < deadline:
            await asyncio.sleep(0.001)

    def refuse_connections(self, count: int) -> None:
        """Drop each of the next ``count`` connections as soon as it is made.

        The central's connection completes, then ends with HCI reason 0x3E (connection
        failed to be established; a controller that refuses that reason from its host
        gets 0x13) under the central's first ATT request, which is never answered - the
        transient failure of a peripheral that misses the first connection events, which a
        central retries. (Dropping it as soon as it is made raced the central's own
        connection-complete event across the loopback relay: its host then saw a
        disconnection of a handle it did not know yet, and its discovery waited out
        Bumble's 30 s GATT timeout.)
        Counted in ``counters.connections_refused``, not in ``counters.connections``.
        """
        if count < 0:
            raise ValueError(f"refused connection count must be >= 0, got {count}")
        self._refuse_left = count

    def _on_att_pdu(self, handle: int, pdu: bytes) -> None:
        """The device's ATT channel, except that a refused connection's first request is
        never answered: the link drops under it (see :meth:`refuse_connections`)."""
        if handle in self._refusing:
            self._refusing.discard(handle)
            connection = self.device.lookup_connection(handle)
            if connection is not None:
                asyncio.get_running_loop().create_task(self._drop_refused(connection))
            return
        self.device.on_gatt_pdu(handle, pdu)

    async def _refuse(self, connection: Connection) -> None:
        """Drop a refused connection at its first ATT request, or after
        :data:`REFUSED_CONNECTION_S` if none comes."""
        self._refusing.add(connection.handle)
        await asyncio.sleep(REFUSED_CONNECTION_S)
        if connection.handle in self._refusing:
            self._refusing.discard(connection.handle)
            await self._drop_refused(connection)

    async def _drop_refused(self, connection: Connection) -> None:
        try:
            await connection.disconnect(REASON_FAILED_TO_ESTABLISH)
        except HCI_Error:
            with contextlib.suppress(HCI_Error):
                await connection.disconnect(REASON_REMOTE_USER_TERMINATED)
        if not self._closed and self._connection is None:
            await self._advertise()

    def set_silent(self, silent: bool) -> None:
        """Stay connected but send no notifications (``True``) or resume (``False``).

        Frames keep arriving from the firmware while silent: the TX buffer fills and then
        refuses them, as on the real module when the radio stalls.
        """
        self._silent = silent

    async def disappear(self, duration_s: float) -> None:
        """Vanish for ``duration_s`` of session time: drop the link, stop advertising, return.

        The central sees a connection timeout, then no advertisements until the module
        comes back and advertises again. Returns once the module is back.
        """
        if duration_s < 0.0:
            raise ValueError(f"disappear duration must be >= 0 s, got {duration_s}")
        self._absent = True
        try:
            await self.drop_link(REASON_CONNECTION_TIMEOUT)
            if self.device.is_advertising:
                await self.device.stop_advertising()
            await self.clock.sleep_until(self.clock.now() + duration_s)
        finally:
            self._absent = False
        if not self._closed and self._connection is None:
            await self._advertise()

    # ---------------------------------------------------------------- internals

    async def _advertise(self) -> None:
        if self._closed or self._absent:
            return
        await self.device.start_advertising(
            advertising_data=self._adv_data,
            scan_response_data=self._scan_response,
            auto_restart=False,
        )

    def _on_connection(self, connection: Connection) -> None:
        if connection.role != Role.PERIPHERAL:
            return
        if self._refuse_left > 0 and self._connection is None and not self._absent:
            self._refuse_left -= 1
            self.counters.connections_refused += 1
            asyncio.get_running_loop().create_task(self._refuse(connection))
            return
        if self._connection is not None or self._absent:
            # The module serves one central; a second one (or one racing a disappearance)
            # is turned away.
            asyncio.get_running_loop().create_task(
                connection.disconnect(REASON_REMOTE_USER_TERMINATED)
            )
            return
        self._connection = connection
        self._subscribed = False
        self.counters.connections += 1
        self.counters.subscriptions_per_connection.append(0)
        self._pacer = ConnectionEventPacer(
            self.limits.connection_interval_s,
            self.limits.notifications_per_event,
            start_s=self.clock.now(),
        )
        self._receiver.reset()
        connection.on(
            connection.EVENT_DISCONNECTION,
            lambda reason: self._on_disconnection(connection, reason),
        )
        if self.on_link_change is not None:
            self.on_link_change(True)
        self._wake.set()

    def _on_disconnection(self, connection: Connection, reason: int) -> None:
        if connection is not self._connection:
            return
        self._connection = None
        self._dropping = None
        self._subscribed = False
        self._pacer = None
        self.counters.disconnections += 1
        discarded = self.fifo.clear()
        self.counters.frames_discarded_on_disconnect += len(discarded)
        self._pending.clear()
        _log.debug("central disconnected (reason 0x%02X)", reason)
        if self.on_link_change is not None:
            self.on_link_change(False)
        if not self._closed and not self._absent:
            self._adv_task = asyncio.get_running_loop().create_task(self._advertise())

    def _on_subscription(
        self, bearer: Any, characteristic: Any, notify_enabled: bool, indicate_enabled: bool
    ) -> None:
        if characteristic is not self._tx or bearer is not self._connection:
            return
        if notify_enabled:  # a second enable on one connection is a central subscribing twice
            self.counters.subscriptions_per_connection[-1] += 1
        self._subscribed = notify_enabled
        self._wake.set()

    def _on_rx_write(self, connection: Connection, value: bytes) -> None:
        if connection is not self._connection:
            return
        data = bytes(value)
        self.counters.rx_writes += 1
        self.counters.rx_bytes += len(data)
        if self.on_receive is not None:
            self.on_receive(data)

    async def _pump(self) -> None:
        """Cut notifications from the TX buffer at connection events and send them."""
        while True:
            now = self.clock.now()
            conn = self._connection
            pacer = self._pacer
            if conn is not None and pacer is not None:
                budget = pacer.grant(now)
                if self._subscribed and not self._silent:
                    self._fill(budget, now, conn)
                await self._send_due(now, conn)
                next_s = pacer.next_event_s
                if self._pending:
                    next_s = min(next_s, self._pending[0].send_at_s)
                floor_s = now + _MIN_TICK_WALL_S * self.clock.speed
                await self._sleep_until(max(next_s, floor_s))
            else:
                self._wake.clear()
                await self._wake.wait()

    async def _sleep_until(self, t_s: float) -> None:
        self._wake.clear()
        delay_wall = max(0.0, (t_s - self.clock.now()) / self.clock.speed)
        await wait_event(self._wake, delay_wall)

    def _fill(self, budget: int, now: float, conn: Connection) -> None:
        payload_max = int(conn.att_mtu) - ATT_NOTIFY_OVERHEAD
        delay = self.injector.faults.delay_s
        for _ in range(budget):
            chunk = self.fifo.take(payload_max)
            if chunk is None:
                return
            outcome = self.injector.apply(chunk.payload)
            if outcome.dropped:
                self.counters.dropped_notifications += 1
            if outcome.corrupted:
                self.counters.corrupted_notifications += 1
            self._pending.append(_Pending(now + delay, chunk, outcome))

    async def _send_due(self, now: float, conn: Connection) -> None:
        while self._pending and self._pending[0].send_at_s <= now:
            if self._connection is not conn or self._dropping is conn:
                return  # the link is gone or going: what is left is discarded with it
            item = self._pending.popleft()
            payload = item.outcome.payload
            if payload is not None:
                await self.device.notify_subscriber(conn, self._tx, payload)
                self.counters.notifications += 1
                self.counters.notified_bytes += len(payload)
            for tag in self._receiver.observe(item.chunk, item.outcome):
                if tag is not None and self.on_frame_delivered is not None:
                    self.on_frame_delivered(tag)
