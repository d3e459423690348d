"""The probe id the daemon records in a session's manifest (``firmware.probe_id``).

A serial port that the system does not list as a USB device (here a pty, what the
emulated Feather and a hardware UART adapter look like to pyserial) is named by its port;
a BLE probe by its address, or by the config's name before it is connected. The emulated
probe's ``emulated`` is checked on a daemon recording in test_study_session.py.
"""

from __future__ import annotations

import os

from serial.tools import list_ports

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import probe_id_of
from stipi_daemon.probe.transports.ble import BleTransport, BleTransportConfig
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig


async def test_serial_port_without_a_usb_serial_number_is_named_by_its_port() -> None:
    master, slave = os.openpty()
    try:
        port = os.ttyname(slave)
        assert port not in {p.device for p in list_ports.comports()}
        transport = SerialTransport(SerialTransportConfig(port=port, exclusive=False))
        await transport.open()
        try:
            assert transport.probe_id == f"serial:{port}" == probe_id_of(transport)
        finally:
            await transport.close()
    finally:
        os.close(master)
        os.close(slave)


def test_ble_probe_is_named_by_its_address_else_its_name() -> None:
    clock = ScaledClock(1.0)
    by_address = BleTransport(BleTransportConfig(address="AA:BB:CC:DD:EE:01"), clock)
    assert probe_id_of(by_address) == "ble:AA:BB:CC:DD:EE:01"
    by_name = BleTransport(BleTransportConfig(name="STIPI-01"), clock)
    assert probe_id_of(by_name) == "ble:STIPI-01"
