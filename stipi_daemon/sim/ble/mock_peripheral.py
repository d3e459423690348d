"""``mock-peripheral``'s run: the emulated probe as a real BLE peripheral playing a scene.

:func:`serve` opens a Bluetooth controller with Bumble (``usb:0``, ``hci-socket:0``,
``serial:...``, ``virtual:NAME`` for an in-process radio, or ``loopback:PORT`` for a
virtual radio served to other processes on 127.0.0.1:PORT, :mod:`.loopback`), advertises
the probe's name and the Nordic UART Service, and streams the scene's load-cell samples in
the real wire protocol through :mod:`.mock_probe`, answering commands as the firmware does, with the
module's BLE limits (:mod:`.peripheral`, :mod:`.module`). Optional periodic faults: drop
the link, go silent, disappear. The command line is
:mod:`stipi_daemon.commands.mock_peripheral`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import ConfigError
from stipi_daemon.probe.nus import LOOPBACK_SCHEME
from stipi_daemon.sim import load_scene
from stipi_daemon.sim.ble.loopback import LoopbackRadioServer
from stipi_daemon.sim.ble.mock_probe import scene_core, start_ble_probe
from stipi_daemon.sim.ble.module import NotificationFaults
from stipi_daemon.sim.ble.peripheral import BleModuleLimits, LinkCounters
from stipi_daemon.sim.ble.radio import VIRTUAL_SCHEME, BleRadioError, VirtualRadio
from stipi_daemon.sim.feather import McuClock

__all__ = ["MockPeripheralOptions", "serve"]


@dataclass(frozen=True)
class MockPeripheralOptions:
    """Everything ``mock-peripheral`` was asked to do (see ``--help`` for each)."""

    scene: Path
    transport: str
    seed: int | None = None
    name: str = "STIPI-01"
    speed: float = 1.0
    duration_s: float | None = None
    max_mtu: int = 23
    connection_interval_ms: float = 15.0
    notifications_per_event: int = 4
    drop: float = 0.0
    corrupt: float = 0.0
    delay_ms: float = 0.0
    disconnect_every_s: float | None = None
    silent_every_s: float | None = None
    silent_for_s: float = 3.0
    disappear_every_s: float | None = None
    disappear_for_s: float = 5.0
    report_every_s: float = 5.0
    refuse_connections: int = 0
    quiet: bool = False


def _check(opts: MockPeripheralOptions) -> None:
    if not (math.isfinite(opts.speed) and opts.speed > 0):
        raise ConfigError(f"--speed must be > 0, got {opts.speed}")
    if opts.refuse_connections < 0:
        raise ConfigError(f"--refuse-connections must be >= 0, got {opts.refuse_connections}")
    if opts.seed is not None and opts.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {opts.seed}")
    for flag, value in (
        ("--duration", opts.duration_s),
        ("--disconnect-every", opts.disconnect_every_s),
        ("--silent-every", opts.silent_every_s),
        ("--disappear-every", opts.disappear_every_s),
    ):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{flag} must be a time > 0 s, got {value}")


async def _open_radio(
    transport: str,
) -> tuple[str, VirtualRadio | None, LoopbackRadioServer | None]:
    """The HCI spec the probe runs on, and the radio or loopback server opened for it."""
    scheme, _, rest = transport.partition(":")
    if scheme == VIRTUAL_SCHEME:
        with contextlib.suppress(BleRadioError):  # reuse an open radio of that name
            return transport, VirtualRadio(rest), None
    elif scheme == LOOPBACK_SCHEME:
        server = await LoopbackRadioServer.start(transport)
        return server.radio.spec, None, server
    return transport, None, None


async def serve(opts: MockPeripheralOptions, *, ready: asyncio.Event | None = None) -> LinkCounters:
    """Run the emulated probe until ``duration_s`` (or cancellation); return its counters.

    Parameters
    ----------
    opts : MockPeripheralOptions
        What to emulate and on which controller.
    ready : asyncio.Event, optional
        Set once the probe advertises.

    Returns
    -------
    LinkCounters
        What the emulated module did.
    """
    _check(opts)
    scene = load_scene(opts.scene)
    try:
        limits = BleModuleLimits(
            max_mtu=opts.max_mtu,
            connection_interval_s=opts.connection_interval_ms * 1e-3,
            notifications_per_event=opts.notifications_per_event,
        )
        faults = NotificationFaults(opts.drop, opts.corrupt, opts.delay_ms * 1e-3)
    except ValueError as exc:
        raise ConfigError(f"mock-peripheral: {exc}") from exc
    hci, radio, server = await _open_radio(opts.transport)
    clock = ScaledClock(opts.speed)
    mcu = McuClock(clock.now())
    core = scene_core(scene, opts.seed, mcu, clock.now())
    try:
        emulator = await start_ble_probe(
            hci, clock, core, mcu, name=opts.name, limits=limits, faults=faults
        )
    except BaseException:
        if server is not None:
            await server.close()
        raise
    p = emulator.peripheral
    p.refuse_connections(opts.refuse_connections)
    where = opts.transport if server is None else server.spec
    if not opts.quiet:
        print(
            f"advertising {opts.name} ({p.address.to_string(False)}) on {where}, "
            f"scene {scene.name}, MTU <= {opts.max_mtu}, "
            f"{limits.bytes_per_second:.0f} B/s ceiling",
            flush=True,
        )
    if server is not None:
        # Always printed (also with --quiet): the other process needs the port.
        print(
            f"serving a virtual radio on {server.host}:{server.port}: run the daemon with "
            f"`hci: {server.spec}` (configs/probe-ble-loopback.yaml)",
            flush=True,
        )
    if ready is not None:
        ready.set()

    async def every(period: float | None, action: Callable[[], Awaitable[object]]) -> None:
        if period is None:
            return
        while True:
            await clock.sleep_until(clock.now() + period)
            await action()

    async def silence() -> None:
        p.set_silent(True)
        await clock.sleep_until(clock.now() + opts.silent_for_s)
        p.set_silent(False)

    async def disappear() -> None:
        await p.disappear(opts.disappear_for_s)

    def status_line() -> None:
        c = p.counters
        print(
            f"t={clock.now():7.1f} s  connected={p.connected}  conns={c.connections}  "
            f"refused={c.connections_refused}  notifications={c.notifications}  "
            f"bytes={c.notified_bytes}  "
            f"frames_lost={emulator.frames_lost}  samples={emulator.ledger.samples_emitted}",
            flush=True,
        )

    async def report() -> None:
        status_line()

    tasks = [
        asyncio.create_task(every(opts.disconnect_every_s, p.drop_link)),
        asyncio.create_task(every(opts.silent_every_s, silence)),
        asyncio.create_task(every(opts.disappear_every_s, disappear)),
    ]
    if not opts.quiet:
        tasks.append(asyncio.create_task(every(opts.report_every_s, report)))
    try:
        if opts.duration_s is None:
            await asyncio.Event().wait()
        else:
            await clock.sleep_until(clock.now() + opts.duration_s)
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        await emulator.close()
        if radio is not None:
            radio.close()
        if server is not None:
            await server.close()
        if not opts.quiet:  # also after Ctrl-C (cancellation): what the module did
            status_line()
    return p.counters
