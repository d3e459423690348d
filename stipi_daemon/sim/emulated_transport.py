"""Emulated transport: an emulated Feather on a pty, reached through the real serial path.

This module owns :class:`EmulatedTransport`, the implementation of the config kind
``emulated`` (its model, :class:`~stipi_daemon.probe.transports.configs.EmulatedTransportConfig`,
lives on the runtime side and is re-exported here; the daemon reaches this class through
:mod:`stipi_daemon.registry` as ``transport:emulated``). Opening
the transport the first time starts an :class:`~stipi_daemon.sim.feather.EmulatedFeather`
(its ADC fed by a simulator scene, paced on the session clock) and then opens a
:class:`~stipi_daemon.probe.transports.serial.SerialTransport` on the emulator's pty through
pyserial, so the demo and the tests exercise the same code as a real ``/dev/ttyACM0``.
``close()`` only closes the serial side (the emulated probe keeps running, like a real one
on its battery); ``release()`` also stops the emulator. The emulator is reachable as
:attr:`EmulatedTransport.feather` to inject faults. It does not decode anything.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import LinkLostError
from stipi_daemon.probe.transports.configs import EmulatedTransportConfig
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig

if TYPE_CHECKING:
    from stipi_daemon.sim.feather import EmulatedFeather

__all__ = ["EmulatedTransport", "EmulatedTransportConfig"]


class EmulatedTransport:
    """A :class:`~stipi_daemon.probe.transports.base.Transport` to an emulated Feather.

    Parameters
    ----------
    config : EmulatedTransportConfig
        The scene and emulation options.
    clock : SessionClock
        The session clock the emulated probe paces itself on.
    """

    def __init__(self, config: EmulatedTransportConfig, clock: SessionClock) -> None:
        self.config = config
        self.clock = clock
        self._feather: EmulatedFeather | None = None
        self._serial: SerialTransport | None = None
        self._unwatch: Callable[[], None] | None = None

    @property
    def name(self) -> str:
        return f"emulated:{self.config.scene.name}"

    @property
    def feather(self) -> EmulatedFeather:
        """The emulated probe (for fault injection); exists after the first :meth:`open`."""
        if self._feather is None:
            raise LinkLostError(f"{self.name}: the emulated probe has not been started")
        return self._feather

    def _make_feather(self) -> EmulatedFeather:
        from stipi_daemon.sim import load_scene
        from stipi_daemon.sim.feather import EmulatedFeather, McuClock, scene_core

        cfg = self.config
        scene = load_scene(cfg.scene)
        mcu = McuClock(self.clock.now(), cfg.boot_offset_us, cfg.rate_error_ppm)
        core = scene_core(
            scene,
            cfg.seed,
            mcu,
            self.clock.now(),
            calibrated=cfg.calibrated,
            scene_start_s=cfg.scene_start_s,
        )
        seed = scene.seed if cfg.seed is None else cfg.seed
        return EmulatedFeather(core, self.clock, mcu, link_path=cfg.link_path, seed=seed)

    async def open(self) -> None:
        if self._feather is None:
            feather = self._make_feather()
            await feather.start()
            self._feather = feather
        if self._serial is None:
            self._serial = SerialTransport(SerialTransportConfig(port=str(self._feather.path)))
        await self._serial.open()
        feather = self._feather
        feather.reset_flight()
        if self._unwatch is None:  # a simulated run's clock waits for bytes in flight
            serial = self._serial
            self._unwatch = self.clock.add_pending(lambda: serial.is_open and feather.in_flight())

    async def read(self) -> bytes:
        if self._serial is None:
            raise LinkLostError(f"{self.name} is not open")
        data = await self._serial.read()
        if self._feather is not None:
            self._feather.host_bytes_read += len(data)
        return data

    async def write(self, data: bytes) -> None:
        if self._serial is None:
            raise LinkLostError(f"{self.name} is not open")
        if self._feather is not None:
            self._feather.host_bytes_written += len(data)
        await self._serial.write(data)

    async def close(self) -> None:
        if self._serial is not None:
            await self._serial.close()

    async def release(self) -> None:
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        await self.close()
        feather, self._feather = self._feather, None
        if feather is not None:
            await feather.stop()
