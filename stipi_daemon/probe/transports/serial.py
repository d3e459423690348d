"""Serial transport: the probe's USB CDC port or its hardware UART, through pyserial.

This module owns :class:`SerialTransportConfig` and :class:`SerialTransport`. pyserial
opens and configures the port (raw 8N1, the baud rate, DTR - which the 32u4's USB CDC
takes as "port open" - and an exclusive lock); the bytes then move on the port's file
descriptor through the asyncio event loop: ``loop.add_reader`` wakes the reader exactly
when the kernel has bytes (no polling, no thread), non-blocking ``os.write`` with
``loop.add_writer`` for the rare write that does not fit the kernel buffer. This needs a
selector event loop on a POSIX system (Linux, macOS), which is where the daemon runs; a
reader thread would be needed for Windows' proactor loop and is not implemented.

A vanished device (USB unplugged, the emulator's pty gone) shows as end-of-file or EIO on
the descriptor: :meth:`SerialTransport.read` raises
:class:`~stipi_daemon.errors.LinkLostError` and the probe adapter reopens the port. A port
missing at open raises :class:`~stipi_daemon.errors.DeviceNotFoundError`
(``serial port /dev/ttyACM0 not found``). It does not frame or decode bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import termios
from typing import Final, Literal

import serial
from pydantic import BaseModel, ConfigDict, Field

from stipi_daemon.errors import DeviceNotFoundError, LinkLostError

__all__ = ["UART1_BAUD", "SerialTransport", "SerialTransportConfig"]

UART1_BAUD: Final = 250_000
"""Baud rate of the firmware's hardware UART ``Serial1`` (config.h ``STIPI_UART1_BAUD``):
exact at 8 MHz. USB CDC ignores the baud rate."""
_READ_SIZE: Final = 4096
_MAX_BUFFERED: Final = 1 << 20


class SerialTransportConfig(BaseModel):
    """A probe on a serial port.

    Parameters
    ----------
    kind : "serial"
        Discriminator.
    port : str
        Device path (``/dev/ttyACM0`` for USB CDC, ``/dev/ttyUSB0`` for a UART adapter on
        ``Serial1``).
    baudrate : int
        Line rate [bit/s]; 250000 for ``Serial1``, ignored by USB CDC.
    write_timeout_s : float
        A write that cannot complete within this time means the link is gone [s].
    exclusive : bool
        Take an exclusive lock on the port (no second program can open it).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["serial"] = "serial"
    port: str = Field(min_length=1)
    baudrate: int = Field(UART1_BAUD, gt=0)
    write_timeout_s: float = Field(2.0, gt=0.0, allow_inf_nan=False)
    exclusive: bool = True


