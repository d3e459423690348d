"""Emulated devices that speak the real protocols, for the demo and the tests.

:mod:`.feather` holds the emulated probe (:class:`FeatherCore`, the firmware's behaviour
as a pure model; :class:`EmulatedFeather`, the same behind a pty). Runtime code reaches it
only through ``EmulatedTransportConfig`` (:mod:`stipi_daemon.transports.emulated`).
"""

from __future__ import annotations

from stipi_daemon.emulator.feather import (
    ConstantAdc,
    EmulatedFeather,
    FeatherCore,
    McuClock,
    SceneAdc,
    flip_bits,
    period_for_rate,
)

__all__ = [
    "ConstantAdc",
    "EmulatedFeather",
    "FeatherCore",
    "McuClock",
    "SceneAdc",
    "flip_bits",
    "period_for_rate",
]
