"""The BLE transport (bleak public API on the Bumble backend) against the emulated probe.

ProbeLink, FrameDecoder and SampleAccounting are the daemon's own; the peripheral is the
firmware model behind the emulated Bluefruit module; between them run two Bumble stacks
over a virtual radio.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import DeviceNotFoundError, LinkLostError
from stipi_daemon.probe.link import ForceRows, ProbeLink
from stipi_daemon.probe.transports import TransportConfig, open_transport
from stipi_daemon.probe.transports.ble import BleEmulationConfig, BleTransport, BleTransportConfig
from stipi_daemon.protocol.decoder import FrameDecoder
from stipi_daemon.protocol.messages import Samples, encode_frame
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.sim.ble.peripheral import BleModuleLimits, NusPeripheral
from stipi_daemon.sim.ble.radio import VirtualRadio, open_hci

from .conftest import SCENES


def test_config_is_part_of_the_transport_union_and_validated() -> None:
    ta: TypeAdapter[TransportConfig] = TypeAdapter(TransportConfig)
    cfg = ta.validate_python({"kind": "ble", "name": "STIPI-01", "hci": "usb:0"})
    assert isinstance(cfg, BleTransportConfig) and cfg.target == "STIPI-01"
    with pytest.raises(ValidationError, match="'name' or its 'address'"):
        ta.validate_python({"kind": "ble"})
    with pytest.raises(ValidationError, match="not AA:BB"):
        ta.validate_python({"kind": "ble", "address": "12:34"})
    with pytest.raises(ValidationError, match="virtual radio"):
        ta.validate_python(
            {"kind": "ble", "name": "x", "hci": "usb:0", "emulate": {"scene": "s.yaml"}}
        )
    with pytest.raises(ValidationError, match="extra"):
        ta.validate_python({"kind": "ble", "name": "x", "heartbeat": 1})


async def test_missing_probe_is_one_clear_line(radio: VirtualRadio) -> None:
    t = BleTransport(
        BleTransportConfig(name="STIPI-99", hci=radio.spec, scan_timeout_s=0.2), ScaledClock()
    )
    with pytest.raises(DeviceNotFoundError) as info:
        await t.open()
    assert str(info.value) == "BLE probe STIPI-99 not found within 0.2 s of scanning"
    with pytest.raises(LinkLostError):
        await t.read()
    await t.release()


async def test_probe_link_streams_the_scene_over_ble(radio: VirtualRadio) -> None:
    """ProbeLink over BLE: GET_INFO, configuration, streaming; forces are the scene's."""
    clock = ScaledClock(8.0)
    scene_path = SCENES / "grade1.yaml"
    cfg = BleTransportConfig(
        name="STIPI-01", hci=radio.spec, emulate=BleEmulationConfig(scene=scene_path, seed=3)
    )
    transport = open_transport(cfg, clock)
    assert isinstance(transport, BleTransport) and transport.name == "ble:STIPI-01"
    probe = ProbeLink(transport, clock=clock, rate_hz=100)
    info = await probe.connect()
    try:
        assert info.batch == 10 and info.adc_bits == 10 and info.span_un_per_count != 0
        assert transport.mtu_size == 23
        await probe.start_stream()
        rows = []
        t_end = clock.now() + 2.0
        async for ev in probe.events():
            if isinstance(ev, ForceRows):
                rows.extend(ev.rows)
            if clock.now() >= t_end and len(rows) >= 150:
                break
        await probe.stop_stream()
    finally:
        await probe.close()
    batch = Pipeline(load_scene(scene_path), 3).force_batch()
    idx = np.array([r.sample_index for r in rows])
    assert (np.diff(idx) == 1).all() and idx[0] == 0  # no gaps, from the first sample
    adc = np.array([r.adc_counts for r in rows])
    np.testing.assert_array_equal(adc, batch.adc_counts[idx])
    zero, span = probe.calibration or (0, 0)
    force = np.array([r.force_n for r in rows], dtype=float)
    np.testing.assert_allclose(force, (adc - zero) * span * 1e-6)
    assert probe.accounting.lost == 0 and probe.decoder.stats.errors == 0
    t_mcu = np.array([r.t_mcu_us for r in rows])
    assert (np.diff(t_mcu) == 10_000).all()  # 100 Hz on the probe's clock
    assert transport.subscriptions == transport.connections == 1