class SerialTransport:
    """A :class:`~stipi_daemon.probe.transports.base.Transport` over one serial port.

    Parameters
    ----------
    config : SerialTransportConfig
        Port and options.
    """

    def __init__(self, config: SerialTransportConfig) -> None:
        self.config = config
        self._serial: serial.Serial | None = None
        self._fd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._chunks: list[bytes] = []
        self._buffered = 0
        self._reading = False
        self._error: str | None = None
        self._waiter: asyncio.Future[None] | None = None
        self.bytes_read = 0
        """Bytes received since creation [bytes]."""
        self.bytes_written = 0
        """Bytes sent since creation [bytes]."""

    @property
    def name(self) -> str:
        return f"serial:{self.config.port}"

    @property
    def probe_id(self) -> str:
        """The probe behind the port: ``usb:<serial number>`` of its USB device when the
        system lists one for the port (pyserial's ``list_ports``), else ``serial:<port>``."""
        from serial.tools import list_ports

        port = os.path.realpath(self.config.port)
        for info in list_ports.comports():
            if os.path.realpath(info.device) == port and info.serial_number:
                return f"usb:{info.serial_number}"
        return self.name

    @property
    def is_open(self) -> bool:
        """Whether the port is open and has not failed."""
        return self._serial is not None and self._error is None

    async def open(self) -> None:
        if self._serial is not None:
            return
        port = self.config.port
        if not os.path.exists(port):
            raise DeviceNotFoundError(f"serial port {port} not found")
        ser = serial.Serial()
        ser.port = port
        ser.baudrate = self.config.baudrate
        ser.timeout = 0
        ser.write_timeout = 0
        ser.exclusive = self.config.exclusive
        try:
            ser.open()
        except (serial.SerialException, OSError) as exc:
            code = getattr(exc, "errno", None)
            if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
                raise DeviceNotFoundError(f"serial port {port} not found") from None
            reason = getattr(exc, "strerror", None) or str(exc)
            raise LinkLostError(f"cannot open serial port {port}: {reason}") from None
        # Like a real port opened afresh: nothing received before this moment.
        with contextlib.suppress(serial.SerialException, OSError, termios.error):
            ser.reset_input_buffer()
        self._serial = ser
        self._fd = ser.fileno()
        os.set_blocking(self._fd, False)
        self._loop = asyncio.get_running_loop()
        self._chunks.clear()
        self._buffered = 0
        self._error = None
        self._start_reading()

    def _start_reading(self) -> None:
        if not self._reading and self._loop is not None and self._fd >= 0:
            self._loop.add_reader(self._fd, self._on_readable)
            self._reading = True

    def _stop_reading(self) -> None:
        if self._reading and self._loop is not None:
            self._loop.remove_reader(self._fd)
            self._reading = False

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _fail(self, reason: str) -> None:
        if self._error is None:
            self._error = f"serial port {self.config.port} {reason}"
        self._stop_reading()
        self._wake()

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, _READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._fail(f"lost: {exc.strerror or exc}")
            return
        if not data:
            self._fail("lost: end of file (device gone)")
            return
        self._chunks.append(data)
        self._buffered += len(data)
        self.bytes_read += len(data)
        if self._buffered >= _MAX_BUFFERED:
            self._stop_reading()  # the consumer is behind: let the kernel buffer hold the rest
        self._wake()

    async def read(self) -> bytes:
        while not self._chunks:
            if self._error is not None:
                raise LinkLostError(self._error)
            if self._serial is None:
                raise LinkLostError(f"serial port {self.config.port} is not open")
            loop = asyncio.get_running_loop()
            self._waiter = loop.create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        data = b"".join(self._chunks)
        self._chunks.clear()
        self._buffered = 0
        if self._error is None:
            self._start_reading()
        return data

    async def write(self, data: bytes) -> None:
        if self._serial is None or self._error is not None:
            raise LinkLostError(self._error or f"serial port {self.config.port} is not open")
        view = memoryview(bytes(data))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.write_timeout_s
        while view:
            try:
                n = os.write(self._fd, view)
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError as exc:
                self._fail(f"lost: {exc.strerror or exc}")
                raise LinkLostError(self._error or "serial port lost") from None
            self.bytes_written += n
            view = view[n:]
            if not view:
                return
            remaining = deadline - loop.time()
            if remaining <= 0:
                self._fail(f"write timed out after {self.config.write_timeout_s} s")
                raise LinkLostError(self._error or "serial write timed out")
            ready: asyncio.Future[None] = loop.create_future()

            def _writable(fut: asyncio.Future[None] = ready) -> None:
                if not fut.done():
                    fut.set_result(None)

            loop.add_writer(self._fd, _writable)
            try:  # asyncio.timeout: a cancel is never dropped (clock.wait_event)
                async with asyncio.timeout(remaining):
                    await ready
            except TimeoutError:
                pass
            finally:
                loop.remove_writer(self._fd)

    async def close(self) -> None:
        ser, self._serial = self._serial, None
        if ser is None:
            return
        self._stop_reading()
        if self._error is None:
            self._error = f"serial port {self.config.port} closed"
        self._wake()
        with contextlib.suppress(serial.SerialException, OSError):
            ser.close()
        self._fd = -1
