"""Config models of the simulated probe links, on the runtime side of the registry.

A daemon config names a simulated probe like a real one: ``probe.transport.kind:
emulated`` (:class:`EmulatedTransportConfig`, an emulated Feather on a pty) or a BLE probe
with ``emulate`` set (:class:`BleEmulationConfig`, an emulated probe on a virtual radio).
The models live here, beside the serial and BLE config models, so validating a config
never loads the simulator; the implementations stay in :mod:`stipi_daemon.sim` and are
imported by name through :mod:`stipi_daemon.registry` when a transport is opened.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["BleEmulationConfig", "EmulatedTransportConfig"]


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


class BleEmulationConfig(BaseModel):
    """An emulated probe on a virtual radio, playing a simulator scene.

    Parameters
    ----------
    scene : Path
        Scene file whose load-cell signal the probe streams.
    seed : int, optional
        Seed of the scene's effects (default: the scene's).
    scene_start_s : float, optional
        Session time of the scene's t = 0 [s]; default: the probe's first sample.
    rate_error_ppm : float
        MCU clock rate error against the session clock [ppm].
    boot_offset_us : int
        ``micros()`` at the emulated boot [µs].
    calibrated : bool
        The probe's EEPROM holds the scene's zero and span.
    max_mtu : int
        Largest ATT MTU the emulated module accepts [bytes] (23: 20-byte notifications).
    connection_interval_s : float
        Connection interval [s] (session time).
    notifications_per_event : int
        Notifications the module sends per connection event.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    scene: Path
    seed: int | None = Field(None, ge=0)
    scene_start_s: float | None = Field(None, allow_inf_nan=False)
    rate_error_ppm: float = Field(0.0, gt=-10_000.0, lt=10_000.0)
    boot_offset_us: int = Field(0, ge=0, lt=1 << 32)
    calibrated: bool = True
    max_mtu: int = Field(23, ge=23, le=517)
    connection_interval_s: float = Field(0.015, ge=0.0075, le=4.0)
    notifications_per_event: int = Field(4, ge=1, le=64)