def _split_test_stream() -> tuple[bytes, list[Samples], list[int]]:
    """Frames of every length 21..67 B, each starting at every offset 0..19 of a notification.

    Zero bytes (empty frames, ignored by receivers) pad the stream so that frame ``k``
    starts at stream position ``≡ offset (mod 20)``.
    """
    stream = bytearray()
    sent: list[Samples] = []
    starts: list[int] = []
    seq = 0
    for count in range(1, 25):
        for offset in range(20):
            stream += b"\x00" * ((offset - len(stream)) % 20)
            msg = Samples(seq * 24, 5000, tuple((seq * 37 + 11 * i) % 1024 for i in range(count)))
            starts.append(len(stream))
            stream += encode_frame(msg, seq, seq * 1000)
            sent.append(msg)
            seq += 1
    return bytes(stream), sent, starts


@pytest.mark.parametrize("max_mtu", [23, 64])
async def test_frames_split_at_every_offset_decode_over_the_real_stack(
    radio: VirtualRadio, max_mtu: int
) -> None:
    stream, sent, starts = _split_test_stream()
    payload = max_mtu - 3
    clock = ScaledClock(1.0)
    limits = BleModuleLimits(
        max_mtu=max_mtu,
        connection_interval_s=0.0075,
        notifications_per_event=32,
        tx_buffer_bytes=len(stream) + 1,
    )
    peripheral = NusPeripheral(await open_hci(radio.spec), clock, name="SPLIT", limits=limits)
    await peripheral.start()
    transport = BleTransport(BleTransportConfig(name="SPLIT", hci=radio.spec), clock)
    try:
        await transport.open()
        assert transport.mtu_size == max_mtu
        assert peripheral.offer_frame(
            stream
        )  # in one piece: notifications cut it every `payload` B
        received = bytearray()
        async with asyncio.timeout(20):
            while len(received) < len(stream):
                received += await transport.read()
    finally:
        await transport.release()
        await peripheral.close()
    assert bytes(received) == stream
    # Every notification but the last was full, so boundaries fall every `payload` bytes...
    assert transport.notifications == math.ceil(len(stream) / payload)
    # ...and with MTU 23 every frame length was cut at every offset.
    if payload == 20:
        lengths = {len(encode_frame(m, 0, 0)) for m in sent}
        for length in lengths:
            cuts = {
                (-s) % 20
                for s, m in zip(starts, sent, strict=True)
                if len(encode_frame(m, 0, 0)) == length
            }
            assert cuts == set(range(20))
    decoder = FrameDecoder()
    frames = []
    for i in range(0, len(received), payload):  # feed as the notifications came
        frames += decoder.feed(received[i : i + payload])
    assert [f.message for f in frames] == sent
    assert decoder.stats.errors == 0


async def test_writes_longer_than_a_notification_are_split(radio: VirtualRadio) -> None:
    clock = ScaledClock(1.0)
    peripheral = NusPeripheral(await open_hci(radio.spec), clock, name="W")
    got = bytearray()
    peripheral.on_receive = got.extend
    await peripheral.start()
    transport = BleTransport(BleTransportConfig(name="W", hci=radio.spec), clock)
    try:
        await transport.open()
        data = bytes(range(1, 256)) * 2
        await transport.write(data)
        async with asyncio.timeout(5):
            while len(got) < len(data):
                await asyncio.sleep(0.005)
        assert bytes(got) == data
        assert peripheral.counters.rx_writes == math.ceil(len(data) / 20)
        await transport.close()
        with pytest.raises(LinkLostError, match="closed"):
            await transport.write(b"x")
        with pytest.raises(LinkLostError):
            await transport.read()
    finally:
        await transport.release()
        await peripheral.close()


async def test_link_up_reports_the_ble_flag(radio: VirtualRadio) -> None:
    clock = ScaledClock(8.0)
    cfg = BleTransportConfig(
        name="STIPI-01",
        hci=radio.spec,
        emulate=BleEmulationConfig(scene=SCENES / "grade1.yaml"),
    )
    probe = ProbeLink(open_transport(cfg, clock), clock=clock)
    await probe.connect()
    try:
        from stipi_daemon.probe.link import StatusReport
        from stipi_daemon.protocol.messages import StatusFlags

        async with asyncio.timeout(10):
            async for ev in probe.events():
                if isinstance(ev, StatusReport):
                    assert ev.flags & StatusFlags.BLE_CONNECTED
                    assert not ev.flags & StatusFlags.USB_OPEN
                    break
    finally:
        await probe.close()
