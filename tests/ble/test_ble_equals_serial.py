"""The same scene and seed give the same force stream over BLE as over the serial path.

Both probes are the same firmware model (``FeatherCore``) playing the same scene; one is
reached through a pty and pyserial (``kind: emulated``), the other through two Bumble
stacks and bleak (``kind: ble`` with ``emulate``). ProbeLink must deliver identical samples:
indices, ADC counts, forces and probe timestamps (from the first sample).
"""

from __future__ import annotations

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ForceRow, ForceRows, ProbeLink
from stipi_daemon.probe.transports import TransportConfig, open_transport
from stipi_daemon.probe.transports.ble import BleEmulationConfig, BleTransportConfig
from stipi_daemon.probe.transports.configs import EmulatedTransportConfig
from stipi_daemon.sim.ble.radio import VirtualRadio

from .conftest import SCENES

N_SAMPLES = 400


async def _stream(config: TransportConfig) -> tuple[list[ForceRow], ProbeLink]:
    clock = ScaledClock(10.0)
    probe = ProbeLink(open_transport(config, clock), clock=clock, rate_hz=100)
    await probe.connect()
    rows: list[ForceRow] = []
    try:
        await probe.start_stream()
        async for ev in probe.events():
            if isinstance(ev, ForceRows):
                rows.extend(ev.rows)
                if len(rows) >= N_SAMPLES:
                    break
    finally:
        await probe.close()
    return rows[:N_SAMPLES], probe


async def test_ble_and_serial_deliver_the_same_samples(radio: VirtualRadio) -> None:
    scene = SCENES / "grade3.yaml"
    serial_rows, serial_probe = await _stream(EmulatedTransportConfig(scene=scene, seed=11))
    ble_rows, ble_probe = await _stream(
        BleTransportConfig(
            name="STIPI-01", hci=radio.spec, emulate=BleEmulationConfig(scene=scene, seed=11)
        )
    )
    # The probes booted at different moments, so compare probe times from the first sample.
    s0, b0 = serial_rows[0].t_mcu_us, ble_rows[0].t_mcu_us
    key = [(r.sample_index, r.adc_counts, r.force_n, r.t_mcu_us - s0) for r in serial_rows]
    assert [(r.sample_index, r.adc_counts, r.force_n, r.t_mcu_us - b0) for r in ble_rows] == key
    assert [r.sample_index for r in ble_rows] == list(range(N_SAMPLES))
    assert serial_probe.calibration == ble_probe.calibration is not None
    assert ble_probe.accounting.lost == serial_probe.accounting.lost == 0
