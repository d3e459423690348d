"""The emulated probe over BLE: the firmware model behind the emulated Bluefruit module.

This module owns :class:`BleProbeEmulator`, the glue between
:class:`~stipi_daemon.sim.feather.FeatherCore` (the firmware's behaviour, fed host bytes and
advanced in MCU time, unchanged) and :class:`~stipi_daemon.sim.ble.peripheral.NusPeripheral`
(the nRF51822 module on a Bumble stack), paced on the session clock. It reproduces what the
firmware's BLE link does (``firmware/feather32u4/src/core/sdep.cpp``): frames go to the
module only while a central is connected, a frame the module cannot take is lost whole (the
host sees a ``seq`` gap), and the first frame after a central connects is preceded by a 0x00
so the new central's decoder starts on a frame boundary. It keeps a ledger of every sample
the probe sent and which of them left the antenna intact, so tests can hold the host's gap
accounting to the truth. It does not decode anything the host sends beyond what the firmware
model does, and it owns no radio (the caller passes an HCI endpoint)."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Final

from stipi_daemon.clock import SessionClock, wait_event
from stipi_daemon.probe.nus import DEFAULT_PROBE_NAME
from stipi_daemon.protocol.cobs import cobs_decode
from stipi_daemon.protocol.messages import Samples, StatusFlags, unpack_frame
from stipi_daemon.sim.ble.module import NotificationFaults
from stipi_daemon.sim.ble.peripheral import BleModuleLimits, NusPeripheral
from stipi_daemon.sim.ble.radio import open_hci
from stipi_daemon.sim.feather import FeatherCore, McuClock
from stipi_daemon.sim.feather import scene_core as feather_scene_core

__all__ = [
    "BleFeatherCore",
    "BleProbeEmulator",
    "SampleLedger",
    "scene_core",
    "start_ble_probe",
]

_RESYNC: Final = b"\x00"


class BleFeatherCore(FeatherCore):
    """:class:`FeatherCore` whose STATUS flags report the BLE link (bit 1), not USB CDC."""

    ble_connected: bool = False

    def status_flags(self) -> StatusFlags:
        flags = super().status_flags() & ~StatusFlags.USB_OPEN
        if self.ble_connected:
            flags |= StatusFlags.BLE_CONNECTED
        return flags


@dataclass
class SampleLedger:
    """Ground truth of the samples the emulated probe put on the BLE link.

    Attributes
    ----------
    emitted : list of (first_index, count)
        Every SAMPLES frame the firmware produced, in order.
    accepted : dict
        Frames the module took into its TX buffer, by tag: (first_index, count).
    refused : list of (first_index, count)
        Frames lost before the air: no central, or the TX buffer full.
    delivered : list of (first_index, count)
        Frames a correct receiver decodes from what the module really notified (their
        bytes and the delimiter before them arrived intact, on one connection) - what the
        host must receive, no more, no less.
    """

    emitted: list[tuple[int, int]] = field(default_factory=list)
    accepted: dict[Hashable, tuple[int, int]] = field(default_factory=dict)
    refused: list[tuple[int, int]] = field(default_factory=list)
    delivered: list[tuple[int, int]] = field(default_factory=list)

    def delivered_indices(self) -> set[int]:
        """Indices of every sample delivered intact."""
        return {i for first, n in self.delivered for i in range(first, first + n)}

    @property
    def samples_emitted(self) -> int:
        """Samples the firmware sent towards the module."""
        return sum(n for _, n in self.emitted)

    @property
    def samples_delivered(self) -> int:
        """Samples that left the antenna intact."""
        return sum(n for _, n in self.delivered)


class BleProbeEmulator:
    """A :class:`FeatherCore` streaming through a :class:`NusPeripheral`, on a session clock.

    Parameters
    ----------
    core : FeatherCore
        Firmware model (use :class:`BleFeatherCore` for BLE status flags).
    peripheral : NusPeripheral
        The emulated BLE module (not yet started).
    clock : SessionClock
        Session clock the probe paces itself on.
    mcu_clock : McuClock
        Session time to MCU ``micros()`` (boot time, drift).
    max_tick_s : float
        Longest session-time sleep between two runs of the model [s].
    """

    def __init__(
        self,
        core: FeatherCore,
        peripheral: NusPeripheral,
        clock: SessionClock,
        mcu_clock: McuClock,
        *,
        max_tick_s: float = 0.1,
    ) -> None:
        self.core = core
        self.peripheral = peripheral
        self.clock = clock
        self.mcu_clock = mcu_clock
        self.ledger = SampleLedger()
        self._max_tick_s = max_tick_s
        self._tags = itertools.count()
        self._resync = False
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        self.frames_sent = 0
        """Frames the module accepted."""
        self.frames_lost = 0
        """Frames the firmware could not hand to the module (no central, buffer full)."""
        peripheral.on_receive = self._on_receive
        peripheral.on_link_change = self._on_link_change
        peripheral.on_frame_delivered = self._on_delivered

    # -------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        """Start the module (advertising) and the firmware's main loop."""
        if self._task is not None:
            return
        await self.peripheral.start()
        self._task = asyncio.get_running_loop().create_task(self._run(), name="ble-probe")

    async def close(self) -> None:
        """Stop the firmware and the module; safe to call twice."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.peripheral.close()

    async def __aenter__(self) -> BleProbeEmulator:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # --------------------------------------------------------------- internals

    def _mcu_now(self) -> int:
        return self.mcu_clock.mcu_us(self.clock.now())

    def _on_receive(self, data: bytes) -> None:
        self.core.feed(data, self._mcu_now())
        self._flush()
        self._wake.set()

    def _on_link_change(self, up: bool) -> None:
        if isinstance(self.core, BleFeatherCore):
            self.core.ble_connected = up
        if up:
            self._resync = True  # sdep.cpp: start a new central's stream on a frame boundary

    def _on_delivered(self, tag: Hashable) -> None:
        span = self.ledger.accepted.pop(tag, None)
        if span is not None:
            self.ledger.delivered.append(span)

    def _flush(self) -> None:
        for frame in self.core.take_output():
            span = _samples_span(frame)
            if span is not None:
                self.ledger.emitted.append(span)
            if frame == _RESYNC:  # the boot flush: a lone delimiter
                if self.peripheral.link_up:
                    self.peripheral.offer_frame(frame)
                continue
            if self._resync and self.peripheral.link_up:
                self._resync = not self.peripheral.offer_frame(_RESYNC)
            tag = next(self._tags)
            if not self._resync and self.peripheral.offer_frame(frame, tag):
                self.frames_sent += 1
                if span is not None:
                    self.ledger.accepted[tag] = span
            else:
                self.frames_lost += 1
                if span is not None:
                    self.ledger.refused.append(span)

    async def _run(self) -> None:
        clock = self.clock
        while True:
            now = clock.now()
            self.core.advance(self.mcu_clock.mcu_us(now))
            self._flush()
            t_next = self.mcu_clock.session_s(self.core.next_event_us() + 1)
            deadline = min(t_next, now + self._max_tick_s)
            wall_s = max(0.0, (deadline - clock.now()) / clock.speed)
            self._wake.clear()
            await wait_event(self._wake, wall_s)


def _samples_span(frame: bytes) -> tuple[int, int] | None:
    """(first_index, count) of a SAMPLES wire frame, None for any other frame."""
    if len(frame) < 3:
        return None
    msg = unpack_frame(cobs_decode(frame[:-1])).message
    if isinstance(msg, Samples):
        return msg.first_index, msg.count
    return None


def scene_core(
    scene: object,
    seed: int | None,
    mcu_clock: McuClock,
    now_s: float,
    *,
    calibrated: bool = True,
    scene_start_s: float | None = None,
) -> BleFeatherCore:
    """A firmware model reading a simulator scene, booted at session time ``now_s``.

    :func:`stipi_daemon.sim.feather.scene_core` with the BLE probe's core
    (:class:`BleFeatherCore`); the parameters are that function's.
    """
    core = feather_scene_core(
        scene,
        seed,
        mcu_clock,
        now_s,
        calibrated=calibrated,
        scene_start_s=scene_start_s,
        core_type=BleFeatherCore,
    )
    assert isinstance(core, BleFeatherCore)
    return core


async def start_ble_probe(
    hci_spec: str,
    clock: SessionClock,
    core: FeatherCore,
    mcu_clock: McuClock,
    *,
    name: str = DEFAULT_PROBE_NAME,
    limits: BleModuleLimits | None = None,
    faults: NotificationFaults | None = None,
    fault_seed: int = 0,
) -> BleProbeEmulator:
    """Open ``hci_spec``, put ``core`` behind an emulated BLE module on it, start advertising.

    Parameters
    ----------
    hci_spec : str
        Controller (``virtual:<radio>``, ``usb:0``, ``hci-socket:0`` ...).
    clock : SessionClock
        Session clock.
    core : FeatherCore
        Firmware model (e.g. :func:`scene_core`), booted at ``mcu_clock``'s time now.
    mcu_clock : McuClock
        Session time to MCU time.
    name, limits, faults, fault_seed
        Passed to :class:`NusPeripheral`.
    """
    hci = await open_hci(hci_spec)
    try:
        peripheral = NusPeripheral(
            hci, clock, name=name, limits=limits, faults=faults, seed=fault_seed
        )
        emulator = BleProbeEmulator(core, peripheral, clock, mcu_clock)
        await emulator.start()
    except BaseException:
        await hci.close()
        raise
    return emulator
