"""The byte-stream interface every probe link implements (serial, emulated, BLE).

This module owns :class:`Transport`, the small async protocol the probe adapter
(:mod:`stipi_daemon.probe.link`) talks through: ``open()``, ``read()`` (waits for at least one
byte, raises :class:`~stipi_daemon.errors.LinkLostError` when the link goes away),
``write(data)``, ``close()`` and a ``name`` for messages; and :class:`Releasable`, the
optional extra a transport that owns a device (an emulated probe) implements so that its
owner can free it for good. It does not frame, decode or retry anything: transports move
bytes, :mod:`stipi_daemon.protocol` understands them and the probe adapter reconnects.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Releasable", "Transport"]


@runtime_checkable
class Transport(Protocol):
    """A reopenable byte stream to one device.

    ``close()`` ends the current connection only; ``open()`` may follow to reconnect to the
    same device. Bytes arrive in order; a read may return any number of them (a serial
    chunk, one 20-byte BLE notification).
    """

    @property
    def name(self) -> str:
        """Short human-readable name of the link (``serial:/dev/ttyACM0``)."""
        ...

    async def open(self) -> None:
        """Connect.

        Raises
        ------
        DeviceNotFoundError
            The device is not there (one line naming it).
        LinkLostError
            The device is there but the connection failed.
        """
        ...

    async def read(self) -> bytes:
        """Wait for and return at least one received byte.

        Raises
        ------
        LinkLostError
            The link went away (unplugged, disconnected) or was never opened.
        """
        ...

    async def write(self, data: bytes) -> None:
        """Send ``data`` (all of it).

        Raises
        ------
        LinkLostError
            The link went away.
        """
        ...

    async def close(self) -> None:
        """Close the connection; safe to call twice or when never opened."""
        ...


@runtime_checkable
class Releasable(Protocol):
    """A transport that owns its device (e.g. an emulated probe) and can free it for good."""

    async def release(self) -> None:
        """Close the connection and stop the device; the transport is not reopened after."""
        ...
