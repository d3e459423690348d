"""HCI endpoints for Bumble devices: a real controller or a virtual radio in this process.

This module owns the way a Bumble host stack reaches a Bluetooth controller. A spec string
names it, in Bumble's own syntax (``usb:0``, ``hci-socket:0``, ``serial:/dev/ttyACM0,1000000``,
``tcp-client:127.0.0.1:9000`` ...), ``loopback:PORT`` for a virtual radio another process
serves on the loopback interface (:mod:`stipi_daemon.sim.ble.loopback`), or ``virtual:NAME``
for a :class:`VirtualRadio`: Bumble's
software controllers (:class:`bumble.controller.Controller`) sharing one in-process
:class:`bumble.link.LocalLink`, over which real link-layer connections, ACL data, ATT and
GATT run between every device on that radio. Tests, the emulated probe and a central then
talk "over the air" with no adapter present. It does not build devices or GATT services
(:mod:`stipi_daemon.sim.ble.peripheral`, :mod:`stipi_daemon.sim.ble.bleak_backend` do).
A controller that cannot be opened is one line naming the spec; for a USB dongle it says
whether the dongle is missing or held by someone else and how to run without one.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Final

from bumble.controller import Controller
from bumble.hci import Address
from bumble.link import LocalLink
from bumble.transport import open_transport
from bumble.transport.common import AsyncPipeSink, Transport, TransportSource

from stipi_daemon.errors import StipiError
from stipi_daemon.probe.nus import (
    DEFAULT_LOOPBACK_PORT,
    LOOPBACK_SCHEME,
    check_hci_spec_is_local,
    parse_loopback_spec,
)

__all__ = [
    "VIRTUAL_SCHEME",
    "BleRadioError",
    "HciEndpoint",
    "VirtualRadio",
    "explain_open_error",
    "open_hci",
    "static_address",
]

#: Spec prefix naming a :class:`VirtualRadio` registered in this process.
VIRTUAL_SCHEME: Final = "virtual"

_RADIOS: dict[str, VirtualRadio] = {}
_USB_SCHEMES: Final = ("usb", "pyusb")
#: What to do without a dongle (printed with every USB error).
NO_DONGLE_HINT: Final = (
    f"without a dongle, serve a virtual radio on this machine: `stipi-daemon mock-peripheral "
    f"--transport {LOOPBACK_SCHEME}:{DEFAULT_LOOPBACK_PORT}` and a daemon with "
    f"`hci: {LOOPBACK_SCHEME}:{DEFAULT_LOOPBACK_PORT}` (configs/probe-ble-loopback.yaml, "
    "docs/bench.md)"
)


class BleRadioError(StipiError):
    """An HCI endpoint cannot be opened (unknown virtual radio, no adapter, bad spec)."""


def static_address(n: int) -> Address:
    """A random static LE address derived from ``n`` (top two bits set, as the spec requires).

    Parameters
    ----------
    n : int
        Any integer 0 .. 2^46-1; equal ``n`` give equal addresses.
    """
    if not 0 <= n < (1 << 46):
        raise ValueError(f"static address index out of range: {n}")
    value = (0b11 << 46) | n
    text = ":".join(f"{(value >> (8 * i)) & 0xFF:02X}" for i in range(5, -1, -1))
    return Address(text, Address.RANDOM_DEVICE_ADDRESS)


class VirtualRadio:
    """A shared radio medium for Bumble software controllers in this process.

    Every :func:`open_hci` of ``virtual:<name>`` attaches a new controller to the radio;
    devices on it see each other's advertisements and connect to each other through the
    controllers' link layer (no adapter, no operating-system stack).

    Parameters
    ----------
    name : str
        Registry name used in ``virtual:<name>`` specs; unique among open radios.
    """

    def __init__(self, name: str) -> None:
        if not name or ":" in name:
            raise ValueError(f"virtual radio name must be non-empty without ':', got {name!r}")
        if name in _RADIOS:
            raise BleRadioError(f"virtual radio {name!r} already exists")
        self.name = name
        self.link = LocalLink()  # type: ignore[no-untyped-call]
        self._counter = itertools.count(1)
        self._controllers: list[Controller] = []
        _RADIOS[name] = self

    @property
    def spec(self) -> str:
        """The HCI spec string naming this radio (``virtual:<name>``)."""
        return f"{VIRTUAL_SCHEME}:{self.name}"

    @property
    def controllers(self) -> tuple[Controller, ...]:
        """Controllers attached so far."""
        return tuple(self._controllers)

    def new_controller(self) -> Controller:
        """Attach a new software controller to this radio."""
        index = next(self._counter)
        controller = Controller(f"{self.name}-{index}", link=self.link)
        self._controllers.append(controller)
        return controller

    def detach(self, controller: Controller) -> None:
        """Remove ``controller`` from the radio (it no longer sends or receives)."""
        if controller in self.link.controllers:
            self.link.remove_controller(controller)
        if controller in self._controllers:
            self._controllers.remove(controller)

    def close(self) -> None:
        """Unregister the radio; attached controllers stay usable until dropped."""
        if _RADIOS.get(self.name) is self:
            del _RADIOS[self.name]

    def __enter__(self) -> VirtualRadio:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @staticmethod
    def lookup(name: str) -> VirtualRadio:
        """The open radio called ``name``."""
        try:
            return _RADIOS[name]
        except KeyError:
            known = ", ".join(sorted(_RADIOS)) or "none"
            raise BleRadioError(f"no virtual radio {name!r} (open radios: {known})") from None


@dataclass
class HciEndpoint:
    """Where a Bumble host sends HCI packets and receives them from.

    Parameters
    ----------
    spec : str
        The spec it was opened from.
    source : TransportSource
        Packet source (the controller's events and data).
    sink : object
        Packet sink (commands and data to the controller).
    """

    spec: str
    source: TransportSource
    sink: object
    _transport: Transport | None = None
    _radio: VirtualRadio | None = None
    _controller: Controller | None = None
    _closed: bool = field(default=False)

    @property
    def is_virtual(self) -> bool:
        """Whether this endpoint is a software controller on a :class:`VirtualRadio`."""
        return self._radio is not None

    async def close(self) -> None:
        """Release the transport or detach the virtual controller (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._transport is not None:
            await self._transport.close()
        if self._radio is not None and self._controller is not None:
            self._radio.detach(self._controller)


def explain_open_error(spec: str, exc: BaseException) -> str:
    """One line saying why the controller ``spec`` could not be opened, and what to do.

    A USB dongle (``usb:N``, ``pyusb:...``) that is absent, held by the kernel's ``btusb``
    driver or another program, or not accessible is named as such, with the hint to run
    without a dongle on a loopback virtual radio; other transports get Bumble's reason.
    """
    scheme = spec.partition(":")[0]
    reason = " ".join(str(exc).split()) or type(exc).__name__
    if scheme in _USB_SCHEMES:
        name = type(exc).__name__
        if "not found" in reason or name in ("USBErrorNotFound", "USBErrorNoDevice"):
            why = "missing: no USB Bluetooth controller matches it; `bumble-usb-probe` lists them"
        elif name == "USBErrorBusy" or "BUSY" in reason:
            why = "in use by the kernel's btusb driver (BlueZ) or another program"
        elif name == "USBErrorAccess" or "ACCESS" in reason:
            why = "not accessible to this user: add the udev rule of docs/bench.md"
        else:
            why = (
                "missing, or in use by the kernel's btusb driver (BlueZ) or another "
                "program; `bumble-usb-probe` lists the dongles"
            )
        return f"no Bluetooth USB dongle at {spec} ({why}): {reason}; {NO_DONGLE_HINT}"
    if scheme == LOOPBACK_SCHEME and isinstance(exc, ConnectionRefusedError):
        host, port = parse_loopback_spec(spec)
        return (
            f"nothing serves a virtual radio at {host}:{port} ({spec}): start "
            f"`stipi-daemon mock-peripheral --scene SCENE --transport {spec}` first"
        )
    return f"cannot open Bluetooth HCI transport {spec!r}: {reason}"


async def open_hci(spec: str) -> HciEndpoint:
    """Open the HCI endpoint ``spec`` names.

    Parameters
    ----------
    spec : str
        ``virtual:<name>`` for a controller on an open :class:`VirtualRadio` of this
        process, ``loopback:[HOST:]PORT`` for a controller on a radio another process
        serves on the loopback interface, otherwise a Bumble transport spec (``usb:0``,
        ``hci-socket:0``, ``tcp-client:127.0.0.1:port`` ...). Network specs must name
        loopback addresses.

    Raises
    ------
    BleRadioError
        The radio is unknown or the transport cannot be opened (one line naming the spec,
        :func:`explain_open_error`).
    """
    scheme, _, rest = spec.partition(":")
    if scheme == VIRTUAL_SCHEME:
        radio = VirtualRadio.lookup(rest)
        controller = radio.new_controller()
        # The controller is the packet source; the pipe sink delivers host packets to it.
        return HciEndpoint(
            spec=spec,
            source=controller,
            sink=AsyncPipeSink(controller),
            _radio=radio,
            _controller=controller,
        )
    try:
        check_hci_spec_is_local(spec)
    except ValueError as exc:
        raise BleRadioError(str(exc)) from None
    bumble_spec = spec
    if scheme == LOOPBACK_SCHEME:
        host, port = parse_loopback_spec(spec)
        bumble_spec = f"tcp-client:{host}:{port}"
    try:
        transport = await open_transport(bumble_spec)
    except Exception as exc:  # Bumble raises many types (usb, OS, spec errors)
        raise BleRadioError(explain_open_error(spec, exc)) from exc
    return HciEndpoint(
        spec=spec, source=transport.source, sink=transport.sink, _transport=transport
    )
