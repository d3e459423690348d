"""SerialTransport over a real pty through pyserial, and transport configs."""

from __future__ import annotations

import asyncio
import os
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import DeviceNotFoundError, LinkLostError, StipiError
from stipi_daemon.probe.transports import (
    EmulatedTransportConfig,
    SerialTransportConfig,
    Transport,
    TransportConfig,
    open_transport,
)
from stipi_daemon.probe.transports.serial import UART1_BAUD, SerialTransport
from stipi_daemon.sim.emulated_transport import EmulatedTransport


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    os.close(slave)  # the transport opens it by path, like a device node
    try:
        yield master, path
    finally:
        try:
            os.close(master)
        except OSError:
            pass


async def test_missing_port_is_one_line_device_not_found(tmp_path: Path) -> None:
    t = SerialTransport(SerialTransportConfig(port=str(tmp_path / "ttyACM9")))
    with pytest.raises(DeviceNotFoundError) as exc:
        await t.open()
    assert str(exc.value) == f"serial port {tmp_path / 'ttyACM9'} not found"
    assert "\n" not in str(exc.value) and isinstance(exc.value, StipiError)
    await t.close()  # never opened: harmless


async def test_round_trip_and_chunking(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    t = SerialTransport(SerialTransportConfig(port=path))
    assert isinstance(t, Transport) and t.name == f"serial:{path}"
    await t.open()
    try:
        await t.write(b"\x01\x02\x00")
        got = b""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 2
        while len(got) < 3 and loop.time() < deadline:
            await asyncio.sleep(0.01)
            try:
                got += os.read(master, 100)
            except BlockingIOError:
                pass
        assert got == b"\x01\x02\x00"
        payload = bytes(range(256)) * 40  # 10 kB: several reads
        os.write(master, payload)
        received = b""
        while len(received) < len(payload):
            received += await asyncio.wait_for(t.read(), 2)
        assert received == payload
    finally:
        await t.close()
        await t.close()
    with pytest.raises(LinkLostError, match="closed"):
        await t.read()


async def test_vanished_device_raises_link_lost(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    t = SerialTransport(SerialTransportConfig(port=path))
    await t.open()
    reader = asyncio.create_task(t.read())
    await asyncio.sleep(0.05)
    os.close(master)  # the device goes away under an open port
    with pytest.raises(LinkLostError, match="lost") as exc:
        await asyncio.wait_for(reader, 2)
    assert "\n" not in str(exc.value)
    with pytest.raises(LinkLostError):
        await t.write(b"x")
    await t.close()


async def test_read_waits_without_busy_polling(pty_pair: tuple[int, str]) -> None:
    _master, path = pty_pair
    t = SerialTransport(SerialTransportConfig(port=path))
    await t.open()
    try:
        cpu0 = os.times()
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(t.read(), 0.5)
        cpu1 = os.times()
        assert (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system) < 0.2
    finally:
        await t.close()


def test_transport_config_union_and_open_transport(tmp_path: Path) -> None:
    adapter: TypeAdapter[SerialTransportConfig | EmulatedTransportConfig] = TypeAdapter(
        TransportConfig
    )
    serial_cfg = adapter.validate_python({"kind": "serial", "port": "/dev/ttyACM0"})
    assert isinstance(serial_cfg, SerialTransportConfig) and serial_cfg.baudrate == UART1_BAUD
    emu_cfg = adapter.validate_python({"kind": "emulated", "scene": "configs/scenes/grade2.yaml"})
    assert isinstance(emu_cfg, EmulatedTransportConfig)
    with pytest.raises(ValidationError):
        adapter.validate_python({"kind": "carrier-pigeon"})
    with pytest.raises(ValidationError):
        adapter.validate_python({"kind": "serial", "port": "/dev/x", "baud": 9600})
    clock = ScaledClock()
    assert isinstance(open_transport(serial_cfg, clock), SerialTransport)
    assert isinstance(open_transport(emu_cfg, clock), EmulatedTransport)
