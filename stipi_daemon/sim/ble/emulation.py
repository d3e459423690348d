"""An emulated BLE probe on a virtual radio, started for the daemon's BLE transport.

A BLE probe config with ``emulate`` set (:class:`~stipi_daemon.probe.transports.configs.
BleEmulationConfig`) asks :class:`~stipi_daemon.probe.transports.ble.BleTransport` for a
probe that plays a simulator scene on an in-process virtual radio. The transport reaches
this module through :mod:`stipi_daemon.registry` (``"ble:emulated_probe"``), never by an
import, so a run on a real probe never loads the simulator. This module owns that glue:
:func:`start_emulated_probe` creates the radio (or joins the one ``hci`` names), boots the
scene's firmware model (:func:`~stipi_daemon.sim.ble.mock_probe.scene_core`) on an emulated
MCU clock and starts it advertising behind the emulated module
(:func:`~stipi_daemon.sim.ble.mock_probe.start_ble_probe`); :class:`EmulatedBleProbe` holds
the running probe, for fault injection, and stops it and its radio.
"""

from __future__ import annotations

import contextlib
import itertools
from dataclasses import dataclass

from stipi_daemon.clock import SessionClock
from stipi_daemon.probe.transports.configs import BleEmulationConfig
from stipi_daemon.sim.ble.mock_probe import BleProbeEmulator, scene_core, start_ble_probe
from stipi_daemon.sim.ble.peripheral import BleModuleLimits
from stipi_daemon.sim.ble.radio import BleRadioError, VirtualRadio
from stipi_daemon.sim.feather import McuClock
from stipi_daemon.sim.scene import load_scene

__all__ = ["EmulatedBleProbe", "start_emulated_probe"]

_radio_ids = itertools.count(1)


@dataclass
class EmulatedBleProbe:
    """A running emulated BLE probe and the virtual radio it was started on.

    Attributes
    ----------
    hci : str
        HCI spec of the radio the probe advertises on (``virtual:NAME``): the central
        connects through it.
    emulator : BleProbeEmulator
        The emulated probe (fault injection: ``emulator.peripheral``, ``emulator.core``).
    radio : VirtualRadio or None
        The radio, when this call created it (closed by :meth:`close`).
    """

    hci: str
    emulator: BleProbeEmulator
    radio: VirtualRadio | None

    async def close(self) -> None:
        """Stop the probe, then unregister the radio if it was created for it."""
        await self.emulator.close()
        if self.radio is not None:
            self.radio.close()


async def start_emulated_probe(
    config: BleEmulationConfig, hci: str | None, clock: SessionClock, *, name: str
) -> EmulatedBleProbe:
    """Start a probe playing ``config.scene`` on a virtual radio, advertising as ``name``.

    Parameters
    ----------
    config : BleEmulationConfig
        Scene, seed, MCU clock error and the emulated module's limits.
    hci : str or None
        ``virtual:NAME`` of the radio to use (created if it does not exist yet), or None
        for a private radio with a fresh name.
    clock : SessionClock
        Session clock the probe paces itself on.
    name : str
        Advertised local name.

    Raises
    ------
    ConfigError
        The scene file is missing or invalid.
    """
    scene = load_scene(config.scene)
    radio: VirtualRadio | None = None
    if hci is None:
        radio = VirtualRadio(f"stipi-ble-{next(_radio_ids)}")
        hci = radio.spec
    else:
        with contextlib.suppress(BleRadioError):  # the radio may exist already
            radio = VirtualRadio(hci.partition(":")[2])
    mcu = McuClock(clock.now(), config.boot_offset_us, config.rate_error_ppm)
    core = scene_core(
        scene,
        config.seed,
        mcu,
        clock.now(),
        calibrated=config.calibrated,
        scene_start_s=config.scene_start_s,
    )
    limits = BleModuleLimits(
        max_mtu=config.max_mtu,
        connection_interval_s=config.connection_interval_s,
        notifications_per_event=config.notifications_per_event,
    )
    try:
        emulator = await start_ble_probe(hci, clock, core, mcu, name=name, limits=limits)
    except BaseException:
        if radio is not None:
            radio.close()
        raise
    return EmulatedBleProbe(hci, emulator, radio)
