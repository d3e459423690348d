"""Emulated transport: an emulated Feather on a pty, reached through the real serial path.

This module owns :class:`EmulatedTransportConfig` and :class:`EmulatedTransport`. Opening
the transport the first time starts an :class:`~stipi_daemon.sim.feather.EmulatedFeather`
(its ADC fed by a simulator scene, paced on the session clock) and then opens a
:class:`~stipi_daemon.probe.transports.serial.SerialTransport` on the emulator's pty through
pyserial, so the demo and the tests exercise the same code as a real ``/dev/ttyACM0``.
``close()`` only closes the serial side (the emulated probe keeps running, like a real one
on its battery); ``release()`` also stops the emulator. The emulator is reachable as
:attr:`EmulatedTransport.feather` to inject faults. It does not decode anything.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field

from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import LinkLostError
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig

if TYPE_CHECKING:
    from stipi_daemon.sim.feather import EmulatedFeather

__all__ = ["EmulatedTransport", "EmulatedTransportConfig"]


class EmulatedTransportConfig(BaseModel):
    """An emulated probe playing a simulator scene.

    Parameters
    ----------
    kind : "emulated"
        Discriminator.
    scene : Path
        Scene file (``configs/scenes/*.yaml``) whose load-cell signal the probe reads.
    seed : int, optional
        Seed of the scene's effects and of the link faults (default: the scene's seed).
    scene_start_s : float, optional
        Session time of the scene's t = 0 [s]; default: the probe's first sample.
    rate_error_ppm : float
        MCU clock rate error against the session clock [ppm] (+: MCU clock fast).
    boot_offset_us : int
        ``micros()`` at the emulated boot [µs] (near 2^32 to test the wrap-around).
    calibrated : bool
        The probe's EEPROM holds the scene's zero and span (else span 0: uncalibrated).
    link_path : Path, optional
        Where the emulated serial device appears (default: a temporary directory).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["emulated"] = "emulated"
    scene: Path
    seed: int | None = Field(None, ge=0)
    scene_start_s: float | None = Field(None, allow_inf_nan=False)
    rate_error_ppm: float = Field(0.0, gt=-10_000.0, lt=10_000.0)
    boot_offset_us: int = Field(0, ge=0, lt=1 << 32)
    calibrated: bool = True
    link_path: Path | None = None


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

    async def read(self) -> bytes:
        if self._serial is None:
            raise LinkLostError(f"{self.name} is not open")
        return await self._serial.read()

    async def write(self, data: bytes) -> None:
        if self._serial is None:
            raise LinkLostError(f"{self.name} is not open")
        await self._serial.write(data)

    async def close(self) -> None:
        if self._serial is not None:
            await self._serial.close()

    async def release(self) -> None:
        await self.close()
        feather, self._feather = self._feather, None
        if feather is not None:
            await feather.stop()
