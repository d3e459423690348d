"""Registry of simulator effects: names to modules, imported only when a scene lists them.

This module owns the mapping from an effect's scene ``name`` to the module that
implements it, and the lazy import of that module. It imports no effect module itself, so
a scene without effects loads and runs none of their code. Each effect module defines
``Params`` (a :class:`~stipi_daemon.sim.effects.base.EffectParams` subclass whose
``name`` is a ``Literal``) and ``Effect`` (built as ``Effect(params, context)``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from stipi_daemon.errors import ConfigError

__all__ = ["EFFECT_MODULES", "effect_module", "known_effects"]

#: Scene name of each effect -> module under this package, in order of application.
EFFECT_MODULES: dict[str, str] = {
    "hand_tremor": "hand_tremor",
    "motion_blur": "motion_blur",
    "vignetting": "vignetting",
    "exposure_drift": "exposure_drift",
    "led_flicker": "led_flicker",
    "outlier_frames": "outlier_frames",
    "saturation": "saturation",
    "sensor_noise": "sensor_noise",
    "jpeg_compression": "jpeg_compression",
    "dropped_frames": "dropped_frames",
    "frame_gap": "frame_gap",
    "corrupt_frames": "corrupt_frames",
    "force_noise": "force_noise",
    "force_drift": "force_drift",
    "mcu_clock_drift": "mcu_clock_drift",
    "ble_link": "ble_link",
    "force_dropout": "force_dropout",
    "processing_stall": "processing_stall",
}


def known_effects() -> tuple[str, ...]:
    """Names of all effects, sorted."""
    return tuple(sorted(EFFECT_MODULES))


def effect_module(name: str) -> ModuleType:
    """Import and return the module implementing effect ``name``.

    Raises
    ------
    ConfigError
        ``name`` is not a known effect; the message lists the known ones.
    """
    module = EFFECT_MODULES.get(name)
    if module is None:
        raise ConfigError(f"unknown effect {name!r} (known: {', '.join(known_effects())})")
    return importlib.import_module(f"{__name__}.{module}")
