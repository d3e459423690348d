"""Probe transports: one per link, chosen by the config's ``kind`` and imported lazily.

Each real transport module holds its pydantic config model and its
:class:`~stipi_daemon.probe.transports.base.Transport`: :mod:`.serial` (USB CDC / UART
through pyserial, ``kind="serial"``) and :mod:`.ble` (BLE UART, ``kind="ble"``). The
simulated link (an emulated probe on a pty, ``kind="emulated"``) has its config model in
:mod:`.configs` and its implementation in :mod:`stipi_daemon.sim.emulated_transport`.
:data:`TransportConfig` is their discriminated union (what the daemon config's
``probe.transport`` holds) and :func:`open_transport` builds the transport a config names,
importing its module by name through :mod:`stipi_daemon.registry` (``transport:<kind>``),
so nothing here imports the simulator. Nothing here frames or decodes bytes;
:mod:`stipi_daemon.probe.link` does.
"""

from __future__ import annotations

from typing import Annotated, TypeAlias

from pydantic import Field

from stipi_daemon.clock import SessionClock
from stipi_daemon.probe.transports.base import Releasable, Transport
from stipi_daemon.probe.transports.ble import BleTransportConfig
from stipi_daemon.probe.transports.configs import EmulatedTransportConfig
from stipi_daemon.probe.transports.serial import SerialTransportConfig
from stipi_daemon.registry import load

__all__ = [
    "BleTransportConfig",
    "EmulatedTransportConfig",
    "Releasable",
    "SerialTransportConfig",
    "Transport",
    "TransportConfig",
    "open_transport",
]

TransportConfig: TypeAlias = Annotated[
    SerialTransportConfig | EmulatedTransportConfig | BleTransportConfig,
    Field(discriminator="kind"),
]
"""Any transport's config, told apart by ``kind`` (the BLE helper adds its model here)."""


def open_transport(
    config: SerialTransportConfig | EmulatedTransportConfig | BleTransportConfig,
    clock: SessionClock,
) -> Transport:
    """Build (not yet connect) the transport ``config`` names; ``await t.open()`` connects.

    Parameters
    ----------
    config : TransportConfig
        Which link and its options.
    clock : SessionClock
        The session clock (emulated devices pace themselves on it).

    Returns
    -------
    Transport
        An unopened transport; :class:`~stipi_daemon.probe.link.ProbeLink` opens and reopens it.
    """
    cls = load(f"transport:{config.kind}")
    transport: Transport = cls(config) if config.kind == "serial" else cls(config, clock)
    return transport
