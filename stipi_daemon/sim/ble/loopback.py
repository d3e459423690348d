"""A virtual radio served on the loopback interface: the BLE bench in two processes.

This module owns :class:`LoopbackRadioServer`. It keeps a
:class:`~stipi_daemon.sim.ble.radio.VirtualRadio` (Bumble software controllers on one
:class:`bumble.link.LocalLink`) in the process that serves it - ``stipi-daemon
mock-peripheral --transport loopback:9321`` puts the emulated probe on it - and listens on
a loopback TCP port. Every client that connects gets a fresh software controller on that
radio and speaks HCI to it over the socket in the H4 framing of Bumble's ``tcp-client:``
transport (what ``bumble-controllers`` does with ``tcp-server:``), so another process's
Bumble host - the daemon's bleak backend with ``hci: loopback:9321`` - scans, connects and
runs GATT to the probe through real link-layer procedures, as through a USB dongle.

A client that goes away (daemon closed, crashed or killed) is a dongle pulled out: its
controller's connections end with a supervision timeout (HCI reason 0x08) at the peer and
the controller leaves the radio, so the probe advertises again for the next client. The
server binds loopback addresses only (:func:`stipi_daemon.probe.nus.parse_loopback_spec`):
HCI carries no authentication.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import itertools
import logging
from typing import Final

from bumble import ll
from bumble.controller import Controller
from bumble.transport.common import StreamPacketSource

from stipi_daemon.probe.nus import parse_loopback_spec
from stipi_daemon.sim.ble.radio import BleRadioError, VirtualRadio

__all__ = ["LoopbackRadioServer"]

_log = logging.getLogger(__name__)

#: HCI reason a peer sees when a client's controller vanishes: "connection timeout".
_REASON_SUPERVISION_TIMEOUT: Final = 0x08
_ids = itertools.count(1)


class _SocketSink:
    """Controller → host packets, written to one client's socket (H4 framing kept)."""

    def __init__(self, transport: asyncio.WriteTransport) -> None:
        self.transport = transport

    def on_packet(self, packet: bytes) -> None:
        if not self.transport.is_closing():
            self.transport.write(packet)


class _ClientProtocol(StreamPacketSource):
    """One client connection: its bytes go to a controller made for it on the radio."""

    def __init__(self, server: LoopbackRadioServer) -> None:
        super().__init__()
        self.server = server
        self.controller: Controller | None = None
        self.transport: asyncio.WriteTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.WriteTransport)
        controller = self.server.radio.new_controller()
        controller.host = _SocketSink(transport)
        self.set_packet_sink(controller)
        self.controller = controller
        self.transport = transport
        self.server.clients += 1
        self.server._connections.add(self)
        _log.debug("loopback radio: client %s connected", transport.get_extra_info("peername"))

    def connection_lost(self, exc: Exception | None) -> None:
        controller, self.controller = self.controller, None
        self.server._connections.discard(self)
        if controller is not None:
            self.server.unplug(controller)


class LoopbackRadioServer:
    """A :class:`VirtualRadio` whose controllers other processes reach over loopback TCP.

    Use :meth:`start`; the radio's own devices attach through ``radio.spec``
    (``virtual:NAME``), remote hosts through ``loopback:PORT``.

    Attributes
    ----------
    radio : VirtualRadio
        The shared medium.
    host : str
        Loopback address listened on.
    port : int
        TCP port listened on (the one picked when started with port 0).
    clients : int
        Client connections accepted so far.
    """

    def __init__(self, radio: VirtualRadio, server: asyncio.Server, host: str, port: int) -> None:
        self.radio = radio
        self.host = host
        self.port = port
        self.clients = 0
        self._server = server
        self._connections: set[_ClientProtocol] = set()

    @property
    def spec(self) -> str:
        """The spec a daemon gives as ``hci`` to reach this radio."""
        if self.host == "127.0.0.1":
            return f"loopback:{self.port}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"loopback:{host}:{self.port}"

    @classmethod
    async def start(cls, spec: str) -> LoopbackRadioServer:
        """Create a radio and serve it on the loopback address and port ``spec`` names.

        Parameters
        ----------
        spec : str
            ``loopback:PORT`` or ``loopback:HOST:PORT`` (HOST a loopback address); port 0
            picks a free port (:attr:`port` tells which).

        Raises
        ------
        BleRadioError
            ``spec`` is malformed or not on loopback, or the port is taken (one line).
        """
        try:
            host, port = parse_loopback_spec(spec, allow_any_port=True)
        except ValueError as exc:
            raise BleRadioError(str(exc)) from None
        radio = VirtualRadio(f"loopback-{port}-{next(_ids)}")
        server_box: list[LoopbackRadioServer] = []
        try:
            server = await asyncio.get_running_loop().create_server(
                lambda: _ClientProtocol(server_box[0]), host=host, port=port
            )
        except OSError as exc:
            radio.close()
            if exc.errno == errno.EADDRINUSE:
                raise BleRadioError(
                    f"cannot serve a virtual radio on {host}:{port}: the port is in use "
                    "(another mock-peripheral?); pick another port, e.g. loopback:9322"
                ) from None
            raise BleRadioError(f"cannot serve a virtual radio on {host}:{port}: {exc}") from exc
        bound = server.sockets[0].getsockname()[1]
        self = cls(radio, server, host, int(bound))
        server_box.append(self)
        return self

    def unplug(self, controller: Controller) -> None:
        """A client left: end its controller's connections (peer: timeout), detach it."""
        for connection in list(controller.le_connections.values()):
            with contextlib.suppress(Exception):  # the peer may be gone already
                connection.send_ll_control_pdu(ll.TerminateInd(_REASON_SUPERVISION_TIMEOUT))
        controller.le_connections.clear()
        with contextlib.suppress(Exception):
            controller.le_legacy_advertiser.stop()
        controller.host = None
        self.radio.detach(controller)

    async def close(self) -> None:
        """Stop listening, drop every client and unregister the radio."""
        self._server.close()
        for client in list(self._connections):
            if client.transport is not None:
                client.transport.close()  # connection_lost unplugs its controller
        await asyncio.sleep(0)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._server.wait_closed(), 5.0)
        self.radio.close()

    async def __aenter__(self) -> LoopbackRadioServer:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"LoopbackRadioServer({self.host}:{self.port}, radio={self.radio.name})"
